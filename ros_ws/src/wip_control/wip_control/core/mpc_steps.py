r"""The MPC's steps before the QP: start-up, speed preview, dead-zone decay, offset-free target.

Each turns the tick's estimates into the data of the QP (22) of [1]_ (why each exists,
with the measured effects: docs/decisions/mpc-parameters.md):

- :class:`StartUp`: for ``disturbance_startup_time`` after a reset, model (1)'s own drift
  at the estimate replaces the ESO's f̂2, f̂3 in the free response (17).
- :class:`SpeedPreview`: the filtered trend dυd/dt that continues υd over the horizon in
  the reference ȳr of (20).
- :func:`decaying_excess`: the part of the disturbance's transient beyond the dead zone,
  which decays over the horizon instead of being held as in (17).
- :class:`OffsetFreeTarget`: the tilt θs of ȳr that balances the estimated constant
  disturbance (θ = 0 in the paper's (20)).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math

from .model import nominal_terms
from .mpc_config import MpcParams
from .mpc_prediction import gravity_coefficients
from wip_description.params import ModelParams


class StartUp:
    """The estimator's start-up after a reset: its f̂ transient is not a disturbance.

    The ESO starts with zero rates and disturbances; for ``disturbance_startup_time`` the
    MPC uses model (1)'s drift at the estimate, and on the first tick no speed error (its
    υ̂ is the zero start, not a measurement).
    """

    def __init__(self, params: ModelParams, config: MpcParams) -> None:
        self.params = params
        self.duration = config.disturbance_startup_time
        self.reset()

    def reset(self) -> None:
        self.ticks = 0
        self.elapsed = 0.0     #: time since the reset at the start of a tick [s]

    @property
    def active(self) -> bool:
        """Whether the start-up is still on (the ESO's f̂ are not used)."""
        return self.elapsed < self.duration - 1e-9

    def estimates(self, v_hat: float, theta_hat: float, theta_dot_hat: float,
                  f2_hat: float, f3_hat: float, v_d: float,
                  period: float) -> tuple[float, float, float]:
        """(υ̂, f̂2, f̂3) the tick uses; counts the tick of length ``period`` [s]."""
        if self.active and math.isfinite(v_hat + theta_hat + theta_dot_hat + f2_hat + f3_hat):
            nominal = nominal_terms(self.params, theta_hat, 0.0, theta_dot_hat)
            f2_hat, f3_hat = nominal.f2, nominal.f3
            if self.ticks == 0:
                v_hat = v_d
        self.ticks += 1
        self.elapsed += period
        return v_hat, f2_hat, f3_hat


class SpeedPreview:
    """dυd/dt, low-passed and bounded, for the speed reference over the horizon.

    The reference of step i is υd + min(i Ts, T) · trend, clipped to ±υmax
    (``speed_preview_time`` T > 0); else υd held, as in (20).
    """

    def __init__(self, config: MpcParams) -> None:
        self.on = config.speed_preview_time > 0.0
        self.time_constant = config.speed_trend_filter_time_constant
        self.max_trend = config.max_speed_trend
        self.reset()

    def reset(self) -> None:
        self.v_d_last: float | None = None
        self.trend = 0.0

    def update(self, v_d: float, period: float) -> float:
        """Filter the trend with this tick's υd, ``period`` [s] after the last; return it."""
        if not self.on:
            return 0.0
        if self.v_d_last is not None:
            ts = period
            rate = (v_d - self.v_d_last) / ts
            gain = ts / (self.time_constant + ts)  # backward Euler
            rate = min(max(rate, -self.max_trend), self.max_trend)
            self.trend += gain * (rate - self.trend)
        self.v_d_last = v_d
        return self.trend


def excess(value: float, band: float) -> float:
    """Return the part of ``value`` beyond ±``band`` (0 inside it)."""
    if value > band:
        return value - band
    if value < -band:
        return value + band
    return 0.0


def decaying_excess(transient: tuple[float, float],
                    zone: tuple[float, float]) -> tuple[float, float]:
    """Return the part of the transient (d2, d3) beyond the zone: it decays over the horizon.

    Only the excess over the dead zone decays; the rest is held like f̂ itself.
    """
    return excess(transient[0], zone[0]), excess(transient[1], zone[1])


def beyond(transient: tuple[float, float], zone: tuple[float, float]) -> bool:
    """Whether either transient (d2, d3) is beyond its band of the dead zone."""
    return abs(transient[0]) > zone[0] or abs(transient[1]) > zone[1]


class OffsetFreeTarget:
    """Steady-state target θs, τs from the estimated constant disturbance.

    Offset-free MPC (Pannocchia & Rawlings 2003; Maeder, Borrelli & Morari 2009) with the
    ESO as the disturbance observer. The linearisation of (1) at θ = 0 is
    υ̇ = a_υθ θ + g2 τ + d2, θ̈ = a_θθ θ + g3 τ + d3 (a_υθ = −mp² l² g/Ω0,
    a_θθ = mv mp g l/Ω0, the gravity-aware prediction's terms). The ESO's f̂ lumps
    everything but g τ: the model's own drift and the external disturbance. Against the
    prediction's model (gains g2p, g3p) the present accelerations f̂ + g τ(k−1) leave

        d2 = f̂2 + (g2 − g2p) τ(k−1) − a_υθ θ̂,   d3 = f̂3 + (g3 − g3p) τ(k−1) − a_θθ θ̂,

    low-passed with ``disturbance_filter_time_constant`` (the transients of the
    unmodelled nonlinear terms are not a constant disturbance). The steady state
    (υ̇ = θ̈ = 0) solves [a_υθ g2p; a_θθ g3p] (θs, τs) = −(d2, d3): θs is the lean that
    holds a constant force (a slope, a push). Tracking it instead of the paper's θ = 0
    of (20) removes the standing speed offset that the position loop (9) turns into a
    position offset. |θs| ≤ ``max_target_tilt``. With ``offset_free`` false, θs = 0.
    """

    def __init__(self, params: ModelParams, config: MpcParams) -> None:
        self.config = config
        self.a_v_theta, self.a_theta_theta = gravity_coefficients(params,
                                                                  config.sampling_period)
        self.reset()

    def reset(self) -> None:
        self.disturbance: list[float] | None = None  # filtered (d2, d3)
        self.theta = 0.0
        self.tau = 0.0
        #: (d2, d3) − filtered: the part of the disturbance not in the slow estimate.
        self.transient = (0.0, 0.0)

    def transient_of(self, theta_hat, f2_hat, f3_hat, g2, g3, g2p, g3p, tau_prev):
        """(d2, d3) minus the filtered estimate, without updating the filter.

        None before its first update or with ``offset_free`` off.
        """
        if self.disturbance is None or not self.config.offset_free:
            return None
        d2 = f2_hat + (g2 - g2p) * tau_prev - self.a_v_theta * theta_hat
        d3 = f3_hat + (g3 - g3p) * tau_prev - self.a_theta_theta * theta_hat
        return d2 - self.disturbance[0], d3 - self.disturbance[1]

    def update(self, theta_hat, f2_hat, f3_hat, g2, g3, g2p, g3p, tau_prev,
               period: float | None = None) -> float:
        """Filter the disturbance estimate and return θs [rad] (τs in ``self.tau``).

        ``period``: time since the last update [s] (None: ``sampling_period``).
        """
        cfg = self.config
        if not cfg.offset_free:
            return self.theta
        d2 = f2_hat + (g2 - g2p) * tau_prev - self.a_v_theta * theta_hat
        d3 = f3_hat + (g3 - g3p) * tau_prev - self.a_theta_theta * theta_hat
        if self.disturbance is None:
            self.disturbance = [d2, d3]
        else:
            ts = cfg.sampling_period if period is None else period
            gain = ts / (cfg.disturbance_filter_time_constant + ts)  # backward Euler
            self.disturbance[0] += gain * (d2 - self.disturbance[0])
            self.disturbance[1] += gain * (d3 - self.disturbance[1])
        d2f, d3f = self.disturbance
        self.transient = (d2 - d2f, d3 - d3f)
        # Cramer's rule; at the nominal gains det = −mp g l / (Ω0 r) ≠ 0.
        det = self.a_v_theta * g3p - self.a_theta_theta * g2p
        theta_s = (g2p * d3f - g3p * d2f) / det
        bound = cfg.max_target_tilt
        self.theta = min(max(theta_s, -bound), bound)
        # τs holds the (possibly saturated) θs against d2: the υ̇ = 0 row.
        self.tau = -(self.a_v_theta * self.theta + d2f) / g2p
        return self.theta
