"""The estimation half of the control loop.

Sensor samples and applied torques in, one estimate out.

One object, used by the in-process runner, the re-run of a bag and the ESO node, so that
the three compute the same thing: yaw unwrapping, wheel odometry, the ESOs (eqs. (4),
(8)) fed with the applied τυ = τl + τr and τω = τr − τl, the planar position, and the
rules for starting and restarting them (docs/control-loop.md).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

from .angles import unwrap_next
from .eso import EsoParams, StateEstimate
from .state_observer import WipStateObserver
from wip_description.params import ModelParams
from .position import (DEAD_RECKONING, FAULT, NO_FIX, PlanarPositionEstimator,
                       PositionParams, TRACKING)
from wip_description.sensors import wheel_odometry
from .obstacle import (DEFAULT_MAX_DRIVE_TORQUE, ObstacleMonitor, ObstacleRelease,
                       ObstacleState)
from .slip import SlipMonitor


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
        self.restart()
        self.restarts = 0

    @classmethod
    def from_scenario(cls, scenario) -> 'StateEstimator':
        """Return the estimator of a scenario's controller settings.

        ``scenario`` is a :class:`~.controller_settings.ControllerParams` (a simulation's
        scenario is one). The model is the nominal one, as the controllers know it (a
        mismatch with the plant shows up in x_v).
        """
        return cls(scenario.controller_model.parameters, scenario.eso, scenario.position,
                   encoders_relative_to_body=scenario.sensors.encoders_relative_to_body,
                   max_drive_torque=2.0 * scenario.mixer.max_wheel_torque)

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
        yaw_unwrapped = yaw if self.yaw_unwrapped is None else unwrap_next(
            self.yaw_unwrapped, yaw)
        x_v, _ = wheel_odometry(phi_left, phi_right, pitch, self.model, 0.0,
                                self.relative_to_body)
        if self.slip is not None and rates is not None:
            r = self.model.wheel_radius
            x_v = self.slip.update(t, r * phi_left, r * phi_right, x_v, pitch, rates[0],
                                   rates[1], tau_left, tau_right).x_v
        observer = self.observer
        if observer is None:
            observer = WipStateObserver(
                self.model, self.eso_config, initial_positions=(yaw_unwrapped, x_v, pitch),
                initial_time=t, encoders_relative_to_body=self.relative_to_body)
        # Raises ValueError before touching the observer on non-finite input.
        estimate = observer.update(t, yaw_unwrapped, x_v, pitch, tau_left + tau_right,
                                   tau_right - tau_left, rates)
        self.observer, self.yaw_unwrapped = observer, yaw_unwrapped
        x, y = self._position(t, x_v, estimate.phi, fix)
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
            self.settled = not observer.in_ramp(t)
        blocked = False
        if self.obstacle is not None:
            blocked = self.obstacle.update(t, estimate.x_v, estimate.theta,
                                           tau_left + tau_right).blocked
        if self.release is not None and self.release.update(
                t, estimate.v, estimate.theta, tau_left + tau_right):
            estimate = estimate._replace(f2=0.0, f3=0.0)
        return PoseEstimate(estimate, x, y, self.settled, self.position_status, blocked)

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
