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

import math
from typing import NamedTuple

from .arc import AdaptiveRobustYawController, ArcConfig, ArcOutput
from .lqr import make_longitudinal_controller
from .mixer import drive_torque_limit, mix
from .model import input_gains
from .mpc import MpcConfig, MpcResult
from .params import WipParameters
from .references import ReferenceState
from .state_estimation import PoseEstimate
from .trajectory_generator import (TrajectoryGenerator, TrajectoryGeneratorConfig,
                                   VelocityCommand)


class ControlOverflow(ValueError):
    """Finite inputs gave a non-finite output; the stage kept its previous state."""


def _all_finite(total: float, values: tuple) -> bool:
    """Whether every value is finite, given their sum ``total`` (NaN and inf propagate
    into it, so the values are looked at one by one only when it is not finite)."""
    return math.isfinite(total) or all(map(math.isfinite, values))


def initial_alpha(model: WipParameters, yaw_input_gain_scale: float) -> float:
    """α̂(0) = 1/ĝ1 of eq. (13), with ĝ1 the ESO's yaw input gain at θ = 0.

    Evaluated upright rather than at θ(0) so that the yaw stage needs no initial tilt
    (g1 changes by 0.2 % at θ = 0.05).
    """
    return 1.0 / (yaw_input_gain_scale * input_gains(model, 0.0)[0])


class GuidanceStage:
    """Reference sample and estimated pose -> (υd, ωd, ω̇d): the generator of eq. (9)."""

    def __init__(self, config: TrajectoryGeneratorConfig | None = None) -> None:
        self.generator = TrajectoryGenerator(config)

    def step(self, t: float, reference: ReferenceState, x: float, y: float,
             phi: float) -> VelocityCommand:
        # (Not a copy of vars(generator): that gives the object a dict of its own, which
        # slows every attribute access to it afterwards, 4 % of a run of the runner.)
        generator = self.generator
        saved = generator.state()
        command = generator.step(t, reference, x, y, phi)
        v_d, omega_d, omega_d_dot, x_e, y_e, phi_e = command
        if not _all_finite(v_d + omega_d + omega_d_dot + x_e + y_e + phi_e, command):
            # Finite but huge inputs (a heading of 1e308 rad) can overflow: keep the
            # derivative filter's state unpoisoned.
            generator.restore(saved)
            raise ControlOverflow(f'non-finite command {tuple(command)} from finite inputs '
                                  '(overflow); generator state kept')
        return command


class YawStage:
    """(ω̂, f̂1) and the command -> τω: the ARC of eqs. (12), (13), at period ``dt``."""

    def __init__(self, config: ArcConfig | None, alpha_initial: float, dt: float) -> None:
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


class DriveStage:
    """Estimate, υd and τω -> τυ: the MPC (or LQR) every ``decimation``-th control tick,
    its torque held in between (:attr:`tau_v`)."""

    def __init__(self, model: WipParameters, config: MpcConfig, max_wheel_torque: float,
                 decimation: int = 1) -> None:
        self.controller = make_longitudinal_controller(model, config)
        self.max_wheel_torque = max_wheel_torque
        self.decimation = decimation
        self.tau_v = 0.0   #: the held drive torque [N m]

    def limit(self, tau_omega: float) -> float:
        """Bound on |τυ| [N m]: 2 τmax − |τω| (``core.mixer.drive_torque_limit``). A NaN τω
        gives a NaN bound, which the controller answers with INPUT_INVALID and a finite
        torque (max(0, NaN) would give 0)."""
        if not math.isfinite(tau_omega):
            return math.nan
        return drive_torque_limit(tau_omega, self.max_wheel_torque)

    def is_tick(self, k: int) -> bool:
        """Whether control tick ``k`` (from 0) is an MPC tick."""
        return k % self.decimation == 0

    def step(self, v_hat: float, theta_hat: float, theta_dot_hat: float, f2_hat: float,
             f3_hat: float, v_d: float, tau_omega: float, hold: bool = True) -> MpcResult:
        """Solve once with the bound :meth:`limit`; ``hold``: the result's τυ becomes the
        held torque."""
        limit = self.limit(tau_omega)
        previous = self.controller.tau_previous
        result = self.controller.step(v_hat=v_hat, theta_hat=theta_hat,
                                      theta_dot_hat=theta_dot_hat, f2_hat=f2_hat,
                                      f3_hat=f3_hat, v_d=v_d, tau_limit=limit)
        if not math.isfinite(result.tau_v):
            self.controller.set_previous_torque(previous)
            raise ControlOverflow(f'non-finite drive torque {result.tau_v!r} (overflow); '
                                  'previous torque kept')
        if hold:
            self.tau_v = result.tau_v
        return result


class ControlOutputs(NamedTuple):
    """One control tick: the torques and what led to them (for recording)."""

    command: VelocityCommand
    arc: ArcOutput
    mpc: MpcResult | None   #: None between MPC ticks
    tau_left: float
    tau_right: float


class ControlStep:
    """guidance -> yaw -> drive (held) -> mixer, for one control tick."""

    def __init__(self, guidance: GuidanceStage, yaw: YawStage, drive: DriveStage,
                 max_wheel_torque: float) -> None:
        self.guidance, self.yaw, self.drive = guidance, yaw, drive
        self.max_wheel_torque = max_wheel_torque

    @classmethod
    def from_scenario(cls, scenario) -> 'ControlStep':
        """The stages of ``scenario`` (a ``core.scenario.Scenario``) with the nominal model."""
        nominal = scenario.controller_model.parameters
        max_wheel = scenario.mixer.max_wheel_torque
        return cls(GuidanceStage(scenario.trajectory_generator),
                   YawStage(scenario.arc, initial_alpha(
                       nominal, scenario.eso.yaw_input_gain_scale), scenario.control_period),
                   DriveStage(nominal, scenario.mpc, max_wheel, scenario.mpc_decimation),
                   max_wheel)

    def step(self, t: float, reference: ReferenceState, pose: PoseEstimate,
             mpc_tick: bool, hold: bool = True) -> ControlOutputs:
        """Torques of the tick at ``t`` [s]; the MPC solves when ``mpc_tick``, and its τυ
        is held from this tick on (``hold``, as the graph in lockstep) or when the caller
        sets ``drive.tau_v`` (a re-run that knows when a real-time mixer got it)."""
        est = pose.estimate
        command = self.guidance.step(t, reference, pose.x, pose.y, est.phi)
        arc = self.yaw.step(est.omega, est.f1, command)
        result = None
        if mpc_tick:
            result = self.drive.step(est.v, est.theta, est.theta_dot, est.f2, est.f3,
                                     command.v_d, arc.tau_omega, hold)
        return ControlOutputs(command, arc, result,
                              *mix(self.drive.tau_v, arc.tau_omega, self.max_wheel_torque))

    def mix(self, tau_omega: float) -> tuple[float, float]:
        """(τl, τr) [N m] of eq. (24) from the held τυ and ``tau_omega``."""
        return mix(self.drive.tau_v, tau_omega, self.max_wheel_torque)
