"""Wheel slip from the disagreement of the wheels with the IMU (pure python, no ROS).

A wheel that spins or skids makes its encoder report a speed the vehicle does not have;
braking on it tips the vehicle over. This monitor tells which wheel's speed is physical
and gives the estimator a distance rolled x_v that follows only those.

The physics: model (1) linearised about upright has one combination of the states that the
drive torque does not drive, w = υ + q θ̇ with q = J_θ / (mp l): ẇ = g θ + d (d: the
external acceleration, a slope, a push; docs/estimation.md). It holds for any torque,
so a wheel speed whose w jumps faster than g θ + d allows has not been moved by the ground:
the wheel slips. Each wheel gives its own estimate of the axle speed with the gyro's yaw
rate ω, υ_l + (d/2) ω and υ_r − (d/2) ω, so one wheel slipping alone is told apart from the
other. A complementary filter of w, ŵ̇ = g θ + d̂ + 2 ω_c (w − ŵ), d̂̇ = ω_c² (w − ŵ),
fed with the wheels that do not slip, tracks the physical speed.

Rules per sample (period h):
    - a wheel starts slipping when its residual acceleration, (w_i − w_i,prev)/h − g θ − d̂
      (mean of the last two), exceeds ``max_acceleration`` in magnitude (no ground force does
      that: friction gives at most μ g ≈ 8 m/s², the paper's push 10 m/s²) in the direction
      of its motor's torque: a wheel spun up by a driving torque or locked by a braking one.
      A wheel stopped against the torque is an obstacle's force (a bump's edge), real
      motion, not slip (docs/estimation.md has the measurements);
    - it stops when the two wheels' w agree within ``agreement`` and their mean is within
      3 ``agreement`` of ŵ for ``hold`` s (a wheel that spun alone rolls with the other
      again; both that spun roll at the speed the IMU followed), or, once it has lasted
      ``longest`` s, when the two wheels agree with each other for ``hold`` s whatever ŵ
      says (ŵ may have coasted off the truth; the wheels are believed again and ŵ restarts
      from them). Never while the wheels disagree with each other and with ŵ: wheels that
      spin in turns on an edge they cannot climb stay out of x_v however long they spin;
    - nothing is judged for the first 3 / ω_c after the start (the filter converging);
    - the measured w is the mean of the gripping wheels'; with none, the least of the two
      wheels' and ŵ's prediction under a driving torque (spin only makes a wheel faster),
      the greatest under braking;
    - x_v passes unchanged while no wheel slips; while one does, x_v advances by the speed
      of the measured w, and the difference stays as an offset (the distance the slipping
      wheel spun away; the GPS corrects the position).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from wip_description.params import ModelParams


class SlipState(NamedTuple):
    """What the monitor says at one sample."""

    x_v: float               #: the distance rolled [m] to use (slip taken out)
    left: bool               #: the left wheel slips
    right: bool              #: the right wheel slips
    offset: float            #: distance [m] the wheels spun (or skidded) away so far
    speed: float             #: the physical axle speed ŵ − q θ̇ [m/s]

    @property
    def slipping(self) -> bool:
        return self.left or self.right


class SlipMonitor:
    """See the module docstring.

    Parameters
    ----------
    params : the controllers' model (r, d, J_θ, mp l, g).
    max_acceleration : [m/s²] residual beyond which a wheel slips.
    agreement : [m/s] |w_l − w_r| under which the wheels grip again (after ``hold`` s).
    bandwidth : ω_c [rad/s] of the complementary filter of w.
    hold : [s] how long the wheels must agree to be believed again.
    longest : [s] after it, two wheels that roll alike are believed whatever ŵ says.
    relative_to_body : the encoders measure the wheels against the body (the default).
    """

    def __init__(self, params: ModelParams, max_acceleration: float = 20.0,
                 agreement: float = 0.1, bandwidth: float = 3.0, hold: float = 0.05,
                 longest: float = 1.0, relative_to_body: bool = True) -> None:
        for name, value in (('max_acceleration', max_acceleration), ('agreement', agreement),
                            ('bandwidth', bandwidth), ('hold', hold), ('longest', longest)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'SlipMonitor: {name} must be finite and > 0, got {value!r}')
        self.q = params.pitch_inertia / (params.body_mass * params.com_height)
        # Encoders on the body: a wheel rolls at r (φ̇_i + θ̇); the gyro's θ̇, not the
        # difference of the pitch angle, whose noise (0.002 rad) differentiated twice is
        # tens of m/s².
        self.body_rate_gain = params.wheel_radius if relative_to_body else 0.0
        self.g = params.gravity
        self.half_track = 0.5 * params.track_width
        self.max_acceleration, self.agreement = max_acceleration, agreement
        self.bandwidth, self.hold, self.longest = bandwidth, hold, longest
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next sample starts the monitor."""
        self._last: tuple | None = None     # (t, s_l, s_r, x_v, θ̇)
        self._w_hat = 0.0
        self._d_hat = 0.0
        self._residual = [0.0, 0.0]          # previous residual acceleration per wheel
        self._w_prev: tuple | None = None
        self._slipping = [False, False]
        self._agree_since = math.inf        # since when the wheels agree with ŵ
        self._together_since = math.inf     # since when the two wheels agree
        self._since = [math.inf, math.inf]   # when each wheel's slip began
        self._start: float | None = None
        self.offset = 0.0
        self.events = 0                      #: slips begun since the start

    @property
    def slipping_wheels(self) -> tuple[bool, bool]:
        """Whether the (left, right) wheel slips now."""
        return self._slipping[0], self._slipping[1]

    def update(self, t: float, left: float, right: float, x_v: float, theta: float,
               pitch_rate: float, yaw_rate: float, tau_left: float = 0.0,
               tau_right: float = 0.0) -> SlipState:
        """Take one sample; return the x_v to use.

        ``left``, ``right``: r φ_i [m], each encoder's angle times the wheel radius;
        ``x_v`` the odometry's; θ [rad], θ̇, ω [rad/s] from the IMU; the wheel torques
        [N m] applied over the last period.
        """
        if not math.isfinite(t + left + right + x_v + theta + pitch_rate + yaw_rate
                             + tau_left + tau_right):
            raise ValueError('SlipMonitor.update: non-finite input (nothing changed)')
        last = self._last
        if last is None or t <= last[0]:
            if last is None:
                self._w_hat = self.q * pitch_rate
                self._start = t
            self._last = (t, left, right, x_v, pitch_rate)
            return SlipState(x_v - self.offset, *self._slipping, self.offset,
                             self._w_hat - self.q * pitch_rate)
        t0, left0, right0, x_v0, rate0 = last
        h = t - t0
        q, g = self.q, self.g
        turn = self.half_track * yaw_rate
        body = (q + self.body_rate_gain) * 0.5 * (pitch_rate + rate0)
        w_now = ((left - left0) / h + turn + body, (right - right0) / h - turn + body)
        model = g * theta + self._d_hat
        w_prev = w_now if self._w_prev is None else self._w_prev
        self._detect(t, h, w_now, w_prev, model, (tau_left, tau_right))
        self._w_prev = w_now
        slipping = self._slipping
        if slipping[0] or slipping[1]:
            self._release(t, w_now)
        gripping = [w for w, slips in zip(w_now, slipping) if not slips]
        if gripping:
            measured = sum(gripping) / len(gripping)
        else:
            # Both slip: a driving torque only makes a wheel faster than the ground, a
            # braking one slower: the least affected of the two wheels and the model's
            # prediction (both wheels may spin alike) is the nearest the truth.
            coast = self._w_hat + h * model
            measured = (min(*w_now, coast) if tau_left + tau_right >= 0.0
                        else max(*w_now, coast))
        # The complementary filter of w (PI: the slope's or a push's d̂ integrated).
        innovation = measured - self._w_hat
        wc = self.bandwidth
        self._w_hat += h * (model + 2.0 * wc * innovation)
        self._d_hat += h * wc * wc * innovation
        mean_rate = 0.5 * (pitch_rate + rate0)
        speed = self._w_hat - q * mean_rate
        if slipping[0] or slipping[1]:
            self.offset += (x_v - x_v0) - h * (measured - q * mean_rate)
        self._last = (t, left, right, x_v, pitch_rate)
        return SlipState(x_v - self.offset, self._slipping[0], self._slipping[1],
                         self.offset, speed)

    def _detect(self, t: float, h: float, w_now: tuple[float, float],
                w_prev: tuple[float, float], model: float,
                torques: tuple[float, float]) -> None:
        """Mark a wheel slipping whose acceleration leaves the tilt's, driven by its torque."""
        judging = t - self._start >= 3.0 / self.bandwidth
        slipping = self._slipping
        for i in (0, 1):
            residual = (w_now[i] - w_prev[i]) / h - model
            mean = 0.5 * (residual + self._residual[i])
            self._residual[i] = residual
            if (not slipping[i] and judging and abs(mean) > self.max_acceleration
                    and mean * torques[i] > 0.0):
                slipping[i] = True
                self._since[i] = t
                self._agree_since = self._together_since = math.inf
                self.events += 1

    def _release(self, t: float, w_now: tuple[float, float]) -> None:
        """End the slip once the wheels grip again (with ŵ, or together after ``longest``)."""
        slipping = self._slipping
        mean_w = 0.5 * (w_now[0] + w_now[1])
        together = abs(w_now[0] - w_now[1]) < self.agreement
        self._together_since = min(self._together_since, t) if together else math.inf
        if together and abs(mean_w - self._w_hat) < 3.0 * self.agreement:
            self._agree_since = min(self._agree_since, t)
        else:
            self._agree_since = math.inf
        # Gripping: the two wheels roll alike (the gyro's yaw taken out) at the speed ŵ
        # followed from the IMU (ẇ = g θ + d̂). Past ``longest`` ŵ may have coasted off
        # the truth, so two wheels rolling alike are enough; a wheel that still
        # disagrees with the other is still spinning (or the other is), and the axle
        # cannot move at its speed.
        hold = self.hold - 1e-9
        if (t - self._agree_since >= hold
                or (t - min(self._since) >= self.longest
                    and t - self._together_since >= hold)):
            both = slipping[0] and slipping[1]
            slipping[0] = slipping[1] = False
            # A later slip is timed from its own start, not from this one's.
            self._since = [math.inf, math.inf]
            if both:
                self._w_hat = mean_w
