"""The MPC's QP filled in place and its prediction, compiled with numba (``cache=True``).

:class:`.mpc.LongitudinalMpc` holds the data (its constructor says what each block is);
these kernels do the per-tick arithmetic of eqs. (20)–(22): the free response, the
Hessian and gradient of the increments, the rows of the soft limits on υ and θ, the τ and
rise rows, compiled because as numpy code their cost was the overhead of many
small-array calls (measured: docs/runner-speed.md). No ``fastmath``: every sum runs in
the order of the loops below, so the bits depend on the data only.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def fill(v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, g2, g3, g2p, g3p, tau_prev, limit,
         transient_v, transient_theta_dot, v_d, speed_trend, preview, target_theta,
         max_speed, sampling_period, n_free_speed, n_rise,
         free_state, free_v, free_theta_dot, transient_v_column, transient_theta_dot_column,
         hessian_blocks, weighted_gains, row_blocks, limits, reach, preview_ramp,
         h, g, c, lower, upper, free):
    """Fill H, g, C, l, u (``h`` … ``upper``) and the free response ``free`` (3Np) in place.

    ``transient_v``, ``transient_theta_dot``: the disturbance's transient beyond its dead
    zone (decays over the horizon). ``preview``: υd's reference continues its trend
    ``speed_trend`` over ``preview_ramp`` (clipped to ±υmax), else υd is held as in (20).
    ``n_free_speed``: speed rows of the first steps left free; ``n_rise``: rise rows.
    """
    n_c = reach.shape[0]
    n_out = free.shape[0]          # 3 Np
    n_p = n_out // 3
    # Free response ȳ_free = M x̂ + (f̂2 + g2 τ(k−1)) b_υ + (f̂3 + g3 τ(k−1)) b_θ̇ [+ transient].
    drive_v = f2_hat + g2 * tau_prev
    drive_theta_dot = f3_hat + g3 * tau_prev
    with_transient = transient_v != 0.0 or transient_theta_dot != 0.0
    for i in range(n_out):
        value = (free_state[i, 0] * v_hat + free_state[i, 1] * theta_hat
                 + free_state[i, 2] * theta_dot_hat)
        value += free_v[i] * drive_v
        value += free_theta_dot[i] * drive_theta_dot
        if with_transient:
            value += transient_v_column[i] * transient_v
            value += transient_theta_dot_column[i] * transient_theta_dot
        free[i] = value
    # Eq. (22): H_ΔΔ = 2(G̃ᵀQG̃ + R) = Σ coef_k K_k, coef = (2g2², 2g2g3, 2g3², 2).
    c0, c1, c2 = 2.0 * g2p * g2p, 2.0 * g2p * g3p, 2.0 * g3p * g3p
    for i in range(n_c):
        for j in range(n_c):
            k = i * n_c + j
            h[i, j] = (c0 * hessian_blocks[0, k] + c1 * hessian_blocks[1, k]
                       + c2 * hessian_blocks[2, k] + 2.0 * hessian_blocks[3, k])
    # g_Δ = −2 (g2 G2ᵀQ e + g3 G3ᵀQ e), e = ȳr − ȳ_free, ȳr = 1 ⊗ (υd, θs, 0).
    error = np.empty(n_out)
    for i in range(n_p):
        if preview:
            reference = min(max(v_d + preview_ramp[i] * speed_trend, -max_speed), max_speed)
        else:
            reference = v_d
        error[3 * i] = reference - free[3 * i]
        error[3 * i + 1] = target_theta - free[3 * i + 1]
        error[3 * i + 2] = 0.0 - free[3 * i + 2]
    for j in range(n_c):
        projected_v = 0.0
        projected_theta = 0.0
        for i in range(n_out):
            projected_v += weighted_gains[j, i] * error[i]
            projected_theta += weighted_gains[n_c + j, i] * error[i]
        g[j] = -2.0 * (g2p * projected_v + g3p * projected_theta)
    # Rows (21): υ and θ of the plan (g2 C2 + g3 C3), identical for the ≤ and ≥ halves,
    # against the limits minus the free response.
    upper_rows, lower_rows = n_c, n_c + 2 * n_p
    for r in range(2 * n_p):
        for j in range(n_c):
            k = r * n_c + j
            value = g2p * row_blocks[0, k] + g3p * row_blocks[1, k]
            c[upper_rows + r, j] = value
            c[lower_rows + r, j] = value
        free_output = free[3 * r] if r < n_p else free[3 * (r - n_p) + 1]
        upper[upper_rows + r] = limits[r] - free_output
        lower[lower_rows + r] = -limits[r] - free_output
    # Speed rows of the first steps are free (``speed_limit_first_step``).
    for r in range(n_free_speed):
        upper[upper_rows + r] = np.inf
        lower[lower_rows + r] = -np.inf
    if n_rise:
        # ±υ(k+i) ≤ ±υ̂ + υmax r. Only braking from at or above the limit: below it, going
        # beyond the limit is the speed slacks' business (a recovery from a hard push may
        # need it), and leaning (one MPC period ahead) the way it travels, the wheels must
        # speed up to catch the body: that is balance, not the rise before braking.
        sign = 1.0 if v_hat >= 0.0 else -1.0
        rise_rows = n_c + 4 * n_p
        for r in range(n_rise):
            for j in range(n_c):
                c[rise_rows + r, j] = sign * c[upper_rows + r, j]
        free_rise = (sign * v_hat < max_speed
                     or sign * (theta_hat + sampling_period * theta_dot_hat) > 0.0)
        for r in range(n_rise):
            upper[rise_rows + r] = (np.inf if free_rise
                                    else sign * v_hat - sign * free[3 * r])
    # τ rows, relaxed to the reachable set if |τ(k−1)| is beyond the limit.
    for j in range(n_c):
        upper[j] = max(limit, tau_prev - reach[j]) - tau_prev
        lower[j] = min(-limit, tau_prev + reach[j]) - tau_prev


def warm_up() -> None:
    """Load or compile the kernels (several seconds when compiling; once per process)."""
    n_c, n_p, n_rise = 1, 1, 1
    n, m = n_c + 2 * n_p + 1, n_c + 4 * n_p + n_rise
    out = 3 * n_p
    free = np.empty(out)
    fill(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, True,
         0.0, 1.0, 0.1, 0, n_rise, np.zeros((out, 3)), np.zeros(out), np.zeros(out),
         np.zeros(out), np.zeros(out), np.zeros((4, n_c * n_c)), np.zeros((2 * n_c, out)),
         np.zeros((2, 2 * n_p * n_c)), np.ones(2 * n_p), np.ones(n_c), np.zeros(n_p),
         np.zeros((n, n)), np.zeros(n), np.zeros((m, n)), np.zeros(m), np.zeros(m), free)
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
