r"""The MPC's QP (20)–(22) of [1]_ as numpy array expressions: the reference of the kernel.

:func:`.mpc_kernel.fill` computes the same QP with explicit loops (compiled, for speed);
tests/wip_control/core/test_mpc.py checks it against :func:`reference_qp` to round-off.
With :class:`~.mpc_qp.TickData` t and the problem's blocks (:mod:`.mpc_problem`):

- free response (18), τ held at τ(k−1), with the decaying transient of the disturbance:
  ȳ_free = M x̂ + γ2 (f̂2 + g2 τ(k−1)) + γ3 (f̂3 + g3 τ(k−1)) + δ2 t2 + δ3 t3;
- Hessian (22): H_ΔΔ = 2(G̃ᵀQG̃ + R) = 2g2p² K22 + 2g2p g3p K23 + 2g3p² K33 + 2R;
- gradient (22): g_Δ = −2 G̃ᵀQ (ȳr − ȳ_free), ȳr = 1 ⊗ (υd + preview, θs, 0) (20);
- output rows (21): one output of the plan each, g2p C2 + g3p C3, between its bounds
  minus ȳ_free (the soft limits on υ and θ; the first ``speed_limit_first_step`` − 1
  speed rows free);
- rise rows: ±υ(k+i) ≤ ±υ̂ + υmax r (sign of υ̂) while braking from at or above υmax;
- τ rows (19): τ(k+j) − τ(k−1) within ±τlim − τ(k−1), relaxed to the reachable set.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import numpy as np

from .mpc_qp import MpcQp, TickData


def reference_qp(qp: MpcQp, tick: TickData) -> tuple[np.ndarray, ...]:
    """H, g, C, l, u and ȳ_free of ``tick``, as :meth:`MpcQp.update` fills them."""
    problem = qp.problem
    blocks, cfg = problem.blocks, problem.config
    n_c, n_p = problem.control_horizon, problem.prediction_horizon
    h, g, c = qp.data.H.copy(), qp.data.g.copy(), qp.data.C.copy()
    lower, upper = qp.data.l.copy(), qp.data.u.copy()
    t = tick
    free = (blocks.free_state @ [t.v_hat, t.theta_hat, t.theta_dot_hat]
            + blocks.free_v * (t.f2_hat + t.g2 * t.tau_prev)
            + blocks.free_theta_dot * (t.f3_hat + t.g3 * t.tau_prev)
            + blocks.transient_v * t.transient_v
            + blocks.transient_theta_dot * t.transient_theta_dot)
    coef = np.array([2 * t.g2p * t.g2p, 2 * t.g2p * t.g3p, 2 * t.g3p * t.g3p, 2.0])
    h[:n_c, :n_c] = (coef @ blocks.hessian_blocks).reshape(n_c, n_c)
    error = np.zeros(3 * n_p)
    error[0::3] = (np.clip(t.v_d + blocks.preview_ramp * t.speed_trend, -cfg.max_speed,
                           cfg.max_speed) if blocks.preview else t.v_d)
    error[1::3] = t.target_theta
    error -= free
    projected = blocks.weighted_gains @ error
    g[:n_c] = -2.0 * (t.g2p * projected[:n_c] + t.g3p * projected[n_c:])
    n_rows = blocks.row_outputs.shape[0]
    rows = (np.array([t.g2p, t.g3p]) @ blocks.row_blocks).reshape(n_rows, n_c)
    c[n_c:n_c + n_rows, :n_c] = rows
    outputs = free[blocks.row_outputs]
    upper[n_c:n_c + n_rows] = blocks.row_upper - outputs
    lower[n_c:n_c + n_rows] = blocks.row_lower - outputs
    n_rise = blocks.n_rise
    if n_rise:
        sign = 1.0 if t.v_hat >= 0.0 else -1.0
        rise = slice(blocks.rise_row, blocks.rise_row + n_rise)
        c[rise, :n_c] = sign * rows[:n_rise]
        braking = (sign * t.v_hat >= cfg.max_speed
                   and sign * (t.theta_hat + cfg.sampling_period * t.theta_dot_hat) <= 0.0)
        upper[rise] = sign * t.v_hat - sign * free[0:3 * n_rise:3] if braking else np.inf
    reach_up, reach_down = qp.reach
    upper[:n_c] = np.maximum(t.limit, t.tau_prev - reach_down) - t.tau_prev
    lower[:n_c] = np.minimum(-t.limit, t.tau_prev + reach_up) - t.tau_prev
    return h, g, c, lower, upper, free
