"""A waypoint path: a polyline with circular fillets and a trapezoidal speed profile."""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple, Sequence

from .reference_state import Reference, ReferenceState

#: Sharpest corner a waypoint list may have [rad] (a U-turn has no fillet).
MAX_CORNER_ANGLE = math.radians(179.0)


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
