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

import numpy as np

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


#: The slots of the monitor's state array: the last sample (t, r φ_l, r φ_r, x_v, θ̇) and
#: 1.0 once there is one, the filter's ŵ and d̂, each wheel's previous residual and w, 1.0
#: once there is a previous w, each wheel's slip flag, since when the wheels agree with ŵ
#: and with each other, when each wheel's slip began, the start, the offset, the events.
(T_LAST, LEFT_LAST, RIGHT_LAST, XV_LAST, RATE_LAST, HAS_LAST, W_HAT, D_HAT, RESIDUAL_LEFT,
 RESIDUAL_RIGHT, W_PREV_LEFT, W_PREV_RIGHT, HAS_W_PREV, SLIPS_LEFT, SLIPS_RIGHT, AGREE_SINCE,
 TOGETHER_SINCE, SINCE_LEFT, SINCE_RIGHT, START, OFFSET, EVENTS) = range(22)
#: The slots of its constants: q = J_θ/(mp l), the encoders' body-rate gain, g, d/2, then
#: the tunables.
(Q, BODY_RATE_GAIN, GRAVITY, HALF_TRACK, MAX_ACCELERATION, AGREEMENT, BANDWIDTH, HOLD,
 LONGEST) = range(9)
#: The step functions' state and constants: the arrays, or lists of their floats.
_State = np.ndarray | list[float]


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

    The state lives in one float64 array (the ``*_LAST`` … ``EVENTS`` slots), which
    :func:`slip_step` updates in place, compiled in the estimator's kernel
    (``estimator_kernel.py``), and here on a list of its Python floats written back (numpy's
    scalars would print warnings on an overflow: absurd input gets its one error).
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
        self.constants = np.array([self.q, self.body_rate_gain, self.g, self.half_track,
                                   max_acceleration, agreement, bandwidth, hold, longest],
                                  dtype=float)
        self._constants = self.constants.tolist()
        self.state = np.zeros(EVENTS + 1)
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next sample starts the monitor."""
        s = self.state
        s[:] = 0.0
        s[AGREE_SINCE] = s[TOGETHER_SINCE] = s[SINCE_LEFT] = s[SINCE_RIGHT] = math.inf

    @property
    def offset(self) -> float:
        """Distance [m] the wheels spun (or skidded) away so far."""
        return float(self.state[OFFSET])

    @property
    def events(self) -> int:
        """Slips begun since the start."""
        return int(self.state[EVENTS])

    @property
    def slipping_wheels(self) -> tuple[bool, bool]:
        """Whether the (left, right) wheel slips now."""
        return bool(self.state[SLIPS_LEFT]), bool(self.state[SLIPS_RIGHT])

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
        state = self.state.tolist()
        x_v_used, speed = slip_step(state, self._constants, t, left, right, x_v, theta,
                                    pitch_rate, yaw_rate, tau_left, tau_right)
        self.state[:] = state
        return SlipState(x_v_used, state[SLIPS_LEFT] != 0.0, state[SLIPS_RIGHT] != 0.0,
                         state[OFFSET], speed)


def slip_step(s: _State, c: _State, t: float, left: float, right: float,
              x_v: float, theta: float, pitch_rate: float, yaw_rate: float,
              tau_left: float, tau_right: float) -> tuple[float, float]:
    """Take one finite sample into the monitor's state ``s`` (constants ``c``), in place.

    Return (the x_v to use, the physical axle speed ŵ − q θ̇). The arguments are those of
    :meth:`SlipMonitor.update`.
    """
    q = c[Q]
    if s[HAS_LAST] == 0.0 or t <= s[T_LAST]:
        if s[HAS_LAST] == 0.0:
            s[W_HAT] = q * pitch_rate
            s[START] = t
        _keep_last(s, t, left, right, x_v, pitch_rate)
        return x_v - s[OFFSET], s[W_HAT] - q * pitch_rate
    t0, left0, right0, x_v0, rate0 = (s[T_LAST], s[LEFT_LAST], s[RIGHT_LAST], s[XV_LAST],
                                      s[RATE_LAST])
    h = t - t0
    turn = c[HALF_TRACK] * yaw_rate
    body = (q + c[BODY_RATE_GAIN]) * 0.5 * (pitch_rate + rate0)
    w_left = (left - left0) / h + turn + body
    w_right = (right - right0) / h - turn + body
    model = c[GRAVITY] * theta + s[D_HAT]
    if s[HAS_W_PREV] == 0.0:
        s[W_PREV_LEFT], s[W_PREV_RIGHT] = w_left, w_right
    judging = t - s[START] >= 3.0 / c[BANDWIDTH]
    _detect(s, c, t, h, judging, 0, w_left, model, tau_left)
    _detect(s, c, t, h, judging, 1, w_right, model, tau_right)
    s[W_PREV_LEFT], s[W_PREV_RIGHT], s[HAS_W_PREV] = w_left, w_right, 1.0
    slips_left, slips_right = s[SLIPS_LEFT] != 0.0, s[SLIPS_RIGHT] != 0.0
    if slips_left or slips_right:
        _release(s, c, t, w_left, w_right)
        slips_left, slips_right = s[SLIPS_LEFT] != 0.0, s[SLIPS_RIGHT] != 0.0
    measured = _measured(slips_left, slips_right, w_left, w_right, s[W_HAT] + h * model,
                         tau_left + tau_right)
    # The complementary filter of w (PI: the slope's or a push's d̂ integrated).
    innovation = measured - s[W_HAT]
    wc = c[BANDWIDTH]
    s[W_HAT] += h * (model + 2.0 * wc * innovation)
    s[D_HAT] += h * wc * wc * innovation
    mean_rate = 0.5 * (pitch_rate + rate0)
    speed = s[W_HAT] - q * mean_rate
    if slips_left or slips_right:
        s[OFFSET] += (x_v - x_v0) - h * (measured - q * mean_rate)
    _keep_last(s, t, left, right, x_v, pitch_rate)
    return x_v - s[OFFSET], speed


def _measured(slips_left: bool, slips_right: bool, w_left: float, w_right: float,
              coast: float, tau_v: float) -> float:
    """Return the measured w: the gripping wheels' mean (as Python's sum, from 0.0)."""
    if not (slips_left and slips_right):
        if slips_left:
            return (0.0 + w_right) / 1
        if slips_right:
            return (0.0 + w_left) / 1
        return (0.0 + w_left + w_right) / 2
    # Both slip: a driving torque only makes a wheel faster than the ground, a braking one
    # slower: the least affected of the two wheels and the model's prediction ``coast``
    # (both wheels may spin alike) is the nearest the truth (Python's min and max: the
    # first of equals).
    measured = w_left
    if tau_v >= 0.0:
        if w_right < measured:
            measured = w_right
        if coast < measured:
            measured = coast
    else:
        if w_right > measured:
            measured = w_right
        if coast > measured:
            measured = coast
    return measured


def _keep_last(s: _State, t: float, left: float, right: float, x_v: float,
               pitch_rate: float) -> None:
    s[T_LAST], s[LEFT_LAST], s[RIGHT_LAST], s[XV_LAST] = t, left, right, x_v
    s[RATE_LAST], s[HAS_LAST] = pitch_rate, 1.0


def _detect(s: _State, c: _State, t: float, h: float, judging: bool, wheel: int,
            w_now: float, model: float, torque: float) -> None:
    """Mark a wheel slipping whose acceleration leaves the tilt's, driven by its torque."""
    residual = (w_now - s[W_PREV_LEFT + wheel]) / h - model
    mean = 0.5 * (residual + s[RESIDUAL_LEFT + wheel])
    s[RESIDUAL_LEFT + wheel] = residual
    if (s[SLIPS_LEFT + wheel] == 0.0 and judging and abs(mean) > c[MAX_ACCELERATION]
            and mean * torque > 0.0):
        s[SLIPS_LEFT + wheel] = 1.0
        s[SINCE_LEFT + wheel] = t
        s[AGREE_SINCE] = s[TOGETHER_SINCE] = math.inf
        s[EVENTS] += 1.0


def _release(s: _State, c: _State, t: float, w_left: float, w_right: float) -> None:
    """End the slip once the wheels grip again (with ŵ, or together after ``longest``)."""
    mean_w = 0.5 * (w_left + w_right)
    agreement = c[AGREEMENT]
    together = abs(w_left - w_right) < agreement
    # min(since, t) as Python's min: the first of equals.
    if together:
        if t < s[TOGETHER_SINCE]:
            s[TOGETHER_SINCE] = t
    else:
        s[TOGETHER_SINCE] = math.inf
    if together and abs(mean_w - s[W_HAT]) < 3.0 * agreement:
        if t < s[AGREE_SINCE]:
            s[AGREE_SINCE] = t
    else:
        s[AGREE_SINCE] = math.inf
    # Gripping: the two wheels roll alike (the gyro's yaw taken out) at the speed ŵ
    # followed from the IMU (ẇ = g θ + d̂). Past ``longest`` ŵ may have coasted off
    # the truth, so two wheels rolling alike are enough; a wheel that still
    # disagrees with the other is still spinning (or the other is), and the axle
    # cannot move at its speed.
    hold = c[HOLD] - 1e-9
    first_since = s[SINCE_RIGHT] if s[SINCE_RIGHT] < s[SINCE_LEFT] else s[SINCE_LEFT]
    if (t - s[AGREE_SINCE] >= hold
            or (t - first_since >= c[LONGEST] and t - s[TOGETHER_SINCE] >= hold)):
        both = s[SLIPS_LEFT] != 0.0 and s[SLIPS_RIGHT] != 0.0
        s[SLIPS_LEFT] = s[SLIPS_RIGHT] = 0.0
        # A later slip is timed from its own start, not from this one's.
        s[SINCE_LEFT] = s[SINCE_RIGHT] = math.inf
        if both:
            s[W_HAT] = mean_w
