r"""Reference trajectories (x_r, y_r, ϕ_r, υ_r, ω_r, ω̇_r) for the generator of eq. (9) in [1]_.

Every reference is a planar curve p(t) = (x_r(t), y_r(t)) with analytic derivatives up to
the third order, from which

.. math::

    \upsilon_r = |\dot p|, \quad
    \omega_r = \frac{\dot x \ddot y - \dot y \ddot x}{\dot x^2 + \dot y^2}, \quad
    \dot\omega_r = \frac{\dot x \dddot y - \dot y \dddot x}{\upsilon_r^2}
        - 2 \omega_r \frac{\dot x \ddot x + \dot y \ddot y}{\upsilon_r^2}

and ϕ_r = atan2(ẏ_r, ẋ_r) given by a closed form on a continuous branch (never
jumping by 2π). ``sample`` uses floats and ``math`` only.

Kinds
-----
``trifolium`` (Section V): x_r = κ cos(3Ω t) cos(Ω t), y_r = κ cos(3Ω t) sin(Ω t),
κ = 3 m, Ω = π/45 rad/s. Its speed is κΩ √(1 + 8 sin²(3Ω t)) ∈ [κΩ, 3κΩ] =
[0.21, 0.63] m/s, never zero, and |ω_r| peaks at 0.70 rad/s at the petal tips.
``circle``, ``line``, ``figure_eight`` (lemniscate of Gerono x = a sin τ,
y = (a/2) sin 2τ, τ = 2π t/P), and ``waypoints``: a polyline with circular fillets at
the corners and a trapezoidal speed profile (see :class:`Waypoints`). ``cmd_vel`` and
``path`` follow velocity commands and paths received at run time (``commanded.py``).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
import math
import threading
from typing import Hashable, NamedTuple, Sequence

from .commanded import CmdVelReference, PathReference, UnicycleLimits
from .config import ConfigError, param
from .reference_state import Reference, ReferenceState

_HALF_PI = 0.5 * math.pi
KINDS = ('trifolium', 'circle', 'line', 'figure_eight', 'waypoints', 'hold', 'cmd_vel',
         'path')
#: Kinds commanded at run time (``core.commanded``): stateful, never time-scaled.
COMMANDED_KINDS = ('cmd_vel', 'path')
#: Sharpest corner a waypoint list may have [rad] (a U-turn has no fillet).
MAX_CORNER_ANGLE = math.radians(179.0)


def _from_derivatives(x: float, y: float, phi: float, xd: float, yd: float, xdd: float,
                      ydd: float, xddd: float, yddd: float) -> ReferenceState:
    """ReferenceState from position derivatives (speed must be > 0)."""
    v2 = xd * xd + yd * yd
    omega = (xd * ydd - yd * xdd) / v2
    omega_dot = ((xd * yddd - yd * xddd) - 2.0 * omega * (xd * xdd + yd * ydd)) / v2
    return ReferenceState(x, y, phi, math.sqrt(v2), omega, omega_dot)


def _speed_and_yaw_rate(xd: float, yd: float, xdd: float, ydd: float,
                        *_third: float) -> tuple[float, float]:
    """(υ_r, ω_r) from the derivatives.

    The expressions of :func:`_from_derivatives`, so the same floats.
    """
    v2 = xd * xd + yd * yd
    return math.sqrt(v2), (xd * ydd - yd * xdd) / v2


class Trifolium(Reference):
    """The paper's trifolium, Section V of [1]_: r = κ cos(3Ω t) at polar angle Ω t.

    Written as p = (κ/2)(e^{i4Ωt} + e^{−i2Ωt}) (complex plane), so every derivative is a
    sum of two phasors. Heading on a continuous branch: with u = 3Ω t,
    ϕ_r = 4Ω t + π/2 + atan2(sin 2u, 1 + 2 sin² u) (the atan2 argument has a positive
    real part, so it never jumps); ϕ_r grows by 4π per figure (π/Ω = 45 s).

    Parameters
    ----------
    size : κ [m], > 0.
    angular_frequency : Ω [rad/s], > 0.
    """

    def __init__(self, size: float = 3.0, angular_frequency: float = math.pi / 45.0) -> None:
        if not (size > 0.0 and angular_frequency > 0.0):
            raise ValueError('Trifolium: size and angular_frequency must be > 0')
        self.size = size
        self.angular_frequency = angular_frequency

    def derivatives(self, t: float) -> tuple[float, ...]:
        a_half, w = 0.5 * self.size, self.angular_frequency
        angle_a, angle_b = 4.0 * w * t, 2.0 * w * t
        ca, sa = math.cos(angle_a), math.sin(angle_a)
        cb, sb = math.cos(angle_b), math.sin(angle_b)
        w2, w3 = w * w, w * w * w
        return (a_half * w * (-4.0 * sa - 2.0 * sb), a_half * w * (4.0 * ca - 2.0 * cb),
                -a_half * w2 * (16.0 * ca + 4.0 * cb), -a_half * w2 * (16.0 * sa - 4.0 * sb),
                a_half * w3 * (64.0 * sa + 8.0 * sb), a_half * w3 * (-64.0 * ca + 8.0 * cb))

    def sample(self, t: float) -> ReferenceState:
        w = self.angular_frequency
        u = 3.0 * w * t
        r = self.size * math.cos(u)
        su = math.sin(u)
        wt = w * t
        phi = 4.0 * w * t + _HALF_PI + math.atan2(math.sin(6.0 * w * t), 1.0 + 2.0 * su * su)
        return _from_derivatives(r * math.cos(wt), r * math.sin(wt), phi,
                                 *self.derivatives(t))

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        # The first two derivatives of :meth:`derivatives`, the same expressions.
        a_half, w = 0.5 * self.size, self.angular_frequency
        angle_a, angle_b = 4.0 * w * t, 2.0 * w * t
        ca, sa = math.cos(angle_a), math.sin(angle_a)
        cb, sb = math.cos(angle_b), math.sin(angle_b)
        w2 = w * w
        return _speed_and_yaw_rate(
            a_half * w * (-4.0 * sa - 2.0 * sb), a_half * w * (4.0 * ca - 2.0 * cb),
            -a_half * w2 * (16.0 * ca + 4.0 * cb), -a_half * w2 * (16.0 * sa - 4.0 * sb))


class Circle(Reference):
    """Uniform motion on a circle.

    Parameters
    ----------
    center : (x, y) [m].
    radius : R [m], > 0.
    speed : υ_r [m/s], > 0.
    direction : ``'ccw'`` (ω_r = υ/R) or ``'cw'`` (ω_r = −υ/R).
    start_angle : polar angle of the start point about the centre [rad].
    """

    def __init__(self, center: Sequence[float] = (0.0, 0.0), radius: float = 2.0,
                 speed: float = 0.5, direction: str = 'ccw', start_angle: float = 0.0) -> None:
        if not (radius > 0.0 and speed > 0.0):
            raise ValueError('Circle: radius and speed must be > 0')
        if direction not in ('ccw', 'cw'):
            raise ValueError(f"Circle: direction must be 'ccw' or 'cw', got {direction!r}")
        self.cx, self.cy = center
        self.radius, self.speed, self.start_angle = radius, speed, start_angle
        self.sign = 1.0 if direction == 'ccw' else -1.0
        self.rate = self.sign * speed / radius

    def derivatives(self, t: float) -> tuple[float, ...]:
        beta = self.start_angle + self.rate * t
        c, s = math.cos(beta), math.sin(beta)
        r, w = self.radius, self.rate
        return (-r * w * s, r * w * c, -r * w * w * c, -r * w * w * s, r * w ** 3 * s,
                -r * w ** 3 * c)

    def sample(self, t: float) -> ReferenceState:
        beta = self.start_angle + self.rate * t
        return ReferenceState(self.cx + self.radius * math.cos(beta),
                              self.cy + self.radius * math.sin(beta),
                              beta + self.sign * _HALF_PI, self.speed, self.rate, 0.0)

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        return self.speed, self.rate


class StraightLine(Reference):
    """Uniform motion on a straight line.

    The motion starts at ``start`` [m] and goes along ``heading`` [rad] at ``speed``
    [m/s] (≥ 0).
    """

    def __init__(self, start: Sequence[float] = (0.0, 0.0), heading: float = 0.0,
                 speed: float = 0.5) -> None:
        if not speed >= 0.0:
            raise ValueError('StraightLine: speed must be >= 0')
        self.x0, self.y0 = start
        self.heading, self.speed = heading, speed
        self._c, self._s = math.cos(heading), math.sin(heading)

    def derivatives(self, t: float) -> tuple[float, ...]:
        return (self.speed * self._c, self.speed * self._s, 0.0, 0.0, 0.0, 0.0)

    def sample(self, t: float) -> ReferenceState:
        d = self.speed * t
        return ReferenceState(self.x0 + d * self._c, self.y0 + d * self._s, self.heading,
                              self.speed, 0.0, 0.0)

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        return self.speed, 0.0


class FigureEight(Reference):
    """Lemniscate of Gerono: x = cx + a sin τ, y = cy + (a/2) sin 2τ, τ = 2π t/P.

    Starts at the centre heading 45°, first lobe to the right (counter-clockwise), the
    second clockwise. ẋ ∝ cos τ and ẏ ∝ 2cos²τ − 1 depend on τ only through c = cos τ, so
    ϕ_r = −π/2 + atan2(c, 1 − 2c²), continuous for c ∈ [−1, 1] (range [−5π/4, π/4]).
    The speed a(2π/P)√(4c⁴ − 3c² + 1) lies in [0.66, 1.41]·a 2π/P, never zero.

    Parameters
    ----------
    center : (x, y) [m].
    size : half-width a [m], > 0.
    period : P, time for the whole figure [s], > 0.
    """

    def __init__(self, center: Sequence[float] = (0.0, 0.0), size: float = 3.0,
                 period: float = 60.0) -> None:
        if not (size > 0.0 and period > 0.0):
            raise ValueError('FigureEight: size and period must be > 0')
        self.cx, self.cy = center
        self.size, self.period = size, period
        self.rate = 2.0 * math.pi / period

    def derivatives(self, t: float) -> tuple[float, ...]:
        a, w = self.size, self.rate
        tau = w * t
        c1, s1 = math.cos(tau), math.sin(tau)
        c2, s2 = math.cos(2.0 * tau), math.sin(2.0 * tau)
        return (a * w * c1, a * w * c2, -a * w * w * s1, -2.0 * a * w * w * s2,
                -a * w ** 3 * c1, -4.0 * a * w ** 3 * c2)

    def sample(self, t: float) -> ReferenceState:
        tau = self.rate * t
        c = math.cos(tau)
        phi = -_HALF_PI + math.atan2(c, 1.0 - 2.0 * c * c)
        return _from_derivatives(self.cx + self.size * math.sin(tau),
                                 self.cy + 0.5 * self.size * math.sin(2.0 * tau), phi,
                                 *self.derivatives(t))

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        return _speed_and_yaw_rate(*self.derivatives(t))


class _Piece(NamedTuple):
    """One line or arc of a waypoint path with its speed-profile phases."""

    t_start: float      # time the piece is entered [s]
    x0: float           # start point [m]
    y0: float
    heading0: float     # heading at the start [rad]
    curvature: float    # κ [1/m], 0 for a line, signed (left > 0) for an arc
    length: float       # [m]
    v_in: float         # speed at the start [m/s]
    v_peak: float       # cruise speed reached [m/s]
    v_out: float        # speed at the end [m/s]
    t_accel: float      # duration of the acceleration phase [s]
    t_cruise: float     # duration of the cruise phase [s]
    t_decel: float      # duration of the deceleration phase [s]


class Waypoints(Reference):
    """A polyline through waypoints, corners filleted, trapezoidal speed profile.

    Geometry: every interior corner of turn angle Δ gets a circular fillet of radius R
    (``corner_radius``), tangent to both legs at distance R tan(|Δ|/2) from the corner;
    where that does not fit (half of each adjacent leg, all of an end leg) R is reduced
    for that corner. The path is thus G1 (continuous heading) with piecewise-constant
    curvature: 0 on legs, ±1/R on fillets.

    Speed: starts and ends at rest, accelerates and brakes at ``acceleration``, cruises
    at ``speed``, and on each fillet is limited to ``max_yaw_rate``·R so that ω_r = υ_r κ
    never exceeds ``max_yaw_rate``. The profile is the time-optimal one under these
    limits (forward/backward pass over the piece boundaries, then a trapezoid or
    triangle per piece). Piecewise constant curvature means ω_r steps at the ends of a
    fillet; ω̇_r = υ̇_r κ omits those (Dirac) steps. Before t = 0 and after the end the
    reference rests at the first and last waypoint.

    Parameters
    ----------
    points : sequence of (x, y) [m], at least 2, consecutive points distinct.
    speed : cruise speed [m/s], > 0.
    acceleration : |υ̇_r| limit [m/s²], > 0.
    corner_radius : fillet radius [m], > 0.
    max_yaw_rate : |ω_r| limit on fillets [rad/s], > 0.

    Raises
    ------
    ValueError
        on coincident consecutive points, a corner sharper than 179°, or bad limits.
    """

    def __init__(self, points: Sequence[Sequence[float]], speed: float = 0.5,
                 acceleration: float = 0.2, corner_radius: float = 1.0,
                 max_yaw_rate: float = 0.25) -> None:
        if len(points) < 2:
            raise ValueError(f'Waypoints: need at least 2 points, got {len(points)}')
        for label, value in (('speed', speed), ('acceleration', acceleration),
                             ('corner_radius', corner_radius),
                             ('max_yaw_rate', max_yaw_rate)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'Waypoints: {label} must be finite and > 0, got {value!r}')
        self.points = [(float(x), float(y)) for x, y in points]
        self.speed, self.acceleration = speed, acceleration
        geometry = self._geometry(self.points, corner_radius)
        self._pieces = self._profile(geometry, speed, acceleration, max_yaw_rate)
        self._starts = [p.t_start for p in self._pieces]
        last = self._pieces[-1]
        self.duration = last.t_start + last.t_accel + last.t_cruise + last.t_decel
        self._end = self._at_piece(last, last.length, 0.0, 0.0)

    @staticmethod
    def _geometry(points: list[tuple[float, float]], radius: float) -> list[tuple]:
        """Pieces (x0, y0, heading0, curvature, length) of the filleted polyline."""
        n_legs = len(points) - 1
        legs = []
        for i in range(n_legs):
            dx = points[i + 1][0] - points[i][0]
            dy = points[i + 1][1] - points[i][1]
            length = math.hypot(dx, dy)
            if not length > 1e-9:
                raise ValueError(f'Waypoints: points {i} and {i + 1} coincide')
            legs.append((math.atan2(dy, dx), length))
        # Continuous headings along the path (each turn in (−π, π)).
        headings = [legs[0][0]]
        turns = [0.0]  # turns[i] = turn at interior point i (index 0 unused)
        for i in range(1, n_legs):
            turn = math.remainder(legs[i][0] - legs[i - 1][0], 2.0 * math.pi)
            if abs(turn) > MAX_CORNER_ANGLE:
                raise ValueError(f'Waypoints: the turn at point {i} is '
                                 f'{math.degrees(abs(turn)):.1f} deg, more than '
                                 f'{math.degrees(MAX_CORNER_ANGLE):.0f} deg')
            turns.append(turn)
            headings.append(headings[-1] + turn)
        tangent = [0.0] * (n_legs + 1)   # distance from point i to the fillet's ends
        radii = [0.0] * (n_legs + 1)
        for i in range(1, n_legs):
            half_tan = math.tan(0.5 * abs(turns[i]))
            if half_tan < 1e-12:
                continue
            room_in = legs[i - 1][1] if i - 1 == 0 else 0.5 * legs[i - 1][1]
            room_out = legs[i][1] if i == n_legs - 1 else 0.5 * legs[i][1]
            radii[i] = min(radius, min(room_in, room_out) / half_tan)
            tangent[i] = radii[i] * half_tan
        pieces = []
        for i in range(n_legs):
            heading = headings[i]
            c, s = math.cos(heading), math.sin(heading)
            if i > 0 and radii[i] > 0.0:  # fillet at point i, entered on leg i−1
                prev = headings[i - 1]
                px, py = points[i]
                d = tangent[i]
                pieces.append((px - d * math.cos(prev), py - d * math.sin(prev), prev,
                               math.copysign(1.0 / radii[i], turns[i]),
                               radii[i] * abs(turns[i])))
            length = legs[i][1] - tangent[i] - tangent[i + 1]
            if length > 1e-9:
                x0, y0 = points[i][0] + tangent[i] * c, points[i][1] + tangent[i] * s
                pieces.append((x0, y0, heading, 0.0, length))
        return pieces

    @staticmethod
    def _profile(geometry: list[tuple], speed: float, accel: float,
                 max_yaw_rate: float) -> list[_Piece]:
        limits = [min(speed, max_yaw_rate / abs(k)) if k != 0.0 else speed
                  for (_, _, _, k, _) in geometry]
        m = len(geometry)
        node = [0.0] * (m + 1)  # speeds at the piece boundaries, at rest at both ends
        for j in range(1, m):
            node[j] = min(limits[j - 1], limits[j])
        for j in range(m):  # forward pass: reachable by accelerating
            node[j + 1] = min(node[j + 1], math.sqrt(node[j] ** 2 + 2.0 * accel
                                                     * geometry[j][4]))
        for j in range(m - 1, -1, -1):  # backward pass: able to brake
            node[j] = min(node[j], math.sqrt(node[j + 1] ** 2 + 2.0 * accel
                                             * geometry[j][4]))
        pieces, t = [], 0.0
        for j, (x0, y0, heading, k, length) in enumerate(geometry):
            v_in, v_out = node[j], node[j + 1]
            v_peak = min(limits[j], math.sqrt(accel * length + 0.5 * (v_in ** 2
                                                                       + v_out ** 2)))
            v_peak = max(v_peak, v_in, v_out)
            d_acc = (v_peak ** 2 - v_in ** 2) / (2.0 * accel)
            d_dec = (v_peak ** 2 - v_out ** 2) / (2.0 * accel)
            d_cruise = max(0.0, length - d_acc - d_dec)
            t_acc, t_dec = (v_peak - v_in) / accel, (v_peak - v_out) / accel
            t_cruise = d_cruise / v_peak if v_peak > 0.0 else 0.0
            pieces.append(_Piece(t, x0, y0, heading, k, length, v_in, v_peak, v_out,
                                 t_acc, t_cruise, t_dec))
            t += t_acc + t_cruise + t_dec
        return pieces

    def _at_piece(self, p: _Piece, s: float, v: float, v_dot: float) -> ReferenceState:
        k = p.curvature
        if k == 0.0:
            x = p.x0 + s * math.cos(p.heading0)
            y = p.y0 + s * math.sin(p.heading0)
            return ReferenceState(x, y, p.heading0, v, 0.0, 0.0)
        heading = p.heading0 + k * s
        x = p.x0 + (math.sin(heading) - math.sin(p.heading0)) / k
        y = p.y0 - (math.cos(heading) - math.cos(p.heading0)) / k
        return ReferenceState(x, y, heading, v, v * k, v_dot * k)

    def sample(self, t: float) -> ReferenceState:
        if t >= self.duration:
            return self._end
        if t <= 0.0:
            return self._at_piece(self._pieces[0], 0.0, 0.0, 0.0)
        p = self._pieces[bisect.bisect_right(self._starts, t) - 1]
        tau = t - p.t_start
        a = self.acceleration
        if tau < p.t_accel:
            v = p.v_in + a * tau
            return self._at_piece(p, (p.v_in + 0.5 * a * tau) * tau, v, a)
        s = (p.v_in + p.v_peak) * 0.5 * p.t_accel
        tau -= p.t_accel
        if tau < p.t_cruise:
            return self._at_piece(p, s + p.v_peak * tau, p.v_peak, 0.0)
        s += p.v_peak * p.t_cruise
        tau = min(tau - p.t_cruise, p.t_decel)
        v = p.v_peak - a * tau
        return self._at_piece(p, min(s + (p.v_peak - 0.5 * a * tau) * tau, p.length), v, -a)


class TimeScaled(Reference):
    r"""A reference run along the same path with a progress s(t) within the limits.

    The progress slows where the path's speed or yaw rate would exceed the limits (time
    scaling, Hollerbach 1984).

    The base reference p(s) is re-timed by ṡ = σ(s), with

    .. math:: \sigma_0(s) = \min\Big(1, \frac{\upsilon_{max}}{\upsilon_r(s)},
        \frac{\omega_{max}}{|\omega_r(s)|}\Big), \qquad
        \sigma(s) = \min_u \big(\sigma_0(u) + k |u - s|\big)

    so that υ(t) = υ_r(s) σ(s) ≤ υmax and |ω(t)| = |ω_r(s)| σ(s) ≤ ωmax: the vehicle is
    asked to stay on the same curve, more slowly where it bends hard, instead of
    chasing a point it cannot keep up with (the paper's trifolium needs 0.70 rad/s at
    its petal tips against ωmax = 0.3). The envelope σ ≤ σ0 with |dσ/ds| ≤ k starts to
    slow down before a sharp bend and speeds up gradually after it: where σ0 jumps (a
    waypoint fillet's curvature step) the speed would otherwise jump too. The pose is
    the base's at s(t); the rates are υ_r σ, ω_r σ and ω̇ = σ (ω̇_r σ + ω_r dσ/ds).

    σ depends on the path only, so s(t) is computed once, independent of the vehicle:
    the reference stays a pure function of time (the reference node publishes it
    unchanged). σ0 is tabulated every ``step`` of s and the envelope taken on that grid
    (σ linear between nodes, and never above σ0 at the sampled s); s(t) is integrated by
    RK4 on a grid of ``step`` in t and interpolated by cubic Hermite (s and ṡ known at
    the nodes). Both tables are extended on demand, always from the start, so the
    values do not depend on the order of the queries; :func:`make_reference` therefore
    lets the time-scaled references of one configuration share them within a thread
    (every run of a campaign in one process re-times the same path once).

    Parameters
    ----------
    base : the reference whose path is followed.
    max_speed, max_yaw_rate : limits [m/s], [rad/s] of the re-timed reference, > 0.
    rate_limit : k [1/s], the largest |dσ/ds|, > 0.
    step : grid [s].
    speed_lead_time : T [s] ≥ 0. The speed υ of the sample at t is the re-timed speed at
        t + T (the pose, ω and ω̇ stay those at t): a speed feed-forward for a speed loop
        that lags the command by about T, so that the vehicle is at the bend's speed when
        it reaches the bend instead of T later (docs/mpc.md §8). 0: υ at t.
    speed_lead_time_accelerating : T_a [s], 0 ≤ T_a; used instead of T where the speed
        at t + T is larger than at t (None: T).
    tables : tables to use and extend, shared with the other TimeScaled of the same
        base, limits and step (:func:`make_reference`); None: its own.
    """

    #: Largest step ahead of the sampled times that one call may integrate [s].
    MAX_EXTENSION = 3600.0
    #: Remembered re-timed states kept before the older ones are dropped (see sample),
    #: and at most kept after that (a 5 s lead at 1 kHz remembers 5000 states ahead).
    MEMO_MIN_SIZE = 512
    MEMO_MAX_SIZE = 8192

    def __init__(self, base: Reference, max_speed: float, max_yaw_rate: float,
                 rate_limit: float = 0.5, step: float = 0.01,
                 speed_lead_time: float = 0.0,
                 speed_lead_time_accelerating: float | None = None,
                 tables: 'RetimingTables | None' = None) -> None:
        if not (max_speed > 0.0 and max_yaw_rate > 0.0 and rate_limit > 0.0
                and step > 0.0):
            raise ValueError('TimeScaled: max_speed, max_yaw_rate, rate_limit and step '
                             'must be > 0')
        if speed_lead_time_accelerating is None:
            speed_lead_time_accelerating = speed_lead_time
        for label, value in (('speed_lead_time', speed_lead_time),
                             ('speed_lead_time_accelerating', speed_lead_time_accelerating)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'TimeScaled: {label} must be finite and >= 0, got {value!r}')
        self.speed_lead_time = float(speed_lead_time)
        self.speed_lead_time_accelerating = float(speed_lead_time_accelerating)
        self.base = base
        self.max_speed = float(max_speed)
        self.max_yaw_rate = float(max_yaw_rate)
        self.rate_limit = float(rate_limit)
        self.step = float(step)
        # Envelope half-width in grid nodes: beyond 1/k the cone exceeds σ0 ≤ 1.
        self._window = int(math.ceil(1.0 / (self.rate_limit * self.step)))
        self._tables = tables = tables if tables is not None else RetimingTables()
        self._raw = tables.raw            # σ0 at s = i·step
        self._sigma = tables.sigma        # σ at s = i·step
        self._s = tables.s                # s at t = n·step
        self._rate = tables.rate          # σ(s) at those nodes
        with tables.lock:
            if not self._s:
                self._rate.append(self.rate_at(0.0))
                self._s.append(0.0)
        self._memo: dict[float, ReferenceState] = {}   # t -> _timed(t), see sample
        self._memo_limit = self.MEMO_MIN_SIZE

    def _raw_rate(self, v: float, omega: float) -> float:
        """σ0 for the base's speed ``v`` and yaw rate ``omega``."""
        sigma = 1.0
        if v > self.max_speed:
            sigma = self.max_speed / v
        if abs(omega) * sigma > self.max_yaw_rate:
            sigma = self.max_yaw_rate / abs(omega)
        return sigma

    def _extend_sigma(self, index: int) -> None:
        """Tabulate σ up to grid node ``index`` (σ0 up to ``index`` + window)."""
        if len(self._sigma) > index:
            return
        import numpy as np
        w, h = self._window, self.step
        with self._tables.lock:
            while len(self._sigma) <= index:
                start = len(self._sigma)
                stop = start + 2048
                while len(self._raw) < stop + w + 1:
                    self._raw.append(self._raw_rate(
                        *self.base.speed_and_yaw_rate(len(self._raw) * h)))
                raw = np.asarray(self._raw)
                env = raw[start:stop].copy()
                for d in range(1, w + 1):
                    cone = self.rate_limit * d * h
                    env = np.minimum(env, raw[start + d:stop + d] + cone)
                    lo = max(0, start - d)
                    shifted = raw[lo:stop - d]
                    if len(shifted) < stop - start:   # before s = 0: no constraint
                        shifted = np.concatenate([np.full(stop - start - len(shifted),
                                                          np.inf), shifted])
                    env = np.minimum(env, shifted + cone)
                self._sigma.extend(float(v) for v in env)

    def _sigma_and_slope(self, s: float) -> tuple[float, float]:
        """σ(s) (linear between grid nodes) and dσ/ds; s < 0 takes σ(0)."""
        if s <= 0.0:
            self._extend_sigma(1)
            return self._sigma[0], 0.0
        u = s / self.step
        i = int(u)
        sigma = self._sigma
        if i + 1 >= len(sigma):   # (tested here: a call per sample costs more than the test)
            self._extend_sigma(i + 1)
        a, b = sigma[i], sigma[i + 1]
        return a + (b - a) * (u - i), (b - a) / self.step

    def rate_at(self, s: float) -> float:
        """σ(s) = ds/dt ∈ (0, 1] (linear between the grid nodes).

        The σ of :meth:`_sigma_and_slope`, without the slope.
        """
        if s <= 0.0:
            return self._sigma_and_slope(s)[0]
        u = s / self.step
        i = int(u)
        sigma = self._sigma
        if i + 1 >= len(sigma):
            self._extend_sigma(i + 1)
        a = sigma[i]
        return a + (sigma[i + 1] - a) * (u - i)

    def _extend(self, n: int) -> None:
        s_list, r_list, h = self._s, self._rate, self.step
        with self._tables.lock:
            while len(s_list) <= n:
                s, k1 = s_list[-1], r_list[-1]
                k2 = self.rate_at(s + 0.5 * h * k1)
                k3 = self.rate_at(s + 0.5 * h * k2)
                k4 = self.rate_at(s + h * k3)
                s_next = s + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
                # σ(s) first: readers check the length of s (lock-free).
                r_list.append(self.rate_at(s_next))
                s_list.append(s_next)
        if len(s_list) > RetimingTables.MAX_SHARED_NODES:
            _unshare(self._tables)

    def progress(self, t: float) -> float:
        """s(t) [s of the base reference]; s = σ(0) t before t = 0.

        Raises ValueError for a time more than ``MAX_EXTENSION`` s beyond the times
        sampled so far: s(t) is integrated from t = 0, so a jump far ahead (a clock
        jump, not a run) would take minutes.
        """
        if not math.isfinite(t):
            raise ValueError(f'TimeScaled: time must be finite, got {t!r}')
        if t <= 0.0:
            return self._rate[0] * t
        n = int(t / self.step)
        if n + 1 >= len(self._s):   # beyond the table (else t < the last node)
            known = (len(self._s) - 1) * self.step
            if t > known + self.MAX_EXTENSION:
                raise ValueError(f'TimeScaled: t = {t:g} s is more than '
                                 f'{self.MAX_EXTENSION:g} s beyond the times sampled so far '
                                 f'({known:g} s); the time-scaled reference is integrated '
                                 'from t = 0')
            self._extend(n + 1)
        h = self.step
        u = t / h - n
        s0, s1, r0, r1 = self._s[n], self._s[n + 1], self._rate[n], self._rate[n + 1]
        u2, u3 = u * u, u * u * u
        return ((2 * u3 - 3 * u2 + 1) * s0 + (u3 - 2 * u2 + u) * h * r0
                + (-2 * u3 + 3 * u2) * s1 + (u3 - u2) * h * r1)

    def _speed_at(self, t: float) -> float:
        """Re-timed speed υ_r(s) σ(s) at s = s(t): ``sample(t).v`` without the lead."""
        s = self.progress(t)
        v, omega = self.base.speed_and_yaw_rate(s)
        # Between grid nodes the linear σ may exceed σ0 by O(step²): never above it.
        return v * min(self.rate_at(s), self._raw_rate(v, omega))

    def _timed(self, t: float) -> ReferenceState:
        """Return the re-timed state at t, without the speed lead.

        The re-timed state at t, without the speed lead: the base's pose at s(t), υ_r σ,
        ω_r σ and σ (ω̇_r σ + ω_r dσ/ds).
        """
        s = self.progress(t)
        ref = self.base.sample(s)
        sigma, d_sigma = self._sigma_and_slope(s)
        sigma = min(sigma, self._raw_rate(ref.v, ref.omega))   # as in _speed_at
        return ReferenceState(ref.x, ref.y, ref.phi, ref.v * sigma, ref.omega * sigma,
                              sigma * (ref.omega_dot * sigma + ref.omega * d_sigma))

    def sample(self, t: float) -> ReferenceState:
        if self.speed_lead_time <= 0.0:
            return self._timed(t)
        # With a speed lead, the re-timed states are remembered by their time (the float):
        # a loop sampling every h asks at t + T for a time it samples again later (the
        # runner's t_k + 0.75 is t_{k+150} to the bit at 98 % of the ticks, t_k + 0.6 is
        # the t_j + 0.75 of a tick 30 earlier at 70 %), so most states are computed once.
        memo = self._memo
        state = memo.get(t)
        if state is None:
            state = memo[t] = self._timed(t)
        t_lead = t + self.speed_lead_time
        ahead = memo.get(t_lead)
        if ahead is None:
            ahead = memo[t_lead] = self._timed(t_lead)
        v_ahead = ahead.v
        lead_up = self.speed_lead_time_accelerating
        if abs(v_ahead) > abs(state.v) and lead_up != self.speed_lead_time:
            # Speeding up: the (shorter) lead of the accelerations, the speed only if it
            # is not remembered.
            ahead = memo.get(t + lead_up)
            v_ahead = ahead.v if ahead is not None else self._speed_at(t + lead_up)
        if len(memo) > self._memo_limit:
            # Forget the states before t (a loop runs forward), amortised O(1); all of
            # them if that leaves too many (queries running backwards, say).
            memo = {time: kept for time, kept in memo.items() if time >= t}
            self._memo = memo if len(memo) <= self.MEMO_MAX_SIZE else {}
            self._memo_limit = max(self.MEMO_MIN_SIZE, 2 * len(self._memo))
        return ReferenceState(state.x, state.y, state.phi, v_ahead, state.omega,
                              state.omega_dot)


class RetimingTables:
    """The tables of a :class:`TimeScaled`.

    σ0 and σ every ``step`` of s, s and σ(s) every ``step`` of t. They are a function of the base
    path, the limits and the step only (extended on demand, always from the start), so TimeScaled
    objects of the same configuration can share them (:func:`make_reference`). They are only
    appended to, under ``lock``, and every value is final once written, so readers need no lock.
    """

    #: Tables longer than this many nodes (1000 s of a 10 ms step; about 13 MB for the
    #: four) are no longer offered for sharing, so that a process does not keep the
    #: tables of a long run after it.
    MAX_SHARED_NODES = 100_000

    __slots__ = ('raw', 'sigma', 's', 'rate', 'lock')

    def __init__(self) -> None:
        self.raw: list[float] = []
        self.sigma: list[float] = []
        self.s: list[float] = []
        self.rate: list[float] = []
        self.lock = threading.RLock()   # reentrant: extending s extends σ


#: Per thread: configuration key -> RetimingTables, the most recently used last.
_shared = threading.local()
#: Configurations whose tables a thread keeps for sharing.
MAX_SHARED_CONFIGURATIONS = 4


def shared_tables(key: Hashable) -> RetimingTables:
    """Return the tables this thread shares among the TimeScaled of configuration ``key``.

    The tables this thread shares among the TimeScaled of configuration ``key`` (new
    ones the first time).
    """
    cache = getattr(_shared, 'tables', None)
    if cache is None:
        cache = _shared.tables = collections.OrderedDict()
    tables = cache.pop(key, None)
    if tables is None:
        tables = RetimingTables()
    cache[key] = tables
    while len(cache) > MAX_SHARED_CONFIGURATIONS:
        cache.popitem(last=False)
    return tables


def _unshare(tables: RetimingTables) -> None:
    """Stop offering ``tables`` for sharing (its users keep it)."""
    cache = getattr(_shared, 'tables', None)
    if cache:
        for key, value in list(cache.items()):
            if value is tables:
                del cache[key]


def distance_to_path(reference: Reference, x: Sequence[float], y: Sequence[float],
                     path_duration: float, resolution: float = 0.001):
    """Distance [m] of each point (x, y) to the path of ``reference``.

    The path is the one traced over [0, ``path_duration``] of the reference's own time (for
    a :class:`TimeScaled`, pass its base).

    The path is sampled every ``resolution`` [m] of arc length at most (nearest sample
    by a k-d tree), so the result exceeds the true distance by at most resolution/2.
    """
    import numpy as np
    import scipy.spatial
    v_peak = max(reference.sample(t).v for t in np.linspace(0.0, path_duration, 2001))
    n = max(2, int(math.ceil(path_duration * max(v_peak, 1e-9) / resolution)) + 1)
    times = np.linspace(0.0, path_duration, n)
    points = np.array([(r.x, r.y) for r in map(reference.sample, times)])
    tree = scipy.spatial.cKDTree(points)
    distance, _ = tree.query(np.column_stack([np.asarray(x, float), np.asarray(y, float)]))
    return distance


@dataclasses.dataclass(frozen=True)
class ReferenceConfig:
    """Which reference to follow and its parameters (prefixed by the kind).

    Only the fields of the selected ``kind`` are used; all are validated.
    """

    kind: str = param('trifolium', '1', 'reference trajectory', choices=KINDS)
    trifolium_size: float = param(3.0, 'm', 'kappa of the trifolium (Section V: 3)',
                                  minimum=0.0, exclusive_minimum=True)
    trifolium_angular_frequency: float = param(
        math.pi / 45.0, 'rad/s', 'Omega_r of the trifolium (Section V: pi/45, one figure '
        'every 45 s)', minimum=0.0, exclusive_minimum=True)
    circle_center: tuple[float, float] = param((0.0, 0.0), 'm', 'centre of the circle')
    circle_radius: float = param(2.0, 'm', 'radius of the circle', minimum=0.0,
                                 exclusive_minimum=True)
    circle_speed: float = param(0.5, 'm/s', 'speed on the circle', minimum=0.0,
                                exclusive_minimum=True)
    circle_direction: str = param('ccw', '1', 'sense of travel on the circle',
                                  choices=('ccw', 'cw'))
    circle_start_angle: float = param(0.0, 'rad', 'polar angle of the start point about '
                                      'the centre')
    line_start: tuple[float, float] = param((0.0, 0.0), 'm', 'start point of the line '
                                            '(kinds hold, cmd_vel, path: the start pose)')
    line_heading: float = param(0.0, 'rad', 'direction of the line (REP 103: 0 = +x; kinds '
                                'hold, cmd_vel, path: the start heading)')
    line_speed: float = param(0.5, 'm/s', 'speed along the line', minimum=0.0,
                              exclusive_minimum=True)
    figure_eight_center: tuple[float, float] = param((0.0, 0.0), 'm',
                                                     'crossing point of the figure eight')
    figure_eight_size: float = param(3.0, 'm', 'half-width a of the lemniscate of Gerono',
                                     minimum=0.0, exclusive_minimum=True)
    figure_eight_period: float = param(60.0, 's', 'time to run the whole figure eight',
                                       minimum=0.0, exclusive_minimum=True)
    waypoints_x: tuple[float, ...] = param((0.0, 4.0, 4.0, 0.0), 'm',
                                           'x of the waypoints, in order')
    waypoints_y: tuple[float, ...] = param((0.0, 0.0, 4.0, 4.0), 'm',
                                           'y of the waypoints (same length as waypoints_x)')
    waypoints_speed: float = param(0.5, 'm/s', 'cruise speed between waypoints',
                                   minimum=0.0, exclusive_minimum=True)
    waypoints_acceleration: float = param(0.2, 'm/s^2', 'acceleration and braking limit '
                                          'of the speed profile', minimum=0.0,
                                          exclusive_minimum=True)
    waypoints_corner_radius: float = param(1.0, 'm', 'radius of the corner fillets '
                                           '(reduced where a leg is too short)',
                                           minimum=0.0, exclusive_minimum=True)
    waypoints_max_yaw_rate: float = param(0.25, 'rad/s', 'yaw-rate limit on the fillets '
                                          '(keep below the generator max_yaw_rate)',
                                          minimum=0.0, exclusive_minimum=True)
    cmd_vel_timeout: float = param(
        0.5, 's', 'cmd_vel: a command older than this (by its stamp) is refused; this long '
        'after the last accepted one the reference brakes to rest', minimum=0.05,
        maximum=10.0)
    cmd_vel_stamped: bool = param(
        True, '1', 'cmd_vel: true: geometry_msgs/TwistStamped (stamp checked); false: '
        'geometry_msgs/Twist (stamped on receipt)')
    commanded_max_speed: float = param(
        0.5, 'm/s', 'cmd_vel, path: |speed| limit of the reference (keep below the generator '
        'max_speed: the feedback of eq. (9) needs headroom)', minimum=0.0,
        exclusive_minimum=True, maximum=1.5)
    commanded_max_acceleration: float = param(
        0.3, 'm/s^2', 'cmd_vel, path: |acceleration| limit of the reference speed',
        minimum=0.0, exclusive_minimum=True, maximum=2.0)
    commanded_max_yaw_rate: float = param(
        0.25, 'rad/s', 'cmd_vel, path: |yaw rate| limit of the reference (keep below the '
        'generator max_yaw_rate)', minimum=0.0, exclusive_minimum=True, maximum=0.3)
    commanded_max_yaw_acceleration: float = param(
        0.5, 'rad/s^2', 'cmd_vel, path: |yaw acceleration| limit of the reference (keep '
        'below the generator max_yaw_acceleration)', minimum=0.0, exclusive_minimum=True,
        maximum=2.0)
    path_speed: float = param(
        0.3, 'm/s', 'path: cruise speed along the received path (at most '
        'commanded_max_speed)', minimum=0.0, exclusive_minimum=True, maximum=1.5)
    path_lookahead: float = param(
        0.5, 'm', 'path: the reference steers towards the point this far ahead on the path '
        '(pure pursuit; shorter: closer to the corners, sharper turns)', minimum=0.05,
        maximum=10.0)
    time_scaling: bool = param(
        True, '1', 'run the reference along its path with a progress that slows where '
        'its speed or yaw rate would exceed path_max_speed, path_max_yaw_rate (any kind; '
        'paper: false)')
    path_max_speed: float = param(
        1.2, 'm/s', 'time_scaling: speed limit of the reference (keep below the '
        'generator max_speed: the feedback of eq. (9) needs headroom)', minimum=0.0,
        exclusive_minimum=True)
    path_max_yaw_rate: float = param(
        0.2, 'rad/s', 'time_scaling: yaw-rate limit of the reference (keep below the '
        'generator max_yaw_rate)', minimum=0.0, exclusive_minimum=True)
    path_progress_rate_limit: float = param(
        0.5, '1/s', 'time_scaling: largest change of the progress rate ds/dt per second '
        'of path (the speed changes by at most this fraction of the path speed per '
        'second, and slows before a sharp bend)', minimum=0.01, maximum=100.0)
    path_speed_lead_time: float = param(
        0.75, 's', 'time_scaling: the reference speed (the feed-forward of eq. (9)) is the '
        're-timed speed this long ahead, for a speed loop that lags its command by about '
        'as much: the vehicle is slow when it reaches a bend or the end instead of later '
        '(sharp corners: 0.52 m off the path without it, 0.08 m with 0.75 s; '
        'docs/mpc.md §8). 0: the speed at t', minimum=0.0, maximum=5.0)
    path_speed_lead_time_accelerating: float = param(
        0.6, 's', 'time_scaling: the lead of path_speed_lead_time where the speed ahead is '
        'larger (speeding up). Shorter than the braking lead: with 0.75 s the trifolium '
        'under noise recovered more slowly from the forward push at 30 s (the vehicle no '
        'longer lags the reference point); 0.6 s is the shortest that still brings the '
        'sharp corners within 0.1 m of the end point (docs/mpc.md §8)', minimum=0.0,
        maximum=5.0)

    def validate(self) -> None:
        if len(self.waypoints_x) != len(self.waypoints_y):
            raise ConfigError(f'waypoints_y: has {len(self.waypoints_y)} values but '
                              f'waypoints_x has {len(self.waypoints_x)}')
        if len(self.waypoints_x) < 2:
            raise ConfigError(f'waypoints_x: need at least 2 waypoints, got '
                              f'{len(self.waypoints_x)}')
        if self.kind == 'waypoints':
            try:
                _make_waypoints(self)
            except ValueError as err:
                raise ConfigError(f'waypoints_x: {err}') from err


def _make_waypoints(config: ReferenceConfig) -> Waypoints:
    return Waypoints(list(zip(config.waypoints_x, config.waypoints_y)),
                     speed=config.waypoints_speed,
                     acceleration=config.waypoints_acceleration,
                     corner_radius=config.waypoints_corner_radius,
                     max_yaw_rate=config.waypoints_max_yaw_rate)


def make_reference(config: ReferenceConfig | None = None) -> Reference:
    """Build the reference selected by ``config.kind`` (default: the paper's trifolium).

    Time-scaled (:class:`TimeScaled`) if ``config.time_scaling``.
    """
    config = config if config is not None else ReferenceConfig()
    config.validate()
    if config.kind in COMMANDED_KINDS:
        return make_commanded(config)
    base = _make_base_reference(config)
    if config.time_scaling:
        # The tables depend on neither lead time: one key for every lead.
        key = dataclasses.replace(config, path_speed_lead_time=0.0,
                                  path_speed_lead_time_accelerating=0.0)
        return TimeScaled(base, config.path_max_speed, config.path_max_yaw_rate,
                          config.path_progress_rate_limit,
                          speed_lead_time=config.path_speed_lead_time,
                          speed_lead_time_accelerating=config.path_speed_lead_time_accelerating,
                          tables=shared_tables(key))
    return base


def _make_base_reference(config: ReferenceConfig) -> Reference:
    if config.kind == 'trifolium':
        return Trifolium(config.trifolium_size, config.trifolium_angular_frequency)
    if config.kind == 'circle':
        return Circle(config.circle_center, config.circle_radius, config.circle_speed,
                      config.circle_direction, config.circle_start_angle)
    if config.kind == 'line':
        return StraightLine(config.line_start, config.line_heading, config.line_speed)
    if config.kind == 'hold':       # stand still: the line's start, at zero speed
        return StraightLine(config.line_start, config.line_heading, 0.0)
    if config.kind == 'figure_eight':
        return FigureEight(config.figure_eight_center, config.figure_eight_size,
                           config.figure_eight_period)
    if config.kind == 'waypoints':
        return _make_waypoints(config)
    raise ConfigError(f'kind: {config.kind!r} is not one of {list(KINDS)}')


def make_commanded(config: ReferenceConfig,
                   t0: float = 0.0) -> CmdVelReference | PathReference:
    """Return the reference of a commanded kind (``cmd_vel``, ``path``).

    The reference of a commanded kind (``cmd_vel``, ``path``), at rest at the start
    pose (``line_start``, ``line_heading``) at time t0 [s] until commanded.
    """
    limits = UnicycleLimits(config.commanded_max_speed, config.commanded_max_acceleration,
                            config.commanded_max_yaw_rate,
                            config.commanded_max_yaw_acceleration)
    start = (*config.line_start, config.line_heading)
    if config.kind == 'cmd_vel':
        return CmdVelReference(limits, config.cmd_vel_timeout, start=start, t0=t0)
    if config.kind == 'path':
        return PathReference(limits, config.path_speed, config.path_lookahead, start=start,
                             t0=t0)
    raise ConfigError(f'kind: {config.kind!r} is not one of {list(COMMANDED_KINDS)}')
