r"""The MPC's problem: horizons, weights, limits and the blocks of (20)–(22) built once.

G̃ of the condensed prediction (18) is bilinear in the input gains (g2, g3) at θ̂
(:mod:`.mpc_prediction`: G̃ = g2 G2 + g3 G3), so everything of the QP (22) that does not
depend on the tick's data is computed here, once: G̃ᵀQG̃ = g2² K22 + g2 g3 K23 + g3² K33
with fixed K's, the gradient's Q-weighted G2ᵀ, G3ᵀ, and the rows of C on υ and θ,
g2 C2 + g3 C3. A tick then costs a few small matrix–vector products
(:mod:`.mpc_qp`, compiled in :mod:`.mpc_kernel`).

Decision vector z = (Δτ̄ (Nc), sυ (Ns), sθ (Ns)[, r]); Ns = Np (``soft_limits:
per_step``) or 1 (``worst_case``), r the rise slack (``speed_rise_penalty`` > 0).
Rows of C: τ(k..k+Nc−1) (Nc), υ ≤ (Np), θ ≤ (Np), υ ≥ (Np), θ ≥ (Np), rise rows.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .mpc_config import MpcConfig
from .mpc_prediction import CondensedPrediction
from .params import WipParameters


class ProblemBlocks(NamedTuple):
    """The problem's constant data as the compiled kernel takes them (C-contiguous).

    Floats, bools, ints and float64 arrays only: another type compiles the kernel anew.
    """

    free_state: np.ndarray            #: M (3Np × 3) of ȳ_free, eq. (18)
    free_v: np.ndarray                #: γ2 (3Np): response to a held input on υ̇
    free_theta_dot: np.ndarray        #: γ3 (3Np): on θ̈
    transient_v: np.ndarray           #: decaying minus held response on υ̇ (3Np)
    transient_theta_dot: np.ndarray   #: the same on θ̈ (3Np)
    hessian_blocks: np.ndarray        #: (K22, K23, K33, R), each Nc² (4 × Nc²)
    weighted_gains: np.ndarray        #: (QG2; QG3)ᵀ (2Nc × 3Np) of the gradient
    row_blocks: np.ndarray            #: (C2, C3) of the υ and θ rows (2 × 2Np·Nc)
    limits: np.ndarray                #: (υmax …, θmax …) (2Np) of (19)
    preview_ramp: np.ndarray          #: min(i Ts, T) (Np) of the speed preview
    preview: bool                     #: whether the speed reference previews υd's trend
    max_speed: float                  #: υmax [m/s]
    sampling_period: float            #: Ts [s]
    n_free_speed: int                 #: speed rows of the first steps left free
    n_rise: int                       #: rise rows (0: no rise slack)


class MpcProblem:
    """Horizons, weights and limits of the MPC and its QP blocks that do not change.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : tunables; see :class:`~.mpc_config.MpcConfig`.
    """

    def __init__(self, params: WipParameters, config: MpcConfig) -> None:
        config.validate()
        self.config = config
        n_p, n_c = config.prediction_horizon, config.control_horizon
        self.prediction_horizon, self.control_horizon = n_p, n_c
        self.prediction = CondensedPrediction(params, config.sampling_period, n_p, n_c,
                                              config.prediction)
        # Soft limits. 'worst_case': one slack per limit, sυ ≥ max_i |υ(k+i)|/υmax − 1. A
        # WIP must first speed up to brake (non-minimum phase), so above υmax every braking
        # plan raises that maximum and, at ρ1 = 1e4, costs more than coasting forever.
        # 'per_step': one slack per step and limit with a linear (exact ℓ1) penalty
        # (Kerrigan & Maciejowski 2000): the cost is the summed violation over the horizon,
        # which braking lowers. Both keep the QP feasible for any state (the slacks are
        # unbounded above).
        self.n_slacks = n_p if config.soft_limits == 'per_step' else 1
        # The rise slack r (last variable) and its rows: ±υ(k+i) ≤ ±υ̂ + υmax r for
        # i = 1..speed_rise_steps, the sign that of υ̂, while ±υ̂ ≥ υmax.
        self.n_rise = config.speed_rise_steps if config.speed_rise_penalty > 0.0 else 0
        self.n_variables = n_c + 2 * self.n_slacks + (1 if self.n_rise else 0)
        self.n_constraints = n_c + 4 * n_p + self.n_rise
        pred = self.prediction
        #: G2, G3 (3Np × Nc) as the kernel's prediction of the plan takes them.
        self.gain_matrices = tuple(np.ascontiguousarray(a) for a in (
            pred.gain_matrix_v, pred.gain_matrix_theta_dot))
        self.blocks = ProblemBlocks(
            *(np.ascontiguousarray(a) for a in (
                pred.free_state_matrix, pred.free_v_column, pred.free_theta_dot_column)),
            *_transient_columns(pred, config), *_cost_blocks(pred, config),
            _row_blocks(pred), np.repeat([config.max_speed, config.max_tilt], n_p),
            # υd trend preview: the reference of step i is υd + min(i Ts, T) · dυd/dt.
            np.minimum(np.arange(1, n_p + 1) * config.sampling_period,
                       config.speed_preview_time),
            config.speed_preview_time > 0.0, float(config.max_speed),
            float(config.sampling_period), min(config.speed_limit_first_step - 1, n_p),
            self.n_rise)


def _transient_columns(pred: CondensedPrediction,
                       config: MpcConfig) -> tuple[np.ndarray, np.ndarray]:
    """Response to the transient part of the disturbance: decaying minus held.

    The free response already holds it constant (17); what
    ``disturbance_decay_time_constant`` lets decay is the difference.
    """
    tau_d = config.disturbance_decay_time_constant
    ratio = math.exp(-config.sampling_period / tau_d) if tau_d > 0.0 else 1.0
    decay_v, decay_theta_dot = pred.decaying_input_columns(ratio)
    return decay_v - pred.free_v_column, decay_theta_dot - pred.free_theta_dot_column


def _cost_blocks(pred: CondensedPrediction,
                 config: MpcConfig) -> tuple[np.ndarray, np.ndarray]:
    """(K22, K23, K33, R) of H and the Q-weighted gains of g, eqs. (20), (22)."""
    n_c = pred.control_horizon
    q = np.tile(np.asarray(config.output_weights, dtype=float), pred.prediction_horizon)
    g2m, g3m = pred.gain_matrix_v, pred.gain_matrix_theta_dot
    # Hessian blocks: H_ΔΔ = coef · K, coef = (2g2², 2g2g3, 2g3², 2).
    qg2, qg3 = q[:, None] * g2m, q[:, None] * g3m
    hessian_blocks = np.stack([
        g2m.T @ qg2, g2m.T @ qg3 + g3m.T @ qg2, g3m.T @ qg3,
        config.input_weight * np.eye(n_c)]).reshape(4, n_c * n_c)
    # Gradient: g_Δ = −2 (g2 G2ᵀQ e + g3 G3ᵀQ e), e = ȳr − ȳ_free.
    weighted_gains = np.ascontiguousarray(np.vstack([qg2.T, qg3.T]))  # (2Nc, 3Np)
    return hessian_blocks, weighted_gains


def _row_blocks(pred: CondensedPrediction) -> np.ndarray:
    """Constraint rows on υ and θ (21): [υ rows; θ rows] = g2 C2 + g3 C3, (2, 2Np·Nc)."""
    g2m, g3m = pred.gain_matrix_v, pred.gain_matrix_theta_dot
    return np.stack([np.vstack([g2m[0::3], g2m[1::3]]).reshape(-1),
                     np.vstack([g3m[0::3], g3m[1::3]]).reshape(-1)])
