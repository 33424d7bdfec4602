r"""The MPC's problem: horizons, weights, limits and the blocks of (20)–(22) built once.

G̃ of the condensed prediction (18) is bilinear in the input gains (g2, g3) at θ̂
(:mod:`.mpc_prediction`: G̃ = g2 G2 + g3 G3), so everything of the QP (22) that does not
depend on the tick's data is computed here, once: G̃ᵀQG̃ = g2² K22 + g2 g3 K23 + g3² K33
with fixed K's, the gradient's Q-weighted G2ᵀ, G3ᵀ, and the rows of C on the predicted
outputs, g2 C2 + g3 C3. A tick then costs a few small matrix–vector products
(:mod:`.mpc_qp`, compiled in :mod:`.mpc_kernel`).

Decision vector z = (Δτ̄ (Nc), sυ (Ns), sθ (Ns)[, r]); Ns = Np (``soft_limits:
per_step``) or 1 (``worst_case``), r the rise slack (``speed_rise_penalty`` > 0).
Rows of C: τ(k..k+Nc−1) (Nc); the output rows (:func:`_output_rows`: υ ≤, θ ≤, υ ≥,
θ ≥, Np each), each bounding one entry of ȳ, so that a new bound on a predicted output
is rows added there; the rise rows.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .mpc_config import MpcParams
from .mpc_prediction import CondensedPrediction
from wip_description.params import ModelParams


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
    row_outputs: np.ndarray           #: index in ȳ of each output row of C (int64)
    row_blocks: np.ndarray            #: (C2, C3) of the output rows (2 × rows·Nc)
    row_upper: np.ndarray             #: bound of each output row on ȳ (inf: none)
    row_lower: np.ndarray             #: lower bound of each output row on ȳ (−inf: none)
    preview_ramp: np.ndarray          #: min(i Ts, T) (Np) of the speed preview
    preview: bool                     #: whether the speed reference previews υd's trend
    max_speed: float                  #: υmax [m/s]
    sampling_period: float            #: Ts [s]
    rise_row: int                     #: first rise row of C
    n_rise: int                       #: rise rows (0: no rise slack)


class MpcProblem:
    """Horizons, weights and limits of the MPC and its QP blocks that do not change.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : tunables; see :class:`~.mpc_config.MpcParams`.
    """

    def __init__(self, params: ModelParams, config: MpcParams) -> None:
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
        outputs, upper, lower = _output_rows(config, n_p)
        self.n_variables = n_c + 2 * self.n_slacks + (1 if self.n_rise else 0)
        self.n_constraints = n_c + outputs.shape[0] + self.n_rise
        pred = self.prediction
        #: G2, G3 (3Np × Nc) as the kernel's prediction of the plan takes them.
        self.gain_matrices = tuple(np.ascontiguousarray(a) for a in (
            pred.gain_matrix_v, pred.gain_matrix_theta_dot))
        self.blocks = ProblemBlocks(
            *(np.ascontiguousarray(a) for a in (
                pred.free_state_matrix, pred.free_v_column, pred.free_theta_dot_column)),
            *_transient_columns(pred, config), *_cost_blocks(pred, config), outputs,
            np.stack([pred.gain_matrix_v[outputs].reshape(-1),
                      pred.gain_matrix_theta_dot[outputs].reshape(-1)]), upper, lower,
            # υd trend preview: the reference of step i is υd + min(i Ts, T) · dυd/dt.
            np.minimum(np.arange(1, n_p + 1) * config.sampling_period,
                       config.speed_preview_time),
            config.speed_preview_time > 0.0, float(config.max_speed),
            float(config.sampling_period), n_c + outputs.shape[0], self.n_rise)

    def constant_qp(self) -> tuple[np.ndarray, ...]:
        """H, g, C, l, u, lb, ub with the entries that do not change between ticks.

        The slacks' penalties ρ2 (diagonal of H) and ρ1 (g), the τ rows' lower-triangular
        ones, the slacks' columns of the soft rows (21), the rise slack's column, the
        boxes (19); the rest is the tick's (:meth:`.mpc_qp.MpcQp.update`).
        """
        config = self.config
        n_p, n_c, n_s = self.prediction_horizon, self.control_horizon, self.n_slacks
        n, m = self.n_variables, self.n_constraints
        h = np.zeros((n, n))
        slack_index = np.arange(n_c, n)
        h[slack_index, slack_index] = 2.0 * config.slack_quadratic_penalty
        h[slack_index[:n_s], slack_index[:n_s]] = 2.0 * config.speed_slack_quadratic_penalty
        g = np.zeros(n)
        g[n_c:n_c + n_s] = config.speed_slack_linear_penalty
        g[n_c + n_s:n_c + 2 * n_s] = config.slack_linear_penalty
        c = np.zeros((m, n))
        c[:n_c, :n_c] = np.tril(np.ones((n_c, n_c)))
        # Row i of the υ (θ) block uses slack column i (per step) or the single column.
        slack_map = np.eye(n_p) if n_s == n_p else np.ones((n_p, 1))
        v_cols, theta_cols = slice(n_c, n_c + n_s), slice(n_c + n_s, n_c + 2 * n_s)
        if self.n_rise:
            h[n - 1, n - 1] = 2.0 * config.speed_rise_penalty
            c[self.blocks.rise_row:m, n - 1] = -config.max_speed
        for rows, sign in ((slice(n_c, n_c + 2 * n_p), -1.0),
                           (slice(n_c + 2 * n_p, n_c + 4 * n_p), 1.0)):
            block = c[rows]
            block[:n_p, v_cols] = sign * config.max_speed * slack_map
            block[n_p:, theta_cols] = sign * config.max_tilt * slack_map
        lb, ub = np.zeros(n), np.full(n, np.inf)
        lb[:n_c] = -config.max_delta_torque
        ub[:n_c] = config.max_delta_torque
        return h, g, c, np.full(m, -np.inf), np.full(m, np.inf), lb, ub


def _output_rows(config: MpcParams, n_p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the rows of C on the predicted outputs: their index in ȳ and bounds.

    υ ≤ υmax (1 + sυ), θ ≤ θmax (1 + sθ), υ ≥ −υmax (1 + sυ), θ ≥ −θmax (1 + sθ) for
    steps 1..Np (21); the speed rows of the steps before ``speed_limit_first_step``
    free. The rows on υ (≤) come first: the rise rows copy them.
    """
    steps = np.arange(n_p)
    v, theta = 3 * steps, 3 * steps + 1
    outputs = np.concatenate((v, theta, v, theta))
    limits = np.repeat([config.max_speed, config.max_tilt], n_p)
    upper = np.concatenate((limits, np.full(2 * n_p, np.inf)))
    lower = np.concatenate((np.full(2 * n_p, -np.inf), -limits))
    n_free = min(config.speed_limit_first_step - 1, n_p)
    upper[:n_free] = np.inf
    lower[2 * n_p:2 * n_p + n_free] = -np.inf
    return outputs, upper, lower


def _transient_columns(pred: CondensedPrediction,
                       config: MpcParams) -> tuple[np.ndarray, np.ndarray]:
    """Response to the transient part of the disturbance: decaying minus held.

    The free response already holds it constant (17); what
    ``disturbance_decay_time_constant`` lets decay is the difference.
    """
    tau_d = config.disturbance_decay_time_constant
    ratio = math.exp(-config.sampling_period / tau_d) if tau_d > 0.0 else 1.0
    decay_v, decay_theta_dot = pred.decaying_input_columns(ratio)
    return decay_v - pred.free_v_column, decay_theta_dot - pred.free_theta_dot_column


def _cost_blocks(pred: CondensedPrediction,
                 config: MpcParams) -> tuple[np.ndarray, np.ndarray]:
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
