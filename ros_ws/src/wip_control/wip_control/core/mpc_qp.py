r"""The MPC's QP (22), built once from its problem and updated every tick.

.. math::

    \min_z \tfrac12 z^T H z + g^T z \quad \text{s.t.} \quad
    l \le C z \le u, \quad lb \le z \le ub

with z = (Δτ̄, sυ, sθ[, r]) (:mod:`.mpc_problem`). The constant entries (slack
penalties ρ1, ρ2, the τ rows' lower-triangular ones, the slacks' columns of the soft
rows, the boxes) are set in :class:`MpcQp`'s constructor; :meth:`MpcQp.update` fills
the rest from one :class:`TickData` with the compiled kernel :func:`.mpc_kernel.fill`,
whose numpy reference is :func:`.mpc_reference.reference_qp`.

Hard rows (19): |Δτ(k+j)| ≤ Δτmax (box; the first one within the box of
:meth:`MpcQp.set_first_box`, lo ≤ Δτ(k|k) ≤ hi) and |τ(k+j)| ≤ τlim for j < Nc, relaxed
to what the increments can reach when |τ(k−1)| > τlim (τ(k−1) − (−lo + j Δτmax) from
above, τ(k−1) + (hi + j Δτmax) from below), so the QP is always feasible.
Soft rows (21): |υ(k+i)| ≤ υmax (1 + sυ,i) from ``speed_limit_first_step`` on and
|θ(k+i)| ≤ θmax (1 + sθ,i), slacks ≥ 0 relative to the limit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .compiled import load_compiled, MPC_KERNEL
from .mpc_problem import MpcProblem


class TickData(NamedTuple):
    """Everything of one tick that the QP depends on (floats only: the kernel's types)."""

    v_hat: float                #: υ̂ [m/s]
    theta_hat: float            #: θ̂ [rad]
    theta_dot_hat: float        #: θ̂̇ [rad/s]
    f2_hat: float               #: f̂2 used by the prediction [m/s²]
    f3_hat: float               #: f̂3 used by the prediction [rad/s²]
    g2: float                   #: input gain of υ̇ of model (1) at θ̂
    g3: float                   #: input gain of θ̈ of model (1) at θ̂
    g2p: float                  #: g2 of the increments' prediction (scaled)
    g3p: float                  #: g3 of the increments' prediction (scaled)
    tau_prev: float             #: τυ(k−1) [N m]
    limit: float                #: |τυ| limit of the tick [N m]
    transient_v: float          #: decaying part of the disturbance on υ̇ [m/s²]
    transient_theta_dot: float  #: decaying part on θ̈ [rad/s²]
    v_d: float                  #: υd [m/s]
    speed_trend: float          #: filtered dυd/dt of the preview [m/s²]
    target_theta: float         #: θs of the offset-free target [rad]


class QpBuffers(NamedTuple):
    """The arrays the kernel writes (H … u) and the τ rows' reach it reads."""

    h: np.ndarray
    g: np.ndarray
    c: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    reach_up: np.ndarray     #: largest reachable τ(k+j) − τ(k−1) under the bounds [N m]
    reach_down: np.ndarray   #: largest reachable τ(k−1) − τ(k+j) under the bounds [N m]


class QpData(NamedTuple):
    """The QP of the last tick: ½ zᵀHz + gᵀz, l ≤ Cz ≤ u, lb ≤ z ≤ ub (live buffers)."""

    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray  # noqa: E741 (the solvers' name)
    u: np.ndarray
    lb: np.ndarray
    ub: np.ndarray


class MpcQp:
    """The QP of a :class:`~.mpc_problem.MpcProblem`: buffers built once, updated per tick.

    Why the Hessian is not whitened: docs/decisions/proxsuite-settings.md.
    """

    def __init__(self, problem: MpcProblem) -> None:
        config = problem.config
        self.problem = problem
        h, g, c, lower, upper, lb, ub = problem.constant_qp()
        self.data = QpData(h, g, c, lower, upper, lb, ub)
        reach = config.max_delta_torque * np.arange(1, problem.control_horizon + 1)
        self._buffers = QpBuffers(h, g, c, lower, upper, reach, reach.copy())
        self._first_box = (-config.max_delta_torque, config.max_delta_torque)
        self._rate = config.max_delta_torque   #: |Δτ| bound of the later increments [N m]
        self._kernels = load_compiled(MPC_KERNEL)   # at construction, not in the first tick
        self._fill = self._kernels.fill_for(problem.blocks, self._buffers)

    def set_first_box(self, lower: float, upper: float) -> None:
        """Bound Δτ(k|k) to [``lower``, ``upper``] [N m] (lower ≤ 0 ≤ upper).

        Sets its box and what the τ rows can reach, upper + j Δτmax up and −lower + j Δτmax
        down (the later increments keep ±Δτmax, :meth:`set_rate`).
        """
        if (lower, upper) == self._first_box:
            return
        self._first_box = (lower, upper)
        self.data.lb[0], self.data.ub[0] = lower, upper
        self._set_reach()

    def set_rate(self, rate: float) -> None:
        """Bound the later increments Δτ(k+j|k), j ≥ 1, to ±``rate`` [N m] (19).

        ``max_delta_torque`` normally; ``impact_delta_torque`` while an obstacle stops the
        base (:class:`~.control_step.DriveControllerStage`).
        """
        if rate == self._rate:
            return
        self._rate = rate
        self.data.lb[1:self.problem.control_horizon] = -rate
        self.data.ub[1:self.problem.control_horizon] = rate
        self._set_reach()

    def _set_reach(self) -> None:
        """Set what the τ rows can reach: upper + j Δτmax up, −lower + j Δτmax down."""
        lower, upper = self._first_box
        steps = self._rate * np.arange(self.problem.control_horizon)
        self._buffers.reach_up[:] = upper + steps
        self._buffers.reach_down[:] = -lower + steps

    @property
    def reach(self) -> tuple[np.ndarray, np.ndarray]:
        """(up, down): the reachable τ(k+j) − τ(k−1) and τ(k−1) − τ(k+j) [N m] (Nc each)."""
        return self._buffers.reach_up, self._buffers.reach_down

    @property
    def first_box(self) -> tuple[float, float]:
        """(lower, upper) of Δτ(k|k) of the last :meth:`set_first_box` [N m]."""
        return self._first_box

    def update(self, tick: TickData) -> np.ndarray:
        """Fill H, g, C, l, u for ``tick``; return the free response ȳ_free (3Np)."""
        return self._fill(tick, self.problem.blocks, self._buffers)

    def predict(self, free: np.ndarray, g2p: float, g3p: float,
                plan: np.ndarray) -> np.ndarray:
        """ȳ = ȳ_free + G̃ Δτ̄ of ``plan`` over the horizon, as (Np, 3)."""
        return self._kernels.predict(free, float(g2p), float(g3p),
                                     *self.problem.gain_matrices, plan)
