"""Tunables of the longitudinal/tilt MPC, eqs. (16)–(23) in [1]_.

One sentence per parameter here; why each default, with the measured effects:
docs/decisions/mpc-parameters.md.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import dataclasses

from wip_runtime.config import ParamError, param
from .mpc_prediction import PREDICTION_MODELS
from .qp import QpSolverParams

#: Soft-limit formulations understood by :class:`MpcParams`.
SOFT_LIMITS = ('per_step', 'worst_case')

#: The settings that reproduce the paper's formulation of (19)–(21) as first implemented
#: (one worst-case slack per limit, speed limited from the first step, θ reference 0, the
#: paper's weights): ``mpc: {**PAPER_MPC_SETTINGS}`` in a scenario.
PAPER_MPC_SETTINGS = {'soft_limits': 'worst_case', 'speed_limit_first_step': 1,
                      'speed_slack_linear_penalty': 1e4, 'offset_free': False,
                      'output_weights': (1.0, 50.0, 1.0), 'input_weight': 1.0,
                      'speed_preview_time': 0.0, 'speed_slack_quadratic_penalty': 1e4,
                      'disturbance_startup_time': 0.0, 'speed_rise_penalty': 0.0,
                      'fast_resolve_period': 0.0, 'impact_delta_torque': 0.0,
                      'disturbance_average_time': 0.0}

_WHY = 'docs/decisions/mpc-parameters.md'


def resolves_faster(sampling_period: float, fast_resolve_period: float) -> bool:
    """Whether the MPC re-solves every ``fast_resolve_period`` after a push.

    On when it is above 0 and shorter than ``sampling_period``, else off.
    """
    return 0.0 < fast_resolve_period < sampling_period


def drive_tick_decimation(decimation: int, fast_decimation: int | None,
                          push_trigger: bool) -> int:
    """Return the control ticks between the drive stage's ticks.

    There it takes its inputs and, in lockstep, answers with a drive torque:
    ``decimation`` (control ticks per ``sampling_period``); ``fast_decimation`` (per
    ``fast_resolve_period``; None: no re-solving) when the MPC re-solves after a push; 1
    when it also looks for a push at every control tick (``push_trigger``).
    """
    if fast_decimation is None or not 1 <= fast_decimation < decimation:
        return decimation
    return 1 if push_trigger else fast_decimation


@dataclasses.dataclass(frozen=True)
class MpcParams:
    """Tunables of the longitudinal/tilt MPC (eqs. (16)–(23) in [1])."""

    controller: str = param(
        'mpc', '-', "'mpc': the QP-based MPC of (16)-(23); 'lqr': the saturated discrete "
        f'LQR baseline on the same model, weights and limits (core/lqr.py); {_WHY}',
        choices=('mpc', 'lqr'))
    sampling_period: float = param(
        0.1, 's', 'Ts: MPC sampling period and Euler step of the prediction (17) (the '
        "paper's ε)", minimum=0.0, exclusive_minimum=True)
    fast_resolve_period: float = param(
        0.05, 's', 'after a push the MPC re-solves (23) every this long for '
        f'fast_resolve_time, within max_delta_torque per Ts; divides Ts; 0: off; {_WHY}',
        minimum=0.0, maximum=10.0)
    push_trigger: bool = param(
        True, '-', 'with fast_resolve_period set, look for a push at every control tick and '
        're-solve on the tick it is seen, the re-solve grid starting there; false: at the '
        f"grid's ticks; {_WHY}")
    resolve_rate_rule: str = param(
        'sum', '-', "while re-solving, how |Δτυ| <= max_delta_torque per Ts holds: 'sum' of "
        "|increments| over the last Ts, or 'net': the torque within it of each torque of the "
        f'last Ts; {_WHY}', choices=('sum', 'net'))
    push_resolve_share: float = param(
        0.75, '1', 'while re-solving after a push, the largest |increment| of one solve as a '
        f'share of max_delta_torque (the rate rule holds besides); {_WHY}', minimum=0.0,
        exclusive_minimum=True, maximum=1.0)
    fast_resolve_time: float = param(
        4.0, 's', 'how long after the last push detected the MPC keeps re-solving every '
        f'fast_resolve_period; {_WHY}', minimum=0.0, maximum=10.0)
    # Upper bounds keep the QP (Nc + 1 variables, about 4 Np constraints) and the
    # prediction (powers of the unstable tilt dynamics up to Np) numerically sane.
    prediction_horizon: int = param(20, '1', 'Np: predicted steps of (18)', minimum=1,
                                    maximum=60)
    control_horizon: int = param(6, '1', 'Nc: input increments optimised in (22) (<= Np)',
                                 minimum=1, maximum=60)
    output_weights: tuple[float, float, float] = param(
        (10.0, 50.0, 1.0), 's²/m², 1/rad², s²/rad²',
        f'diagonal of the per-step output weight Q of (20) for (υ, θ, θ̇); paper: (1, 50, 1); '
        f'{_WHY}', minimum=0.0)
    input_weight: float = param(
        0.5, '1/(N m)²', f'R = r I: weight of Δτ in (20); paper: 1; {_WHY}', minimum=0.0,
        exclusive_minimum=True)
    max_drive_torque: float = param(
        30.0, 'N m', 'hard |τυ| limit 2 τmax of (19); the per-call tau_limit is capped to it',
        minimum=0.0, exclusive_minimum=True)
    max_delta_torque: float = param(10.0, 'N m', 'hard |Δτυ| limit per sampling period (19)',
                                    minimum=0.0, exclusive_minimum=True)
    impact_delta_torque: float = param(
        20.0, 'N m', 'hard |Δτυ| limit per sampling period for impact_hold after a solve saw '
        'f̂2 oppose υd by more than impact_deceleration (an obstacle); <= max_delta_torque: '
        f'off; {_WHY}',
        minimum=0.0)
    impact_deceleration: float = param(
        2.0, 'm/s²', 'the drift f̂2 against the direction of υd that a solve takes for an '
        f'obstacle stopping the base (impact_delta_torque); {_WHY}', minimum=0.0,
        exclusive_minimum=True)
    impact_hold: float = param(
        2.0, 's', 'how long after a solve last saw an obstacle stopping the base the rate '
        f'limit stays impact_delta_torque; {_WHY}', minimum=0.0, maximum=60.0)
    max_speed: float = param(1.5, 'm/s', 'soft |υ| limit (19)', minimum=0.0,
                             exclusive_minimum=True)
    max_tilt: float = param(0.1, 'rad', 'soft |θ| limit (19)', minimum=0.0,
                            exclusive_minimum=True)
    slack_linear_penalty: float = param(
        1e4, '1', 'ρ1 of (20): cost per unit of relative violation of a soft limit',
        minimum=0.0)
    slack_quadratic_penalty: float = param(
        1e4, '1', 'ρ2 of (20): cost per squared unit of relative violation of a soft limit',
        minimum=0.0, exclusive_minimum=True)
    soft_limits: str = param(
        'per_step', '-', "slacks of (19)-(21): 'per_step' one per predicted step and limit, "
        f"'worst_case' (the paper's) one per limit for the horizon; {_WHY}",
        choices=SOFT_LIMITS)
    speed_limit_first_step: int = param(
        4, '1', 'first predicted step (1..Np) whose speed is limited in (19) (1: every '
        f'step, the paper); {_WHY}', minimum=1)
    offset_free: bool = param(
        True, '-', 'track the tilt that balances the estimated constant disturbance instead '
        f"of θ = 0 (false: the paper's reference (20)); {_WHY}")
    disturbance_filter_time_constant: float = param(
        0.5, 's', 'low-pass time constant of the constant-disturbance estimate behind the '
        'offset-free target', minimum=0.0)
    disturbance_average_time: float = param(
        0.1, 's', 'a solve takes the mean over this long of f̂2, f̂3 less their gravity part, '
        'not their sample (but on a push and while re-solving); 0: the sample (the paper); '
        f'{_WHY}', minimum=0.0, maximum=10.0)
    disturbance_decay_time_constant: float = param(
        0.1, 's', 'the transient of the disturbance estimate beyond the dead zone decays '
        f'with this time constant over the horizon of (17); 0: held (the paper); {_WHY}',
        minimum=0.0, maximum=10.0)
    disturbance_decay_dead_zone: tuple[float, float] = param(
        (1.0, 1.0), 'm/s², rad/s²', '(d2, d3): the part of the transient disturbance '
        f'estimate within this band is held over the horizon as in (17); {_WHY}',
        minimum=0.0)
    push_threshold: tuple[float, float] = param(
        (1.0, 1.0), 'm/s², rad/s²', '(d2, d3): a transient disturbance estimate beyond this '
        f'band is a push, on which the MPC re-solves (fast_resolve_period); {_WHY}',
        minimum=0.0)
    push_restart: bool = param(
        False, '-', 'while re-solving, a transient newly beyond disturbance_decay_dead_zone '
        f'solves at once and restarts the re-solve grid there; {_WHY}')
    push_restart_max_slack: float = param(
        0.15, '1', 'push_restart moves the grid only if the plan solved there keeps |θ| '
        f'within (1 + this)·max_tilt (the tilt slack of (20)); {_WHY}', minimum=0.0)
    speed_preview_time: float = param(
        0.5, 's', 'the speed reference of (20) continues the low-passed trend of υd for '
        f'this long over the horizon, then holds; 0: υd held (the paper); {_WHY}',
        minimum=0.0, maximum=10.0)
    speed_trend_filter_time_constant: float = param(
        0.3, 's', 'low-pass time constant of the υd trend of speed_preview_time',
        minimum=0.0, maximum=10.0)
    max_speed_trend: float = param(
        1.0, 'm/s²', f'|dυd/dt| bound of the trend of speed_preview_time; {_WHY}',
        minimum=0.0, exclusive_minimum=True)
    max_target_tilt: float = param(
        0.08, 'rad', '|θ| bound of the offset-free steady-state target (a larger '
        'disturbance is not held: the target saturates)', minimum=0.0)
    prediction_gain_scale: tuple[float, float] = param(
        (1.0, 1.0), '1', '(g2, g3) of model (1) are multiplied by these in the prediction '
        f'of the increments (18); {_WHY}', minimum=0.0, exclusive_minimum=True)
    speed_slack_linear_penalty: float = param(
        0.0, '1', 'ρ1 of (20) for the speed slacks (the tilt slacks use '
        f'slack_linear_penalty); 0: quadratic only; paper: ρ1; {_WHY}', minimum=0.0)
    disturbance_startup_time: float = param(
        0.25, 's', "for this long after a reset the MPC predicts with model (1)'s drift "
        f'instead of the ESO f̂2, f̂3 (and no speed error on the first tick); 0: off; {_WHY}',
        minimum=0.0, maximum=10.0)
    speed_slack_quadratic_penalty: float = param(
        100.0, '1', 'ρ2 of (20) for the speed slacks (the tilt slacks use '
        f'slack_quadratic_penalty); paper: 1e4; {_WHY}', minimum=0.0,
        exclusive_minimum=True)
    speed_rise_penalty: float = param(
        1e4, '1', 'weight of the squared rise of the planned speed above |υ̂| ≥ υmax over '
        f'the first speed_rise_steps (one more slack of (20)); 0: off; {_WHY}',
        minimum=0.0)
    speed_rise_steps: int = param(
        5, '1', 'predicted steps covered by speed_rise_penalty', minimum=1, maximum=60)
    prediction: str = param(
        'gravity_aware', '-', "'gravity_aware' (adopted) or 'paper' (the literal G̃ of "
        "(18), which falls; for the ablation)", choices=PREDICTION_MODELS)
    backend: str = param('proxsuite', '-', 'solver of the QP (22)',
                         choices=('proxsuite', 'daqp'))
    eps_abs: float = param(
        1e-7, '1', f'ProxSuite absolute tolerance of the QP (22); {_WHY}', minimum=1e-12,
        maximum=1e-3)
    eps_rel: float = param(
        1e-11, '1', f'ProxSuite relative tolerance of the QP (22), tiny but not 0; {_WHY}',
        minimum=0.0, maximum=1e-3)
    eps_primal_inf: float = param(
        0.0, '1', 'ProxSuite primal infeasibility tolerance; 0 disables the certificate '
        f'(the QP (22) is feasible by construction); {_WHY}', minimum=0.0, maximum=1e-3)
    eps_dual_inf: float = param(
        0.0, '1', 'ProxSuite dual infeasibility tolerance; 0 disables it (H of (22) is '
        'positive definite)', minimum=0.0, maximum=1e-3)
    max_iter: int = param(1000, '1', 'iteration limit of the QP solver (ProxSuite: outer '
                          'iterations)', minimum=1, maximum=100000)
    max_inner_iter: int = param(
        30, '1', 'ProxSuite inner iterations per outer one; with max_iter it bounds the '
        'worst-case solve time', minimum=1, maximum=10000)

    def validate(self) -> None:
        if resolves_faster(self.sampling_period, self.fast_resolve_period):
            ratio = self.sampling_period / self.fast_resolve_period
            if abs(ratio - round(ratio)) > 1e-6:
                raise ParamError(f'fast_resolve_period: must divide sampling_period '
                                  f'({self.sampling_period}) when shorter, got '
                                  f'{self.fast_resolve_period}')
        if self.speed_rise_steps > self.prediction_horizon:
            raise ParamError(f'speed_rise_steps: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.speed_rise_steps}')
        if self.speed_limit_first_step > self.prediction_horizon:
            raise ParamError(f'speed_limit_first_step: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.speed_limit_first_step}')
        if self.control_horizon > self.prediction_horizon:
            raise ParamError(f'control_horizon: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.control_horizon}')

    def largest_delta_torque(self) -> float:
        """Return the largest |Δτυ| per Ts the drive stage may apply [N m] (19).

        ``impact_delta_torque`` where it is larger and can act (the MPC re-solving after a
        push, which the obstacle's drift sets off), else ``max_delta_torque``.
        """
        if (self.controller == 'mpc'
                and resolves_faster(self.sampling_period, self.fast_resolve_period)):
            return max(self.max_delta_torque, self.impact_delta_torque)
        return self.max_delta_torque

    def qp_settings(self) -> QpSolverParams:
        return QpSolverParams(self.eps_abs, self.eps_rel, self.eps_primal_inf, self.eps_dual_inf,
                          self.max_iter, self.max_inner_iter)
