r"""MPC of the longitudinal/tilt subsystem, eqs. (16)–(23) in [1]_.

Every ``sampling_period`` Ts the controller takes the ESO's estimates (υ̂, θ̂, θ̂̇, f̂2, f̂3)
and the desired speed υd, solves the condensed QP (22) over the increments
Δτ̄ = (Δτ(k|k), …, Δτ(k+Nc−1|k)) and applies, eq. (23),

.. math::

    \tau_\upsilon(k) = \tau_\upsilon(k-1) + \Delta\tau(k|k).

Cost (20), with ȳ = G̃ Δτ̄ + ȳ_free from :mod:`.mpc_prediction`:

.. math::

    J = \|\bar y_r - \bar y\|^2_Q + \|\Delta\bar\tau\|^2_R
        + \sum_i \left(\rho_{1\upsilon} s_{\upsilon,i} + \rho_1 s_{\theta,i}
        + \rho_2 (s_{\upsilon,i}^2 + s_{\theta,i}^2)\right)

with ȳr = 1_Np ⊗ (υd, θs, 0), Q = I_Np ⊗ diag(q), R = r I_Nc. θs is the offset-free
target of :class:`OffsetFreeTarget` (0 in the paper's (20), ``offset_free: false``). With
``speed_preview_time`` > 0 the speed entry of step i continues υd's trend (bounded,
low-passed) for that long instead of holding υd; the free response ȳ_free holds the
ESO's f̂ as (17) does, except the part of its fast transient beyond
``disturbance_decay_dead_zone``, which decays (a push is not a slope). Why, with
measured effects: ``docs/mpc.md`` §5, §6. As a
QP in z = (Δτ̄, sυ, sθ): ½ zᵀ H z + gᵀ z with H = 2(G̃ᵀQG̃ + R) and
g = −2 G̃ᵀQ(ȳr − ȳ_free) on the Δτ̄ block (eq. (22)), 2ρ2 and ρ1 (ρ1υ for the speed
slacks, ``speed_slack_linear_penalty``) on the slack entries. ``soft_limits: per_step``
(default): one slack per predicted step and limit (Np each); ``worst_case`` (the
paper's): one per limit for the whole horizon. Why the default differs, with measured
effects: ``docs/mpc.md``. With ``speed_rise_penalty`` > 0 a last entry r of z bounds the
rise of the first ``speed_rise_steps`` planned speeds above |υ̂| when |υ̂| ≥ υmax,
weighted ρr r² (docs/mpc.md §9).

Constraints (19), (21), as adopted in docs/paper.md §5:

- hard, box: |Δτ(k+j)| ≤ Δτmax; hard, rows: |τ(k+j)| ≤ τlim for j < Nc (τ is constant
  after Nc−1), τlim = min(``tau_limit``, ``max_drive_torque``);
- soft, rows: |υ(k+i)| ≤ υmax (1 + sυ,i) for i = ``speed_limit_first_step``..Np and
  |θ(k+i)| ≤ θmax (1 + sθ,i) for i = 1..Np, slacks in units relative to the limit,
  ≥ 0 (box); θ̇ unbounded. (With ``worst_case`` every sυ,i is the one sυ.)

Deviation (feasibility): if |τ(k−1)| > τlim (the limit shrinks when |τω| grows), the
hard τ rows cannot all hold under the Δτ limit. The τ bound of step j is then relaxed
to what is reachable, |τ(k+j)| ≤ max(τlim, |τ(k−1)| − (j+1) Δτmax): the torque goes
back inside the limit as fast as the increment limit allows. The QP is always feasible.

Failure handling (logged in :class:`MpcResult`):

- solver status other than solved: apply the previous plan shifted by one step (last
  increment 0), clipped to the hard limits; with no previous plan hold τ(k−1) clipped
  (Δτ = 0 clipped). ``used_fallback`` is set and ``status`` says why.
- NaN/inf input, or a magnitude above :data:`INPUT_MAGNITUDE_LIMIT` (estimates, υd or the
  limit; such values overflow the QP data to inf): no solve, status ``INPUT_INVALID``, and τ
  ramps toward 0 by at most Δτmax. Why not hold τ(k−1): a held drive torque accelerates
  the vehicle without bound while the state is unknown, and the safety layer (mixer)
  zeroes the applied torque on invalid estimates anyway; ramping the MPC's own τ(k−1)
  toward that applied 0 (within the increment limit) means the controller restarts from
  about what is really applied when the estimates come back, instead of from a stale
  torque that the increment limit would then make it unwind slowly.
- a negative ``tau_limit`` is a caller's bug (the limit is 2τmax − |τω| ≥ 0 after the
  yaw controller's saturation) and raises :class:`MpcInputError`.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import NamedTuple

import numpy as np

from .compiled import load_compiled, MPC_QP
from .config import ConfigError, param
from .model import input_gains, nominal_terms
from .mpc_prediction import (PREDICTION_MODELS, CondensedPrediction,
                             gravity_aware_state_matrix)
from .params import WipParameters
from .qp import MpcStatus, QpSettings, make_solver

#: Largest magnitude of an input (SI units: m/s, rad, rad/s, m/s², rad/s², N m) taken as
#: data. Far beyond anything physical (the safety layer's divergence bounds are ≤ 100),
#: far below where the QP data would overflow (values ~1e300 made the gradient inf).
INPUT_MAGNITUDE_LIMIT = 1e9

#: Soft-limit formulations understood by :class:`MpcConfig`.
SOFT_LIMITS = ('per_step', 'worst_case')

#: Status text of a drive torque published at a tick of the re-solve grid without a solve
#: (``mpc.fast_resolve_period``, lockstep; docs/mpc.md §10): the held τυ, no plan. Readers of
#: a record (the report, the viewer, tests) tell it from a solve by this text.
HELD_STATUS_TEXT = 'HELD'

__all__ = ['HELD_STATUS_TEXT', 'LongitudinalMpc', 'MpcConfig', 'MpcInputError', 'MpcResult',
           'MpcStatus', 'PAPER_MPC_SETTINGS', 'QpData']


#: The settings that reproduce the paper's formulation of (19)–(21) as first implemented
#: (one worst-case slack per limit, speed limited from the first step, θ reference 0, the
#: paper's weights): ``mpc: {**PAPER_MPC_SETTINGS}`` in a scenario.
PAPER_MPC_SETTINGS = {'soft_limits': 'worst_case', 'speed_limit_first_step': 1,
                      'speed_slack_linear_penalty': 1e4, 'offset_free': False,
                      'output_weights': (1.0, 50.0, 1.0), 'input_weight': 1.0,
                      'speed_preview_time': 0.0, 'speed_slack_quadratic_penalty': 1e4,
                      'disturbance_startup_time': 0.0, 'speed_rise_penalty': 0.0,
                      'fast_resolve_period': 0.0}


def resolves_faster(sampling_period: float, fast_resolve_period: float) -> bool:
    """Whether the MPC re-solves every ``fast_resolve_period`` after a push (docs/mpc.md §10).

    On when it is above 0 and shorter than ``sampling_period``, else off.
    """
    return 0.0 < fast_resolve_period < sampling_period


class MpcInputError(ValueError):
    """An argument of :meth:`LongitudinalMpc.step` or ``reset`` is not admissible."""


@dataclasses.dataclass(frozen=True)
class MpcConfig:
    """Tunables of the longitudinal/tilt MPC (eqs. (16)–(23) in [1])."""

    controller: str = param(
        'mpc', '-', "'mpc': this QP-based MPC; 'lqr': the saturated discrete LQR baseline "
        'on the same model, rate, weights and torque limits (core/lqr.py)',
        choices=('mpc', 'lqr'))
    sampling_period: float = param(
        0.1, 's', 'Ts: MPC sampling period and Euler step of the prediction (17) '
        '(the paper calls it ε, like the ESO gain)', minimum=0.0, exclusive_minimum=True)
    fast_resolve_period: float = param(
        0.05, 's', 'after a push (the transient disturbance estimate of the offset-free '
        'target beyond disturbance_decay_dead_zone, the part the prediction lets decay) the '
        'MPC re-solves every fast_resolve_period instead of every sampling_period, for '
        'fast_resolve_time; the prediction step stays sampling_period, and each first '
        'increment is bounded so that the torque changes by at most max_delta_torque '
        'within any sampling_period (max_delta_torque · fast_resolve_period / '
        'sampling_period a solve while re-solving). When shorter than sampling_period it '
        'must divide it and be a multiple of the control period (not shorter: off). The '
        'paper plant under IMU/gyro noise fell in 3 of 100 seeds after the 10 m/s² pulse '
        'with the torque held 0.1 s, in none with it; '
        'without a push nothing changes (docs/mpc.md §10). 0: off, the torque is held for '
        'sampling_period (the paper); the LQR baseline never re-solves', minimum=0.0,
        maximum=10.0)
    fast_resolve_time: float = param(
        4.0, 's', 'how long after the last push detected the MPC keeps re-solving every '
        'fast_resolve_period: the recovery, not only the push (1 s: on the full plant under '
        'noise |theta| 0.1008 and 0.1010 rad at 34.3 s, 4 s after the pulse, in 2 of 100 '
        'seeds; 4 s: 0.099 and 0.092)', minimum=0.0, maximum=10.0)
    # Upper bounds keep the QP (Nc + 1 variables, about 4 Np constraints) and the
    # prediction (powers of the unstable tilt dynamics up to Np) numerically sane.
    prediction_horizon: int = param(20, '1', 'Np: predicted steps', minimum=1, maximum=60)
    control_horizon: int = param(6, '1', 'Nc: input increments optimised (<= Np)',
                                 minimum=1, maximum=60)
    output_weights: tuple[float, float, float] = param(
        (10.0, 50.0, 1.0), 's²/m², 1/rad², s²/rad²',
        'diagonal of the per-step output weight of Q in (20), for (υ, θ, θ̇); the paper '
        'uses (1, 50, 1), whose speed loop lags 1.7 s and rides the speed limit',
        minimum=0.0)
    input_weight: float = param(
        0.5, '1/(N m)²', 'R = r I: weight of Δτ in (20); the paper uses 1, with which the '
        'full plant (motor reaction torque) decays 3x slower', minimum=0.0,
        exclusive_minimum=True)
    max_drive_torque: float = param(
        30.0, 'N m', 'hard |τυ| limit 2 τmax (19); the per-call tau_limit is capped to it',
        minimum=0.0, exclusive_minimum=True)
    max_delta_torque: float = param(10.0, 'N m', 'hard |Δτυ| limit per sampling period (19)',
                                    minimum=0.0, exclusive_minimum=True)
    max_speed: float = param(1.5, 'm/s', 'soft |υ| limit (19)', minimum=0.0,
                             exclusive_minimum=True)
    max_tilt: float = param(0.1, 'rad', 'soft |θ| limit (19)', minimum=0.0,
                            exclusive_minimum=True)
    slack_linear_penalty: float = param(
        1e4, '1', 'ρ1: cost per unit of relative violation of a soft limit', minimum=0.0)
    slack_quadratic_penalty: float = param(
        1e4, '1', 'ρ2: cost per squared unit of relative violation of a soft limit',
        minimum=0.0, exclusive_minimum=True)
    soft_limits: str = param(
        'per_step', '-', "'per_step': one slack per predicted step and limit (adopted: "
        "braking from above a limit is preferred to coasting); "
        "'worst_case': one slack per limit for the whole horizon (the paper's reading of "
        '(19)-(21); above the speed limit it coasts)', choices=SOFT_LIMITS)
    speed_limit_first_step: int = param(
        4, '1', 'first predicted step (1..Np) whose speed is limited: a WIP must speed up '
        'before it brakes, so limiting the first steps makes every braking plan costlier '
        'than riding the limit (1 = every step, as in the paper)', minimum=1)
    offset_free: bool = param(
        True, '-', 'track the steady-state target (tilt that balances the estimated '
        "constant disturbance) instead of theta = 0 (false: the paper's reference (20))")
    disturbance_filter_time_constant: float = param(
        0.5, 's', 'low-pass time constant of the constant-disturbance estimate behind the '
        'offset-free target', minimum=0.0)
    disturbance_decay_time_constant: float = param(
        0.1, 's', 'the part of the disturbance estimate not (yet) in the slow estimate of '
        'the offset-free target is predicted to decay with this time constant instead of '
        'staying constant over the horizon (a push is not a slope), beyond '
        "disturbance_decay_dead_zone; 0: held constant (the paper's prediction). With "
        'the dead zone it saved the 6 hard-push falls of the acceptance campaign, docs/mpc.md',
        minimum=0.0, maximum=10.0)
    disturbance_decay_dead_zone: tuple[float, float] = param(
        (1.0, 1.0), 'm/s², rad/s²', '(d2, d3): only the part of the transient disturbance '
        'estimate beyond this band decays (disturbance_decay_time_constant); the part within '
        'it is held constant over the horizon as in the paper. A push of several m/s² is '
        'not extrapolated, while the small transients of model error are held as before',
        minimum=0.0)
    speed_preview_time: float = param(
        0.5, 's', 'the speed reference over the horizon continues the trend of υd (its '
        'change since the last tick, low-passed) for this long, then holds: the MPC '
        'starts braking before the command has dropped (it lags a constant-υd reference '
        'by about a second). 0: υd held over the horizon, as in (20)', minimum=0.0,
        maximum=10.0)
    speed_trend_filter_time_constant: float = param(
        0.3, 's', 'low-pass time constant of the υd trend of speed_preview_time',
        minimum=0.0, maximum=10.0)
    max_speed_trend: float = param(
        1.0, 'm/s²', '|dυd/dt| bound of the trend of speed_preview_time (a push moves υd '
        'faster than any planned speed change; that jump is not extrapolated)',
        minimum=0.0, exclusive_minimum=True)
    max_target_tilt: float = param(
        0.08, 'rad', '|theta| bound of the offset-free steady-state target (a larger '
        'disturbance is not held: the target saturates)', minimum=0.0)
    prediction_gain_scale: tuple[float, float] = param(
        (1.0, 1.0), '1', '(g2, g3) of model (1) are multiplied by these in the prediction '
        'of the increments (toward the motor reaction torque that model (1) omits; (1.11, '
        '1.22) helps the full plant but the paper plant then fell at speed, docs/mpc.md)',
        minimum=0.0, exclusive_minimum=True)
    speed_slack_linear_penalty: float = param(
        0.0, '1', 'rho1 of the speed slacks (the tilt slacks use slack_linear_penalty). 0: '
        'quadratic only. The speed command never exceeds the limit (9), so no exact penalty is '
        'needed, and a linear one makes the small overshoot that precedes braking cost more '
        'than riding the limit; the paper uses rho1 for both', minimum=0.0)
    disturbance_startup_time: float = param(
        0.25, 's', 'start-up of the estimator (it starts with zero rates and disturbances): '
        'for this long after a reset the MPC uses the nominal drift of model (1) at the '
        "estimate instead of the ESO's f2, f3, and on the first tick no speed error "
        '(its speed estimate is the zero start, not a measurement). At speed, the start-up '
        'transient of f2 (+4 m/s2 at 0.1 s) made it brake hard and overshoot to 1.65 m/s. '
        '0: off (the paper)', minimum=0.0, maximum=10.0)
    speed_slack_quadratic_penalty: float = param(
        100.0, '1', 'rho2 of the speed slacks (the tilt slacks use slack_quadratic_penalty). '
        "A WIP must speed up to brake: 1e4 (the paper's, for both limits) made it brake "
        'from 2.2 m/s after a push with a +10 N m step that took it to 2.53 m/s; with 100 '
        'the speed weight q_v still brings it under the limit within 2 s, more gently',
        minimum=0.0, exclusive_minimum=True)
    speed_rise_penalty: float = param(
        1e4, '1', 'weight of the squared rise of the planned speed above |υ̂| ≥ υmax '
        'over the first speed_rise_steps (one slack, relative to υmax). At or above the '
        'limit a WIP must first speed up to brake: this term makes that rise small (the '
        'plan brakes more gently), while it costs nothing to brake or to stay below the '
        'limit. Relative to the current speed, so braking is never costlier than coasting '
        '(a cap at υmax alone made the vehicle run away at 5e3). Only at or above the '
        'limit, and not while the body leans the way it travels (θ̂ + Ts θ̂̇, signed by υ̂, '
        '> 0): then the wheels must speed up to catch it (without these gates, heavy tall '
        'bodies hard pushed fell). '
        'Line entered at the 1.5 m/s limit: peak 1.554 m/s without it, 1.542 with it '
        '(docs/mpc.md §9). 0: off',
        minimum=0.0)
    speed_rise_steps: int = param(
        5, '1', 'predicted steps covered by speed_rise_penalty (the rise before a braking '
        'WIP leans back lasts about 0.3-0.4 s)', minimum=1, maximum=60)
    prediction: str = param(
        'gravity_aware', '-', "'gravity_aware' (adopted) or 'paper' (literal G̃ of (18), "
        'falls; for the ablation)', choices=PREDICTION_MODELS)
    backend: str = param('proxsuite', '-', 'QP solver', choices=('proxsuite', 'daqp'))
    eps_abs: float = param(
        1e-7, '1', 'ProxSuite absolute tolerance (spec: 1e-6 to 1e-8). 1e-7: with 1e-6 and '
        'the speed slacks at rho2 = 100, inputs 1e-9 apart (the node graph against the '
        'runner) gave torques 3e-7 N m apart (the solver stopping an iteration apart); '
        '12.5 iterations per solve on average instead of 12.1', minimum=1e-12, maximum=1e-3)
    eps_rel: float = param(
        1e-11, '1', 'ProxSuite relative tolerance; tiny but not 0, so that the badly scaled '
        'QPs of a falling vehicle converge instead of running for seconds', minimum=0.0,
        maximum=1e-3)
    eps_primal_inf: float = param(
        0.0, '1', 'ProxSuite primal infeasibility tolerance; 0 disables the certificate '
        '(the QP is feasible by construction, 1e-9 gave false alarms)', minimum=0.0,
        maximum=1e-3)
    eps_dual_inf: float = param(
        0.0, '1', 'ProxSuite dual infeasibility tolerance; 0 disables it (H is positive '
        'definite)', minimum=0.0, maximum=1e-3)
    max_iter: int = param(1000, '1', 'iteration limit of the QP solver (ProxSuite: outer '
                          'iterations)', minimum=1, maximum=100000)
    max_inner_iter: int = param(
        30, '1', 'ProxSuite inner iterations per outer one; with max_iter it bounds the '
        'worst-case solve time', minimum=1, maximum=10000)

    def validate(self) -> None:
        if resolves_faster(self.sampling_period, self.fast_resolve_period):
            ratio = self.sampling_period / self.fast_resolve_period
            if abs(ratio - round(ratio)) > 1e-6:
                raise ConfigError(f'fast_resolve_period: must divide sampling_period '
                                  f'({self.sampling_period}) when shorter, got '
                                  f'{self.fast_resolve_period}')
        if self.speed_rise_steps > self.prediction_horizon:
            raise ConfigError(f'speed_rise_steps: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.speed_rise_steps}')
        if self.speed_limit_first_step > self.prediction_horizon:
            raise ConfigError(f'speed_limit_first_step: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.speed_limit_first_step}')
        if self.control_horizon > self.prediction_horizon:
            raise ConfigError(f'control_horizon: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.control_horizon}')

    def qp_settings(self) -> QpSettings:
        return QpSettings(self.eps_abs, self.eps_rel, self.eps_primal_inf, self.eps_dual_inf,
                          self.max_iter, self.max_inner_iter)


class MpcResult(NamedTuple):
    """Output and diagnostics of one MPC tick."""

    tau_v: float             #: τυ(k) to apply and hold for Ts [N m]
    delta_tau: float         #: τυ(k) − τυ(k−1) [N m]
    status: MpcStatus        #: int code; ``status.name`` is the text
    iterations: int          #: QP solver iterations (0 if not run)
    solve_time_s: float      #: wall time of the solver's update + solve [s]
    build_time_s: float      #: wall time of building H, g, C, l, u [s]
    slack_v: float           #: largest sυ,i: relative violation of |υ| ≤ υmax (nan: no solve)
    slack_theta: float       #: largest sθ,i: relative violation of |θ| ≤ θmax (nan: no solve)
    used_fallback: bool      #: true if the applied plan is not a fresh QP solution
    predicted: np.ndarray    #: (Np, 3) predicted (υ, θ, θ̇) for the applied plan
    plan: np.ndarray         #: (Nc,) applied increments Δτ(k|k) … Δτ(k+Nc−1|k) [N m]
    target_theta: float = 0.0  #: θs, tilt reference of the offset-free target [rad]

    @property
    def status_text(self) -> str:
        return self.status.name


class QpData(NamedTuple):
    """The QP of the last tick: ½ zᵀHz + gᵀz, l ≤ Cz ≤ u, lb ≤ z ≤ ub (live buffers)."""

    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray  # noqa: E741 (the solvers' name)
    u: np.ndarray
    lb: np.ndarray
    ub: np.ndarray


def tick_gains(params: WipParameters, config: MpcConfig,
               theta_hat: float) -> tuple[float, float, float, float]:
    """Input gains of model (1) at θ̂ and the scaled gains of the increments.

    (g2, g3, g2p, g3p): the input gains of model (1) at θ̂ (what the ESO assumes, so
    f̂ + g τ(k−1) is its estimate of the present accelerations) and the scaled gains the
    increments are predicted with (``prediction_gain_scale``).
    """
    _, g2, g3 = input_gains(params, theta_hat)
    scale2, scale3 = config.prediction_gain_scale
    return g2, g3, scale2 * g2, scale3 * g3


class PreviousTorque:
    """τυ(k−1) and the start of a tick, of a longitudinal controller.

    τυ(k−1), the drive torque applied since the last tick, and the start of a tick, of a
    longitudinal controller (the MPC and the LQR baseline; both set ``config``,
    ``params``, ``_target`` and ``_tau_previous``).
    """

    config: MpcConfig
    params: WipParameters
    _target: OffsetFreeTarget
    _tau_previous: float = 0.0
    #: Time since the previous tick [s] for the offset-free target's filter (None: the
    #: sampling period; the MPC sets it per tick when it re-solves after a push).
    _period: float | None = None

    def _begin_tick(self, tau_limit: float | None, v_hat: float, theta_hat: float,
                    theta_dot_hat: float, f2_hat: float, f3_hat: float, v_d: float):
        """Start a tick: its |τυ| limit, the input gains at θ̂ and the offset-free target.

        What every tick starts with: the tick's |τυ| limit, the input gains at θ̂
        (``tick_gains``) and the offset-free target updated with them. None when an input
        is invalid (the caller then returns ``_hold_invalid_input()``).
        """
        limit = drive_limit(self.config, tau_limit, v_hat, theta_hat, theta_dot_hat, f2_hat,
                            f3_hat, v_d)
        if limit is None:
            return None
        gains = tick_gains(self.params, self.config, theta_hat)
        self._target.update(theta_hat, f2_hat, f3_hat, *gains, self._tau_previous,
                            self._period)
        return limit, gains

    @property
    def tau_previous(self) -> float:
        """τυ(k−1) [N m], the torque applied since the last tick."""
        return self._tau_previous

    def set_previous_torque(self, tau_previous: float) -> None:
        """Overwrite τυ(k−1) [N m] with the torque really applied.

        E.g. after the safety layer cut it, or to replay a recorded tick.
        """
        tau_previous = float(tau_previous)
        if not math.isfinite(tau_previous):
            raise MpcInputError(f'tau_previous must be finite, got {tau_previous!r}')
        self._tau_previous = tau_previous

    def _hold_invalid_input(self) -> MpcResult:
        """No solve on NaN/inf input: ramp τ toward 0 within Δτmax (see the module doc)."""
        result = invalid_input_result(self.config, self._tau_previous)
        self._tau_previous = result.tau_v
        return result


class LongitudinalMpc(PreviousTorque):
    """Condensed MPC of (υ, θ, θ̇) with the drive torque τυ as input.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : tunables; see :class:`MpcConfig`.
    solver : optional replacement of the backend named by ``config.backend``: any object
        with ``solve(H, g, C, l, u, lb, ub) -> QpSolution`` and ``reset()`` (tests inject
        a failing one).

    Notes
    -----
    Everything that does not depend on the tick's data is computed here: G̃ is bilinear in
    (g2, g3), so G̃ᵀQG̃ = g2² K22 + g2 g3 K23 + g3² K33 with fixed K's, and the rows of C
    are g2 C2 + g3 C3. A tick costs a few small matrix–vector products. The solver
    keeps one persistent workspace (see :mod:`.qp`).

    Decision vector z = (Δτ̄ (Nc), sυ, sθ); Δτ̄ and the slacks' signs are box constraints.
    Rows of C: τ(k..k+Nc−1) (Nc), υ ≤ (Np), θ ≤ (Np), υ ≥ (Np), θ ≥ (Np).

    Why the Hessian is not whitened: docs/decisions/proxsuite-settings.md.
    """

    def __init__(self, params: WipParameters, config: MpcConfig | None = None,
                 solver=None) -> None:
        config = MpcConfig() if config is None else config
        config.validate()
        self.params = params
        self.config = config
        n_p, n_c = config.prediction_horizon, config.control_horizon
        self.prediction = CondensedPrediction(params, config.sampling_period, n_p, n_c,
                                              config.prediction)
        pred = self.prediction
        # Transient part of the disturbance (see disturbance_decay_time_constant): its
        # response, decaying, minus the constant one that the free response already has.
        tau_d = config.disturbance_decay_time_constant
        ratio = math.exp(-config.sampling_period / tau_d) if tau_d > 0.0 else 1.0
        decay_v, decay_theta_dot = pred.decaying_input_columns(ratio)
        self._transient_v = decay_v - pred.free_v_column
        self._transient_theta_dot = decay_theta_dot - pred.free_theta_dot_column
        q = np.tile(np.asarray(config.output_weights, dtype=float), n_p)
        r = config.input_weight

        g2m, g3m = pred.gain_matrix_v, pred.gain_matrix_theta_dot

        # Hessian blocks: H_ΔΔ = coef · K, coef = (2g2², 2g2g3, 2g3², 2).
        qg2, qg3 = q[:, None] * g2m, q[:, None] * g3m
        self._hessian_blocks = np.stack([
            g2m.T @ qg2, g2m.T @ qg3 + g3m.T @ qg2, g3m.T @ qg3,
            r * np.eye(n_c)]).reshape(4, n_c * n_c)
        # Gradient: g_Δ = −2 (g2 G2ᵀQ e + g3 G3ᵀQ e), e = ȳr − ȳ_free.
        self._weighted_gains = np.ascontiguousarray(np.vstack([qg2.T, qg3.T]))  # (2Nc, 3Np)
        # Constraint rows on υ and θ: [υ rows; θ rows] = g2 C2 + g3 C3, stacked (2, 2Np·Nc).
        self._row_blocks = np.stack([
            np.vstack([g2m[0::3], g2m[1::3]]).reshape(-1),
            np.vstack([g3m[0::3], g3m[1::3]]).reshape(-1)])
        # Reachable |τ(k+j) − τ(k−1)| under the increment limit, for the τ rows.
        self._reach = config.max_delta_torque * np.arange(1, n_c + 1)

        # Soft limits. 'worst_case': one slack per limit, sυ ≥ max_i |υ(k+i)|/υmax − 1. A
        # WIP must first speed up to brake (non-minimum phase), so above υmax every braking
        # plan raises that maximum and, at ρ1 = 1e4, costs more than coasting forever.
        # 'per_step': one slack per step and limit with a linear (exact ℓ1) penalty
        # (Kerrigan & Maciejowski 2000): the cost is the summed violation over the horizon,
        # which braking lowers (the speed slacks default to a quadratic penalty only, see
        # ``speed_slack_linear_penalty``). Both keep the QP feasible for any state (the
        # slacks are unbounded above).
        n_s = n_p if config.soft_limits == 'per_step' else 1
        self.n_slacks = n_s
        # The rise slack r (last variable) and its rows: ±υ(k+i) ≤ ±υ̂ + υmax r for
        # i = 1..speed_rise_steps, the sign that of υ̂ (the direction of travel), while
        # ±υ̂ ≥ υmax (else the rows are free, see _build).
        n_rise = config.speed_rise_steps if config.speed_rise_penalty > 0.0 else 0
        self._n_rise = n_rise
        n = n_c + 2 * n_s + (1 if n_rise else 0)
        m = n_c + 4 * n_p + n_rise
        self.n_variables, self.n_constraints = n, m
        self._slice_upper = slice(n_c, n_c + 2 * n_p)
        self._slice_lower = slice(n_c + 2 * n_p, n_c + 4 * n_p)
        self._h = np.zeros((n, n))
        slack_index = np.arange(n_c, n)
        self._h[slack_index, slack_index] = 2.0 * config.slack_quadratic_penalty
        self._h[slack_index[:n_s], slack_index[:n_s]] = 2.0 * config.speed_slack_quadratic_penalty
        self._g = np.zeros(n)
        self._g[n_c:n_c + n_s] = config.speed_slack_linear_penalty
        self._g[n_c + n_s:n_c + 2 * n_s] = config.slack_linear_penalty
        self._c = np.zeros((m, n))
        self._c[:n_c, :n_c] = np.tril(np.ones((n_c, n_c)))
        limits = np.repeat([config.max_speed, config.max_tilt], n_p)
        self._limits = limits
        # Row i of the υ (θ) block uses slack column i (per step) or the single column.
        slack_map = np.eye(n_p) if n_s == n_p else np.ones((n_p, 1))
        v_cols, theta_cols = slice(n_c, n_c + n_s), slice(n_c + n_s, n_c + 2 * n_s)
        self._rise_rows = slice(n_c + 4 * n_p, m)
        if n_rise:
            self._h[n - 1, n - 1] = 2.0 * config.speed_rise_penalty
            self._c[self._rise_rows, n - 1] = -config.max_speed
        for rows, sign in ((self._slice_upper, -1.0), (self._slice_lower, 1.0)):
            block = self._c[rows]
            block[:n_p, v_cols] = sign * config.max_speed * slack_map
            block[n_p:, theta_cols] = sign * config.max_tilt * slack_map
        self._l = np.full(m, -np.inf)
        self._u = np.full(m, np.inf)
        self._lb = np.zeros(n)
        self._ub = np.full(n, np.inf)
        self._lb[:n_c] = -config.max_delta_torque
        self._ub[:n_c] = config.max_delta_torque
        self._n_free_speed = min(config.speed_limit_first_step - 1, n_p)
        self._target = OffsetFreeTarget(params, config)
        self.last_qp = QpData(self._h, self._g, self._c, self._l, self._u, self._lb,
                              self._ub)

        self.last_solution = None  # QpSolution of the last solve (z with every slack)
        self._solver = (make_solver(config.backend, n, m, config.qp_settings())
                        if solver is None else solver)
        self._kernels = _compiled_kernels()   # at construction, not in the first tick
        # The prediction's matrices as the kernels take them (C-contiguous).
        self._free_response = tuple(np.ascontiguousarray(a) for a in (
            pred.free_state_matrix, pred.free_v_column, pred.free_theta_dot_column))
        self._gain_matrices = tuple(np.ascontiguousarray(a) for a in (
            pred.gain_matrix_v, pred.gain_matrix_theta_dot))
        self._tau_previous = 0.0
        # υd trend preview: the reference of step i is υd + min(i Ts, T) · dυd/dt.
        steps = np.arange(1, n_p + 1) * config.sampling_period
        self._preview_ramp = np.minimum(steps, config.speed_preview_time)
        self._v_d_last: float | None = None
        self._v_d_trend = 0.0
        self._plan: np.ndarray | None = None
        self._ticks = 0
        self._elapsed = 0.0            # time since the reset at the start of a tick [s]
        self._period = config.sampling_period   # the tick's elapsed time [s]
        self._first_bound = config.max_delta_torque

    # ------------------------------------------------------------------ state
    def reset(self, tau_previous: float = 0.0) -> None:
        """Forget the plan and the solver's workspace; τυ(k−1) = ``tau_previous`` [N m]."""
        self.set_previous_torque(tau_previous)
        self._plan = None
        self._target.reset()
        self._v_d_last = None
        self._v_d_trend = 0.0
        self._ticks = 0
        self._elapsed = 0.0
        self._solver.reset()

    def set_previous_torque(self, tau_previous: float) -> None:
        """Overwrite τυ(k−1) [N m] with the torque really applied.

        Use it, for example, after the safety layer cut the torque, or to replay a recorded
        tick. The plan and workspace are kept.
        """
        super().set_previous_torque(tau_previous)

    # ------------------------------------------------------------------ tick
    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_limit: float | None = None,
             max_first_delta: float | None = None,
             elapsed: float | None = None) -> MpcResult:
        """One MPC tick: build and solve the QP, apply τ(k) = τ(k−1) + Δτ(k|k) (23).

        Parameters
        ----------
        v_hat : υ̂ [m/s]; theta_hat : θ̂ [rad]; theta_dot_hat : θ̂̇ [rad/s].
        f2_hat : f̂2, the ESO's lumped drift of υ̇ [m/s²]; f3_hat : f̂3, of θ̈ [rad/s²].
        v_d : desired speed υd [m/s] from the trajectory generator (9).
        tau_limit : |τυ| limit for this tick [N m], 2τmax − |τω| so that each wheel stays
            within τmax after mixing (24); capped to ``max_drive_torque``; None uses it.
        max_first_delta : bound of this tick's increment |Δτ(k|k)| [N m], at most (None:)
            ``max_delta_torque``; the later increments keep ``max_delta_torque`` (a tick
            between the sampling instants, ``fast_resolve_period``).
        elapsed : time since the previous tick [s] (None: ``sampling_period``), for the
            filters that run once per tick (υd trend, offset-free target, start-up).
        """
        cfg = self.config
        tau_prev = self._tau_previous
        t_start = time.perf_counter()
        self._set_first_bound(cfg.max_delta_torque if max_first_delta is None
                              else min(max(float(max_first_delta), 0.0), cfg.max_delta_torque))
        period = cfg.sampling_period if elapsed is None else float(elapsed)
        self._period = period
        if (self._elapsed < cfg.disturbance_startup_time - 1e-9
                and math.isfinite(v_hat + theta_hat + theta_dot_hat + f2_hat + f3_hat)):
            # The estimator's start-up (it starts with zero rates and disturbances): its
            # f̂ transient is not a disturbance; use model (1)'s own drift at the estimate.
            nominal = nominal_terms(self.params, theta_hat, 0.0, theta_dot_hat)
            f2_hat, f3_hat = nominal.f2, nominal.f3
            if self._ticks == 0:
                # The first tick's υ̂ is the zero start, not a measurement: no speed error.
                v_hat = v_d
        self._ticks += 1
        self._elapsed += period
        tick = self._begin_tick(tau_limit, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat,
                                v_d)
        if tick is None:
            return self._hold_invalid_input()
        limit, (g2, g3, g2p, g3p) = tick
        free = self._build(v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, v_d, limit, g2,
                           g3, g2p, g3p, tau_prev)
        t_built = time.perf_counter()
        solution = self._solver.solve(self._h, self._g, self._c, self._l, self._u,
                                      self._lb, self._ub)
        t_solved = time.perf_counter()

        n_c = cfg.control_horizon
        n_s = self.n_slacks
        self.last_solution = solution
        if solution.status == MpcStatus.SOLVED:
            plan = solution.z[:n_c].copy()
            slack_v = float(solution.z[n_c:n_c + n_s].max())
            slack_theta = float(solution.z[n_c + n_s:n_c + 2 * n_s].max())
            used_fallback = False
        else:
            plan = self._shifted_plan()
            slack_v = slack_theta = math.nan
            used_fallback = True
        delta = self._admissible_increment(plan[0], tau_prev, limit)
        plan[0] = delta
        self._plan = plan
        self._tau_previous = tau_prev + delta
        predicted = self._kernels.predict(free, float(g2p), float(g3p),
                                          *self._gain_matrices, plan)
        return MpcResult(self._tau_previous, delta, solution.status, solution.iterations,
                         t_solved - t_built, t_built - t_start, slack_v, slack_theta,
                         used_fallback, predicted, plan.copy(),
                         self._target.theta)

    @property
    def target_theta(self) -> float:
        """θs [rad], the tilt reference of the last tick (0 unless ``offset_free``)."""
        return self._target.theta

    def _build(self, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, v_d, limit, g2, g3,
               g2p, g3p, tau_prev) -> np.ndarray:
        """Fill H, g, C, l, u in place; return the free response ȳ_free (3Np).

        The arithmetic is :func:`.mpc_qp.fill` (compiled); the data are this object's.
        """
        cfg = self.config
        transient_v, transient_theta_dot = self._target.transient
        # Only the excess over the dead zone decays; the rest is held like f̂ itself.
        zone_v, zone_theta_dot = cfg.disturbance_decay_dead_zone
        free = np.empty(3 * cfg.prediction_horizon)
        # Floats and C-contiguous float arrays only: the kernel is compiled for those types
        # (another type would compile anew, seconds, in a control tick).
        self._kernels.fill(
            float(v_hat), float(theta_hat), float(theta_dot_hat), float(f2_hat),
            float(f3_hat), float(g2), float(g3), float(g2p), float(g3p), float(tau_prev),
            float(limit), float(_excess(transient_v, zone_v)),
            float(_excess(transient_theta_dot, zone_theta_dot)), float(v_d),
            float(self._speed_trend(v_d)), cfg.speed_preview_time > 0.0,
            float(self._target.theta),
            float(cfg.max_speed), float(cfg.sampling_period), self._n_free_speed,
            self._n_rise, *self._free_response, self._transient_v, self._transient_theta_dot,
            self._hessian_blocks, self._weighted_gains, self._row_blocks, self._limits,
            self._reach, self._preview_ramp, self._h, self._g, self._c, self._l, self._u, free)
        return free

    def _speed_trend(self, v_d: float) -> float:
        """dυd/dt, filtered, for the speed reference over the horizon (0 without a preview).

        The reference of step i is υd + min(i Ts, T) · trend, clipped to ±υmax
        (``speed_preview_time`` T > 0); else υd held, as in (20).
        """
        cfg = self.config
        if cfg.speed_preview_time <= 0.0:
            return 0.0
        if self._v_d_last is not None:
            ts = self._period
            rate = (v_d - self._v_d_last) / ts
            gain = ts / (cfg.speed_trend_filter_time_constant + ts)  # backward Euler
            rate = min(max(rate, -cfg.max_speed_trend), cfg.max_speed_trend)
            self._v_d_trend += gain * (rate - self._v_d_trend)
        self._v_d_last = v_d
        return self._v_d_trend

    # ------------------------------------------------------------------ fallbacks
    def _shifted_plan(self) -> np.ndarray:
        """Previous plan shifted by one tick, last increment 0, within the Δτ limit."""
        n_c = self.config.control_horizon
        shifted = np.zeros(n_c)
        if self._plan is not None:
            shifted[:-1] = self._plan[1:]
        dmax = self.config.max_delta_torque
        return np.clip(shifted, -dmax, dmax)

    def _admissible_increment(self, delta: float, tau_prev: float, limit: float) -> float:
        return admissible_increment(delta, tau_prev, limit, self._first_bound)

    def _set_first_bound(self, bound: float) -> None:
        """Bound |Δτ(k|k)| by ``bound``.

        |Δτ(k|k)| ≤ ``bound``: its box and the reachable |τ(k+j) − τ(k−1)| of the τ
        rows, bound + j Δτmax (the later increments keep Δτmax).
        """
        if bound == self._first_bound:
            return
        self._first_bound = bound
        self._lb[0], self._ub[0] = -bound, bound
        dmax = self.config.max_delta_torque
        self._reach = bound + dmax * np.arange(self.config.control_horizon)

    def push_detected(self, theta_hat: float, f2_hat: float, f3_hat: float) -> bool:
        """Whether the disturbance estimate shows a push.

        Whether the disturbance estimate (f̂2, f̂3) at θ̂, against the offset-free
        target's slow estimate, has a transient beyond ``disturbance_decay_dead_zone`` (what
        the prediction lets decay: a push). Reads the filter without updating it; False
        before its first tick, within ``disturbance_startup_time`` of a reset (the MPC
        does not use the estimator's start-up f̂ then) or with ``offset_free`` off.
        """
        if self._elapsed < self.config.disturbance_startup_time - 1e-9:
            return False
        transient = self._target.transient_of(theta_hat, f2_hat, f3_hat,
                                              *tick_gains(self.params, self.config, theta_hat),
                                              self._tau_previous)
        return (transient is not None
                and _beyond(transient, self.config.disturbance_decay_dead_zone))

    def _hold_invalid_input(self) -> MpcResult:
        self._plan = None
        return super()._hold_invalid_input()


def _beyond(transient: tuple[float, float], zone: tuple[float, float]) -> bool:
    """Whether either transient (d2, d3) is beyond its band of the dead zone."""
    return abs(transient[0]) > zone[0] or abs(transient[1]) > zone[1]


def _compiled_kernels():
    """:mod:`.mpc_qp`, imported and warmed up by the first call in a process."""
    return load_compiled(MPC_QP)


def _excess(value: float, band: float) -> float:
    """Return the part of ``value`` beyond ±``band`` (0 inside it)."""
    if value > band:
        return value - band
    if value < -band:
        return value + band
    return 0.0


def drive_limit(config: MpcConfig, tau_limit: float | None, *inputs: float) -> float | None:
    """Return the |τυ| limit of a tick, capped to ``max_drive_torque``.

    The |τυ| limit of a tick, capped to ``max_drive_torque`` (``tau_limit`` None: that
    cap); None when an input or the limit is not finite or beyond
    :data:`INPUT_MAGNITUDE_LIMIT` (the caller then holds, see ``invalid_input_result``).
    MpcInputError on a negative limit (a caller's bug: 2τmax − |τω| ≥ 0).
    """
    limit = config.max_drive_torque if tau_limit is None else float(tau_limit)
    if not all(math.isfinite(v) and abs(v) <= INPUT_MAGNITUDE_LIMIT
               for v in (*inputs, limit)):
        return None
    if limit < 0.0:
        raise MpcInputError(f'tau_limit must be >= 0 N m, got {limit!r}')
    return min(limit, config.max_drive_torque)


def admissible_increment(delta: float, tau_prev: float, limit: float, dmax: float) -> float:
    """Clip Δτ to the hard limits: |Δτ| ≤ Δτmax and |τ(k−1) + Δτ| ≤ limit when reachable."""
    delta = min(max(float(delta), -dmax), dmax)
    tau = tau_prev + delta
    if tau > limit:
        tau = max(limit, tau_prev - dmax)
    elif tau < -limit:
        tau = min(-limit, tau_prev + dmax)
    return tau - tau_prev


def invalid_input_result(config: MpcConfig, tau_prev: float) -> MpcResult:
    """Return the tick's result on NaN/inf input: τ ramps toward 0 by at most Δτmax."""
    delta = min(max(-tau_prev, -config.max_delta_torque), config.max_delta_torque)
    plan = np.zeros(config.control_horizon)
    plan[0] = delta
    predicted = np.full((config.prediction_horizon, 3), np.nan)
    return MpcResult(tau_prev + delta, delta, MpcStatus.INPUT_INVALID, 0, 0.0, 0.0,
                     math.nan, math.nan, True, predicted, plan)


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

    def __init__(self, params: WipParameters, config: MpcConfig) -> None:
        ts = config.sampling_period
        a = gravity_aware_state_matrix(params, ts)
        self.config = config
        self.a_v_theta = a[0, 1] / ts
        self.a_theta_theta = a[2, 1] / ts
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
