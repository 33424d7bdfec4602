r"""MPC of the longitudinal/tilt subsystem, eqs. (16)–(23) in [1]_: the tick.

Every ``sampling_period`` Ts the controller takes the ESO's estimates (υ̂, θ̂, θ̂̇, f̂2, f̂3)
and the desired speed υd, solves the condensed QP (22) over the increments
Δτ̄ = (Δτ(k|k), …, Δτ(k+Nc−1|k)) and applies, eq. (23),

.. math::

    \tau_\upsilon(k) = \tau_\upsilon(k-1) + \Delta\tau(k|k).

Three nouns (docs/mpc.md): the problem (:class:`~.mpc_problem.MpcProblem`: horizons,
weights, limits, the blocks built once), its QP (:class:`~.mpc_qp.MpcQp`: built once,
updated from one :class:`~.mpc_qp.TickData` per tick) and the plan
(:class:`~.mpc_plan.MpcResult`). Before the QP, the named steps of :mod:`.mpc_steps`
(start-up, speed preview, dead-zone decay, offset-free target) turn the estimates into
the tick's data. Cost (20), with ȳ = G̃ Δτ̄ + ȳ_free from :mod:`.mpc_prediction`:

.. math::

    J = \|\bar y_r - \bar y\|^2_Q + \|\Delta\bar\tau\|^2_R
        + \sum_i \left(\rho_{1\upsilon} s_{\upsilon,i} + \rho_1 s_{\theta,i}
        + \rho_2 (s_{\upsilon,i}^2 + s_{\theta,i}^2)\right)

with ȳr = 1_Np ⊗ (υd, θs, 0), Q = I_Np ⊗ diag(q), R = r I_Nc; constraints (19), (21) in
:mod:`.mpc_qp`. Failure handling: :mod:`.mpc_plan`; a negative ``tau_limit`` is a caller's
bug (the limit is 2τmax − |τω| ≥ 0 after the yaw controller's saturation) and raises
:class:`MpcInputError`.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math
import time

import numpy as np

from .model import input_gains
from .mpc_config import MpcParams
from .mpc_plan import admissible_increment, invalid_input_result, MpcResult, plan_of
from .mpc_problem import MpcProblem
from .mpc_qp import MpcQp, TickData
from .mpc_steps import beyond, decaying_excess, OffsetFreeTarget, SpeedPreview, StartUp
from wip_description.params import ModelParams
from .qp import MpcStatus, make_solver

#: Largest magnitude of an input (SI units: m/s, rad, rad/s, m/s², rad/s², N m) taken as
#: data. Far beyond anything physical (the safety layer's divergence bounds are ≤ 100),
#: far below where the QP data would overflow (values ~1e300 made the gradient inf).
INPUT_MAGNITUDE_LIMIT = 1e9

__all__ = ['LongitudinalController', 'LongitudinalMpc', 'MpcInputError', 'MpcStatus']


class MpcInputError(ValueError):
    """An argument of :meth:`LongitudinalMpc.step` or ``reset`` is not admissible."""


def tick_gains(params: ModelParams, config: MpcParams,
               theta_hat: float) -> tuple[float, float, float, float]:
    """Input gains of model (1) at θ̂ and the scaled gains of the increments.

    Returns (g2, g3, g2p, g3p): g2, g3 are what the ESO assumes, so f̂ + g τ(k−1) is its
    estimate of the present accelerations; g2p, g3p are scaled by
    ``prediction_gain_scale`` for the prediction of the increments.
    """
    _, g2, g3 = input_gains(params, theta_hat)
    scale2, scale3 = config.prediction_gain_scale
    return g2, g3, scale2 * g2, scale3 * g3


def drive_limit(config: MpcParams, tau_limit: float | None, *inputs: float) -> float | None:
    """Return the |τυ| limit of a tick, capped to ``max_drive_torque``.

    ``tau_limit`` None: that cap. None when an input or the limit is not finite or beyond
    :data:`INPUT_MAGNITUDE_LIMIT` (the caller then holds, see ``invalid_input_result``).
    MpcInputError on a negative limit (a caller's bug: 2τmax − |τω| ≥ 0).
    """
    limit = config.max_drive_torque if tau_limit is None else float(tau_limit)
    if not all(math.isfinite(v) and abs(v) <= INPUT_MAGNITUDE_LIMIT
               for v in (*inputs, limit)):
        return None
    if limit < 0.0:
        raise MpcInputError(f'tau_limit must be >= 0 N m, got {limit!r}')
    return min(limit, config.max_drive_torque)


def _first_box(box: tuple[float, float] | None, dmax: float) -> tuple[float, float]:
    """Return the bounds of Δτ(k|k) [N m]: ``box`` within ±``dmax`` (None: ±``dmax``).

    MpcInputError when its lower bound is above its upper one or either is NaN.
    """
    if box is None:
        return -dmax, dmax
    lower, upper = min(max(float(box[0]), -dmax), dmax), min(max(float(box[1]), -dmax), dmax)
    if not lower <= upper:
        raise MpcInputError(f'first_box must have lower <= upper, got {box!r}')
    return lower, upper


class LongitudinalController:
    """τυ(k−1) and the start of a tick, shared by the MPC and the LQR baseline.

    Holds the configuration, the model, the offset-free target and τυ(k−1), the drive
    torque applied since the last tick.
    """

    def __init__(self, params: ModelParams, config: MpcParams) -> None:
        config.validate()
        self.params = params
        self.config = config
        self._target = OffsetFreeTarget(params, config)
        self._tau_previous = 0.0
        #: Time since the previous tick [s] for the offset-free target's filter (None: the
        #: sampling period; the MPC sets it per tick when it re-solves after a push).
        self._period: float | None = None

    def _begin_tick(self, tau_limit: float | None, v_hat: float, theta_hat: float,
                    theta_dot_hat: float, f2_hat: float, f3_hat: float, v_d: float):
        """Start a tick: its |τυ| limit, the input gains at θ̂ and the offset-free target.

        (limit, ``tick_gains``), the target updated with them; None when an input is
        invalid (the caller then returns ``_hold_invalid_input()``).
        """
        limit = drive_limit(self.config, tau_limit, v_hat, theta_hat, theta_dot_hat, f2_hat,
                            f3_hat, v_d)
        if limit is None:
            return None
        gains = tick_gains(self.params, self.config, theta_hat)
        self._target.update(theta_hat, f2_hat, f3_hat, *gains, self._tau_previous,
                            self._period)
        return limit, gains

    @property
    def tau_previous(self) -> float:
        """τυ(k−1) [N m], the torque applied since the last tick."""
        return self._tau_previous

    @property
    def target_theta(self) -> float:
        """θs [rad], the tilt reference of the last tick (0 unless ``offset_free``)."""
        return self._target.theta

    def set_previous_torque(self, tau_previous: float) -> None:
        """Overwrite τυ(k−1) [N m] with the torque really applied.

        E.g. after the safety layer cut it, or to replay a recorded tick; the plan and the
        solver's workspace are kept.
        """
        tau_previous = float(tau_previous)
        if not math.isfinite(tau_previous):
            raise MpcInputError(f'tau_previous must be finite, got {tau_previous!r}')
        self._tau_previous = tau_previous

    def _hold_invalid_input(self) -> MpcResult:
        """No solve on NaN/inf input: ramp τ toward 0 within Δτmax (see :mod:`.mpc_plan`)."""
        result = invalid_input_result(self.config, self._tau_previous)
        self._tau_previous = result.tau_v
        return result


class LongitudinalMpc(LongitudinalController):
    """Condensed MPC of (υ, θ, θ̇) with the drive torque τυ as input.

    Parameters
    ----------
    params : nominal physical parameters (the controller's model).
    config : tunables; see :class:`~.mpc_config.MpcParams`.
    solver : optional replacement of the backend named by ``config.backend``: any object
        with ``solve(H, g, C, l, u, lb, ub) -> QpSolution`` and ``reset()`` (tests inject
        a failing one). It keeps one persistent workspace (see :mod:`.qp`).
    """

    def __init__(self, params: ModelParams, config: MpcParams | None = None,
                 solver=None) -> None:
        config = MpcParams() if config is None else config
        super().__init__(params, config)
        self.problem = MpcProblem(params, config)
        self.prediction = self.problem.prediction
        self.n_slacks = self.problem.n_slacks
        self.n_variables = self.problem.n_variables
        self.n_constraints = self.problem.n_constraints
        self.qp = MpcQp(self.problem)
        self.last_qp = self.qp.data
        self.last_solution = None  # QpSolution of the last solve (z with every slack)
        self._solver = (make_solver(config.backend, self.n_variables, self.n_constraints,
                                    config.qp_settings()) if solver is None else solver)
        self._startup = StartUp(params, config)
        self._preview = SpeedPreview(config)
        self._plan: np.ndarray | None = None
        self._period = config.sampling_period   # the tick's elapsed time [s]

    def reset(self, tau_previous: float = 0.0) -> None:
        """Forget the plan and the solver's workspace; τυ(k−1) = ``tau_previous`` [N m]."""
        self.set_previous_torque(tau_previous)
        self._plan = None
        self._target.reset()
        self._preview.reset()
        self._startup.reset()
        self._solver.reset()

    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_limit: float | None = None,
             first_box: tuple[float, float] | None = None,
             elapsed: float | None = None, rate: float | None = None) -> MpcResult:
        """One MPC tick: build and solve the QP, apply τ(k) = τ(k−1) + Δτ(k|k) (23).

        Parameters
        ----------
        v_hat : υ̂ [m/s]; theta_hat : θ̂ [rad]; theta_dot_hat : θ̂̇ [rad/s].
        f2_hat : f̂2, the ESO's lumped drift of υ̇ [m/s²]; f3_hat : f̂3, of θ̈ [rad/s²].
        v_d : desired speed υd [m/s] from the trajectory generator (9).
        tau_limit : |τυ| limit for this tick [N m], 2τmax − |τω| so that each wheel stays
            within τmax after mixing (24); capped to ``max_drive_torque``; None uses it.
        first_box : (lower, upper) bounds of this tick's increment Δτ(k|k) [N m], within
            (None:) ±``rate``; the later increments keep ±``rate``
            (a tick between the sampling instants, ``fast_resolve_period``).
        elapsed : time since the previous tick [s] (None: ``sampling_period``), for the
            filters that run once per tick (υd trend, offset-free target, start-up).
        rate : the |Δτυ| limit per Ts of (19) for this tick [N m] (None:
            ``max_delta_torque``).
        """
        cfg = self.config
        tau_prev = self._tau_previous
        t_start = time.perf_counter()
        rate = cfg.max_delta_torque if rate is None else float(rate)
        self.qp.set_rate(rate)
        self.qp.set_first_box(*_first_box(first_box, rate))
        period = cfg.sampling_period if elapsed is None else float(elapsed)
        self._period = period
        v_hat, f2_hat, f3_hat = self._startup.estimates(v_hat, theta_hat, theta_dot_hat,
                                                        f2_hat, f3_hat, v_d, period)
        begun = self._begin_tick(tau_limit, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat,
                                 v_d)
        if begun is None:
            return self._hold_invalid_input()
        limit, (g2, g3, g2p, g3p) = begun
        transient = decaying_excess(self._target.transient, cfg.disturbance_decay_dead_zone)
        free = self.qp.update(TickData(
            float(v_hat), float(theta_hat), float(theta_dot_hat), float(f2_hat),
            float(f3_hat), float(g2), float(g3), float(g2p), float(g3p), float(tau_prev),
            float(limit), float(transient[0]), float(transient[1]), float(v_d),
            float(self._preview.update(v_d, period)), float(self._target.theta)))
        t_built = time.perf_counter()
        solution = self._solver.solve(*self.qp.data)
        t_solved = time.perf_counter()
        self.last_solution = solution
        return self._apply(solution, tau_prev, limit, free, g2p, g3p, rate,
                           t_solved - t_built, t_built - t_start)

    def _apply(self, solution, tau_prev: float, limit: float, free: np.ndarray, g2p: float,
               g3p: float, rate: float, solve_time: float, build_time: float) -> MpcResult:
        """Apply the first increment (23) of the plan of ``solution`` (or of the fallback)."""
        cfg = self.config
        proposed = plan_of(solution, cfg.control_horizon, self.n_slacks, self._plan,
                           rate)
        plan = proposed.increments
        lower, upper = self.qp.first_box
        delta = admissible_increment(plan[0], tau_prev, limit, upper, lower)
        plan[0] = delta
        self._plan = plan
        self._tau_previous = tau_prev + delta
        predicted = self.qp.predict(free, g2p, g3p, plan)
        return MpcResult(self._tau_previous, delta, solution.status, solution.iterations,
                         solve_time, build_time, proposed.slack_v, proposed.slack_theta,
                         proposed.used_fallback, predicted, plan.copy(), self._target.theta)

    def push_detected(self, theta_hat: float, f2_hat: float, f3_hat: float,
                      band: tuple[float, float] | None = None) -> bool:
        """Whether the disturbance estimate shows a push.

        A push: (f̂2, f̂3) at θ̂, against the offset-free target's slow estimate, has a
        transient beyond ``band`` (None: ``push_threshold``). Reads the filter without
        updating it; False before its first tick, within ``disturbance_startup_time`` of a
        reset (the MPC does not use the estimator's start-up f̂ then) or with
        ``offset_free`` off.
        """
        if self._startup.active:
            return False
        transient = self._target.transient_of(theta_hat, f2_hat, f3_hat,
                                              *tick_gains(self.params, self.config, theta_hat),
                                              self._tau_previous)
        return (transient is not None
                and beyond(transient, self.config.push_threshold if band is None else band))

    def _hold_invalid_input(self) -> MpcResult:
        self._plan = None
        return super()._hold_invalid_input()
