"""The MPC's QP filled in place and its prediction, compiled with numba (``cache=True``).

:class:`.mpc_problem.MpcProblem` holds the constant data (what each block is) and
:class:`.mpc_qp.MpcQp` the buffers; these kernels do the per-tick arithmetic of eqs.
(20)–(22): the free response, the Hessian and gradient of the increments, the rows of the
soft limits on υ and θ, the τ and rise rows (numpy reference: :mod:`.mpc_reference`),
compiled because as numpy code their cost was the overhead of many
small-array calls (measured: docs/runner-speed.md). No ``fastmath``: every sum runs in
the order of the loops below, so the bits depend on the data only.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def fill(tick, problem, qp):
    """Fill H, g, C, l, u of ``qp`` for ``tick``; return the free response ȳ_free (3Np).

    ``tick``: :class:`.mpc_qp.TickData`; ``problem``: :class:`.mpc_problem.ProblemBlocks`;
    ``qp``: :class:`.mpc_qp.QpBuffers`. The reference in numpy, with the equations:
    :func:`.mpc_reference.reference_qp`.
    """
    free = _free_response(tick, problem)
    _cost(tick, problem, qp, free)
    _output_rows(tick, problem, qp, free)
    # τ rows, relaxed to the reachable set if |τ(k−1)| is beyond the limit.
    limit, tau_prev, reach_up, reach_down = tick.limit, tick.tau_prev, qp.reach_up, qp.reach_down
    for j in range(reach_up.shape[0]):
        qp.upper[j] = max(limit, tau_prev - reach_down[j]) - tau_prev
        qp.lower[j] = min(-limit, tau_prev + reach_up[j]) - tau_prev
    return free


@numba.njit(cache=True, nogil=True)
def _free_response(tick, problem):
    """ȳ_free = M x̂ + (f̂2 + g2 τ(k−1)) γ2 + (f̂3 + g3 τ(k−1)) γ3 [+ transient], eq. (18)."""
    free_state = problem.free_state
    n_out = free_state.shape[0]          # 3 Np
    free = np.empty(n_out)
    drive_v = tick.f2_hat + tick.g2 * tick.tau_prev
    drive_theta_dot = tick.f3_hat + tick.g3 * tick.tau_prev
    transient_v, transient_theta_dot = tick.transient_v, tick.transient_theta_dot
    with_transient = transient_v != 0.0 or transient_theta_dot != 0.0
    for i in range(n_out):
        value = (free_state[i, 0] * tick.v_hat + free_state[i, 1] * tick.theta_hat
                 + free_state[i, 2] * tick.theta_dot_hat)
        value += problem.free_v[i] * drive_v
        value += problem.free_theta_dot[i] * drive_theta_dot
        if with_transient:
            value += problem.transient_v[i] * transient_v
            value += problem.transient_theta_dot[i] * transient_theta_dot
        free[i] = value
    return free


@numba.njit(cache=True, nogil=True)
def _cost(tick, problem, qp, free):
    """H_ΔΔ and g_Δ of eq. (22) from the cost (20)."""
    g2p, g3p = tick.g2p, tick.g3p
    n_c = qp.reach_up.shape[0]
    n_out = free.shape[0]
    n_p = n_out // 3
    hessian_blocks, weighted_gains = problem.hessian_blocks, problem.weighted_gains
    # Eq. (22): H_ΔΔ = 2(G̃ᵀQG̃ + R) = Σ coef_k K_k, coef = (2g2², 2g2g3, 2g3², 2).
    c0, c1, c2 = 2.0 * g2p * g2p, 2.0 * g2p * g3p, 2.0 * g3p * g3p
    for i in range(n_c):
        for j in range(n_c):
            k = i * n_c + j
            qp.h[i, j] = (c0 * hessian_blocks[0, k] + c1 * hessian_blocks[1, k]
                          + c2 * hessian_blocks[2, k] + 2.0 * hessian_blocks[3, k])
    # g_Δ = −2 (g2 G2ᵀQ e + g3 G3ᵀQ e), e = ȳr − ȳ_free, ȳr = 1 ⊗ (υd, θs, 0).
    error = np.empty(n_out)
    max_speed, v_d = problem.max_speed, tick.v_d
    for i in range(n_p):
        if problem.preview:
            reference = min(max(v_d + problem.preview_ramp[i] * tick.speed_trend,
                                -max_speed), max_speed)
        else:
            reference = v_d
        error[3 * i] = reference - free[3 * i]
        error[3 * i + 1] = tick.target_theta - free[3 * i + 1]
        error[3 * i + 2] = 0.0 - free[3 * i + 2]
    for j in range(n_c):
        projected_v = 0.0
        projected_theta = 0.0
        for i in range(n_out):
            projected_v += weighted_gains[j, i] * error[i]
            projected_theta += weighted_gains[n_c + j, i] * error[i]
        qp.g[j] = -2.0 * (g2p * projected_v + g3p * projected_theta)


@numba.njit(cache=True, nogil=True)
def _output_rows(tick, problem, qp, free):
    """Rows of C on the predicted outputs (21), and the rise rows of ``speed_rise_penalty``."""
    g2p, g3p = tick.g2p, tick.g3p
    c, lower, upper = qp.c, qp.lower, qp.upper
    n_c = qp.reach_up.shape[0]
    row_blocks, outputs = problem.row_blocks, problem.row_outputs
    # Each row bounds one output of the plan, ȳ_free + (g2 C2 + g3 C3) Δτ̄: its bounds
    # minus the free response (±inf: that side free).
    for r in range(outputs.shape[0]):
        for j in range(n_c):
            k = r * n_c + j
            c[n_c + r, j] = g2p * row_blocks[0, k] + g3p * row_blocks[1, k]
        free_output = free[outputs[r]]
        upper[n_c + r] = problem.row_upper[r] - free_output
        lower[n_c + r] = problem.row_lower[r] - free_output
    n_rise = problem.n_rise
    if n_rise:
        # ±υ(k+i) ≤ ±υ̂ + υmax r. Only braking from at or above the limit: below it, going
        # beyond the limit is the speed slacks' business (a recovery from a hard push may
        # need it), and leaning (one MPC period ahead) the way it travels, the wheels must
        # speed up to catch the body: that is balance, not the rise before braking.
        v_hat = tick.v_hat
        sign = 1.0 if v_hat >= 0.0 else -1.0
        rise_rows = problem.rise_row
        for r in range(n_rise):
            for j in range(n_c):
                c[rise_rows + r, j] = sign * c[n_c + r, j]   # the υ(k+1+r) ≤ rows
        free_rise = (sign * v_hat < problem.max_speed
                     or sign * (tick.theta_hat + problem.sampling_period
                                * tick.theta_dot_hat) > 0.0)
        for r in range(n_rise):
            upper[rise_rows + r] = (np.inf if free_rise
                                    else sign * v_hat - sign * free[3 * r])


def fill_for(problem, qp):
    """Return :func:`fill` compiled for the types of ``problem`` and ``qp``, to call directly.

    Called with the returned entry point, a tick skips numba's resolution of the argument
    types, which for named tuples of arrays is done in Python (measured: about 10 µs a
    call against 4 µs for the kernel itself). The types are fixed when the QP is made:
    ``problem`` and ``qp`` are its own, the tick a :class:`.mpc_qp.TickData` of floats.
    """
    from .mpc_qp import TickData
    tick = TickData(*(0.0,) * len(TickData._fields))
    return fill.compile((numba.typeof(tick), numba.typeof(problem), numba.typeof(qp)))


def warm_up() -> None:
    """Load or compile the kernels (several seconds when compiling; once per process)."""
    from .mpc_problem import ProblemBlocks
    from .mpc_qp import QpBuffers, TickData
    n_c, n_p, n_rise = 1, 1, 1
    n, m = n_c + 2 * n_p + 1, n_c + 4 * n_p + n_rise
    out = 3 * n_p
    problem = ProblemBlocks(
        np.zeros((out, 3)), np.zeros(out), np.zeros(out), np.zeros(out), np.zeros(out),
        np.zeros((4, n_c * n_c)), np.zeros((2 * n_c, out)), np.zeros(4 * n_p, np.int64),
        np.zeros((2, 4 * n_p * n_c)), np.ones(4 * n_p), -np.ones(4 * n_p), np.zeros(n_p),
        True, 1.0, 0.1, n_c + 4 * n_p, n_rise)
    qp = QpBuffers(np.zeros((n, n)), np.zeros(n), np.zeros((m, n)), np.zeros(m),
                   np.zeros(m), np.ones(n_c), np.ones(n_c))
    free = fill(TickData(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0,
                         0.0, 0.0), problem, qp)
    predict(free, 1.0, 1.0, np.zeros((out, n_c)), np.zeros((out, n_c)), np.zeros(n_c))


@numba.njit(cache=True, nogil=True)
def predict(free, g2p, g3p, gain_matrix_v, gain_matrix_theta_dot, plan):
    """ȳ = ȳ_free + g2 G2 Δτ̄ + g3 G3 Δτ̄ over the horizon, as (Np, 3)."""
    n_out = free.shape[0]
    predicted = np.empty((n_out // 3, 3))
    for i in range(n_out):
        by_v = 0.0
        by_theta_dot = 0.0
        for j in range(plan.shape[0]):
            by_v += gain_matrix_v[i, j] * plan[j]
            by_theta_dot += gain_matrix_theta_dot[i, j] * plan[j]
        predicted[i // 3, i % 3] = free[i] + g2p * by_v + g3p * by_theta_dot
    return predicted
