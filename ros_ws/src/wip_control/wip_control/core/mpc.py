"""MPC of the longitudinal/tilt subsystem, eqs. (16)–(23) in [1]_.

Every ``sampling_period`` Ts the controller takes the ESO's estimates (υ̂, θ̂, θ̂̇, f̂2, f̂3)
and the desired speed υd, solves the condensed QP (22) over the increments
Δτ̄ = (Δτ(k|k), …, Δτ(k+Nc−1|k)) and applies, eq. (23),

.. math::

    \\tau_\\upsilon(k) = \\tau_\\upsilon(k-1) + \\Delta\\tau(k|k).

Cost (20), with ȳ = G̃ Δτ̄ + ȳ_free from :mod:`.mpc_prediction`:

.. math::

    J = \\|\\bar y_r - \\bar y\\|^2_Q + \\|\\Delta\\bar\\tau\\|^2_R
        + \\rho_1 (s_\\upsilon + s_\\theta) + \\rho_2 (s_\\upsilon^2 + s_\\theta^2)

with ȳr = 1_Np ⊗ (υd, 0, 0), Q = I_Np ⊗ diag(q), R = r I_Nc. As a QP in
z = (Δτ̄, sυ, sθ): ½ zᵀ H z + gᵀ z with H = 2(G̃ᵀQG̃ + R) and g = −2 G̃ᵀQ(ȳr − ȳ_free)
on the Δτ̄ block (eq. (22)), 2ρ2 and ρ1 on the slack entries.

Constraints (19), (21), as adopted in ``shared/spec/model-and-controllers.md`` §5:

- hard, box: |Δτ(k+j)| ≤ Δτmax; hard, rows: |τ(k+j)| ≤ τlim for j < Nc (τ is constant
  after Nc−1), τlim = min(``tau_limit``, ``max_drive_torque``);
- soft, rows: |υ(k+i)| ≤ υmax (1 + sυ) and |θ(k+i)| ≤ θmax (1 + sθ) for i = 1..Np,
  one slack per quantity in units relative to its limit, sυ, sθ ≥ 0 (box); θ̇ unbounded.

Deviation (feasibility): if |τ(k−1)| > τlim (the limit shrinks when |τω| grows), the
hard τ rows cannot all hold under the Δτ limit. The τ bound of step j is then relaxed
to what is reachable, |τ(k+j)| ≤ max(τlim, |τ(k−1)| − (j+1) Δτmax): the torque goes
back inside the limit as fast as the increment limit allows. The QP is always feasible.

Failure handling (logged in :class:`MpcResult`):

- solver status other than solved: apply the previous plan shifted by one step (last
  increment 0), clipped to the hard limits; with no previous plan hold τ(k−1) clipped
  (Δτ = 0 clipped). ``used_fallback`` is set and ``status`` says why.
- NaN/inf input, or a magnitude above :data:`INPUT_MAGNITUDE_LIMIT` (estimates, υd or the
  limit; such values overflow the QP data to inf): no solve, status ``INPUT_INVALID``, and τ
  ramps toward 0 by at most Δτmax. Why not hold τ(k−1): a held drive torque accelerates
  the vehicle without bound while the state is unknown, and the safety layer (mixer)
  zeroes the applied torque on invalid estimates anyway; ramping the MPC's own τ(k−1)
  toward that applied 0 (within the increment limit) means the controller restarts from
  about what is really applied when the estimates come back, instead of from a stale
  torque that the increment limit would then make it unwind slowly.
- a negative ``tau_limit`` is a caller's bug (the limit is 2τmax − |τω| ≥ 0 after the
  yaw controller's saturation) and raises :class:`MpcInputError`.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import NamedTuple

import numpy as np

from .config import ConfigError, param
from .model import input_gains
from .mpc_prediction import PREDICTION_MODELS, CondensedPrediction
from .params import WipParameters
from .qp import MpcStatus, QpSettings, make_solver

#: Largest magnitude of an input (SI units: m/s, rad, rad/s, m/s², rad/s², N m) taken as
#: data. Far beyond anything physical (the safety layer's divergence bounds are ≤ 100),
#: far below where the QP data would overflow (values ~1e300 made the gradient inf).
INPUT_MAGNITUDE_LIMIT = 1e9

__all__ = ['LongitudinalMpc', 'MpcConfig', 'MpcInputError', 'MpcResult', 'MpcStatus',
           'QpData']


class MpcInputError(ValueError):
    """An argument of :meth:`LongitudinalMpc.step` or ``reset`` is not admissible."""


@dataclasses.dataclass(frozen=True)
class MpcConfig:
    """Tunables of the longitudinal/tilt MPC (eqs. (16)–(23) in [1])."""

    sampling_period: float = param(
        0.1, 's', 'Ts: MPC sampling period and Euler step of the prediction (17) '
        '(the paper calls it ε, like the ESO gain)', minimum=0.0, exclusive_minimum=True)
    # Upper bounds keep the QP (Nc + 1 variables, about 4 Np constraints) and the
    # prediction (powers of the unstable tilt dynamics up to Np) numerically sane.
    prediction_horizon: int = param(20, '1', 'Np: predicted steps', minimum=1, maximum=60)
    control_horizon: int = param(6, '1', 'Nc: input increments optimised (<= Np)',
                                 minimum=1, maximum=60)
    output_weights: tuple[float, float, float] = param(
        (1.0, 50.0, 1.0), 's²/m², 1/rad², s²/rad²',
        'diagonal of the per-step output weight of Q in (20), for (υ, θ, θ̇)', minimum=0.0)
    input_weight: float = param(1.0, '1/(N m)²', 'R = r I: weight of Δτ in (20)',
                                minimum=0.0, exclusive_minimum=True)
    max_drive_torque: float = param(
        30.0, 'N m', 'hard |τυ| limit 2 τmax (19); the per-call tau_limit is capped to it',
        minimum=0.0, exclusive_minimum=True)
    max_delta_torque: float = param(10.0, 'N m', 'hard |Δτυ| limit per sampling period (19)',
                                    minimum=0.0, exclusive_minimum=True)
    max_speed: float = param(1.5, 'm/s', 'soft |υ| limit (19)', minimum=0.0,
                             exclusive_minimum=True)
    max_tilt: float = param(0.1, 'rad', 'soft |θ| limit (19)', minimum=0.0,
                            exclusive_minimum=True)
    slack_linear_penalty: float = param(
        1e4, '1', 'ρ1: cost per unit of relative violation of a soft limit', minimum=0.0)
    slack_quadratic_penalty: float = param(
        1e4, '1', 'ρ2: cost per squared unit of relative violation of a soft limit',
        minimum=0.0, exclusive_minimum=True)
    prediction: str = param(
        'gravity_aware', '-', "'gravity_aware' (adopted) or 'paper' (literal G̃ of (18), "
        'falls; for the ablation)', choices=PREDICTION_MODELS)
    backend: str = param('proxsuite', '-', 'QP solver', choices=('proxsuite', 'daqp'))
    eps_abs: float = param(1e-6, '1', 'ProxSuite absolute tolerance (spec: 1e-6 to 1e-8)',
                           minimum=1e-12, maximum=1e-3)
    eps_rel: float = param(
        1e-11, '1', 'ProxSuite relative tolerance; tiny but not 0, so that the badly scaled '
        'QPs of a falling vehicle converge instead of running for seconds', minimum=0.0,
        maximum=1e-3)
    eps_primal_inf: float = param(
        0.0, '1', 'ProxSuite primal infeasibility tolerance; 0 disables the certificate '
        '(the QP is feasible by construction, 1e-9 gave false alarms)', minimum=0.0,
        maximum=1e-3)
    eps_dual_inf: float = param(
        0.0, '1', 'ProxSuite dual infeasibility tolerance; 0 disables it (H is positive '
        'definite)', minimum=0.0, maximum=1e-3)
    max_iter: int = param(1000, '1', 'iteration limit of the QP solver (ProxSuite: outer '
                          'iterations)', minimum=1, maximum=100000)
    max_inner_iter: int = param(
        30, '1', 'ProxSuite inner iterations per outer one; with max_iter it bounds the '
        'worst-case solve time', minimum=1, maximum=10000)

    def validate(self) -> None:
        if self.control_horizon > self.prediction_horizon:
            raise ConfigError(f'control_horizon: must be <= prediction_horizon '
                              f'({self.prediction_horizon}), got {self.control_horizon}')

    def qp_settings(self) -> QpSettings:
        return QpSettings(self.eps_abs, self.eps_rel, self.eps_primal_inf, self.eps_dual_inf,
                          self.max_iter, self.max_inner_iter)


class MpcResult(NamedTuple):
    """Output and diagnostics of one MPC tick."""

    tau_v: float             #: τυ(k) to apply and hold for Ts [N m]
    delta_tau: float         #: τυ(k) − τυ(k−1) [N m]
    status: MpcStatus        #: int code; ``status.name`` is the text
    iterations: int          #: QP solver iterations (0 if not run)
    solve_time_s: float      #: wall time of the solver's update + solve [s]
    build_time_s: float      #: wall time of building H, g, C, l, u [s]
    slack_v: float           #: sυ, relative violation of |υ| ≤ υmax (nan if not solved)
    slack_theta: float       #: sθ, relative violation of |θ| ≤ θmax (nan if not solved)
    used_fallback: bool      #: true if the applied plan is not a fresh QP solution
    predicted: np.ndarray    #: (Np, 3) predicted (υ, θ, θ̇) for the applied plan
    plan: np.ndarray         #: (Nc,) applied increments Δτ(k|k) … Δτ(k+Nc−1|k) [N m]

    @property
    def status_text(self) -> str:
        return self.status.name


class QpData(NamedTuple):
    """The QP of the last tick: ½ zᵀHz + gᵀz, l ≤ Cz ≤ u, lb ≤ z ≤ ub (live buffers)."""

    H: np.ndarray
    g: np.ndarray
    C: np.ndarray
    l: np.ndarray  # noqa: E741 (the solvers' name)
    u: np.ndarray
    lb: np.ndarray
    ub: np.ndarray


class LongitudinalMpc:
    """Condensed MPC of (υ, θ, θ̇) with the drive torque τυ as input.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : tunables; see :class:`MpcConfig`.
    solver : optional replacement of the backend named by ``config.backend``: any object
        with ``solve(H, g, C, l, u, lb, ub) -> QpSolution`` and ``reset()`` (tests inject
        a failing one).

    Notes
    -----
    Everything that does not depend on the tick's data is computed here: G̃ is bilinear in
    (g2, g3), so G̃ᵀQG̃ = g2² K22 + g2 g3 K23 + g3² K33 with fixed K's, and the rows of C
    are g2 C2 + g3 C3. A tick costs a few small matrix–vector products. The solver
    keeps one persistent workspace (see :mod:`.qp`).

    Decision vector z = (Δτ̄ (Nc), sυ, sθ); Δτ̄ and the slacks' signs are box constraints.
    Rows of C: τ(k..k+Nc−1) (Nc), υ ≤ (Np), θ ≤ (Np), υ ≥ (Np), θ ≥ (Np).

    Not done: the spec's whitening of the Hessian (computed once at θ = 0). Tried: it cut
    the closed-loop p99 iterations from 40 to 27, but the whitened Δτ limits become
    general rows and ProxSuite then reached MAX_ITER on about half of the QPs at random
    states and on 19 of 10 187 closed-loop QPs (0 without it).
    """

    def __init__(self, params: WipParameters, config: MpcConfig | None = None,
                 solver=None) -> None:
        config = MpcConfig() if config is None else config
        config.validate()
        self.params = params
        self.config = config
        n_p, n_c = config.prediction_horizon, config.control_horizon
        self.prediction = CondensedPrediction(params, config.sampling_period, n_p, n_c,
                                              config.prediction)
        pred = self.prediction
        q = np.tile(np.asarray(config.output_weights, dtype=float), n_p)
        r = config.input_weight

        g2m, g3m = pred.gain_matrix_v, pred.gain_matrix_theta_dot

        # Hessian blocks: H_ΔΔ = coef · K, coef = (2g2², 2g2g3, 2g3², 2).
        qg2, qg3 = q[:, None] * g2m, q[:, None] * g3m
        self._hessian_blocks = np.stack([
            g2m.T @ qg2, g2m.T @ qg3 + g3m.T @ qg2, g3m.T @ qg3,
            r * np.eye(n_c)]).reshape(4, n_c * n_c)
        self._hessian_coef = np.empty(4)
        # Gradient: g_Δ = −2 (g2 G2ᵀQ e + g3 G3ᵀQ e), e = ȳr − ȳ_free.
        self._weighted_gains = np.vstack([qg2.T, qg3.T])  # (2Nc, 3Np)
        self._reference_pattern = np.zeros(3 * n_p)
        self._reference_pattern[0::3] = 1.0
        # Constraint rows on υ and θ: [υ rows; θ rows] = g2 C2 + g3 C3, stacked (2, 2Np·Nc).
        self._row_blocks = np.stack([
            np.vstack([g2m[0::3], g2m[1::3]]).reshape(-1),
            np.vstack([g3m[0::3], g3m[1::3]]).reshape(-1)])
        self._row_coef = np.empty(2)
        # Reachable |τ(k+j) − τ(k−1)| under the increment limit, for the τ rows.
        self._reach = config.max_delta_torque * np.arange(1, n_c + 1)

        n = n_c + 2
        m = n_c + 4 * n_p
        self.n_variables, self.n_constraints = n, m
        self._slice_upper = slice(n_c, n_c + 2 * n_p)
        self._slice_lower = slice(n_c + 2 * n_p, n_c + 4 * n_p)
        self._h = np.zeros((n, n))
        self._h[n_c, n_c] = self._h[n_c + 1, n_c + 1] = 2.0 * config.slack_quadratic_penalty
        self._g = np.zeros(n)
        self._g[n_c:] = config.slack_linear_penalty
        self._c = np.zeros((m, n))
        self._c[:n_c, :n_c] = np.tril(np.ones((n_c, n_c)))
        limits = np.repeat([config.max_speed, config.max_tilt], n_p)
        self._limits = limits
        self._c[self._slice_upper, n_c] = np.r_[-limits[:n_p], np.zeros(n_p)]
        self._c[self._slice_upper, n_c + 1] = np.r_[np.zeros(n_p), -limits[n_p:]]
        self._c[self._slice_lower, n_c] = np.r_[limits[:n_p], np.zeros(n_p)]
        self._c[self._slice_lower, n_c + 1] = np.r_[np.zeros(n_p), limits[n_p:]]
        self._l = np.full(m, -np.inf)
        self._u = np.full(m, np.inf)
        self._lb = np.zeros(n)
        self._ub = np.full(n, np.inf)
        self._lb[:n_c] = -config.max_delta_torque
        self._ub[:n_c] = config.max_delta_torque
        self._x_hat = np.empty(3)
        self.last_qp = QpData(self._h, self._g, self._c, self._l, self._u, self._lb,
                              self._ub)

        self._solver = (make_solver(config.backend, n, m, config.qp_settings())
                        if solver is None else solver)
        self._tau_previous = 0.0
        self._plan: np.ndarray | None = None

    # ------------------------------------------------------------------ state
    @property
    def tau_previous(self) -> float:
        """τυ(k−1) [N m], the torque applied since the last tick."""
        return self._tau_previous

    def reset(self, tau_previous: float = 0.0) -> None:
        """Forget the plan and the solver's workspace; τυ(k−1) = ``tau_previous`` [N m]."""
        self.set_previous_torque(tau_previous)
        self._plan = None
        self._solver.reset()

    def set_previous_torque(self, tau_previous: float) -> None:
        """Overwrite τυ(k−1) [N m] with the torque really applied (e.g. after the safety
        layer cut it, or to replay a recorded tick). The plan and workspace are kept."""
        tau_previous = float(tau_previous)
        if not math.isfinite(tau_previous):
            raise MpcInputError(f'tau_previous must be finite, got {tau_previous!r}')
        self._tau_previous = tau_previous

    # ------------------------------------------------------------------ tick
    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_limit: float | None = None) -> MpcResult:
        """One MPC tick: build and solve the QP, apply τ(k) = τ(k−1) + Δτ(k|k) (23).

        Parameters
        ----------
        v_hat : υ̂ [m/s]; theta_hat : θ̂ [rad]; theta_dot_hat : θ̂̇ [rad/s].
        f2_hat : f̂2, the ESO's lumped drift of υ̇ [m/s²]; f3_hat : f̂3, of θ̈ [rad/s²].
        v_d : desired speed υd [m/s] from the trajectory generator (9).
        tau_limit : |τυ| limit for this tick [N m], 2τmax − |τω| so that each wheel stays
            within τmax after mixing (24); capped to ``max_drive_torque``; None uses it.
        """
        cfg = self.config
        tau_prev = self._tau_previous
        limit = cfg.max_drive_torque if tau_limit is None else float(tau_limit)
        values = (v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, v_d, limit)
        if not all(math.isfinite(v) and abs(v) <= INPUT_MAGNITUDE_LIMIT for v in values):
            return self._hold_invalid_input()
        if limit < 0.0:
            raise MpcInputError(f'tau_limit must be >= 0 N m, got {limit!r}')
        limit = min(limit, cfg.max_drive_torque)

        t_start = time.perf_counter()
        _, g2, g3 = input_gains(self.params, theta_hat)
        free = self._build(v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, v_d, limit, g2,
                           g3, tau_prev)
        t_built = time.perf_counter()
        solution = self._solver.solve(self._h, self._g, self._c, self._l, self._u,
                                      self._lb, self._ub)
        t_solved = time.perf_counter()

        n_c = cfg.control_horizon
        if solution.status == MpcStatus.SOLVED:
            plan = solution.z[:n_c].copy()
            slack_v, slack_theta = float(solution.z[n_c]), float(solution.z[n_c + 1])
            used_fallback = False
        else:
            plan = self._shifted_plan()
            slack_v = slack_theta = math.nan
            used_fallback = True
        delta = self._admissible_increment(plan[0], tau_prev, limit)
        plan[0] = delta
        self._plan = plan
        self._tau_previous = tau_prev + delta
        predicted = (free + g2 * (self.prediction.gain_matrix_v @ plan)
                     + g3 * (self.prediction.gain_matrix_theta_dot @ plan))
        return MpcResult(self._tau_previous, delta, solution.status, solution.iterations,
                         t_solved - t_built, t_built - t_start, slack_v, slack_theta,
                         used_fallback, predicted.reshape(-1, 3), plan.copy())

    def _build(self, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, v_d, limit, g2, g3,
               tau_prev) -> np.ndarray:
        """Fill H, g, C, l, u in place; return the free response ȳ_free (3Np)."""
        n_c = self.config.control_horizon
        n_p = self.config.prediction_horizon
        pred = self.prediction
        x = self._x_hat
        x[0], x[1], x[2] = v_hat, theta_hat, theta_dot_hat
        free = pred.free_state_matrix @ x
        free += pred.free_v_column * (f2_hat + g2 * tau_prev)
        free += pred.free_theta_dot_column * (f3_hat + g3 * tau_prev)

        # Eq. (22): H_ΔΔ = 2(G̃ᵀQG̃ + R), g_Δ = −2 G̃ᵀQ(ȳr − ȳ_free).
        coef = self._hessian_coef
        coef[0], coef[1], coef[2], coef[3] = 2.0 * g2 * g2, 2.0 * g2 * g3, 2.0 * g3 * g3, 2.0
        self._h[:n_c, :n_c] = (coef @ self._hessian_blocks).reshape(n_c, n_c)
        error = self._reference_pattern * v_d
        error -= free
        projected = self._weighted_gains @ error
        self._g[:n_c] = -2.0 * (g2 * projected[:n_c] + g3 * projected[n_c:])

        # Rows (21): υ and θ of the plan, identical for the ≤ and ≥ halves.
        self._row_coef[0], self._row_coef[1] = g2, g3
        rows = (self._row_coef @ self._row_blocks).reshape(2 * n_p, n_c)
        self._c[self._slice_upper, :n_c] = rows
        self._c[self._slice_lower, :n_c] = rows
        free_outputs = np.concatenate((free[0::3], free[1::3]))
        np.subtract(self._limits, free_outputs, out=self._u[self._slice_upper])
        np.subtract(-self._limits, free_outputs, out=self._l[self._slice_lower])
        # τ rows, relaxed to the reachable set if |τ(k−1)| is beyond the limit (see module).
        np.subtract(np.maximum(limit, tau_prev - self._reach), tau_prev, out=self._u[:n_c])
        np.subtract(np.minimum(-limit, tau_prev + self._reach), tau_prev, out=self._l[:n_c])
        return free

    # ------------------------------------------------------------------ fallbacks
    def _shifted_plan(self) -> np.ndarray:
        """Previous plan shifted by one tick, last increment 0, within the Δτ limit."""
        n_c = self.config.control_horizon
        shifted = np.zeros(n_c)
        if self._plan is not None:
            shifted[:-1] = self._plan[1:]
        dmax = self.config.max_delta_torque
        return np.clip(shifted, -dmax, dmax)

    def _admissible_increment(self, delta: float, tau_prev: float, limit: float) -> float:
        """Clip Δτ to the hard limits: |Δτ| ≤ Δτmax and |τ(k−1) + Δτ| ≤ limit when reachable."""
        dmax = self.config.max_delta_torque
        delta = min(max(float(delta), -dmax), dmax)
        tau = tau_prev + delta
        if tau > limit:
            tau = max(limit, tau_prev - dmax)
        elif tau < -limit:
            tau = min(-limit, tau_prev + dmax)
        return tau - tau_prev

    def _hold_invalid_input(self) -> MpcResult:
        """No solve on NaN/inf input: ramp τ toward 0 within Δτmax (see the module doc)."""
        cfg = self.config
        tau_prev = self._tau_previous
        delta = min(max(-tau_prev, -cfg.max_delta_torque), cfg.max_delta_torque)
        self._tau_previous = tau_prev + delta
        self._plan = None
        plan = np.zeros(cfg.control_horizon)
        plan[0] = delta
        predicted = np.full((cfg.prediction_horizon, 3), np.nan)
        return MpcResult(self._tau_previous, delta, MpcStatus.INPUT_INVALID, 0, 0.0, 0.0,
                         math.nan, math.nan, True, predicted, plan)
