r"""Extended state observers (ESO) of eqs. (4) and (8) in [1]_, one per measured position.

Each channel is the third-order observer

.. math::

    \dot{\hat x}_1 = \hat x_2 + \frac{\alpha_1}{\varepsilon}(y - \hat x_1), \quad
    \dot{\hat x}_2 = b u + \hat f + \frac{\alpha_2}{\varepsilon^2}(y - \hat x_1), \quad
    \dot{\hat f} = \frac{\alpha_3}{\varepsilon^3}(y - \hat x_1)

of a double integrator ``ÿ = b u + f`` with the lumped disturbance ``f`` as an extra state.
:class:`.state_observer.WipStateObserver` runs three of them: yaw (y = ϕ,
b u = ĝ1(θ̂) τω), distance rolled (y = x_v, b u = g2(θ̂) τυ) and tilt (y = θ,
b u = g3(θ̂) τυ), eq. (1).

Discretisation
--------------
The observer runs at the measurement period h (default 5 ms). With ε = 0.01 its poles
are at −100, −200, −300 rad/s, i.e. |λ| h up to 1.5, so it is integrated **exactly**:
the torque input b u is held over the period (it is: the wheel torques are zero-order
held), and the measurement is reconstructed between two samples. With a constant ε the
transition matrices are computed once with ``scipy.linalg.expm`` and each update is a
3×3 mat-vec in plain floats.

The measurement is, by default, **linearly interpolated** between the previous and the
newest sample (first-order hold), not held: a held one biases a fast observer (why, with
the figures: docs/decisions/estimation-parameters.md). Both are available
(``measurement_hold``); both are the exact solution of the continuous observer for their
input reconstruction (tested against RK4).

With the paper's ε schedule (``'paper_ramp'``) the gains change with time, so each
period is integrated by classic RK4 in equal sub-steps of at most 1 ms (and at most
1/|λ|max of the final observer, so that RK4 is accurate for any user gains) while the
ramp lasts, and exactly after it.

The ε schedule of Section V is ε(t) = 1/(100 t³) for 0 < t ≤ 1 s, 1/100 after. Here it is
scaled to a ramp of length T ending at the configured ε_f: ε(t) = ε_f (T/t)³, and the
gains are written αi/ε^i = αi ((t/T)³/ε_f)^i, finite (zero) at t = 0.

References
----------
.. [1] M. Yue, C. An, Z. Li, "Constrained Adaptive Robust Trajectory Tracking for WIP
   Vehicles Using Model Predictive Control and Extended State Observer", IEEE Trans.
   Syst., Man, Cybern.: Systems, 2016, doi:10.1109/TSMC.2016.2621181.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Sequence

import numpy as np

from wip_runtime.config import ParamError, param
from .compiled import array_slot
from .integration import rk4_step

_TWO_PI = 2.0 * math.pi
#: Longest RK4 sub-step while the ε ramp lasts [s] (docs/paper.md §2: at most 1 ms).
MAX_RAMP_SUBSTEP = 1e-3
#: Relative mismatch of the period below which the precomputed matrices are used [1].
PERIOD_TOLERANCE = 1e-6
#: Off-nominal sample periods (real-time stamps jitter by microseconds to milliseconds) are
#: discretised for the period rounded to this resolution [s], once per distinct value:
#: a timing error of at most 0.5 µs (0.75 µm at 1.5 m/s), where a matrix exponential per
#: sample and channel cost ~150 µs (a third of a core at 200 Hz on a slow machine).
PERIOD_RESOLUTION = 1e-6
_MAX_CACHED_PERIODS = 4096

SCHEDULES = ('constant', 'paper_ramp')
MEASUREMENT_HOLDS = ('linear', 'zero_order')
#: 'paper': three third-order ESOs on the measured positions, eqs. (4), (8);
#: 'gyro': the IMU's angular rate measured, see :class:`.rate_aided.RateAidedChannel`.
ESTIMATORS = ('paper', 'gyro')
#: How the x_v ESO's speed estimate starts (:class:`EsoParams` ``speed_start``).
SPEED_STARTS = ('zero', 'first_difference')


def check_hurwitz(gains: Sequence[float], name: str = 'gains') -> None:
    """Raise :class:`ParamError` unless s³ + α1 s² + α2 s + α3 is Hurwitz.

    Routh–Hurwitz for a cubic: all coefficients positive and α1 α2 > α3.
    """
    if len(gains) != 3:
        raise ParamError(f'{name}: expected 3 gains (alpha1, alpha2, alpha3), '
                          f'got {len(gains)}')
    a1, a2, a3 = (float(g) for g in gains)
    if not all(math.isfinite(a) for a in (a1, a2, a3)):
        raise ParamError(f'{name}: gains must be finite, got {tuple(gains)}')
    if min(a1, a2, a3) <= 0.0:
        raise ParamError(f'{name}: s^3 + {a1:g} s^2 + {a2:g} s + {a3:g} is not Hurwitz: '
                          f'every gain must be > 0, got {tuple(gains)}')
    if not a1 * a2 > a3:
        raise ParamError(f'{name}: s^3 + {a1:g} s^2 + {a2:g} s + {a3:g} is not Hurwitz: '
                          f'alpha1*alpha2 = {a1 * a2:g} must exceed alpha3 = {a3:g}')


def observer_matrices(gains: Sequence[float], epsilon: float) -> tuple[np.ndarray, ...]:
    """Continuous matrices (A, B_y, B_u) of one ESO: ż = A z + B_y y + B_u (b u).

    z = (x̂1, x̂2, f̂); A = [[−k1, 1, 0], [−k2, 0, 1], [−k3, 0, 0]], k_i = α_i/ε^i.
    """
    a1, a2, a3 = gains
    k = np.array([a1 / epsilon, a2 / epsilon ** 2, a3 / epsilon ** 3])
    a = np.array([[-k[0], 1.0, 0.0], [-k[1], 0.0, 1.0], [-k[2], 0.0, 0.0]])
    return a, k, np.array([0.0, 1.0, 0.0])


def discretise(gains: Sequence[float], epsilon: float, period: float,
               measurement_hold: str = 'linear') -> tuple[np.ndarray, ...]:
    """Exact discretisation of one ESO over ``period`` [s].

    Returns ``(Ad, G_prev, G_new, G_u)`` such that

        z(t+h) = Ad z(t) + G_prev y_prev + G_new y_new + G_u (b u)

    with b u held over the period and y linearly interpolated from ``y_prev`` (at t) to
    ``y_new`` (at t+h) (``'linear'``), or ``y_new`` held (``'zero_order'``, G_prev = 0).
    Computed with the matrix exponential of the augmented system (states z, the
    interpolated y, its slope, b u).
    """
    if measurement_hold not in MEASUREMENT_HOLDS:
        raise ValueError(f'measurement_hold must be one of {MEASUREMENT_HOLDS}, '
                         f'got {measurement_hold!r}')
    a, b_y, b_u = observer_matrices(gains, epsilon)
    m = np.zeros((6, 6))
    m[:3, :3] = a
    m[:3, 3] = b_y          # y(τ) = w(τ), state 3
    m[3, 4] = 1.0 / period  # ẇ = (y_new − y_prev)/h, slope in state 4
    m[:3, 5] = b_u          # b u in state 5
    import scipy.linalg   # here: SciPy is loaded only where an observer is built
    e = scipy.linalg.expm(m * period)
    ad, g_w, g_slope, g_u = e[:3, :3], e[:3, 3], e[:3, 4], e[:3, 5]
    if measurement_hold == 'linear':
        # z+ = Ad z + g_w y_prev + g_slope (y_new − y_prev)
        return ad, g_w - g_slope, g_slope.copy(), g_u.copy()
    return ad, np.zeros(3), g_w.copy(), g_u.copy()


@dataclasses.dataclass(frozen=True)
class EsoParams:
    """Tunables of the observers: the paper's three ESOs or the gyro-aided design.

    The paper's three ESOs, eqs. (4) and (8) in [1]_ (gains and ε: Section V), or the gyro-aided
    design (default; docs/estimation.md).
    """

    yaw_gains: tuple[float, float, float] = param(
        (6.0, 11.0, 6.0), '1', '(alpha1, alpha2, alpha3) of the yaw ESO, eq. (4); '
        's^3 + a1 s^2 + a2 s + a3 must be Hurwitz')
    longitudinal_gains: tuple[float, float, float] = param(
        (6.0, 11.0, 6.0), '1', '(alpha4, alpha5, alpha6) of the x_v ESO, eq. (8)')
    tilt_gains: tuple[float, float, float] = param(
        (6.0, 11.0, 6.0), '1', '(alpha7, alpha8, alpha9) of the tilt ESO, eq. (8)')
    epsilon: float = param(
        0.01, 's', 'observer time scale epsilon (poles at roots(alpha)/epsilon); with '
        "'paper_ramp' the value reached at the end of the ramp", minimum=0.0,
        exclusive_minimum=True)
    epsilon_schedule: str = param(
        'constant', '1', "'constant': epsilon throughout (project default); 'paper_ramp': "
        'Section V schedule epsilon*(ramp_duration/t)^3 until ramp_duration, against '
        'peaking', choices=SCHEDULES)
    ramp_duration: float = param(
        1.0, 's', "length of the 'paper_ramp' epsilon schedule (paper: 1 s)", minimum=0.0,
        exclusive_minimum=True)
    yaw_input_gain_scale: float = param(
        1.2, '1', 'g1 used by the yaw ESO = scale * g1(theta_hat) (paper: 20 % error, 1.2)',
        minimum=0.0, exclusive_minimum=True)
    sample_period: float = param(
        0.005, 's', 'measurement period the observer is discretised at', minimum=0.0,
        exclusive_minimum=True, maximum=1.0)
    measurement_hold: str = param(
        'linear', '1', "y between samples in the exact ESO (4), (8): 'linear' interpolation "
        "or 'zero_order' hold (docs/decisions/estimation-parameters.md)",
        choices=MEASUREMENT_HOLDS)
    estimator: str = param(
        'gyro', '1', "'paper': third-order ESOs (4), (8) on the angles; 'gyro': "
        'complementary filter with gyro bias and a reduced-order rate ESO (4) '
        '(docs/decisions/estimation-parameters.md)', choices=ESTIMATORS)
    tilt_angle_bandwidth: float = param(
        5.0, 'rad/s', "'gyro': crossover w_c of the tilt complementary filter "
        '(docs/decisions/estimation-parameters.md)', minimum=0.01, maximum=100.0)
    yaw_angle_bandwidth: float = param(
        5.0, 'rad/s', "'gyro': crossover of the yaw complementary filter (as the tilt's)",
        minimum=0.01, maximum=100.0)
    gyro_bias_bandwidth: float = param(
        0.2, 'rad/s', "'gyro': pole of the gyro bias estimate (slower than the angle "
        'bandwidths: the bias is a slow drift)', minimum=0.001, maximum=10.0)
    tilt_rate_bandwidth: float = param(
        40.0, 'rad/s', "'gyro': double pole w_o of the reduced-order tilt-rate ESO (8), "
        'giving f3 (docs/decisions/estimation-parameters.md)', minimum=0.1, maximum=150.0)
    yaw_rate_bandwidth: float = param(
        20.0, 'rad/s', "'gyro': double pole w_o of the reduced-order yaw-rate ESO (4), "
        'giving f1 (docs/decisions/estimation-parameters.md)', minimum=0.1, maximum=150.0)
    longitudinal_bandwidth: float = param(
        60.0, 'rad/s', "'gyro': triple pole of the x_v ESO (eq. (8), gains (3w, 3w^2, "
        'w^3)); it differentiates encoder and pitch noise', minimum=0.1, maximum=300.0)
    speed_start: str = param(
        'first_difference', '1', "start of the x_v ESO's (8) speed: 'zero' (Section V) or "
        "'first_difference', x_v difference over the first period "
        '(docs/decisions/estimation-parameters.md)', choices=SPEED_STARTS)
    slip_max_acceleration: float = param(
        20.0, 'm/s^2', "'gyro': a wheel whose speed changes this much faster than the tilt "
        'allows slips and is left out of x_v (core/slip.py); 0 = off', minimum=0.0,
        maximum=1000.0)
    obstacle_stall_time: float = param(
        0.3, 's', 'wheels that stay still this long against a forward drive torque and lean '
        'are reported blocked by an obstacle (core/obstacle.py); 0 = off', minimum=0.0,
        maximum=10.0)
    obstacle_release_hold: float = param(
        0.0, 's', 'after the wheels roll on from a stall against the torque, f2 and f3 are '
        'handed on as zero this long (core/obstacle.py); 0 = off', minimum=0.0,
        maximum=5.0)
    obstacle_stall_torque: float = param(
        10.0, 'N m', 'least forward drive torque of a stall against an obstacle (above the '
        'torque that holds the vehicle on a 10 % slope, 6.9 N m)', minimum=0.1, maximum=1000.0)

    def validate(self) -> None:
        for name in ('yaw_gains', 'longitudinal_gains', 'tilt_gains'):
            check_hurwitz(getattr(self, name), name)
        if self.estimator == 'gyro':
            h = self.sample_period
            fastest = max(self.tilt_angle_bandwidth, self.yaw_angle_bandwidth,
                          self.tilt_rate_bandwidth, self.yaw_rate_bandwidth,
                          self.longitudinal_bandwidth)
            if fastest * h > 1.0:
                raise ParamError(f'sample_period: the fastest observer pole '
                                  f'{fastest:g} rad/s times sample_period {h:g} s must be '
                                  '<= 1 (discrete observer)')
            for name in ('tilt_angle_bandwidth', 'yaw_angle_bandwidth'):
                if not self.gyro_bias_bandwidth < getattr(self, name):
                    raise ParamError(f'gyro_bias_bandwidth: must be below {name} = '
                                      f'{getattr(self, name)} rad/s')


#: The slots of a channel's state array shared by both kinds of channel; each kind's own
#: state follows from ``_OWN``.
X1, X2, F, TIME, _OWN = 0, 1, 2, 3, 4


class ChannelEstimate:
    """The read-out of a second-order channel observer.

    It holds x̂1, x̂2 and f̂ at ``_t_prev``, and is the same for the ESO (25) and the
    rate-aided channel. The state lives in one float64 array, ``_s`` (slots ``X1``,
    ``X2``, ``F``, ``TIME``, then the channel's own), which the methods and the compiled
    estimator (``estimator_kernel.py``) update in place. The methods run the step functions
    on a list of the state's Python floats and write it back (numpy's scalars would print
    warnings on an overflow: absurd input gets its one error).
    """

    name: str
    _s: np.ndarray
    x1 = array_slot('_s', X1, 'x̂1, the output estimate')
    x2 = array_slot('_s', X2, 'x̂2, the rate estimate')
    f = array_slot('_s', F, 'f̂, the lumped-disturbance estimate')
    _t_prev = array_slot('_s', TIME, 'time [s] of the estimate')

    @property
    def state(self) -> tuple[float, float, float]:
        """(x̂1, x̂2, f̂): output, rate and lumped-disturbance estimates."""
        return self.x1, self.x2, self.f

    @property
    def time(self) -> float:
        """Time [s] of the current estimate."""
        return self._t_prev

    def _reset_estimate(self, initial_output: float, initial_time: float) -> None:
        """(x̂1, x̂2, f̂) = (y0, 0, 0); ValueError naming the channel if not finite."""
        if not (math.isfinite(initial_output) and math.isfinite(initial_time)):
            raise ValueError(f'{self.name}: non-finite reset ({initial_output!r}, '
                             f'{initial_time!r})')
        self.x1 = float(initial_output)
        self.x2 = 0.0
        self.f = 0.0


#: The ESO's own slots: the previous measurement, and 1.0 while its first period's rate is
#: still to be seeded (``rate_start`` 'first_difference').
Y_PREV, UNSEEDED = _OWN, _OWN + 1


def eso_step(s: np.ndarray | list[float], t: float, y: float, b_u: float, m) -> None:
    """Advance an ESO's state ``s`` in place by one period, to ``t`` [s] with ``y`` at t.

    ``m``: the period's 18 floats (``ExtendedStateObserver._as_floats``). The exact ZOH/FOH
    solution of eq. (4) over the period (see the module docstring); the compiled estimator
    runs this very function.
    """
    x1, x2, x3, yp = s[X1], s[X2], s[F], s[Y_PREV]
    s[X1] = m[0] * x1 + m[1] * x2 + m[2] * x3 + m[9] * yp + m[12] * y + m[15] * b_u
    s[X2] = m[3] * x1 + m[4] * x2 + m[5] * x3 + m[10] * yp + m[13] * y + m[16] * b_u
    s[F] = m[6] * x1 + m[7] * x2 + m[8] * x3 + m[11] * yp + m[14] * y + m[17] * b_u
    s[Y_PREV] = y
    s[TIME] = t


class ExtendedStateObserver(ChannelEstimate):
    """One third-order ESO channel, eq. (4) in [1]_, exactly discretised.

    Parameters
    ----------
    gains : (α1, α2, α3), Hurwitz.
    epsilon : ε [s] (final value for the ramp schedule).
    sample_period : nominal measurement period h [s]; updates at this period use
        matrices precomputed here, any other positive period is discretised on the fly.
    schedule : ``'constant'`` or ``'paper_ramp'``.
    ramp_duration : T [s] of the ramp schedule.
    measurement_hold : ``'linear'`` or ``'zero_order'``.
    name : used in error messages.
    initial_output, initial_time : see :meth:`reset`.
    """

    def __init__(self, gains: Sequence[float], epsilon: float = 0.01,
                 sample_period: float = 0.005, *, schedule: str = 'constant',
                 ramp_duration: float = 1.0, measurement_hold: str = 'linear',
                 name: str = 'eso', initial_output: float = 0.0,
                 initial_time: float = 0.0, rate_start: str = 'zero') -> None:
        check_hurwitz(gains, name)
        for label, value in (('epsilon', epsilon), ('sample_period', sample_period),
                             ('ramp_duration', ramp_duration)):
            if not (math.isfinite(value) and value > 0.0):
                raise ParamError(f'{name}.{label}: must be finite and > 0, got {value!r}')
        if schedule not in SCHEDULES:
            raise ParamError(f'{name}.schedule: {schedule!r} is not one of {list(SCHEDULES)}')
        if rate_start not in SPEED_STARTS:
            raise ParamError(f'{name}.rate_start: {rate_start!r} is not one of '
                              f'{list(SPEED_STARTS)}')
        self.rate_start = rate_start
        if measurement_hold not in MEASUREMENT_HOLDS:
            raise ParamError(f'{name}.measurement_hold: {measurement_hold!r} is not one of '
                              f'{list(MEASUREMENT_HOLDS)}')
        self.name = name
        self.gains = tuple(float(g) for g in gains)
        self.epsilon = float(epsilon)
        self.sample_period = float(sample_period)
        self.schedule = schedule
        self.ramp_duration = float(ramp_duration)
        self.measurement_hold = measurement_hold
        self._s = np.zeros(_OWN + 2)
        # Built once: the per-sample update is then 3 dot products (the compiled estimator
        # reads the array).
        self._nominal = self._as_floats(discretise(self.gains, self.epsilon,
                                                   self.sample_period, measurement_hold))
        self._nominal_array = np.array(self._nominal)
        self._cached: dict[int, tuple[float, ...]] = {}   # period in PERIOD_RESOLUTION
        # RK4 sub-step during the ramp: ≤ 1 ms and ≤ 1/|λ|max of the final observer.
        fastest_pole = max(abs(r) for r in np.roots([1.0, *self.gains])) / self.epsilon
        self._max_substep = min(MAX_RAMP_SUBSTEP, 1.0 / fastest_pole)
        self.reset(initial_output, initial_time)

    _y_prev = array_slot('_s', Y_PREV, 'the previous measurement')

    @staticmethod
    def _as_floats(matrices: tuple[np.ndarray, ...]) -> tuple[float, ...]:
        ad, g_prev, g_new, g_u = matrices
        return tuple(float(v) for v in (*ad.ravel(), *g_prev, *g_new, *g_u))

    def reset(self, initial_output: float, initial_time: float = 0.0) -> None:
        """State (y0, 0, 0) at ``initial_time`` [s], the origin of the ε ramp."""
        self._reset_estimate(initial_output, initial_time)
        self._y_prev = float(initial_output)
        self._t_prev = float(initial_time)
        self._t0 = float(initial_time)
        self._s[UNSEEDED] = 1.0 if self.rate_start == 'first_difference' else 0.0

    def epsilon_at(self, t: float) -> float:
        """ε(t) [s]; ``inf`` at the very start of the ramp (zero gains)."""
        if self.schedule == 'constant':
            return self.epsilon
        s = (t - self._t0) / self.ramp_duration
        if s >= 1.0:
            return self.epsilon
        if s <= 0.0:
            return math.inf
        return self.epsilon / (s * s * s)

    def in_ramp(self, t: float) -> bool:
        """Return True while the ε ramp is still running at time ``t`` [s]."""
        return self.schedule == 'paper_ramp' and t - self._t0 < self.ramp_duration

    def update(self, t: float, y: float, b_u: float) -> tuple[float, float, float]:
        """Advance to time ``t`` [s] with measurement ``y`` at t.

        ``b_u`` is the input held since the previous update. Return (x̂1, x̂2, f̂).

        ``t`` equal to the previous time leaves the estimate unchanged (e.g. a first call
        at the initial time). Non-finite inputs or a time going backwards raise
        ``ValueError`` and leave the state unchanged.
        """
        if not math.isfinite(t + y + b_u):
            raise ValueError(f'{self.name}: non-finite input t={t!r}, y={y!r}, b_u={b_u!r}')
        dt = t - self._t_prev
        if dt <= 0.0:
            if dt < 0.0:
                raise ValueError(f'{self.name}: time went backwards from {self._t_prev} '
                                 f'to {t}')
            return self.x1, self.x2, self.f
        if self._s[UNSEEDED]:
            # The first period after a reset: the rate is the difference of the first two
            # samples rather than 0, so a channel started in motion does not first read
            # rest and then overshoot (the disturbance starts at 0 as in Section V).
            self._s[UNSEEDED] = 0.0
            self.x1, self.x2, self.f = y, (y - self._y_prev) / dt, 0.0
        elif self.schedule == 'paper_ramp' and self._t_prev - self._t0 < self.ramp_duration:
            self._integrate_ramp(dt, y, b_u)
        else:
            if abs(dt - self.sample_period) <= PERIOD_TOLERANCE * self.sample_period:
                m = self._nominal
            else:
                m = self._off_nominal(dt)
            state = self._s.tolist()
            eso_step(state, t, y, b_u, m)
            self._s[:] = state
            return state[X1], state[X2], state[F]
        self._y_prev = y
        self._t_prev = t
        return self.x1, self.x2, self.f

    def _off_nominal(self, dt: float) -> tuple[float, ...]:
        """Discretisation for an off-nominal period (real-time jitter).

        Cached by the period rounded to :data:`PERIOD_RESOLUTION`.
        """
        key = round(dt / PERIOD_RESOLUTION)
        m = self._cached.get(key)
        if m is None:
            period = key * PERIOD_RESOLUTION if key > 0 else dt
            m = self._as_floats(discretise(self.gains, self.epsilon, period,
                                           self.measurement_hold))
            if key > 0:
                if len(self._cached) >= _MAX_CACHED_PERIODS:
                    self._cached.clear()
                self._cached[key] = m
        return m

    def _gains_at(self, t: float) -> tuple[float, float, float]:
        """α_i/ε(t)^i written as α_i ((t/T)³/ε_f)^i, finite (zero) at the ramp start."""
        s = (t - self._t0) / self.ramp_duration
        inv_eps = (min(max(s, 0.0), 1.0) ** 3) / self.epsilon
        a1, a2, a3 = self.gains
        return a1 * inv_eps, a2 * inv_eps * inv_eps, a3 * inv_eps * inv_eps * inv_eps

    def _integrate_ramp(self, dt: float, y: float, b_u: float) -> None:
        """Classic RK4 in equal sub-steps of at most ``_max_substep`` (time-varying ε)."""
        n = max(1, math.ceil(dt / self._max_substep - 1e-9))
        h = dt / n
        t_start, y_prev = self._t_prev, self._y_prev
        slope = (y - y_prev) / dt if self.measurement_hold == 'linear' else 0.0
        y_base = y_prev if self.measurement_hold == 'linear' else y

        def rates(tau: float, z: tuple[float, float, float]) -> tuple[float, float, float]:
            k1, k2, k3 = self._gains_at(tau)
            e = y_base + slope * (tau - t_start) - z[0]
            return z[1] + k1 * e, b_u + z[2] + k2 * e, k3 * e

        z = (self.x1, self.x2, self.f)
        for i in range(n):
            z = rk4_step(rates, t_start + i * h, z, h)
        self.x1, self.x2, self.f = z


class StateEstimate(NamedTuple):
    """Output of :class:`.state_observer.WipStateObserver` at one sample."""

    phi: float        #: ϕ̂, yaw, continuous (not wrapped) [rad]
    omega: float      #: ω̂, yaw rate [rad/s]
    f1: float         #: f̂1, lumped yaw disturbance (fω1 + τd1) [rad/s²]
    x_v: float        #: x̂v, distance rolled [m]
    v: float          #: υ̂, longitudinal speed [m/s]
    f2: float         #: f̂2, lumped longitudinal disturbance (fυ2 + τd2) [m/s²]
    theta: float      #: θ̂, tilt, positive leaning forward [rad]
    theta_dot: float  #: θ̂̇, tilt rate [rad/s]
    f3: float         #: f̂3, lumped tilt disturbance (fθ3 + τd3) [rad/s²]
    epsilon: float    #: ε in use at this sample [s] (inf at the start of the ramp)
