"""References commanded at run time: velocity commands (teleop) and paths (a planner).

Both are a virtual unicycle whose speed and yaw rate are clipped and rate limited, so the
reference (x_r, y_r, ϕ_r, υ_r, ω_r, ω̇_r) handed to the generator of eq. (9) never asks
for more than the limits, whatever arrives:

- :class:`CmdVelReference` (kind ``cmd_vel``): the latest accepted velocity command
  (linear.x, angular.z); after ``timeout`` without one the command is zero, so the
  reference slows to a stop at the acceleration limits and the vehicle balances in place.
- :class:`PathReference` (kind ``path``): the latest accepted polyline; the unicycle
  drives along it (pure pursuit of a point ``lookahead`` ahead, turning on the spot where
  the path turns sharply), brakes so that it stops at the last point, and stands there.

Explicit state, one ``update(t)`` per control period; no ROS here (the reference node
feeds messages in, see ``nodes/reference_node.py``). Times are seconds of the reference
node's time base; a command or path refused is reported by the returned reason (the node
counts it on /diagnostics) and changes nothing.
"""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple, Sequence

from .reference_state import Reference, ReferenceState

#: Longest step of the integration [s]: a late tick is integrated in steps of this size.
MAX_STEP = 0.01
#: Closer than this to the last point of a path [m], the path is done.
PATH_END_TOLERANCE = 0.01


class UnicycleLimits(NamedTuple):
    """Limits of a commanded reference (each > 0)."""

    max_speed: float             #: |υ_r| [m/s]
    max_acceleration: float      #: |υ̇_r| [m/s²]
    max_yaw_rate: float          #: |ω_r| [rad/s]
    max_yaw_acceleration: float  #: |ω̇_r| [rad/s²]


def _clip(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _toward(value: float, target: float, step: float) -> float:
    return value + _clip(target - value, step)


class Unicycle:
    """A unicycle whose (υ, ω) follow commands at bounded rates.

    State: time ``t`` [s], pose ``x``, ``y`` [m], ``phi`` [rad, continuous], ``v`` [m/s],
    ``omega`` [rad/s], ``omega_dot`` [rad/s²] (the last step's yaw acceleration).
    """

    def __init__(self, limits: UnicycleLimits, x: float = 0.0, y: float = 0.0,
                 phi: float = 0.0, t: float = 0.0) -> None:
        for name, value in limits._asdict().items():
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {value!r}')
        self.limits = limits
        self.reset(t, x, y, phi)

    def reset(self, t: float, x: float, y: float, phi: float) -> None:
        """At rest at (x, y, phi) at time t."""
        self.t, self.x, self.y, self.phi = float(t), float(x), float(y), float(phi)
        self.v = self.omega = self.omega_dot = 0.0

    def state(self) -> ReferenceState:
        return ReferenceState(self.x, self.y, self.phi, self.v, self.omega, self.omega_dot)

    def update(self, t: float, v_command: float, omega_command: float) -> ReferenceState:
        """Advance to time t [s] under a command held constant since the last update."""
        lim = self.limits
        v_command = _clip(v_command, lim.max_speed)
        omega_command = _clip(omega_command, lim.max_yaw_rate)
        while t > self.t:
            dt = min(MAX_STEP, t - self.t)
            v0, w0 = self.v, self.omega
            self.v = _toward(v0, v_command, lim.max_acceleration * dt)
            self.omega = _toward(w0, omega_command, lim.max_yaw_acceleration * dt)
            self.omega_dot = (self.omega - w0) / dt
            # Mean speed and yaw rate over the step; the heading at mid-step (second order).
            v_mean, w_mean = 0.5 * (v0 + self.v), 0.5 * (w0 + self.omega)
            heading = self.phi + 0.5 * w_mean * dt
            self.x += v_mean * dt * math.cos(heading)
            self.y += v_mean * dt * math.sin(heading)
            self.phi += w_mean * dt
            self.t += dt
        return self.state()


class CmdVelReference(Reference):
    """Follows velocity commands (kind ``cmd_vel``).

    Parameters
    ----------
    limits : clip and rate limits.
    timeout : a command older than this [s] (by its stamp) is refused, and once the last
        accepted one is this old the command is zero: the reference brakes to rest.
    max_lead : a command stamped more than this [s] after the current time is refused.
    start : (x, y, phi) at rest at ``t0``.
    """

    pure = False   # its sample depends on the commands received so far

    def __init__(self, limits: UnicycleLimits, timeout: float = 0.5, max_lead: float = 0.0,
                 start: Sequence[float] = (0.0, 0.0, 0.0), t0: float = 0.0) -> None:
        if not (math.isfinite(timeout) and timeout > 0.0):
            raise ValueError(f'timeout must be finite and > 0, got {timeout!r}')
        self.unicycle = Unicycle(limits, *start, t=t0)
        self.timeout, self.max_lead = timeout, max_lead
        self.command_t: float | None = None  # stamp of the last accepted command [s]
        self.v_command = self.omega_command = 0.0

    @property
    def timed_out(self) -> bool:
        """No command in force (none yet, or the last one is older than the timeout)."""
        return (self.command_t is None
                or self.unicycle.t - self.command_t > self.timeout)

    def reset(self, t: float, x: float, y: float, phi: float) -> None:
        """At rest at (x, y, phi) at time t, forgetting the command."""
        self.unicycle.reset(t, x, y, phi)
        self.command_t = None
        self.v_command = self.omega_command = 0.0

    def command(self, stamp: float, now: float, linear_x: float,
                angular_z: float) -> str | None:
        """Offer a command stamped ``stamp`` [s], received at ``now`` [s].

        Returns None if accepted, else why it was refused ('invalid', 'future', 'stale').
        """
        if not all(math.isfinite(value) for value in (stamp, now, linear_x, angular_z)):
            return 'invalid'
        if stamp > now + self.max_lead:
            return 'future'
        if now - stamp > self.timeout:
            return 'stale'
        if self.command_t is not None and stamp < self.command_t:
            return 'stale'      # out of order: the newer command stays in force
        self.command_t = stamp
        lim = self.unicycle.limits
        self.v_command = _clip(linear_x, lim.max_speed)
        self.omega_command = _clip(angular_z, lim.max_yaw_rate)
        return None

    def update(self, t: float) -> ReferenceState:
        """Return the reference at time t [s] (t earlier than the last update: the last state)."""
        if t <= self.unicycle.t:
            return self.unicycle.state()
        if self.command_t is None or t - self.command_t > self.timeout:
            # The timeout falls inside this step: the command holds until it, then zero.
            if self.command_t is not None and self.command_t + self.timeout > self.unicycle.t:
                self.unicycle.update(self.command_t + self.timeout, self.v_command,
                                     self.omega_command)
            return self.unicycle.update(t, 0.0, 0.0)
        return self.unicycle.update(t, self.v_command, self.omega_command)

    def sample(self, t: float) -> ReferenceState:
        return self.update(t)


#: A path point farther than this [m] from the map origin is refused: no robot drives a
#: route across a continent in one map frame, and arc lengths of such a path lose the
#: precision that centimetre segments need (2^53 m: none).
MAX_PATH_COORDINATE = 1e6


def _polyline(points: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    """Return the points as floats, consecutive duplicates removed.

    ValueError if a point is not finite or beyond MAX_PATH_COORDINATE.
    """
    out: list[tuple[float, float]] = []
    for point in points:
        x, y = float(point[0]), float(point[1])
        if not (abs(x) <= MAX_PATH_COORDINATE and abs(y) <= MAX_PATH_COORDINATE):
            raise ValueError('a path point is not finite or too far from the map origin')
        if not out or math.hypot(x - out[-1][0], y - out[-1][1]) > 1e-6:
            out.append((x, y))
    return out


#: Points of a new path no more than this [m] farther from the reference than its closest
#: point count as closest too, and the earliest is taken (the start of a closed route).
JOIN_TIE = 0.1
#: A new path is searched for its point closest to the reference over its first metres:
#: the reference's distance from its first point plus this [m].
JOIN_SEARCH = 2.0


def _cumulative(polyline: Sequence[tuple[float, float]]) -> list[float]:
    cumulative = [0.0]
    for (x0, y0), (x1, y1) in zip(polyline, polyline[1:]):
        cumulative.append(cumulative[-1] + math.hypot(x1 - x0, y1 - y0))
    return cumulative


def _point_on(polyline: Sequence[tuple[float, float]], cumulative: Sequence[float],
              s: float) -> tuple[float, float]:
    """Return the point at arc length s of a polyline (clamped to its ends)."""
    if len(polyline) < 2:
        return polyline[0]
    s = max(0.0, min(cumulative[-1], s))
    i = max(0, min(len(polyline) - 2, bisect.bisect_right(cumulative, s) - 1))
    (x0, y0), (x1, y1) = polyline[i], polyline[i + 1]
    seg = cumulative[i + 1] - cumulative[i]
    f = (s - cumulative[i]) / seg if seg > 0.0 else 0.0
    return x0 + f * (x1 - x0), y0 + f * (y1 - y0)


def _point_within(s: float, s0: float, s1: float, x0: float, y0: float, dx: float,
                  dy: float) -> tuple[float, float] | None:
    """:func:`_point_on` of a point of the segment from (x0, y0) by (dx, dy), s in [s0, s1].

    Without its search, the same floats (at the segment's start _point_on's point is
    x0 + 0 dx). None at its end, where _point_on may take the next segment.
    """
    if s == s0:
        return x0, y0
    if s0 < s < s1:
        f = (s - s0) / (s1 - s0)
        return x0 + f * dx, y0 + f * dy
    return None


def _closest(polyline: Sequence[tuple[float, float]], cumulative: Sequence[float],
             x: float, y: float, window: float) -> float:
    """Arc length of the point of a polyline's first ``window`` [m] closest to (x, y).

    The earliest of those within JOIN_TIE of the closest.
    """
    if len(polyline) < 2:
        return 0.0
    candidates = []
    for i in range(len(polyline) - 1):
        if cumulative[i] > window:
            break
        (x0, y0), (x1, y1) = polyline[i], polyline[i + 1]
        seg = cumulative[i + 1] - cumulative[i]
        if seg <= 0.0:
            continue
        f = max(0.0, min(1.0, ((x - x0) * (x1 - x0) + (y - y0) * (y1 - y0)) / (seg * seg)))
        f = min(f, (window - cumulative[i]) / seg)
        candidates.append((math.hypot(x0 + f * (x1 - x0) - x, y0 + f * (y1 - y0) - y),
                           cumulative[i] + f * seg))
    if not candidates:
        return 0.0
    nearest = min(d for d, _ in candidates)
    return min(s for d, s in candidates if d <= nearest + JOIN_TIE)


class PathReference(Reference):
    """Drives along the latest polyline and stops at its end (kind ``path``).

    The unicycle is never reset by a path: it heads for the point ``lookahead`` [m]
    further along the path than its own projection (pure pursuit: ω = 2 υ sin α / L),
    slows with cos² α so that it turns on the spot where the path turns by more than
    about 90°, and its speed never exceeds √(2 a d) (d: the distance left along the path,
    a: 80 % of the acceleration limit) so that it comes to rest on the last point.

    A new path is taken up where the reference is, as Nav2's controllers prune a new plan
    to the robot (:meth:`set_path`): the same path again changes nothing; a path that
    passes the point reached on the old one, heading the same way, is followed on from
    there; any other path from its point closest to the reference.

    Parameters
    ----------
    limits : clip and rate limits.
    speed : cruise speed [m/s], clipped to ``limits.max_speed``.
    lookahead : pure-pursuit distance [m].
    heading_gain : yaw rate per heading error [1/s] when turning on the spot.
    start : (x, y, phi) at rest at ``t0``. Without a path it stays there.
    """

    pure = False   # its sample depends on the commands received so far

    def __init__(self, limits: UnicycleLimits, speed: float = 0.3, lookahead: float = 0.5,
                 heading_gain: float = 1.0, start: Sequence[float] = (0.0, 0.0, 0.0),
                 t0: float = 0.0) -> None:
        for name, value in (('speed', speed), ('lookahead', lookahead),
                            ('heading_gain', heading_gain)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {value!r}')
        self.unicycle = Unicycle(limits, *start, t=t0)
        self.speed = min(speed, limits.max_speed)
        self.lookahead, self.heading_gain = lookahead, heading_gain
        self.points: list[tuple[float, float]] = []
        self._cumulative: list[float] = []
        self.route: list[tuple[float, float]] = []   # the last accepted path, as received
        self.joined = 'none'    # how the last path was taken up (see set_path)
        self.progress = 0.0     # arc length of the unicycle's projection [m]
        self.done = True        # no path, or its end reached

    @property
    def length(self) -> float:
        return self._cumulative[-1] if self._cumulative else 0.0

    def reset(self, t: float, x: float, y: float, phi: float) -> None:
        """At rest at (x, y, phi) at time t, without a path."""
        self.unicycle.reset(t, x, y, phi)
        self.points, self._cumulative, self.progress, self.done = [], [], 0.0, True
        self.route, self.joined = [], 'none'

    def set_path(self, points: Sequence[Sequence[float]]) -> str | None:
        """Replace the path by ``points`` [(x, y), ...], taken up where the reference is.

        - The same points as the last path: nothing changes (``joined`` 'same').
        - A path that passes within ``lookahead`` of the point reached on the current
          path, heading within 60° of the same way (a route published again from
          another start, a replanned path from the robot): followed on from the nearest
          such point (``joined`` 'continued'); the earliest of several.
        - Otherwise from its point closest to the reference, the earliest of those no
          more than ``JOIN_TIE`` farther than the closest, so that a closed route starting
          at the robot is driven from its start, not its end (``joined`` 'closest').
          Farther than ``lookahead``, a straight first leg leads there (``joined``
          'joined').

        The reference itself never jumps: only what it steers for changes. Returns None
        if accepted, else why it was refused ('invalid', 'empty').
        """
        try:
            polyline = _polyline(points)
        except (ValueError, TypeError, IndexError):
            return 'invalid'
        if not polyline:
            return 'empty'
        if self.points and polyline == self.route:
            self.joined = 'same'
            return None
        u = self.unicycle
        cumulative = _cumulative(polyline)
        start = self._continuation(polyline, cumulative)
        if start is not None:
            self.joined = 'continued'
        else:
            # Searched over the path's first metres only, as Nav2's RPP searches the first
            # max_robot_pose_search_dist of a plan: a route that comes back past the
            # reference later (a closed loop) is driven from its start.
            window = math.hypot(polyline[0][0] - u.x, polyline[0][1] - u.y) + JOIN_SEARCH
            start = _closest(polyline, cumulative, u.x, u.y, window)
            self.joined = 'closest'
        # The path from that point on; what lies before it is never driven (Nav2 prunes it).
        i = max(0, min(len(polyline) - 1, bisect.bisect_right(cumulative, start) - 1))
        head = _point_on(polyline, cumulative, start)
        rest = polyline[i + 1:]
        if rest and math.hypot(rest[0][0] - head[0], rest[0][1] - head[1]) <= 1e-6:
            rest = rest[1:]
        path = [head] + rest
        gap = math.hypot(head[0] - u.x, head[1] - u.y)
        if gap > 1e-6 and (gap > self.lookahead or len(path) < 2):
            # Far from the path (or a single point): a first leg leads the reference there.
            path.insert(0, (u.x, u.y))
            self.joined = 'joined'
        self.route = polyline
        self.points, self._cumulative, self.progress = path, _cumulative(path), 0.0
        self.done = len(path) < 2
        return None

    def _continuation(self, polyline: list[tuple[float, float]],
                      cumulative: list[float]) -> float | None:
        """Arc length on ``polyline`` where it continues the current path, or None."""
        if len(self.points) < 2:
            return None
        px, py = self._point_at(self.progress)
        i = max(0, min(len(self.points) - 2,
                       bisect.bisect_right(self._cumulative, self.progress) - 1))
        (x0, y0), (x1, y1) = self.points[i], self.points[i + 1]
        seg = math.hypot(x1 - x0, y1 - y0)
        if seg <= 0.0:
            return None
        tx, ty = (x1 - x0) / seg, (y1 - y0) / seg
        best, best_d = None, self.lookahead
        for j in range(len(polyline) - 1):
            (a0, b0), (a1, b1) = polyline[j], polyline[j + 1]
            length = cumulative[j + 1] - cumulative[j]
            if length <= 0.0 or (a1 - a0) * tx + (b1 - b0) * ty < 0.5 * length:
                continue    # heading more than 60° away from the current path
            f = max(0.0, min(1.0, ((px - a0) * (a1 - a0) + (py - b0) * (b1 - b0))
                             / (length * length)))
            d = math.hypot(a0 + f * (a1 - a0) - px, b0 + f * (b1 - b0) - py)
            if d < best_d - 1e-9:
                best, best_d = cumulative[j] + f * length, d
        return best

    def _point_at(self, s: float) -> tuple[float, float]:
        return _point_on(self.points, self._cumulative, s)

    def _project(self, x: float, y: float) -> float:
        """Arc length of the point of the path nearest (x, y).

        Not behind the progress (a path that crosses itself is followed in order) and at most one
        lookahead on.
        """
        best, best_d2 = self.progress, math.inf
        horizon = self.progress + self.lookahead
        # Only the segments within [progress, horizon]: a planner's path has a pose every
        # few centimetres, and this runs every integration step.
        first = max(0, bisect.bisect_left(self._cumulative, self.progress) - 1)
        for i in range(first, len(self.points) - 1):
            s0, s1 = self._cumulative[i], self._cumulative[i + 1]
            if s0 > horizon:
                break
            if s1 < self.progress:
                continue
            (x0, y0), (x1, y1) = self.points[i], self.points[i + 1]
            dx, dy, seg = x1 - x0, y1 - y0, s1 - s0
            f = ((x - x0) * dx + (y - y0) * dy) / (seg * seg) if seg > 0.0 else 0.0
            s = max(self.progress, min(horizon, s0 + max(0.0, min(1.0, f)) * seg))
            px, py = _point_within(s, s0, s1, x0, y0, dx, dy) or self._point_at(s)
            d2 = (px - x) ** 2 + (py - y) ** 2
            if d2 < best_d2:
                best, best_d2 = s, d2
        return best

    def _command(self) -> tuple[float, float]:
        u = self.unicycle
        self.progress = self._project(u.x, u.y)
        end_x, end_y = self.points[-1]
        remaining = max(self.length - self.progress, math.hypot(end_x - u.x, end_y - u.y))
        if remaining < PATH_END_TOLERANCE:
            self.done = True
            return 0.0, 0.0
        tx, ty = self._point_at(self.progress + self.lookahead)
        distance = math.hypot(tx - u.x, ty - u.y)
        if distance < 1e-9:
            return 0.0, 0.0
        alpha = math.remainder(math.atan2(ty - u.y, tx - u.x) - u.phi, 2.0 * math.pi)
        brake = math.sqrt(2.0 * 0.8 * u.limits.max_acceleration * remaining)
        v = min(self.speed, brake) * max(0.0, math.cos(alpha)) ** 2
        omega = 2.0 * v * math.sin(alpha) / distance
        if abs(alpha) > 0.5 * math.pi or v < 0.05:
            # Slow or facing away: turn towards the target on the spot.
            omega = self.heading_gain * alpha
        return v, omega

    def update(self, t: float) -> ReferenceState:
        """Return the reference at time t [s] (t earlier than the last update: the last state)."""
        u = self.unicycle
        while t > u.t:
            step_end = min(t, u.t + MAX_STEP)
            if self.done:
                u.update(t, 0.0, 0.0)
                break
            u.update(step_end, *self._command())
        return u.state()

    def sample(self, t: float) -> ReferenceState:
        return self.update(t)
