r"""Extended state observers (ESO) of eqs. (4) and (8) in [1]_, one per measured position.

Each channel is the third-order observer

.. math::

    \dot{\hat x}_1 = \hat x_2 + \frac{\alpha_1}{\varepsilon}(y - \hat x_1), \quad
    \dot{\hat x}_2 = b u + \hat f + \frac{\alpha_2}{\varepsilon^2}(y - \hat x_1), \quad
    \dot{\hat f} = \frac{\alpha_3}{\varepsilon^3}(y - \hat x_1)

of a double integrator ``ÿ = b u + f`` with the lumped disturbance ``f`` as an extra state.
:class:`WipStateObserver` runs three of them: yaw (y = ϕ, b u = ĝ1(θ̂) τω), distance
rolled (y = x_v, b u = g2(θ̂) τυ) and tilt (y = θ, b u = g3(θ̂) τυ), eq. (1).

Discretisation
--------------
The observer runs at the measurement period h (default 5 ms). With ε = 0.01 its poles
are at −100, −200, −300 rad/s, i.e. |λ| h up to 1.5, so it is integrated **exactly**:
the torque input b u is held over the period (it is: the wheel torques are zero-order
held), and the measurement is reconstructed between two samples. With a constant ε the
transition matrices are computed once with ``scipy.linalg.expm`` and each update is a
3×3 mat-vec in plain floats.

*Deviation from the obvious choice*: the measurement is, by default, **linearly
interpolated** between the previous and the newest sample (first-order hold), not held.
A held (staircase) measurement biases a fast observer badly: on a ramp y = 0.6 t at
h = 5 ms and ε = 0.01 the held-sample observer settles with x̂2 = 0.47 instead of 0.6
(−21 %) and f̂ = −6.8 instead of 0, because within each period it sees a motionless
output for 5 ms against time constants of 3–10 ms. The interpolated measurement is
exact for a ramp (zero error) and leaves a bias of about 0.3 % of the acceleration in f̂.
Both are available (``measurement_hold``); both are the exact solution of the
continuous observer for their input reconstruction (tested against RK4).

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
import scipy.linalg

from .config import ConfigError, param
from .model import input_gains
from .params import WipParameters

_TWO_PI = 2.0 * math.pi
#: Longest RK4 sub-step while the ε ramp lasts [s] (docs/paper.md §2: at most 1 ms).
MAX_RAMP_SUBSTEP = 1e-3
#: Relative mismatch of the period below which the precomputed matrices are used [1].
_PERIOD_TOLERANCE = 1e-6
#: Off-nominal sample periods (real-time stamps jitter by microseconds to milliseconds) are
#: discretised for the period rounded to this resolution [s], once per distinct value:
#: a timing error of at most 0.5 µs (0.75 µm at 1.5 m/s), where a matrix exponential per
#: sample and channel cost ~150 µs (a third of a core at 200 Hz on a slow machine).
PERIOD_RESOLUTION = 1e-6
_MAX_CACHED_PERIODS = 4096

SCHEDULES = ('constant', 'paper_ramp')
MEASUREMENT_HOLDS = ('linear', 'zero_order')
#: 'paper': three third-order ESOs on the measured positions, eqs. (4), (8);
#: 'gyro': the IMU's angular rate measured, see :class:`RateAidedChannel`.
ESTIMATORS = ('paper', 'gyro')
#: How the x_v ESO's speed estimate starts (:class:`EsoConfig` ``speed_start``).
SPEED_STARTS = ('zero', 'first_difference')


def check_hurwitz(gains: Sequence[float], name: str = 'gains') -> None:
    """Raise :class:`ConfigError` unless s³ + α1 s² + α2 s + α3 is Hurwitz.

    Routh–Hurwitz for a cubic: all coefficients positive and α1 α2 > α3.
    """
    if len(gains) != 3:
        raise ConfigError(f'{name}: expected 3 gains (alpha1, alpha2, alpha3), '
                          f'got {len(gains)}')
    a1, a2, a3 = (float(g) for g in gains)
    if not all(math.isfinite(a) for a in (a1, a2, a3)):
        raise ConfigError(f'{name}: gains must be finite, got {tuple(gains)}')
    if min(a1, a2, a3) <= 0.0:
        raise ConfigError(f'{name}: s^3 + {a1:g} s^2 + {a2:g} s + {a3:g} is not Hurwitz: '
                          f'every gain must be > 0, got {tuple(gains)}')
    if not a1 * a2 > a3:
        raise ConfigError(f'{name}: s^3 + {a1:g} s^2 + {a2:g} s + {a3:g} is not Hurwitz: '
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
    e = scipy.linalg.expm(m * period)
    ad, g_w, g_slope, g_u = e[:3, :3], e[:3, 3], e[:3, 4], e[:3, 5]
    if measurement_hold == 'linear':
        # z+ = Ad z + g_w y_prev + g_slope (y_new − y_prev)
        return ad, g_w - g_slope, g_slope.copy(), g_u.copy()
    return ad, np.zeros(3), g_w.copy(), g_u.copy()


@dataclasses.dataclass(frozen=True)
class EsoConfig:
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
        'linear', '1', "reconstruction of y between samples: 'linear' interpolation "
        "(unbiased on ramps) or 'zero_order' hold of the newest sample (biased, see "
        'eso.py)', choices=MEASUREMENT_HOLDS)
    estimator: str = param(
        'gyro', '1', "'paper': third-order ESOs on the measured angles, eqs. (4), (8) "
        "(Section V); 'gyro': the IMU angular rate is measured: complementary filter of "
        'angle and gyro with bias estimation, and a reduced-order ESO on the rate for '
        'the disturbance (docs/estimation.md)', choices=ESTIMATORS)
    tilt_angle_bandwidth: float = param(
        5.0, 'rad/s', "'gyro': crossover of the tilt complementary filter; the "
        'steady-state Kalman choice is sigma_gyro / sigma_angle (0.01 / 0.002)',
        minimum=0.01, maximum=100.0)
    yaw_angle_bandwidth: float = param(
        5.0, 'rad/s', "'gyro': crossover of the yaw complementary filter (as the tilt's)",
        minimum=0.01, maximum=100.0)
    gyro_bias_bandwidth: float = param(
        0.2, 'rad/s', "'gyro': pole of the gyro bias estimate (slower than the angle "
        'bandwidths: the bias is a slow drift)', minimum=0.001, maximum=10.0)
    tilt_rate_bandwidth: float = param(
        40.0, 'rad/s', "'gyro': double pole of the reduced-order ESO of the tilt rate "
        '(gives f3, which holds the gravity torque: it must track the pendulum, about '
        '10x its 4 rad/s unstable pole); f3 noise std grows as bandwidth^1.5',
        minimum=0.1, maximum=150.0)
    yaw_rate_bandwidth: float = param(
        20.0, 'rad/s', "'gyro': double pole of the reduced-order ESO of the yaw rate "
        "(gives f1 to the ARC; the yaw disturbances are slower than the tilt's and f1 "
        'noise drives the adaptation)', minimum=0.1, maximum=150.0)
    longitudinal_bandwidth: float = param(
        60.0, 'rad/s', "'gyro': triple pole of the x_v ESO (eq. (8), gains (3w, 3w^2, "
        'w^3)); it differentiates encoder and pitch noise', minimum=0.1, maximum=300.0)
    speed_start: str = param(
        'first_difference', '1', "start of the x_v ESO's speed estimate: 'zero' (Section "
        "V: the ESOs start at rest, and one at speed first reads 0 m/s, then overshoots the "
        "true speed by 0.1 m/s at 0.1 s); 'first_difference': at the second sample, the "
        'distance difference over the period (a vehicle started at speed brakes from its '
        'true speed: f2 transient 23.5 m/s2 -> 0, docs/estimation.md)',
        choices=SPEED_STARTS)
    slip_max_acceleration: float = param(
        0.0, 'm/s^2', "'gyro': a wheel whose speed changes this much faster than the tilt "
        'allows slips and is left out of x_v (core/slip.py); 0 = off', minimum=0.0,
        maximum=1000.0)

    def validate(self) -> None:
        for name in ('yaw_gains', 'longitudinal_gains', 'tilt_gains'):
            check_hurwitz(getattr(self, name), name)
        if self.estimator == 'gyro':
            h = self.sample_period
            fastest = max(self.tilt_angle_bandwidth, self.yaw_angle_bandwidth,
                          self.tilt_rate_bandwidth, self.yaw_rate_bandwidth,
                          self.longitudinal_bandwidth)
            if fastest * h > 1.0:
                raise ConfigError(f'sample_period: the fastest observer pole '
                                  f'{fastest:g} rad/s times sample_period {h:g} s must be '
                                  '<= 1 (discrete observer)')
            for name in ('tilt_angle_bandwidth', 'yaw_angle_bandwidth'):
                if not self.gyro_bias_bandwidth < getattr(self, name):
                    raise ConfigError(f'gyro_bias_bandwidth: must be below {name} = '
                                      f'{getattr(self, name)} rad/s')


class _ChannelEstimate:
    """The read-out of a second-order channel observer.

    It holds x̂1, x̂2 and f̂ at ``_t_prev``, and is the same for the ESO (25) and the
    rate-aided channel.
    """

    name: str
    x1: float
    x2: float
    f: float
    _t_prev: float

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


class ExtendedStateObserver(_ChannelEstimate):
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
                raise ConfigError(f'{name}.{label}: must be finite and > 0, got {value!r}')
        if schedule not in SCHEDULES:
            raise ConfigError(f'{name}.schedule: {schedule!r} is not one of {list(SCHEDULES)}')
        if rate_start not in SPEED_STARTS:
            raise ConfigError(f'{name}.rate_start: {rate_start!r} is not one of '
                              f'{list(SPEED_STARTS)}')
        self.rate_start = rate_start
        if measurement_hold not in MEASUREMENT_HOLDS:
            raise ConfigError(f'{name}.measurement_hold: {measurement_hold!r} is not one of '
                              f'{list(MEASUREMENT_HOLDS)}')
        self.name = name
        self.gains = tuple(float(g) for g in gains)
        self.epsilon = float(epsilon)
        self.sample_period = float(sample_period)
        self.schedule = schedule
        self.ramp_duration = float(ramp_duration)
        self.measurement_hold = measurement_hold
        # Built once: the per-sample update is then 3 dot products of plain floats.
        self._nominal = self._as_floats(discretise(self.gains, self.epsilon,
                                                   self.sample_period, measurement_hold))
        self._cached: dict[int, tuple[float, ...]] = {}   # period in PERIOD_RESOLUTION
        # RK4 sub-step during the ramp: ≤ 1 ms and ≤ 1/|λ|max of the final observer.
        fastest_pole = max(abs(r) for r in np.roots([1.0, *self.gains])) / self.epsilon
        self._max_substep = min(MAX_RAMP_SUBSTEP, 1.0 / fastest_pole)
        self.reset(initial_output, initial_time)

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
        self._rate_unseeded = self.rate_start == 'first_difference'

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
        if self._rate_unseeded:
            # The first period after a reset: the rate is the difference of the first two
            # samples rather than 0, so a channel started in motion does not first read
            # rest and then overshoot (the disturbance starts at 0 as in Section V).
            self._rate_unseeded = False
            self.x1, self.x2, self.f = y, (y - self._y_prev) / dt, 0.0
        elif self.schedule == 'paper_ramp' and self._t_prev - self._t0 < self.ramp_duration:
            self._integrate_ramp(dt, y, b_u)
        else:
            if abs(dt - self.sample_period) <= _PERIOD_TOLERANCE * self.sample_period:
                m = self._nominal
            else:
                m = self._off_nominal(dt)
            x1, x2, x3, yp = self.x1, self.x2, self.f, self._y_prev
            # Exact ZOH/FOH solution of eq. (4) over the period (see module docstring).
            self.x1 = m[0] * x1 + m[1] * x2 + m[2] * x3 + m[9] * yp + m[12] * y + m[15] * b_u
            self.x2 = m[3] * x1 + m[4] * x2 + m[5] * x3 + m[10] * yp + m[13] * y + m[16] * b_u
            self.f = m[6] * x1 + m[7] * x2 + m[8] * x3 + m[11] * yp + m[14] * y + m[17] * b_u
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
        x1, x2, x3 = self.x1, self.x2, self.f

        def rates(tau: float, z1: float, z2: float, z3: float) -> tuple[float, float, float]:
            k1, k2, k3 = self._gains_at(tau)
            e = y_base + slope * (tau - t_start) - z1
            return z2 + k1 * e, b_u + z3 + k2 * e, k3 * e

        for i in range(n):
            tau = t_start + i * h
            a = rates(tau, x1, x2, x3)
            b = rates(tau + 0.5 * h, x1 + 0.5 * h * a[0], x2 + 0.5 * h * a[1],
                      x3 + 0.5 * h * a[2])
            c = rates(tau + 0.5 * h, x1 + 0.5 * h * b[0], x2 + 0.5 * h * b[1],
                      x3 + 0.5 * h * b[2])
            d = rates(tau + h, x1 + h * c[0], x2 + h * c[1], x3 + h * c[2])
            x1 += h / 6.0 * (a[0] + 2.0 * b[0] + 2.0 * c[0] + d[0])
            x2 += h / 6.0 * (a[1] + 2.0 * b[1] + 2.0 * c[1] + d[1])
            x3 += h / 6.0 * (a[2] + 2.0 * b[2] + 2.0 * c[2] + d[2])
        self.x1, self.x2, self.f = x1, x2, x3


def complementary_bandwidth(angle_noise_std: float, rate_noise_std: float) -> float:
    """Crossover ω_c [rad/s] of the angle/gyro complementary filter.

    This crossover minimises the angle error variance for white angle noise σ_a [rad] and
    white rate noise σ_g [rad/s] sampled at the same period: ω_c = σ_g / σ_a.

    Why: the filter θ̂̇ = r + ω_c (θ_m − θ̂) is the steady-state Kalman filter of θ̇ = r
    with process noise PSD q = σ_g² h and measurement noise PSD ρ = σ_a² h, whose gain
    is √(q/ρ). The variance is then h (σ_a² ω_c + σ_g²/ω_c)/2 = h σ_a σ_g.
    """
    if not (angle_noise_std > 0.0 and rate_noise_std > 0.0):
        raise ValueError('complementary_bandwidth: both noise levels must be > 0, got '
                         f'{angle_noise_std!r}, {rate_noise_std!r}')
    return rate_noise_std / angle_noise_std


def discrete_pole_gains(pole_a: float, pole_b: float, period: float) -> tuple[float, float]:
    """Gains (L1, L2) of the two-state predictor-corrector of :class:`RateAidedChannel`.

    The channel uses the predictor-corrector twice. The gains put its error poles at
    e^{−a h}, e^{−b h}.

    Both loops have the error matrix [[1 − L1, ∓(1 − L1) h], [±L2, 1 − L2 h]], whose
    characteristic polynomial is z² − (2 − L1 − L2 h) z + (1 − L1): with p, q the wanted
    discrete poles, L1 = 1 − p q and L2 = (1 − p)(1 − q)/h.
    """
    p, q = math.exp(-pole_a * period), math.exp(-pole_b * period)
    return 1.0 - p * q, (1.0 - p) * (1.0 - q) / period


class RateAidedChannel(_ChannelEstimate):
    """One angle channel (tilt or yaw) of a WIP whose IMU measures the angle AND its rate.

    Two discrete loops per sample of period h (the gyro reading r = ẏ + b + noise, b a
    slowly drifting bias):

    1. complementary filter with bias estimate (angle â, bias b̂):
       â⁻ = â + h ((r_prev + r)/2 − b̂);  e = y_m − â⁻;  â = â⁻ + L1 e;  b̂ = b̂ − L2 e.
       Error poles at −``angle_bandwidth`` and −``bias_bandwidth`` (discrete e^{−ω h}).
       The angle noise passes below ω_c, the integrated gyro noise above it;
    2. reduced-order ESO of the rate (the paper's eq. (4) with the position channel
       removed, since the rate is measured): the rate ẑ1 and lumped disturbance f̂ of
       ÿ = b u + f from the bias-corrected rate r − b̂:
       ẑ1⁻ = ẑ1 + h (b u + f̂);  e = r − b̂ − ẑ1⁻;  ẑ1 = ẑ1⁻ + M1 e;  f̂ = f̂ + M2 e,
       a double pole at −``rate_bandwidth``. f̂ is thereby a second-order low-pass of
       the true f; its noise variance for white rate noise σ_g is ≈ σ_g² h ω_o³/4
       (H2 norm of ω_o² s/(s + ω_o)², see :func:`rate_eso_noise_variance`).

    The outputs (â, ẑ1, f̂) replace the paper ESO's (x̂1, x̂2, f̂).
    """

    def __init__(self, angle_bandwidth: float, bias_bandwidth: float,
                 rate_bandwidth: float, sample_period: float, name: str = 'channel',
                 initial_output: float = 0.0, initial_time: float = 0.0) -> None:
        for label, value in (('angle_bandwidth', angle_bandwidth),
                             ('bias_bandwidth', bias_bandwidth),
                             ('rate_bandwidth', rate_bandwidth),
                             ('sample_period', sample_period)):
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'{name}.{label}: must be finite and > 0, got {value!r}')
        self.name = name
        self.angle_bandwidth = float(angle_bandwidth)
        self.bias_bandwidth = float(bias_bandwidth)
        self.rate_bandwidth = float(rate_bandwidth)
        self.sample_period = float(sample_period)
        self._gains_cache: dict[float, tuple[float, float, float, float]] = {}
        self._nominal_gains = self._gains(self.sample_period)
        self.reset(initial_output, initial_time)

    def _gains(self, h: float) -> tuple[float, float, float, float]:
        gains = self._gains_cache.get(h)
        if gains is None:
            if len(self._gains_cache) > 16:
                self._gains_cache.clear()
            l1, l2 = discrete_pole_gains(self.angle_bandwidth, self.bias_bandwidth, h)
            m1, m2 = discrete_pole_gains(self.rate_bandwidth, self.rate_bandwidth, h)
            gains = self._gains_cache[h] = (l1, l2, m1, m2)
        return gains

    def reset(self, initial_output: float, initial_time: float = 0.0) -> None:
        """Angle y0 at ``initial_time`` [s]; rate, bias, disturbance zero.

        The first update at the same time takes the measured rate as the rate estimate.
        """
        self._reset_estimate(initial_output, initial_time)
        self.bias = 0.0
        self._t_prev = float(initial_time)
        self._rate_started = False
        self._rate_prev = 0.0

    def update(self, t: float, y: float, rate: float, b_u: float) -> tuple[float, float, float]:
        """Advance to ``t`` [s] with the angle ``y`` [rad] and the gyro ``rate`` [rad/s].

        Both are measured at t; ``b_u`` [rad/s²] is the input held since the previous
        update. Return (â, ẑ1, f̂).
        """
        if not math.isfinite(t + y + rate + b_u):
            raise ValueError(f'{self.name}: non-finite input t={t!r}, y={y!r}, '
                             f'rate={rate!r}, b_u={b_u!r}')
        h = t - self._t_prev
        if h < 0.0:
            raise ValueError(f'{self.name}: time went backwards from {self._t_prev} to {t}')
        if not self._rate_started:
            self.x2 = rate - self.bias
            self._rate_prev = rate
            self._rate_started = True
        if h == 0.0:
            return self.x1, self.x2, self.f
        if abs(h - self.sample_period) <= _PERIOD_TOLERANCE * self.sample_period:
            h = self.sample_period
            l1, l2, m1, m2 = self._nominal_gains
        else:
            l1, l2, m1, m2 = self._gains(h)
        # 1: complementary filter with bias (predict with the corrected gyro, correct
        # with the angle).
        # Trapezoidal integration of the gyro: exact for a constant acceleration (the
        # rectangle rule would leave a bias estimate off by h θ̈/2).
        angle = self.x1 + h * (0.5 * (self._rate_prev + rate) - self.bias)
        self._rate_prev = rate
        e = y - angle
        self.x1 = angle + l1 * e
        self.bias -= l2 * e
        # 2: reduced-order ESO on the bias-corrected rate.
        w = self.x2 + h * (b_u + self.f)
        e = rate - self.bias - w
        self.x2 = w + m1 * e
        self.f += m2 * e
        self._t_prev = t
        return self.x1, self.x2, self.f


def rate_eso_noise_variance(rate_noise_std: float, bandwidth: float, period: float,
                            exact: bool = True) -> float:
    """Stationary variance of f̂ [(rad/s²)²] of the reduced-order rate ESO.

    The ESO is the one of :class:`RateAidedChannel`, and the rate noise is white with std
    σ [rad/s] per sample.

    ``exact``: the discrete Lyapunov equation of the error loop; else the continuous
    approximation σ² h ω³/4 (valid for ω h ≪ 1).
    """
    if not exact:
        return rate_noise_std ** 2 * period * bandwidth ** 3 / 4.0
    m1, m2 = discrete_pole_gains(bandwidth, bandwidth, period)
    # Error e = (e1, e2) = (w − ẑ1, f − f̂), noise n on the measured rate:
    # e⁺ = A e + B n, A = [[1 − M1, (1 − M1) h], [−M2, 1 − M2 h]], B = (−M1, −M2)... sign
    # irrelevant for the variance.
    a = np.array([[1.0 - m1, (1.0 - m1) * period], [-m2, 1.0 - m2 * period]])
    b = np.array([[m1], [m2]])
    cov = scipy.linalg.solve_discrete_lyapunov(a, rate_noise_std ** 2 * (b @ b.T))
    return float(cov[1, 1])


class StateEstimate(NamedTuple):
    """Output of :class:`WipStateObserver` at one sample."""

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


class WipStateObserver:
    """The three ESOs of [1]_ for a WIP: yaw, eq. (4); distance and tilt, eq. (8).

    The input gains are those of eq. (1) at the current tilt estimate θ̂ (taken at the
    start of each period and held with the torques); the yaw channel uses
    ĝ1 = ``yaw_input_gain_scale`` · g1(θ̂), the paper's 20 % error.

    Parameters
    ----------
    params : nominal WIP parameters (the controllers' model).
    config : observer tunables.
    initial_positions : (ϕ [rad], x_v [m], θ [rad]) at ``initial_time``; the ESOs start
        there with zero rates and disturbances (Section V).
    initial_time : time [s] of the initial state, and origin of the ε ramp.
    """

    def __init__(self, params: WipParameters, config: EsoConfig | None = None,
                 initial_positions: Sequence[float] = (0.0, 0.0, 0.0),
                 initial_time: float = 0.0, *,
                 encoders_relative_to_body: bool = False) -> None:
        self.params = params
        # 'gyro': x_v = r((φl + φr)/2 + θ) is recomputed with the filtered θ̂ instead of
        # the raw IMU pitch, whose noise r·σθ the x_v ESO would otherwise differentiate.
        self._xv_pitch_correction = (params.wheel_radius if encoders_relative_to_body
                                     else 0.0)
        self.config = config = config if config is not None else EsoConfig()
        config.validate()
        common = dict(epsilon=config.epsilon, sample_period=config.sample_period,
                      schedule=config.epsilon_schedule, ramp_duration=config.ramp_duration,
                      measurement_hold=config.measurement_hold)
        self.gyro = config.estimator == 'gyro'
        if self.gyro:
            # The rates are measured: angle/rate channels, and a bandwidth-parameterised
            # x_v ESO (all three poles at −ω_l: gains (3, 3, 1), ε = 1/ω_l).
            h = config.sample_period
            self.yaw = RateAidedChannel(config.yaw_angle_bandwidth,
                                        config.gyro_bias_bandwidth,
                                        config.yaw_rate_bandwidth, h, name='yaw')
            self.tilt = RateAidedChannel(config.tilt_angle_bandwidth,
                                         config.gyro_bias_bandwidth,
                                         config.tilt_rate_bandwidth, h, name='tilt')
            self.longitudinal = ExtendedStateObserver(
                (3.0, 3.0, 1.0), 1.0 / config.longitudinal_bandwidth, h,
                measurement_hold=config.measurement_hold, name='longitudinal',
                rate_start=config.speed_start)
        else:
            self.yaw = ExtendedStateObserver(config.yaw_gains, name='yaw_gains', **common)
            self.longitudinal = ExtendedStateObserver(config.longitudinal_gains,
                                                      name='longitudinal_gains',
                                                      rate_start=config.speed_start, **common)
            self.tilt = ExtendedStateObserver(config.tilt_gains, name='tilt_gains',
                                              **common)
        self._yaw_scale = config.yaw_input_gain_scale
        self.reset(initial_positions, initial_time)

    def reset(self, initial_positions: Sequence[float], initial_time: float = 0.0) -> None:
        """Restart from positions (ϕ, x_v, θ) with zero rates and disturbances."""
        if len(initial_positions) != 3:
            raise ValueError('initial_positions: expected (phi, x_v, theta), got '
                             f'{initial_positions!r}')
        phi, x_v, theta = (float(v) for v in initial_positions)
        for label, value in (('phi', phi), ('x_v', x_v), ('theta', theta),
                             ('initial_time', initial_time)):
            if not math.isfinite(value):
                raise ValueError(f'initial {label} must be finite, got {value!r}')
        self.yaw.reset(phi, initial_time)
        self.longitudinal.reset(x_v, initial_time)
        self.tilt.reset(theta, initial_time)
        self._phi_meas = phi
        self._estimate = self._make_estimate(initial_time)

    @property
    def estimate(self) -> StateEstimate:
        """The latest estimate."""
        return self._estimate

    def _make_estimate(self, t: float) -> StateEstimate:
        y, lon, tilt = self.yaw, self.longitudinal, self.tilt
        return StateEstimate(y.x1, y.x2, y.f, lon.x1, lon.x2, lon.f, tilt.x1, tilt.x2,
                             tilt.f, self.epsilon_at(t))

    def epsilon_at(self, t: float) -> float:
        """ε [s] in use at ``t`` (gyro estimator: 1/ω_l of the x_v ESO, constant)."""
        return self.longitudinal.epsilon_at(t) if self.gyro else self.yaw.epsilon_at(t)

    def in_ramp(self, t: float) -> bool:
        """Return True while the paper's ε ramp runs (never with the gyro estimator)."""
        return False if self.gyro else self.yaw.in_ramp(t)

    @property
    def needs_rates(self) -> bool:
        """Whether :meth:`update` needs the IMU angular rates."""
        return self.gyro

    def update(self, t: float, phi_meas: float, xv_meas: float, theta_meas: float,
               tau_v_applied: float, tau_omega_applied: float,
               rates: Sequence[float] | None = None) -> StateEstimate:
        """Advance the three ESOs to time ``t`` [s].

        Parameters
        ----------
        t : sample time [s], ≥ the previous one (equal: estimate unchanged).
        phi_meas : measured yaw ϕ [rad]; moved to the 2π branch nearest the previous
            sample, so a wrapped (−π, π] yaw is accepted.
        xv_meas : measured distance rolled x_v [m] (wheel odometry; with
            ``encoders_relative_to_body`` the 'gyro' estimator replaces the raw pitch in
            it by θ̂).
        theta_meas : measured tilt θ [rad] (IMU).
        tau_v_applied, tau_omega_applied : τυ = τl + τr and τω = τr − τl [N·m] applied
            (held) since the previous update.
        rates : (θ̇, ϕ̇) [rad/s] measured by the IMU's gyro (sensor_msgs/Imu
            angular_velocity, as Euler rates); required by the 'gyro' estimator,
            ignored by the 'paper' one.

        Raises
        ------
        ValueError
            on a non-finite input or a time going backwards; the state is unchanged.
        """
        # One sum detects any NaN/inf among the inputs (inf − inf = NaN).
        if not math.isfinite(t + phi_meas + xv_meas + theta_meas + tau_v_applied
                             + tau_omega_applied):
            names = ('t', 'phi_meas', 'xv_meas', 'theta_meas', 'tau_v_applied',
                     'tau_omega_applied')
            values = (t, phi_meas, xv_meas, theta_meas, tau_v_applied, tau_omega_applied)
            bad = [f'{n}={v!r}' for n, v in zip(names, values) if not math.isfinite(v)]
            raise ValueError(f'WipStateObserver.update: non-finite input {", ".join(bad)}')
        if t < self.yaw.time:
            raise ValueError(f'WipStateObserver.update: time went backwards from '
                             f'{self.yaw.time} to {t}')
        d = phi_meas - self._phi_meas
        if d > math.pi or d < -math.pi:
            phi_meas -= _TWO_PI * round(d / _TWO_PI)
        self._phi_meas = phi_meas
        # Eq. (1) input gains at θ̂ of the start of the period, held like the torques.
        g1, g2, g3 = input_gains(self.params, self.tilt.x1)
        if self.gyro:
            if rates is None or len(rates) != 2:
                raise ValueError("WipStateObserver.update: the 'gyro' estimator needs the "
                                 f'IMU rates (pitch_rate, yaw_rate), got {rates!r}')
            pitch_rate, yaw_rate = float(rates[0]), float(rates[1])
            if not math.isfinite(pitch_rate + yaw_rate):
                raise ValueError(f'WipStateObserver.update: non-finite rates {rates!r}')
            self.yaw.update(t, phi_meas, yaw_rate, self._yaw_scale * g1 * tau_omega_applied)
            theta_hat = self.tilt.update(t, theta_meas, pitch_rate, g3 * tau_v_applied)[0]
            xv_meas += self._xv_pitch_correction * (theta_hat - theta_meas)
            self.longitudinal.update(t, xv_meas, g2 * tau_v_applied)
        else:
            self.yaw.update(t, phi_meas, self._yaw_scale * g1 * tau_omega_applied)
            self.longitudinal.update(t, xv_meas, g2 * tau_v_applied)
            self.tilt.update(t, theta_meas, g3 * tau_v_applied)
        self._estimate = estimate = self._make_estimate(t)
        return estimate
