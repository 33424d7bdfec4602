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


def _polyline(points: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    """Return the points as floats, consecutive duplicates removed; ValueError if not finite."""
    out: list[tuple[float, float]] = []
    for point in points:
        x, y = float(point[0]), float(point[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError('a path point is not finite')
        if not out or math.hypot(x - out[-1][0], y - out[-1][1]) > 1e-6:
            out.append((x, y))
    return out


class PathReference(Reference):
    """Drives along the latest polyline and stops at its end (kind ``path``).

    The unicycle starts from its current pose (a new path replaces the old one without a
    jump of the reference): it heads for the point ``lookahead`` [m] further along the
    path than its own projection (pure pursuit: ω = 2 υ sin α / L), slows with
    cos² α so that it turns on the spot where the path turns by more than about 90°,
    and its speed never exceeds √(2 a d) (d: the distance left along the path, a: 80 %
    of the acceleration limit) so that it comes to rest on the last point.

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
        self.progress = 0.0     # arc length of the unicycle's projection [m]
        self.done = True        # no path, or its end reached

    @property
    def length(self) -> float:
        return self._cumulative[-1] if self._cumulative else 0.0

    def reset(self, t: float, x: float, y: float, phi: float) -> None:
        """At rest at (x, y, phi) at time t, without a path."""
        self.unicycle.reset(t, x, y, phi)
        self.points, self._cumulative, self.progress, self.done = [], [], 0.0, True

    def set_path(self, points: Sequence[Sequence[float]]) -> str | None:
        """Replace the path by ``points`` [(x, y), ...]; the reference starts where it is.

        Returns None if accepted, else why it was refused ('invalid', 'empty').
        """
        try:
            polyline = _polyline(points)
        except (ValueError, TypeError, IndexError):
            return 'invalid'
        if not polyline:
            return 'empty'
        u = self.unicycle
        # From the current reference point: the first leg joins it to the path.
        if math.hypot(polyline[0][0] - u.x, polyline[0][1] - u.y) > 1e-6:
            polyline.insert(0, (u.x, u.y))
        cumulative = [0.0]
        for (x0, y0), (x1, y1) in zip(polyline, polyline[1:]):
            cumulative.append(cumulative[-1] + math.hypot(x1 - x0, y1 - y0))
        self.points, self._cumulative, self.progress = polyline, cumulative, 0.0
        self.done = len(polyline) < 2
        return None

    def _point_at(self, s: float) -> tuple[float, float]:
        s = max(0.0, min(self.length, s))
        i = max(0, min(len(self.points) - 2, bisect.bisect_right(self._cumulative, s) - 1))
        (x0, y0), (x1, y1) = self.points[i], self.points[i + 1]
        seg = self._cumulative[i + 1] - self._cumulative[i]
        f = (s - self._cumulative[i]) / seg if seg > 0.0 else 0.0
        return x0 + f * (x1 - x0), y0 + f * (y1 - y0)

    def _project(self, x: float, y: float) -> float:
        """Arc length of the point of the path nearest (x, y).

        Not behind the progress (a path that crosses itself is followed in order) and at most one
        lookahead on.
        """
        best, best_d2 = self.progress, math.inf
        horizon = self.progress + self.lookahead
        for i in range(len(self.points) - 1):
            s0, s1 = self._cumulative[i], self._cumulative[i + 1]
            if s1 < self.progress or s0 > horizon:
                continue
            (x0, y0), (x1, y1) = self.points[i], self.points[i + 1]
            dx, dy, seg = x1 - x0, y1 - y0, s1 - s0
            f = ((x - x0) * dx + (y - y0) * dy) / (seg * seg) if seg > 0.0 else 0.0
            s = max(self.progress, min(horizon, s0 + max(0.0, min(1.0, f)) * seg))
            px, py = self._point_at(s)
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
