"""The polish of :func:`.qp.polish`, compiled with numba (``cache=True``).

One call per MPC solve, compiled because as numpy code its cost was the overhead of many
small-array calls (measured: docs/runner-speed.md). The linear solve is Gaussian
elimination with partial pivoting written out here, not LAPACK: no ``fastmath``, so every
operation is an IEEE operation in a fixed order and the bits depend on the data only, not
on a BLAS kernel chosen for the CPU. :mod:`.qp` imports this module when the first
ProxSuite solver is made, so a process that solves no QP does not import numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Outcomes of :func:`polish`, indices into :data:`REASONS`.
OK, SINGULAR, STATIONARITY, PRIMAL_INFEASIBLE, DUAL_SIGN = range(5)
REASONS = ('ok', 'singular KKT matrix', 'stationarity', 'primal infeasible', 'dual sign')


@numba.njit(cache=True, nogil=True)
def lu_solve(a, b):
    """Solve a x = b in place: ``b`` becomes x, ``a`` is overwritten.

    Gaussian elimination with partial pivoting (the largest |pivot| of the column, the
    first one on ties). Returns False on a zero pivot; a NaN in the data gives NaN in x.
    """
    n = b.shape[0]
    for col in range(n):
        pivot_row = col
        largest = abs(a[col, col])
        for row in range(col + 1, n):
            value = abs(a[row, col])
            if value > largest:
                largest = value
                pivot_row = row
        if largest == 0.0:
            return False
        if pivot_row != col:
            for j in range(col, n):
                a[col, j], a[pivot_row, j] = a[pivot_row, j], a[col, j]
            b[col], b[pivot_row] = b[pivot_row], b[col]
        pivot = a[col, col]
        for row in range(col + 1, n):
            factor = a[row, col] / pivot
            if factor != 0.0:
                for j in range(col + 1, n):
                    a[row, j] -= factor * a[col, j]
                b[row] -= factor * b[col]
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total -= a[i, j] * b[j]
        b[i] = total / a[i, i]
    return True


@numba.njit(cache=True, nogil=True)
def _kkt_solve(h, g, c, lo, hi, at_upper, at_lower, tolerance, z, y, over, under, wrong):
    """One equality-constrained solve of :func:`polish` and its checks; returns its outcome.

    The variables at an active bound are fixed there and eliminated (the MPC's slacks at
    0 are about half the variables); the free ones z_f and the multipliers λ of the
    active rows A of C solve

        [H_ff  A_fᵀ] [z_f]   [−(g + H z_b)_f]
        [A_f   0   ] [ λ ] = [ b − A z_b    ]

    with z_b the fixed values (zero elsewhere); the box multipliers then close the
    stationarity of the fixed variables. Fills z, y (the multipliers in ProxSuite's
    layout), and over, under (constraints violated beyond ``tolerance``) and wrong (active
    ones whose multiplier has the wrong sign).
    """
    m = c.shape[0]
    free, n_free = _fix_at_bounds(lo, hi, at_upper, at_lower, m, z)
    rows = np.empty(m, np.int64)
    n_rows = 0
    for i in range(m):
        if at_upper[i] or at_lower[i]:
            rows[n_rows] = i
            n_rows += 1
    kkt, rhs = _kkt_system(h, g, c, lo, hi, at_upper, free, n_free, rows, n_rows, z)
    if not lu_solve(kkt, rhs):
        return SINGULAR
    for a in range(n_free + n_rows):
        if not math.isfinite(rhs[a]):
            return SINGULAR
    for a in range(n_free):
        z[free[a]] = rhs[a]
    y[:] = 0.0
    for r in range(n_rows):
        y[rows[r]] = rhs[n_free + r]
    if not _close_stationarity(h, g, c, at_upper, at_lower, tolerance, rows, n_rows, z, y):
        return STATIONARITY
    return _check(c, lo, hi, at_upper, at_lower, tolerance, z, y, over, under, wrong)


@numba.njit(cache=True, nogil=True)
def _fix_at_bounds(lo, hi, at_upper, at_lower, m, z):
    """Fix the variables at an active bound in ``z`` (0 elsewhere); the free ones' indices."""
    n = z.shape[0]
    free = np.empty(n, np.int64)
    n_free = 0
    for j in range(n):
        if at_upper[m + j]:
            z[j] = hi[m + j]
        elif at_lower[m + j]:
            z[j] = lo[m + j]
        else:
            z[j] = 0.0
            free[n_free] = j
            n_free += 1
    return free, n_free


@numba.njit(cache=True, nogil=True)
def _kkt_system(h, g, c, lo, hi, at_upper, free, n_free, rows, n_rows, z):
    """Return the KKT matrix and right-hand side of :func:`_kkt_solve` (free variables)."""
    n = h.shape[0]
    size = n_free + n_rows
    kkt = np.zeros((size, size))
    rhs = np.empty(size)
    for a in range(n_free):
        i = free[a]
        total = 0.0
        for j in range(n):
            total += h[i, j] * z[j]
        rhs[a] = -(g[i] + total)
        for b in range(n_free):
            kkt[a, b] = h[i, free[b]]
    for r in range(n_rows):
        i = rows[r]
        total = 0.0
        for j in range(n):
            total += c[i, j] * z[j]
        rhs[n_free + r] = (hi[i] if at_upper[i] else lo[i]) - total
        for b in range(n_free):
            value = c[i, free[b]]
            kkt[n_free + r, b] = value
            kkt[b, n_free + r] = value
    return kkt, rhs


@numba.njit(cache=True, nogil=True)
def _close_stationarity(h, g, c, at_upper, at_lower, tolerance, rows, n_rows, z, y):
    """Box multipliers of the fixed variables; False if a free one is not stationary.

    Stationarity, H z + g + Cᵀ y_C = 0 on the free variables; the rest is the boxes'.
    """
    n = h.shape[0]
    m = c.shape[0]
    for j in range(n):
        total = 0.0
        for i in range(n):
            total += h[j, i] * z[i]
        total += g[j]
        for r in range(n_rows):
            total += c[rows[r], j] * y[rows[r]]
        if at_upper[m + j] or at_lower[m + j]:
            y[m + j] = -total
        elif not abs(total) <= tolerance:    # (NaN too)
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _check(c, lo, hi, at_upper, at_lower, tolerance, z, y, over, under, wrong):
    """Primal feasibility and the multipliers' signs: OK, or why not (and which ones)."""
    n = z.shape[0]
    m = c.shape[0]
    infeasible = False
    for i in range(m + n):
        if i < m:
            value = 0.0
            for j in range(n):
                value += c[i, j] * z[j]
        else:
            value = z[i - m]
        over[i] = value > hi[i] + tolerance
        under[i] = value < lo[i] - tolerance
        infeasible = infeasible or over[i] or under[i]
        wrong[i] = (at_upper[i] and y[i] < -tolerance) or (at_lower[i] and y[i] > tolerance)
    if infeasible:
        return PRIMAL_INFEASIBLE
    for i in range(m + n):
        if wrong[i]:
            return DUAL_SIGN
    return OK


@numba.njit(cache=True, nogil=True)
def polish(h, g, c, lower, upper, lower_box, upper_box, multipliers, tolerance, rounds,
           z, y):
    """:func:`.qp.polish` (its docstring says what and why); the point into ``z``, ``y``.

    Returns the outcome, an index into :data:`REASONS`; ``z`` and ``y`` hold the result
    only when it is :data:`OK`.
    """
    n = h.shape[0]
    m = c.shape[0]
    lo = np.concatenate((lower, lower_box))
    hi = np.concatenate((upper, upper_box))
    # A multiplier pointing to an infinite bound is round-off: that constraint is left out.
    at_upper = (multipliers > tolerance) & (hi < np.inf)
    at_lower = (multipliers < -tolerance) & (lo > -np.inf)
    over = np.empty(m + n, np.bool_)
    under = np.empty(m + n, np.bool_)
    wrong = np.empty(m + n, np.bool_)
    outcome = OK
    for _ in range(rounds):
        outcome = _kkt_solve(h, g, c, lo, hi, at_upper, at_lower, tolerance, z, y, over,
                             under, wrong)
        if outcome == OK:
            # The set found may hold constraints with λ ≈ 0 that another start (ProxSuite's
            # last bits) would have left out: the same point, other round-off. Solving
            # again with only |λ| > tolerance makes the bits a function of the optimum.
            strong = np.abs(y) > tolerance
            if np.array_equal(strong, at_upper | at_lower):
                return OK
            z_strong = np.empty(n)
            y_strong = np.empty(m + n)
            if _kkt_solve(h, g, c, lo, hi, at_upper & strong, at_lower & strong,
                          tolerance, z_strong, y_strong, over, under, wrong) == OK:
                z[:] = z_strong
                y[:] = y_strong
            return OK
        if outcome == SINGULAR or outcome == STATIONARITY:
            return outcome
        at_upper = (at_upper & ~wrong) | over
        at_lower = (at_lower & ~wrong) | under
    return outcome


def warm_up() -> None:
    """Load or compile :func:`polish` (a few seconds when compiling; once per process)."""
    eye = np.eye(2)
    polish(eye, np.ones(2), np.ones((1, 2)), np.full(1, -np.inf), np.ones(1),
           np.zeros(2), np.full(2, np.inf), np.zeros(3), 1e-9, 4, np.empty(2), np.empty(3))
