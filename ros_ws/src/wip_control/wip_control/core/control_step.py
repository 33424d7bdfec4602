"""The control half of the loop: estimate and reference in, wheel torques out.

Four stages, each a small object that one node can drive on its own and that
:class:`ControlStep` chains for the in-process runner and the re-run of a bag:
guidance (trajectory generator, eq. (9)), yaw (ARC, eqs. (12), (13)), drive (MPC,
eqs. (16)-(23), or the LQR baseline, at its own period with the torque held in between)
and the mixer (eq. (24)). Each stage checks its result before it keeps any state: on
finite input that overflows it restores what it had and raises :class:`ControlOverflow`
(docs/control-loop.md).
"""

from __future__ import annotations

import collections
import math
from typing import NamedTuple

from .arc import AdaptiveRobustYawController, ArcParams, ArcOutput
from .lqr import make_longitudinal_controller
from .mixer import drive_torque_limit, mix
from .model import input_gains
from .position import TRACKING
from .obstacle_refusal import make_refusal
from .mpc_config import drive_tick_decimation, MpcParams, resolves_faster
from .mpc_plan import MpcResult
from .mpc_prediction import gravity_coefficients
from wip_description.params import ModelParams
from .reference_state import ReferenceState
from .state_estimation import PoseEstimate
from .trajectory_generator import (TrajectoryGenerator, TrajectoryGeneratorParams,
                                   VelocityCommand)


class ControlOverflow(ValueError):
    """Finite inputs gave a non-finite output; the stage kept its previous state."""


def _all_finite(total: float, values: tuple) -> bool:
    """Whether every value is finite, given their sum ``total``.

    NaN and inf propagate into it, so the values are looked at one by one only when it is not
    finite.
    """
    return math.isfinite(total) or all(map(math.isfinite, values))


def initial_alpha(model: ModelParams, yaw_input_gain_scale: float) -> float:
    """α̂(0) = 1/ĝ1 of eq. (13), with ĝ1 the ESO's yaw input gain at θ = 0.

    Evaluated upright rather than at θ(0) so that the yaw stage needs no initial tilt
    (g1 changes by 0.2 % at θ = 0.05).
    """
    return 1.0 / (yaw_input_gain_scale * input_gains(model, 0.0)[0])


class TrajectoryGeneratorStage:
    """Reference sample and estimated pose -> (υd, ωd, ω̇d): the generator of eq. (9).

    With ``obstacle_back_off`` > 0, the reference passes through the obstacle refusal
    (core/obstacle_refusal.py) first: the estimate's ``obstacle_blocked`` is handed to
    :meth:`step` as ``blocked``.
    """

    def __init__(self, config: TrajectoryGeneratorParams | None = None) -> None:
        self.generator = TrajectoryGenerator(config)
        self.refusal = make_refusal(self.generator.config)

    def step(self, t: float, reference: ReferenceState, x: float, y: float,
             phi: float, blocked: bool = False, fixed: bool = True) -> VelocityCommand:
        # (Not a copy of vars(generator): that gives the object a dict of its own, which
        # slows every attribute access to it afterwards, 4 % of a run of the runner.)
        generator = self.generator
        saved = generator.state()
        refusal = self.refusal
        held = refusal.state() if refusal is not None else None
        try:
            if refusal is not None:
                reference = refusal.update(t, blocked, reference, x, y, phi, fixed)
            command = generator.step(t, reference, x, y, phi)
        except ValueError:
            if refusal is not None:
                refusal.restore(held)
            raise
        v_d, omega_d, omega_d_dot, x_e, y_e, phi_e = command
        if not _all_finite(v_d + omega_d + omega_d_dot + x_e + y_e + phi_e, command):
            # Finite but huge inputs (a heading of 1e308 rad) can overflow: keep the
            # derivative filter's state unpoisoned.
            generator.restore(saved)
            if refusal is not None:
                refusal.restore(held)
            raise ControlOverflow(f'non-finite command {tuple(command)} from finite inputs '
                                  '(overflow); generator state kept')
        return command


class YawControllerStage:
    """(ω̂, f̂1) and the command -> τω: the ARC of eqs. (12), (13), at period ``dt``."""

    def __init__(self, config: ArcParams | None, alpha_initial: float, dt: float) -> None:
        self.controller = AdaptiveRobustYawController(config, alpha_initial)
        self.dt = dt

    def step(self, omega_hat: float, f1_hat: float, command: VelocityCommand) -> ArcOutput:
        controller = self.controller
        alpha = controller.alpha_hat
        out = controller.step(self.dt, omega_hat, f1_hat, command.omega_d,
                              command.omega_d_dot)
        tau_omega, alpha_used, e_omega = out
        # (_all_finite, without building the tuple of values on the usual finite path)
        if not (math.isfinite(tau_omega + alpha_used + e_omega + controller.alpha_hat)
                or all(map(math.isfinite, (*out, controller.alpha_hat)))):
            # eω = ω̂ − ωd can overflow to inf and (13) give α̂ = NaN, which would clip
            # τω to +max_yaw_torque forever: keep α̂.
            controller.alpha_hat = alpha
            raise ControlOverflow(f'non-finite yaw control {tuple(out)} from finite inputs '
                                  '(overflow); alpha_hat kept')
        return out


def net_change_box(window: list[float], tau_previous: float,
                   dmax: float) -> tuple[float, float]:
    """Bounds (lower, upper) of the next increment from τ(k−1) [N m] under the limit (19).

    The torque applied now must be within ``dmax`` of each torque of ``window`` and of
    ``tau_previous``: [max τj − Δτmax, min τj + Δτmax] − τ(k−1). Then no two torques
    applied within Ts differ by more than Δτmax, whatever their increments in between;
    with ``window`` holding τ(k−1) alone the box is exactly ±Δτmax, eq. (19).
    """
    offsets = [tau - tau_previous for tau in window]
    return max([0.0, *offsets]) - dmax, min([0.0, *offsets]) + dmax


class DriveControllerStage:
    """Estimate, υd and τω -> τυ: the MPC (or LQR) every ``decimation``-th control tick.

    Its torque held in between (:attr:`tau_v`).

    With ``fast_decimation`` (control ticks per ``mpc.fast_resolve_period``, < decimation)
    the MPC also solves at the ticks of that finer grid for ``mpc.fast_resolve_time``
    after a push (``LongitudinalMpc.push_detected``; docs/history/mpc.md §10). With
    ``mpc.push_trigger`` the stage looks for a push at every control tick and solves on
    the tick it first sees one; the finer grid then runs from that tick (§14). The limit
    (19), |Δτυ| ≤ Δτmax per Ts, holds over any ``decimation`` ticks by
    ``mpc.resolve_rate_rule``: the increments' |Δτ| sum to at most ``max_delta_torque``
    (``sum``), or the torque applied at a tick is within it of every torque in force
    over the last ``decimation`` ticks (``net``, :func:`net_change_box`); each increment,
    while re-solving, within ``max_delta_torque · push_resolve_share``. The ticks at
    which the stage takes inputs are :meth:`is_tick`; :meth:`solves` says whether it
    solves there.
    """

    def __init__(self, model: ModelParams, config: MpcParams, max_wheel_torque: float,
                 decimation: int = 1, fast_decimation: int | None = None) -> None:
        self.controller = make_longitudinal_controller(model, config)
        self.max_wheel_torque = max_wheel_torque
        self.decimation = decimation
        self.tau_v = 0.0   #: the held drive torque [N m]
        fast = (fast_decimation is not None
                and resolves_faster(config.sampling_period, config.fast_resolve_period)
                and 1 <= fast_decimation < decimation)
        #: Control ticks between the ticks at which the stage takes inputs.
        self.every = drive_tick_decimation(decimation, fast_decimation if fast else None,
                                           config.push_trigger)
        # Re-solving applies to the MPC; the LQR (a fixed gain for Ts) solves at Ts only.
        self._fast = fast and config.controller == 'mpc'
        self._fast_every = fast_decimation if fast else decimation
        self._fast_ticks = (int(round(config.fast_resolve_time / config.fast_resolve_period))
                            * fast_decimation if self._fast else 0)
        self._fast_until = -1      # re-solve at the fine grid's ticks before this tick
        self._grid_start = 0       # the fine grid's ticks are those ≡ this (mod _fast_every)
        #: (tick, τυ, |Δτ|) of the solves since the last one at or before ``decimation``
        #: ticks ago.
        self._applied: list[tuple[int, float, float]] = []
        self._last_solve: int | None = None
        self._strong_seen = False   # a transient beyond the decay's dead zone at the last solve
        # The rate limit while an obstacle stops the base, and until which tick it holds.
        self._impact_rate = config.largest_delta_torque()   # used only while re-solving
        self._impact_ticks = int(round(config.impact_hold / config.sampling_period * decimation))
        self._impact_until = -1
        #: The |Δτυ| limit per Ts of the last solve [N m] (``impact_delta_torque`` while an
        #: obstacle stops the base).
        self.rate = config.max_delta_torque
        # The mean drift of a solve (disturbance_average_time): f̂2, f̂3 less their part
        # linear in θ̂ (the gravity-aware prediction's a_υθ, a_θθ), which changes within
        # the window and is taken at the solve's θ̂. (tick, d2, d3) of the ticks taken.
        self._gravity = gravity_coefficients(model, config.sampling_period)
        self._average_ticks = (int(round(config.disturbance_average_time
                                         / config.sampling_period * decimation))
                               if config.controller == 'mpc' else 0)
        self._drifts: collections.deque = collections.deque(maxlen=max(self._average_ticks, 1))

    def limit(self, tau_omega: float) -> float:
        """Bound on |τυ| [N m]: 2 τmax − |τω| (``core.mixer.drive_torque_limit``).

        A NaN τω gives a NaN bound, which the controller answers with INPUT_INVALID and a finite
        torque (max(0, NaN) would give 0).
        """
        if not math.isfinite(tau_omega):
            return math.nan
        return drive_torque_limit(tau_omega, self.max_wheel_torque)

    def is_tick(self, k: int) -> bool:
        """Whether control tick ``k`` (from 0) is a tick of the stage.

        The stage's ticks are the MPC's or, with re-solving after a push, those of its
        finer grid, or every control tick with ``mpc.push_trigger``. At these ticks the
        stage takes its inputs and, in lockstep, the drive torque is published.
        """
        return k % self.every == 0

    def solves(self, k: int, theta_hat: float, f2_hat: float, f3_hat: float) -> bool:
        """Whether the controller solves at tick ``k`` of :meth:`is_tick`.

        At every ``decimation``-th tick; while re-solving after a push, at the finer
        grid's; else when the estimate shows a push now.
        """
        if k % self.decimation == 0:
            return True
        if not self._fast:
            return False
        if k < self._fast_until:
            return ((k - self._grid_start) % self._fast_every == 0
                    or (self.controller.config.push_restart and not self._strong_seen
                        and self._strong_push(theta_hat, f2_hat, f3_hat)))
        return self.controller.push_detected(theta_hat, f2_hat, f3_hat)

    def observe(self, k: int, theta_hat: float, f2_hat: float, f3_hat: float) -> None:
        """Take the estimate of control tick ``k`` for the mean drift of the next solve.

        Called at each of the stage's ticks (:meth:`is_tick`); again for the same tick it
        does nothing. A non-finite estimate is left out (the solve answers it).
        """
        drifts = self._drifts
        if self._average_ticks <= 1 or (drifts and drifts[-1][0] == k):
            return
        if not math.isfinite(theta_hat + f2_hat + f3_hat):
            return
        if drifts and k < drifts[-1][0]:
            drifts.clear()   # the ticks restarted
        a_v_theta, a_theta_theta = self._gravity
        drifts.append((k, f2_hat - a_v_theta * theta_hat, f3_hat - a_theta_theta * theta_hat))

    def solve_drifts(self, k: int | None, theta_hat: float, f2_hat: float,
                     f3_hat: float, pushed: bool | None = None) -> tuple[float, float]:
        """(f̂2, f̂3) a solve at tick ``k`` takes: their mean over disturbance_average_time.

        The ESO's f̂ passes noise up to its bandwidth, far above the Nyquist rate of a solve
        every Ts: sampled, that noise folds down into the band of the position loop (9). The
        mean over the period is the decimation's anti-alias filter. A push and the re-solves
        after it take the sample, which keeps the push's first, sharp estimate. ``pushed``:
        the controller's ``push_detected`` for this estimate, if the caller has it.
        """
        if self._average_ticks <= 1 or k is None or k < self._fast_until:
            return f2_hat, f3_hat
        if pushed is None:
            pushed = self.controller.push_detected(theta_hat, f2_hat, f3_hat)
        if pushed:
            return f2_hat, f3_hat
        self.observe(k, theta_hat, f2_hat, f3_hat)
        start = k - self._average_ticks
        window = [entry for entry in self._drifts if entry[0] > start]
        if not window or not math.isfinite(theta_hat):
            return f2_hat, f3_hat
        count = len(window)
        a_v_theta, a_theta_theta = self._gravity
        return (sum(entry[1] for entry in window) / count + a_v_theta * theta_hat,
                sum(entry[2] for entry in window) / count + a_theta_theta * theta_hat)

    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_omega: float, hold: bool = True,
             k: int | None = None) -> MpcResult:
        """Solve once with the bound :meth:`limit`.

        ``hold``: the result's τυ becomes the held torque. ``k``: the control tick (needed with
        re-solving after a push, for the increment bound and the push's time, and for the
        mean drift of :meth:`solve_drifts`).
        """
        limit = self.limit(tau_omega)
        previous = self.controller.tau_previous
        fast = self._fast and k is not None
        # Asked once: the mean drift and the re-solving both need it (a pure read).
        pushed = (self.controller.push_detected(theta_hat, f2_hat, f3_hat) if fast
                  else None)
        f2_solve, f3_solve = self.solve_drifts(k, theta_hat, f2_hat, f3_hat, pushed)
        if fast:
            result = self._step_fast(k, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat,
                                     (f2_solve, f3_solve), v_d, limit, pushed)
        else:
            result = self.controller.step(v_hat=v_hat, theta_hat=theta_hat,
                                          theta_dot_hat=theta_dot_hat, f2_hat=f2_solve,
                                          f3_hat=f3_solve, v_d=v_d, tau_limit=limit)
        if not math.isfinite(result.tau_v):
            self.controller.set_previous_torque(previous)
            raise ControlOverflow(f'non-finite drive torque {result.tau_v!r} (overflow); '
                                  'previous torque kept')
        if hold:
            self.tau_v = result.tau_v
        return result

    def _step_fast(self, k, v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, drifts, v_d,
                   limit, pushed):
        """Solve with re-solving after a push.

        The solve gets the increment bound of the window, the time since the last solve and
        ``drifts``, the (f̂2, f̂3) of :meth:`solve_drifts`; the sample (``f2_hat``, ``f3_hat``)
        finds pushes and obstacles (``pushed``: a push seen in it before this solve). A push
        seen now (re)starts the re-solving.
        """
        mpc = self.controller
        dmax = self._rate_limit(k, f2_hat, v_d)
        window = k - self.decimation
        # The torque in force ``decimation`` ticks ago and those applied since.
        held = [entry for entry in self._applied if entry[0] <= window][-1:]
        self._applied = held + [entry for entry in self._applied if entry[0] > window]
        lower, upper = self._rate_box(window, dmax)
        fresh = False
        if mpc.config.push_restart:
            # A push, not the noise that a threshold below the dead zone also sees.
            strong = self._strong_push(theta_hat, f2_hat, f3_hat)
            fresh, self._strong_seen = strong and not self._strong_seen, strong
        resolving = k < self._fast_until
        if pushed or resolving:
            share = dmax * mpc.config.push_resolve_share
            lower, upper = max(lower, -share), min(upper, share)
        elapsed = (None if self._last_solve is None
                   else (k - self._last_solve) * mpc.config.sampling_period / self.decimation)
        result = mpc.step(v_hat=v_hat, theta_hat=theta_hat, theta_dot_hat=theta_dot_hat,
                          f2_hat=drifts[0], f3_hat=drifts[1], v_d=v_d, tau_limit=limit,
                          first_box=(lower, upper), elapsed=elapsed, rate=dmax)
        self._last_solve = k
        if math.isfinite(result.tau_v):
            self._applied.append((k, result.tau_v, abs(result.delta_tau)))
        if pushed or mpc.push_detected(theta_hat, f2_hat, f3_hat):   # (after its update)
            if not resolving or (fresh and self._restart_keeps_tilt(result)):
                # The finer grid runs from the push: the old grid's next tick, coming a
                # few ticks later, tipped the heavier body further (docs/history/mpc.md §14).
                self._grid_start = k
            self._fast_until = k + self._fast_ticks
        return result

    def _rate_limit(self, k: int, f2_hat: float, v_d: float) -> float:
        """Return the |Δτυ| limit per Ts of (19) for a solve at tick ``k`` [N m].

        ``max_delta_torque``, or ``impact_delta_torque`` for ``impact_hold`` after a solve
        that saw the drift f̂2 oppose the desired motion υd by more than
        ``impact_deceleration`` (an obstacle stopping the base, or a push against the
        motion; docs/decisions/mpc-parameters.md).
        """
        config = self.controller.config
        if self._impact_rate <= config.max_delta_torque:
            return config.max_delta_torque
        if (math.isfinite(f2_hat) and math.isfinite(v_d) and v_d != 0.0
                and -f2_hat * math.copysign(1.0, v_d) > config.impact_deceleration):
            self._impact_until = k + self._impact_ticks
        self.rate = self._impact_rate if k < self._impact_until else config.max_delta_torque
        return self.rate

    def _restart_keeps_tilt(self, result: MpcResult) -> bool:
        """Whether a fresh push's solve may restart the grid: its plan within the tilt margin.

        A fresh push while re-solving is mostly the rebound of the push being recovered
        (the transient of f̂2 turning sign). Restarting there moves the next solve up to
        Ts/2 later; when the plan already leans past the soft limit |θ| ≤ θmax of (19)
        (its slack sθ of (20) large), the catch of the lean, rate-limited by (19), then
        comes too late and overshoots (docs/history/mpc.md §21, §23).
        """
        slack = result.slack_theta
        return math.isfinite(slack) and slack <= self.controller.config.push_restart_max_slack

    def _rate_box(self, window: int, dmax: float) -> tuple[float, float]:
        """Bounds of the next increment [N m] under ``resolve_rate_rule`` (19)."""
        if self.controller.config.resolve_rate_rule == 'net':
            return net_change_box([tau for _, tau, _ in self._applied],
                                  self.controller.tau_previous, dmax)
        # The increments since ``window`` count by their size, a back-and-forth too (§10).
        bound = max(dmax - sum(move for tick, _, move in self._applied if tick > window), 0.0)
        return -bound, bound

    def _strong_push(self, theta_hat: float, f2_hat: float, f3_hat: float) -> bool:
        """Whether the transient is beyond ``disturbance_decay_dead_zone`` (a push)."""
        mpc = self.controller
        return mpc.push_detected(theta_hat, f2_hat, f3_hat,
                                 mpc.config.disturbance_decay_dead_zone)


class ControlOutputs(NamedTuple):
    """One control tick: the torques and what led to them (for recording)."""

    command: VelocityCommand
    arc: ArcOutput
    mpc: MpcResult | None   #: None between MPC ticks
    tau_left: float
    tau_right: float


class ControlStep:
    """Trajectory generator -> yaw controller -> drive controller (held) -> mixer, one tick."""

    def __init__(self, guidance: TrajectoryGeneratorStage, yaw: YawControllerStage,
                 drive: DriveControllerStage, max_wheel_torque: float) -> None:
        self.guidance, self.yaw, self.drive = guidance, yaw, drive
        self.max_wheel_torque = max_wheel_torque

    @classmethod
    def from_scenario(cls, scenario) -> 'ControlStep':
        """Return the stages of a scenario's controller settings, with the nominal model."""
        nominal = scenario.controller_model.parameters
        max_wheel = scenario.mixer.max_wheel_torque
        return cls(TrajectoryGeneratorStage(scenario.trajectory_generator),
                   YawControllerStage(scenario.arc, initial_alpha(
                       nominal, scenario.eso.yaw_input_gain_scale), scenario.control_period),
                   DriveControllerStage(nominal, scenario.mpc, max_wheel, scenario.mpc_decimation,
                              scenario.mpc_fast_decimation),
                   max_wheel)

    def step(self, t: float, reference: ReferenceState, pose: PoseEstimate,
             mpc_tick: bool, hold: bool = True, k: int | None = None,
             decide: bool = True) -> ControlOutputs:
        """Torques of control tick ``k`` at ``t`` [s].

        The MPC solves when ``mpc_tick`` (``drive.is_tick(k)``) and, with ``decide``,
        ``drive.solves(k, …)``; its τυ is held from this tick on (``hold``, as the graph in
        lockstep) or when the caller sets ``drive.tau_v`` (a re-run that knows when a real-time
        mixer got it).
        """
        est = pose.estimate
        command = self.guidance.step(t, reference, pose.x, pose.y, est.phi,
                                     pose.obstacle_blocked, pose.position_status == TRACKING)
        arc = self.yaw.step(est.omega, est.f1, command)
        result = None
        drive = self.drive
        if k is not None and drive.is_tick(k):
            drive.observe(k, est.theta, est.f2, est.f3)
        if mpc_tick and (not decide or k is None
                         or drive.solves(k, est.theta, est.f2, est.f3)):
            result = drive.step(est.v, est.theta, est.theta_dot, est.f2, est.f3,
                                command.v_d, arc.tau_omega, hold, k)
        return ControlOutputs(command, arc, result,
                              *mix(self.drive.tau_v, arc.tau_omega, self.max_wheel_torque))

    def mix(self, tau_omega: float) -> tuple[float, float]:
        """(τl, τr) [N m] of eq. (24) from the held τυ and ``tau_omega``."""
        return mix(self.drive.tau_v, tau_omega, self.max_wheel_torque)
