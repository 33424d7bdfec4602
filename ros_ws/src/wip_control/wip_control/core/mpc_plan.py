r"""The MPC's plan: the tick's torque, its increments, the predicted states and the status.

A solved QP (22) gives z = (Δτ̄, sυ, sθ[, r]); the plan applies its first increment,
clipped to the hard limits (19), as τ(k) = τ(k−1) + Δτ(k|k) (23) of [1]_. Failure handling
(the status says which):

- solver status other than solved: the previous plan shifted by one step (last increment
  0), clipped to the hard limits; with no previous plan τ(k−1) held, clipped.
- NaN/inf input, or a magnitude beyond the input limit of :mod:`.mpc`: no solve, status
  ``INPUT_INVALID``, and τ ramps toward 0 by at most Δτmax (why: docs/mpc.md).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .mpc_config import MpcParams
from .qp import MpcStatus, QpSolution

#: Status text of a drive torque published at a tick of the re-solve grid without a solve
#: (``mpc.fast_resolve_period``, lockstep; docs/history/mpc.md §10): the held τυ, no
#: plan. Readers of a record (the report, the viewer, tests) tell it from a solve by it.
HELD_STATUS_TEXT = 'HELD'


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


class SolvedPlan(NamedTuple):
    """The increments a solve proposes and its largest slacks (before clipping)."""

    increments: np.ndarray   #: Δτ̄ (Nc) [N m]
    slack_v: float           #: largest sυ,i (nan: not solved)
    slack_theta: float       #: largest sθ,i (nan: not solved)
    used_fallback: bool      #: the previous plan shifted, not a fresh solution


def plan_of(solution: QpSolution, n_c: int, n_slacks: int, previous: np.ndarray | None,
            max_delta: float) -> SolvedPlan:
    """Return the plan of ``solution``, or the previous plan shifted when it is not solved."""
    if solution.status == MpcStatus.SOLVED:
        z = solution.z
        return SolvedPlan(z[:n_c].copy(), float(z[n_c:n_c + n_slacks].max()),
                          float(z[n_c + n_slacks:n_c + 2 * n_slacks].max()), False)
    return SolvedPlan(shifted_plan(previous, n_c, max_delta), math.nan, math.nan, True)


def shifted_plan(previous: np.ndarray | None, n_c: int, max_delta: float) -> np.ndarray:
    """Previous plan shifted by one tick, last increment 0, within the Δτ limit."""
    shifted = np.zeros(n_c)
    if previous is not None:
        shifted[:-1] = previous[1:]
    return np.clip(shifted, -max_delta, max_delta)


def admissible_increment(delta: float, tau_prev: float, limit: float, upper: float,
                         lower: float | None = None) -> float:
    """Clip Δτ to the hard limits (19): ``lower`` ≤ Δτ ≤ ``upper``, |τ(k−1) + Δτ| ≤ limit.

    ``lower`` None: −``upper`` (the symmetric |Δτ| ≤ Δτmax). The |τ| limit holds when the
    box can reach it, else the box's nearest end.
    """
    lower = -upper if lower is None else lower
    delta = min(max(float(delta), lower), upper)
    tau = tau_prev + delta
    if tau > limit:
        tau = max(limit, tau_prev + lower)
    elif tau < -limit:
        tau = min(-limit, tau_prev + upper)
    return tau - tau_prev


def invalid_input_result(config: MpcParams, tau_prev: float) -> MpcResult:
    """Return the tick's result on NaN/inf input: τ ramps toward 0 by at most Δτmax."""
    delta = min(max(-tau_prev, -config.max_delta_torque), config.max_delta_torque)
    plan = np.zeros(config.control_horizon)
    plan[0] = delta
    predicted = np.full((config.prediction_horizon, 3), np.nan)
    return MpcResult(tau_prev + delta, delta, MpcStatus.INPUT_INVALID, 0, 0.0, 0.0,
                     math.nan, math.nan, True, predicted, plan)
