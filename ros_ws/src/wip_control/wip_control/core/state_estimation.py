"""The estimation half of the control loop.

Sensor samples and applied torques in, one estimate out.

One object, used by the in-process runner, the re-run of a bag and the ESO node, so that
the three compute the same thing: yaw unwrapping, wheel odometry, the ESOs (eqs. (4),
(8)) fed with the applied τυ = τl + τr and τω = τr − τl, the planar position, and the
rules for starting and restarting them (docs/control-loop.md).
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import NamedTuple, Sequence

import numpy as np

from .angles import unwrap_next
from .eso import EsoParams, StateEstimate
from .state_observer import WipStateObserver
from wip_description.params import ModelParams
from .position import (DEAD_RECKONING, FAULT, NO_FIX, PlanarPositionEstimator,
                       PositionParams, TRACKING)
from wip_description.sensors import wheel_odometry
from .obstacle import (DEFAULT_MAX_DRIVE_TORQUE, ObstacleMonitor, ObstacleRelease,
                       ObstacleState)
from . import slip as slip_monitor
from .slip import SlipMonitor

#: The slip monitor's arrays that the compiled kernel is given when there is no monitor.
_NO_SLIP = SimpleNamespace(state=np.zeros(slip_monitor.EVENTS + 1),
                           constants=np.ones(slip_monitor.LONGEST + 1))
#: The samples over which the compiled kernel is compared with the interpreter, at the
#: period: past the slip monitor's first 1 s, with a wheel spun up at 1.5 s.
_KERNEL_CHECKS = 400


def _bits(pose: 'PoseEstimate') -> bytes:
    """Return the bytes of a pose's numbers (its estimate's, position, flags, status)."""
    return np.array((*pose.estimate, *pose[1:]), dtype=float).tobytes()


class EstimatorOverflow(ValueError):
    """Finite inputs gave a non-finite estimate; the estimator restarted (nothing kept)."""


class PoseEstimate(NamedTuple):
    """What the controllers get from the estimator at one sample."""

    estimate: StateEstimate
    x: float               #: planar position x̂ in the map frame [m]
    y: float               #: ŷ [m]
    settled: bool = True   #: False while the paper's ε ramp runs
    position_status: int = TRACKING   #: core.position NO_FIX, TRACKING, DEAD_RECKONING or FAULT
    obstacle_blocked: bool = False   #: the wheels are blocked by an obstacle (core/obstacle.py)


class StateEstimator:
    """ESOs and planar position from one sensor sample at a time.

    Starting rule (a real robot does not know its true state): the observer starts at the
    first sample, from the measured positions (ϕ, x_v, θ) with zero rates and
    disturbances (Section V), and that sample's time as the origin of the ε schedule. The
    position starts at the first GPS fix; until one arrives it dead-reckons from (0, 0)
    (``has_fix`` says so). With ``dead_reckoning`` no fix is expected: the position is
    wheel odometry along the IMU's yaw from (0, 0) for good. The wheel odometry's yaw
    output is not used (the yaw comes from the IMU), so the odometry's initial yaw is 0.

    Overflow rule: finite but absurd input (a wheel angle of 1e307 rad) can overflow the
    observer to inf/NaN. Then nothing of that sample is kept, the estimator restarts (the
    next sample starts it afresh, like the first) and :class:`EstimatorOverflow` is
    raised. Restarting rather than restoring the previous state also recovers from a
    persistent jump of a sensor (an encoder re-zeroed far away), which would otherwise
    overflow at every later sample. Non-finite input raises ValueError and changes nothing.
    """

    def __init__(self, model: ModelParams, eso_config: EsoParams | None = None,
                 position_config: PositionParams | None = None, *,
                 encoders_relative_to_body: bool = True, dead_reckoning: bool = False,
                 max_drive_torque: float = DEFAULT_MAX_DRIVE_TORQUE) -> None:
        self.model = model
        self.max_drive_torque = max_drive_torque
        self.eso_config = eso_config if eso_config is not None else EsoParams()
        self.position_config = (position_config if position_config is not None
                                else PositionParams())
        self.relative_to_body = encoders_relative_to_body
        self.dead_reckoning = bool(dead_reckoning)
        self.refused = ''   #: why the caller refused the position source ('' if not)
        self.restarts = 0   #: restarts after an overflow
        # The compiled steady sample (use_compiled), its module, and its constants and ε
        # for an observer.
        self._kernel = None
        self._kernel_module = None
        self._kernel_constants: tuple = (None, None, math.nan)
        self.restart()
        self.restarts = 0

    @classmethod
    def from_scenario(cls, scenario, compiled: bool = False) -> 'StateEstimator':
        """Return the estimator of a scenario's controller settings.

        ``scenario`` is a :class:`~.controller_settings.ControllerParams` (a simulation's
        scenario is one). The model is the nominal one, as the controllers know it (a
        mismatch with the plant shows up in x_v). ``compiled``: take the steady samples
        compiled where the estimator has a compiled form (:meth:`use_compiled`; the same
        floats either way).
        """
        estimator = cls(scenario.controller_model.parameters, scenario.eso, scenario.position,
                        encoders_relative_to_body=scenario.sensors.encoders_relative_to_body,
                        max_drive_torque=2.0 * scenario.mixer.max_wheel_torque)
        if compiled:
            estimator.use_compiled()
        return estimator

    def restart(self) -> None:
        """Forget everything: the next sample starts the observer and the position."""
        self.observer: WipStateObserver | None = None
        # Wheel slip (core/slip.py): the x_v that only the gripping wheels saw.
        self.slip = (SlipMonitor(self.model, self.eso_config.slip_max_acceleration,
                                 relative_to_body=self.relative_to_body)
                     if self.eso_config.slip_max_acceleration > 0.0
                     and self.eso_config.estimator == 'gyro' else None)
        # Wheels blocked by an obstacle (core/obstacle.py): reported, and handed on in the
        # estimate (the trajectory generator refuses to push on, core/obstacle_refusal.py).
        config = self.eso_config
        self.obstacle = (ObstacleMonitor(self.model, config.obstacle_stall_time,
                                         config.obstacle_stall_torque,
                                         max_drive_torque=self.max_drive_torque)
                         if config.obstacle_stall_time > 0.0 else None)
        # After a stall, the obstacle's force is not handed on as a disturbance.
        self.release = (ObstacleRelease(config.obstacle_release_hold)
                        if config.obstacle_release_hold > 0.0 else None)
        self.position = PlanarPositionEstimator(self.position_config)
        self.yaw_unwrapped: float | None = None
        self.has_fix = False
        self.position_started = False
        self.settled = False   # the ε ramp is over (it does not start again until a restart)
        self.restarts += 1

    def use_compiled(self) -> str:
        """Take the steady samples with the compiled kernel (``estimator_kernel.py``).

        Only for the gyro estimator. The kernel is compared with the interpreter on a
        scratch estimator of the same settings first. Return '' when it is used, else why
        not. The estimates are the same floats either way.
        """
        if self.eso_config.estimator != 'gyro':
            return f"no compiled form of the '{self.eso_config.estimator}' estimator"
        from . import estimator_kernel
        from .compiled import ESTIMATOR_KERNEL, load_checked
        module, difference = load_checked(ESTIMATOR_KERNEL,
                                          lambda m: self._kernel_difference(m.step))
        if difference:
            return f'the compiled estimator differs from the interpreted one {difference}'
        self._kernel, self._kernel_module = module.step, estimator_kernel
        return ''

    def _kernel_difference(self, kernel) -> str:
        """Where ``kernel`` differs from the interpreter on a made-up drive ('' nowhere)."""
        from . import estimator_kernel   # its status codes and constants (numba loaded)
        pair = []
        for compiled in (kernel, None):
            estimator = StateEstimator(self.model, self.eso_config, self.position_config,
                                       encoders_relative_to_body=self.relative_to_body,
                                       dead_reckoning=self.dead_reckoning,
                                       max_drive_torque=self.max_drive_torque)
            estimator._kernel, estimator._kernel_module = compiled, estimator_kernel
            pair.append(estimator)
        h = self.eso_config.sample_period
        for k in range(_KERNEL_CHECKS):
            t = k * h
            # Rolling and turning, the yaw wrapping past ±π, the left wheel spun up for
            # 0.1 s at 1.5 s, a fix now and then.
            spin = 40.0 * (t - 1.5) ** 2 if 1.5 <= t < 1.6 else 0.0
            sample = (t, 2.0 * t + 0.1 * math.sin(3.0 * t) + spin, 2.1 * t,
                      0.05 * math.sin(2.0 * t), math.remainder(3.0 + 0.8 * t, 2.0 * math.pi),
                      2.0 * math.cos(5.0 * t), 1.5 * math.sin(4.0 * t),
                      (0.1 * math.cos(2.0 * t), 0.8), (0.5 * t, 0.1) if k % 37 == 5 else None)
            compiled, interpreted = (estimator.update(*sample[:-2], rates=sample[-2],
                                                      fix=sample[-1]) for estimator in pair)
            # To the bit (== would take -0.0 for 0.0).
            if _bits(compiled) != _bits(interpreted):
                return f'at t = {t!r}: {compiled} != {interpreted}'
        return ''

    @property
    def started(self) -> bool:
        return self.observer is not None

    @property
    def obstacle_state(self) -> ObstacleState | None:
        """What the obstacle monitor says now (None when it is off)."""
        return None if self.obstacle is None else self.obstacle.state

    @property
    def position_fault(self) -> str:
        """Why the position source is not to be trusted ('' if it is)."""
        return self.refused or self.position.fault

    @property
    def position_status(self) -> int:
        """NO_FIX, TRACKING, DEAD_RECKONING or FAULT (core.position)."""
        if self.refused or self.position.fault:
            return FAULT
        if self.dead_reckoning:
            return DEAD_RECKONING
        return TRACKING if self.has_fix else NO_FIX

    def update(self, t: float, phi_left: float, phi_right: float, pitch: float, yaw: float,
               tau_left: float, tau_right: float, rates: Sequence[float] | None = None,
               fix: Sequence[float] | None = None) -> PoseEstimate:
        """Return the estimate at sample time ``t`` [s].

        Parameters
        ----------
        phi_left, phi_right : wheel encoder angles [rad] (forward positive).
        pitch, yaw : IMU pitch θ and yaw ϕ [rad]; the yaw may be wrapped.
        tau_left, tau_right : wheel torques [N m] applied since the previous sample.
        rates : IMU (θ̇, ϕ̇) [rad/s], needed by the 'gyro' estimator.
        fix : GPS (x, y) [m] in the map frame taken at this sample, or None.

        Raises
        ------
        ValueError
            on non-finite input (state unchanged); :class:`EstimatorOverflow` when the
            result overflows (the estimator restarted).
        """
        observer = self.observer
        if (self._kernel is not None and fix is None and rates is not None
                and observer is not None and self.position_started):
            pose = self._compiled_update(observer, t, phi_left, phi_right, pitch, yaw,
                                         tau_left, tau_right, rates)
            if pose is not None:
                return pose
        yaw_unwrapped = yaw if self.yaw_unwrapped is None else unwrap_next(
            self.yaw_unwrapped, yaw)
        x_v, _ = wheel_odometry(phi_left, phi_right, pitch, self.model, 0.0,
                                self.relative_to_body)
        if self.slip is not None and rates is not None:
            r = self.model.wheel_radius
            x_v = self.slip.update(t, r * phi_left, r * phi_right, x_v, pitch, rates[0],
                                   rates[1], tau_left, tau_right).x_v
        if observer is None:
            observer = WipStateObserver(
                self.model, self.eso_config, initial_positions=(yaw_unwrapped, x_v, pitch),
                initial_time=t, encoders_relative_to_body=self.relative_to_body)
        # Raises ValueError before touching the observer on non-finite input.
        estimate = observer.update(t, yaw_unwrapped, x_v, pitch, tau_left + tau_right,
                                   tau_right - tau_left, rates)
        self.observer, self.yaw_unwrapped = observer, yaw_unwrapped
        x, y = self._position(t, x_v, estimate.phi, fix)
        return self._finish(t, estimate, x, y, tau_left + tau_right)

    def _finish(self, t: float, estimate: StateEstimate, x: float, y: float,
                tau_v: float) -> PoseEstimate:
        """Run the checks and monitors after the observer and the position."""
        # ε (the last field) is inf at the start of the paper's ramp: not checked. One sum
        # first (NaN and inf propagate), each value only if it is not finite.
        a, b, c, d, e, f, g, h, i, _ = estimate
        if not (math.isfinite(a + b + c + d + e + f + g + h + i + x + y)
                or all(map(math.isfinite, (*estimate[:-1], x, y)))):
            self.restart()
            raise EstimatorOverflow(
                f'non-finite estimate from finite inputs (overflow): {estimate}, x={x!r}, '
                f'y={y!r}; the estimator restarts at the next sample')
        if not self.settled:
            self.settled = not self.observer.in_ramp(t)
        blocked = False
        if self.obstacle is not None:
            blocked = self.obstacle.update(t, estimate.x_v, estimate.theta, tau_v).blocked
        if self.release is not None and self.release.update(t, estimate.v, estimate.theta,
                                                            tau_v):
            estimate = estimate._replace(f2=0.0, f3=0.0)
        return PoseEstimate(estimate, x, y, self.settled, self.position_status, blocked)

    def _compiled_update(self, observer: WipStateObserver, t: float, phi_left: float,
                         phi_right: float, pitch: float, yaw: float, tau_left: float,
                         tau_right: float, rates: Sequence[float]) -> PoseEstimate | None:
        """Take a steady sample compiled; None if the kernel leaves it to the interpreter."""
        kernel = self._kernel_module
        for_observer, constants, epsilon = self._kernel_constants
        if for_observer is not observer:
            constants = kernel.constants(observer, self.relative_to_body, self.slip is not None)
            # The gyro estimator's ε: 1/ω_l of the x_v ESO, constant.
            epsilon = observer.epsilon_at(t)
            self._kernel_constants = observer, constants, epsilon
        slip = self.slip if self.slip is not None else _NO_SLIP
        longitudinal = observer.longitudinal
        out = self._kernel(constants, observer.yaw._s, observer.tilt._s, longitudinal._s,
                           longitudinal._nominal_array, slip.state, slip.constants,
                           self.position.state, self.yaw_unwrapped, observer._phi_meas, t,
                           phi_left, phi_right, pitch, yaw, tau_left, tau_right, rates[0],
                           rates[1])
        status = out[0]
        if status == kernel.TAKEN:
            estimate = StateEstimate._make((*out[6:], epsilon))
            observer._estimate = estimate
            observer._phi_meas = out[2]
            self.yaw_unwrapped = out[1]
            return self._finish(t, estimate, out[4], out[5], tau_left + tau_right)
        return None

    def _position(self, t: float, x_v: float, phi: float,
                  fix: Sequence[float] | None) -> tuple[float, float]:
        """(x, y) [m]: the odometry at (x_v, ϕ̂) and the fix if any; NaN on a refusal."""
        position = self.position
        try:
            if fix is not None and not self.has_fix:
                # The position starts at the first fix (odometry then adds nothing, and
                # the fix itself is a zero innovation).
                position.reset(fix[0], fix[1], x_v, phi)
                self.has_fix = True
            elif not self.position_started:
                position.reset(0.0, 0.0, x_v, phi)
            self.position_started = True
            x, y = position.update_odometry(x_v, phi)
            if fix is not None:
                x, y = position.update_gps(fix[0], fix[1], t)
        except ValueError:
            x = y = math.nan
        return x, y
