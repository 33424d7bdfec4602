"""The rate-aided channel: an angle and its rate measured by the IMU (estimator 'gyro').

A complementary filter with a gyro-bias estimate gives the angle, and a reduced-order ESO
(the paper's eq. (4) without its position channel) on the bias-corrected rate gives the
rate and the lumped disturbance of [1]_. The design and its noise figures:
docs/estimation.md.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import math

import numpy as np

from wip_runtime.config import ParamError
from .compiled import array_slot
from .eso import _OWN, ChannelEstimate, F, PERIOD_TOLERANCE, TIME, X1, X2

#: The rate-aided channel's own slots: the gyro bias b̂, the previous gyro reading, and 1.0
#: once the rate estimate has started from a gyro reading.
BIAS, RATE_PREV, RATE_STARTED = _OWN, _OWN + 1, _OWN + 2


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


def rate_aided_step(s: np.ndarray | list[float], t: float, h: float, y: float, rate: float,
                    b_u: float, l1: float, l2: float, m1: float, m2: float) -> None:
    """Advance a rate-aided channel's state ``s`` in place by one period h, to ``t`` [s].

    The two loops of :class:`RateAidedChannel` with their gains; the compiled estimator
    runs this very function.
    """
    # 1: complementary filter with bias (predict with the corrected gyro, correct
    # with the angle).
    # Trapezoidal integration of the gyro: exact for a constant acceleration (the
    # rectangle rule would leave a bias estimate off by h θ̈/2).
    angle = s[X1] + h * (0.5 * (s[RATE_PREV] + rate) - s[BIAS])
    s[RATE_PREV] = rate
    e = y - angle
    s[X1] = angle + l1 * e
    s[BIAS] -= l2 * e
    # 2: reduced-order ESO on the bias-corrected rate.
    w = s[X2] + h * (b_u + s[F])
    e = rate - s[BIAS] - w
    s[X2] = w + m1 * e
    s[F] += m2 * e
    s[TIME] = t


class RateAidedChannel(ChannelEstimate):
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
                raise ParamError(f'{name}.{label}: must be finite and > 0, got {value!r}')
        self.name = name
        self.angle_bandwidth = float(angle_bandwidth)
        self.bias_bandwidth = float(bias_bandwidth)
        self.rate_bandwidth = float(rate_bandwidth)
        self.sample_period = float(sample_period)
        self._s = np.zeros(_OWN + 3)
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
        self._s[RATE_STARTED] = 0.0
        self._s[RATE_PREV] = 0.0

    bias = array_slot('_s', BIAS, 'b̂, the gyro bias estimate [rad/s]')

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
        s = self._s.tolist()   # Python floats (see ChannelEstimate)
        if not s[RATE_STARTED]:
            s[X2] = rate - s[BIAS]
            s[RATE_PREV] = rate
            s[RATE_STARTED] = 1.0
        if h != 0.0:
            if abs(h - self.sample_period) <= PERIOD_TOLERANCE * self.sample_period:
                h = self.sample_period
                l1, l2, m1, m2 = self._nominal_gains
            else:
                l1, l2, m1, m2 = self._gains(h)
            rate_aided_step(s, t, h, y, rate, b_u, l1, l2, m1, m2)
        self._s[:] = s
        return s[X1], s[X2], s[F]


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
    import scipy.linalg   # here: only this variance needs SciPy, not the observer
    cov = scipy.linalg.solve_discrete_lyapunov(a, rate_noise_std ** 2 * (b @ b.T))
    return float(cov[1, 1])
