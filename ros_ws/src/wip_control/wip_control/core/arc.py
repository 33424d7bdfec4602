r"""Adaptive robust control (ARC) of the yaw rate, eqs. (10)–(15) in [1]_.

The yaw subsystem ω̇ = f1 + g1 τω (10) is written α ω̇ = α f1 + τω (11), α = 1/g1 [kg m²],
and controlled with

.. math::

    e_\omega = \hat\omega - \omega_d, \quad
    \tau_\omega = \mathrm{sat}\big(\hat\alpha \dot\omega_d - \hat\alpha \hat f_1
        - k_\omega e_\omega, \pm\tau_{\omega,max}\big) \quad (12), \qquad
    \dot{\hat\alpha} = -\gamma e_\omega (\dot\omega_d - \hat f_1) \quad (13)

Sign check (REP 103, τω = τr − τl turns counter-clockwise, g1 > 0): with α̂ = α and
f̂1 = f1, (10) and (12) give ω̇ = f1 + (ω̇_d − f1) − g1 kω e_ω, i.e. ė_ω = −g1 kω e_ω.

Deviations from the paper:

- α̂ is kept in [``alpha_min``, ``alpha_max``] by projection (docs/paper.md §4: the
  law (13) alone can drift, e.g. when f̂1 is biased). Defaults [0.05, 5] kg m²: α(θ)
  of the default robot is 0.39 at θ = 0 and 4.0 at θ = ±π/2, so the interval holds every
  tilt and an unknown yaw inertia down to 1/8 of the nominal;
- (13) is integrated by explicit Euler at the control period with the projection applied
  after each step (clip to the interval: the standard discrete projection, which makes
  the update non-expansive toward any α in the interval);
- the saturation of (12) is the paper's "practical" remark after Theorem 3;
- optional robust modifications of (13) (all off with the paper's settings): dead zone
  on e_ω, normalisation by 1 + ν φ², σ-leakage toward α̂(0) (docs/estimation.md).

The α̂ returned with τω is the one used to compute it (before this step's update).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

from wip_runtime.config import ParamError, param


@dataclasses.dataclass(frozen=True)
class ArcParams:
    """Gains and limits of the yaw ARC, eqs. (12), (13) in [1]_.

    Gains: Section V; the robust adaptation terms default on, the scenario key ``design: paper``
    turns them off.
    """

    yaw_rate_gain: float = param(20.0, 'N m s/rad', 'k_omega of eq. (12)', minimum=0.0,
                                 exclusive_minimum=True)
    adaptation_gain: float = param(50.0, 'N m s^4/rad^3', 'gamma of eq. (13); 0 freezes '
                                   'alpha_hat', minimum=0.0)
    max_yaw_torque: float = param(0.8, 'N m', 'tau_omega,max: saturation of eq. (12)',
                                  minimum=0.0, exclusive_minimum=True)
    alpha_min: float = param(0.05, 'kg m^2', 'lower projection bound of alpha_hat = 1/g1 '
                             'estimate', minimum=0.0, exclusive_minimum=True)
    alpha_max: float = param(5.0, 'kg m^2', 'upper projection bound of alpha_hat',
                             minimum=0.0, exclusive_minimum=True)
    adaptation_dead_zone: float = param(
        0.005, 'rad/s', 'no adaptation (13) of alpha_hat while |e_omega| is below this '
        '(paper: 0; docs/decisions/estimation-parameters.md)', minimum=0.0, maximum=10.0)
    adaptation_normalisation: float = param(
        1.0, 's^4/rad^2', 'nu in d(alpha_hat)/dt = -gamma e phi / (1 + nu phi^2), phi = '
        'omega_d_dot - f1_hat: bounds the step when phi jumps (corners, GPS jumps; '
        'paper: 0)', minimum=0.0, maximum=1e6)
    adaptation_leakage: float = param(
        0.01, '1/s', 'sigma-modification -sigma (alpha_hat - alpha_initial): alpha_hat '
        'returns to the nominal 1/g1 when not excited (paper: 0)', minimum=0.0,
        maximum=100.0)
    adapt_while_saturated: bool = param(
        False, '1', 'run the adaptation (13) while tau_omega is saturated (paper: true; '
        'docs/decisions/estimation-parameters.md)')

    def validate(self) -> None:
        if not self.alpha_max > self.alpha_min:
            raise ParamError(f'alpha_max: must exceed alpha_min = {self.alpha_min}, got '
                              f'{self.alpha_max}')


class ArcOutput(NamedTuple):
    """Output of :class:`AdaptiveRobustYawController` at one step."""

    tau_omega: float  #: τω = τr − τl, saturated [N·m]
    alpha_hat: float  #: α̂ used for this τω [kg m²]
    e_omega: float    #: e_ω = ω̂ − ω_d [rad/s]


class AdaptiveRobustYawController:
    """Yaw-rate tracking by eqs. (12), (13) with projection and saturation.

    Parameters
    ----------
    config : gains and limits.
    alpha_initial : α̂(0) [kg m²], the paper's 1/ĝ1; clipped into the projection interval.
    """

    def __init__(self, config: ArcParams | None = None, alpha_initial: float = 1.0) -> None:
        self.config = config = config if config is not None else ArcParams()
        config.validate()
        self.reset(alpha_initial)

    def reset(self, alpha_initial: float) -> None:
        """Restart the adaptation at α̂ = ``alpha_initial`` [kg m²] (projected)."""
        if not math.isfinite(alpha_initial):
            raise ValueError(f'alpha_initial must be finite, got {alpha_initial!r}')
        cfg = self.config
        self.alpha_hat = min(max(float(alpha_initial), cfg.alpha_min), cfg.alpha_max)
        self.alpha_nominal = self.alpha_hat   #: the leakage's target [kg m²]

    def step(self, dt: float, omega_hat: float, f1_hat: float, omega_d: float,
             omega_d_dot: float) -> ArcOutput:
        """One control period.

        Parameters
        ----------
        dt : control period [s], > 0 (Euler step of (13)).
        omega_hat : ω̂ [rad/s] from the ESO.
        f1_hat : f̂1 [rad/s²] from the ESO.
        omega_d, omega_d_dot : ω_d [rad/s], ω̇_d [rad/s²] from the generator.

        Raises
        ------
        ValueError
            on non-finite inputs or dt ≤ 0; α̂ is unchanged.
        """
        if not (math.isfinite(dt + omega_hat + f1_hat + omega_d + omega_d_dot) and dt > 0.0):
            raise ValueError(f'AdaptiveRobustYawController.step: need finite inputs and '
                             f'dt > 0, got dt={dt!r}, omega_hat={omega_hat!r}, '
                             f'f1_hat={f1_hat!r}, omega_d={omega_d!r}, '
                             f'omega_d_dot={omega_d_dot!r}')
        cfg = self.config
        alpha = self.alpha_hat
        e_omega = omega_hat - omega_d
        regressor = omega_d_dot - f1_hat
        tau = alpha * regressor - cfg.yaw_rate_gain * e_omega            # Eq. (12) in [1]
        limit = cfg.max_yaw_torque
        saturated = abs(tau) > limit
        tau = max(-limit, min(limit, tau))
        if saturated and not cfg.adapt_while_saturated:
            return ArcOutput(tau, alpha, e_omega)
        # Eq. (13), explicit Euler, then projection onto [alpha_min, alpha_max]; with the
        # robust modifications (Ioannou & Sun, ch. 8): a dead zone on e_ω (the update is
        # off while |e_ω| ≤ e0, and uses e_ω − e0 sign(e_ω) beyond, continuous), the
        # normalised regressor φ/(1 + ν φ²) and the σ-leakage toward α̂(0).
        dead = cfg.adaptation_dead_zone
        if abs(e_omega) <= dead:
            error = 0.0
        else:
            error = e_omega - math.copysign(dead, e_omega)
        rate = -cfg.adaptation_gain * error * regressor / (
            1.0 + cfg.adaptation_normalisation * regressor * regressor)
        rate -= cfg.adaptation_leakage * (alpha - self.alpha_nominal)
        alpha_next = alpha + rate * dt
        self.alpha_hat = min(max(alpha_next, cfg.alpha_min), cfg.alpha_max)
        return ArcOutput(tau, alpha, e_omega)
