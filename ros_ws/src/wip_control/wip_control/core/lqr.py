r"""Discrete LQR baseline of the longitudinal/tilt subsystem, on the MPC's own model.

A controller a user would pick instead of the MPC of eqs. (16)–(23): same model, same
rate, same weights, same hard limits, no QP.

Model: the MPC's gravity-aware Euler prediction at θ = 0 (:mod:`.mpc_prediction`),
x = (υ, θ, θ̇), x(k+1) = A x(k) + B τ(k) + c with B = Ts (g2(0), 0, g3(0)), and the
increment form of (23), τ(k) = τ(k−1) + Δτ(k). Augmented with τ(k−1), the deviation
ξ = (υ − υd, θ − θs, θ̇, τ(k−1) − τs) from the steady-state target of
:class:`~.mpc_steps.OffsetFreeTarget` (θs = 0 unless ``offset_free``) obeys

.. math::

    \xi(k+1) = \begin{bmatrix} A & B \\ 0 & 1 \end{bmatrix} \xi(k)
              + \begin{bmatrix} B \\ 1 \end{bmatrix} \Delta\tau(k),

and the stage cost is the MPC's (20) with an infinite horizon:
ξᵀ diag(q, 0) ξ + r Δτ². The gain K of Δτ = −K ξ solves the discrete algebraic Riccati
equation (``scipy.linalg.solve_discrete_are``), once, at construction.

Limits: Δτ is clipped to ±Δτmax and τ to the tick's ``tau_limit`` (the MPC's hard
limits, with the same return-at-the-increment-limit rule when |τ(k−1)| is beyond a
shrunken limit). There is no speed or tilt limit: an LQR cannot anticipate them, which
is the point of the comparison.

The result is an :class:`~.mpc_plan.MpcResult` (status SOLVED, 0 iterations, slacks 0, the
predicted outputs and plan of the closed-loop linear model), so the runner, the mpc node
and the metrics use either controller unchanged.
"""

from __future__ import annotations

import time

import numpy as np

from .model import input_gains
from .mpc import LongitudinalController, LongitudinalMpc
from .mpc_config import MpcParams
from .mpc_plan import admissible_increment, MpcResult
from .mpc_prediction import gravity_aware_state_matrix
from wip_description.params import ModelParams
from .qp import MpcStatus

__all__ = ['CONTROLLERS', 'LongitudinalLqr', 'dlqr', 'make_longitudinal_controller']

#: Values of ``mpc.controller``.
CONTROLLERS = ('mpc', 'lqr')


def dlqr(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """Infinite-horizon discrete LQR: (K, P) with u = −K x minimising Σ xᵀQx + uᵀRu.

    P solves P = AᵀPA − AᵀPB (R + BᵀPB)⁻¹ BᵀPA + Q and K = (R + BᵀPB)⁻¹ BᵀPA.
    """
    a, b = np.atleast_2d(a).astype(float), np.atleast_2d(b).astype(float)
    q, r = np.atleast_2d(q).astype(float), np.atleast_2d(r).astype(float)
    import scipy.linalg   # here: SciPy is loaded only where an LQR is built
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    return k, p


class LongitudinalLqr(LongitudinalController):
    """Saturated discrete LQR with the interface of :class:`~.mpc.LongitudinalMpc`.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : the MPC's configuration: sampling period, weights (``output_weights``,
        ``input_weight``), torque and increment limits, offset-free target settings and
        ``prediction_gain_scale``; the QP and soft-limit settings are not used.
    """

    def __init__(self, params: ModelParams, config: MpcParams | None = None) -> None:
        config = MpcParams() if config is None else config
        super().__init__(params, config)
        ts = config.sampling_period
        a = gravity_aware_state_matrix(params, ts)
        _, g2, g3 = input_gains(params, 0.0)
        scale2, scale3 = config.prediction_gain_scale
        b = ts * np.array([scale2 * g2, 0.0, scale3 * g3])
        a_aug = np.zeros((4, 4))
        a_aug[:3, :3] = a
        a_aug[:3, 3] = b
        a_aug[3, 3] = 1.0
        b_aug = np.r_[b, 1.0][:, None]
        q_aug = np.diag(np.r_[np.asarray(config.output_weights, dtype=float), 0.0])
        # The MPC weighs x(k+1), …; over an infinite horizon that differs from weighing
        # x(k), x(k+1), … by the fixed term x(k)ᵀQx(k) only: the same optimal gain.
        gain, p = dlqr(a_aug, b_aug, q_aug, np.array([[config.input_weight]]))
        self.gain = gain.reshape(-1)  # Δτ = −K ξ
        self.riccati = p
        self.a_aug, self.b_aug = a_aug, b_aug
        self.closed_loop = a_aug - b_aug @ gain
        self.n_variables = config.control_horizon
        self.n_constraints = 0
        self.last_qp = None

    def reset(self, tau_previous: float = 0.0) -> None:
        """Forget the disturbance filter; τυ(k−1) = ``tau_previous`` [N m]."""
        self.set_previous_torque(tau_previous)
        self._target.reset()

    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_limit: float | None = None) -> MpcResult:
        """One tick: Δτ = −K ξ, clipped to the hard limits (see the module docstring)."""
        cfg = self.config
        tau_prev = self._tau_previous
        t_start = time.perf_counter()
        tick = self._begin_tick(tau_limit, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat,
                                v_d)
        if tick is None:
            return self._hold_invalid_input()
        limit = tick[0]
        theta_s = self._target.theta
        tau_s = self._target.tau
        xi = np.array([v_hat - v_d, theta_hat - theta_s, theta_dot_hat, tau_prev - tau_s])
        delta = float(-self.gain @ xi)
        delta = admissible_increment(delta, tau_prev, limit, cfg.max_delta_torque)
        self._tau_previous = tau_prev + delta
        # Closed-loop prediction of the linear model (for the message and the plots).
        n_p, n_c = cfg.prediction_horizon, cfg.control_horizon
        predicted = np.empty((n_p, 3))
        plan = np.empty(n_c)
        state = xi.copy()
        for i in range(n_p):
            increment = delta if i == 0 else float(-self.gain @ state)
            if i < n_c:
                plan[i] = increment
            state = self.a_aug @ state + self.b_aug[:, 0] * increment
            predicted[i] = state[:3] + (v_d, theta_s, 0.0)
        elapsed = time.perf_counter() - t_start
        return MpcResult(self._tau_previous, delta, MpcStatus.SOLVED, 0, 0.0, elapsed, 0.0,
                         0.0, False, predicted, plan, theta_s)


def make_longitudinal_controller(params: ModelParams, config: MpcParams
                                 ) -> LongitudinalMpc | LongitudinalLqr:
    """Return the controller named by ``config.controller``: the MPC (default) or the LQR."""
    if config.controller == 'lqr':
        return LongitudinalLqr(params, config)
    return LongitudinalMpc(params, config)
