"""Wheels blocked by an obstacle: a stall against the drive torque (pure python, no ROS).

A wheel that meets an edge it cannot climb stops while the motors push forward and the
body leans into it. Nothing in model (1) stops the axle against a forward torque with the
body leaning forward (the torque and the lean both accelerate it, eq. (1)'s second row):
only a force of the ground does. The monitor names that, with the physics of why, so
that /diagnostics can say why the vehicle stopped (docs/mujoco-plant.md, kerbs).

Rule per sample: the vehicle is *stalled* while the drive torque τυ is at least
``stall_torque`` forward and the lean θ is forward (> 0); it is *blocked* once the
distance the axle advanced over the last ``stall_time`` s of a stall is less than
``stall_speed`` · ``stall_time`` (a mean speed, so the noise of one speed sample does
not decide). It is released as soon as the torque (below half ``stall_torque`` once blocked)
or the lean stops pushing forward, or the axle moves on faster than that.

The closed forms it reports (docs/mujoco-plant.md derives them): a wheel of radius r
against a square edge of height h pivots on the edge a = √(r² − (r − h)²) ahead of the
axle, and climbs quasi-statically only if τυ ≥ M g a, so the highest edge is
h_max = r − √(r² − (τυ,max / (M g))²); over blocked wheels the body is held only while
m_p g l sin θ ≤ τυ (the motors' reaction is the only couple that tips it back).
"""

from __future__ import annotations

import collections
import math
from typing import NamedTuple

from wip_description.params import ModelParams


def climbable_edge_height(wheel_radius: float, drive_torque: float, total_mass: float,
                          gravity: float) -> float:
    """h_max [m]: the highest square edge ``drive_torque`` [N m] lifts quasi-statically.

    The wheel's radius once the torque could lift the vehicle with the edge at the
    axle's height.
    """
    a = drive_torque / (total_mass * gravity)
    if a >= wheel_radius:
        return wheel_radius
    return wheel_radius - math.sqrt(wheel_radius * wheel_radius - a * a)


def holding_lean(drive_torque: float, body_mass: float, com_height: float,
                 gravity: float) -> float:
    """Largest forward lean θ [rad] at which ``drive_torque`` holds the body over blocked wheels.

    m_p g l sin θ = τυ; π/2 when the torque holds the body level.
    """
    ratio = drive_torque / (body_mass * gravity * com_height)
    return math.pi / 2 if ratio >= 1.0 else math.asin(ratio)


class ObstacleState(NamedTuple):
    """What the monitor says at one sample."""

    blocked: bool     #: the wheels are held back by an obstacle
    since: float      #: when the stall that blocks them began [s] (nan if not blocked)
    reason: str       #: why, with the physics ('' if not blocked)


class ObstacleMonitor:
    """See the module docstring.

    Parameters
    ----------
    params : the controllers' model (r, masses, l, g).
    stall_time : [s] how long the axle must stay (nearly) still against the torque, > 0.
    stall_torque : [N m] the least forward drive torque τυ of a stall, > 0.
    stall_speed : [m/s] the mean speed under which the axle counts as still, > 0.
    max_drive_torque : [N m] the largest τυ the motors give (for h_max in the reason).
    """

    def __init__(self, params: ModelParams, stall_time: float = 0.3,
                 stall_torque: float = 10.0, stall_speed: float = 0.05,
                 max_drive_torque: float = 30.0) -> None:
        for name, value in (('stall_time', stall_time), ('stall_torque', stall_torque),
                            ('stall_speed', stall_speed),
                            ('max_drive_torque', max_drive_torque)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'ObstacleMonitor: {name} must be finite and > 0, '
                                 f'got {value!r}')
        self.params = params
        self.stall_time, self.stall_torque = stall_time, stall_torque
        self.stall_speed, self.max_drive_torque = stall_speed, max_drive_torque
        total = params.body_mass + params.chassis_mass + 2.0 * params.wheel_mass
        self.edge_height = climbable_edge_height(params.wheel_radius, max_drive_torque,
                                                 total, params.gravity)
        self.lean_limit = holding_lean(max_drive_torque, params.body_mass,
                                       params.com_height, params.gravity)
        self.reset()

    def reset(self) -> None:
        """Forget everything: no stall."""
        self._samples: collections.deque = collections.deque()   # (t, x_v) of the stall
        self._stall_start = math.nan
        self.state = ObstacleState(False, math.nan, '')
        self.events = 0   #: blockings since the start
        self.first: ObstacleState | None = None   #: the first blocking

    def update(self, t: float, x_v: float, theta: float, tau_v: float) -> ObstacleState:
        """Take one sample: the axle's distance x_v [m], lean θ [rad], drive torque τυ [N m]."""
        if not math.isfinite(t + x_v + theta + tau_v):
            raise ValueError('ObstacleMonitor.update: non-finite input (nothing changed)')
        samples = self._samples
        # Once blocked, half the stall torque keeps it so (the torque of a held body
        # wanders about the stall torque: one report, not one per crossing).
        least = 0.5 * self.stall_torque if self.state.blocked else self.stall_torque
        if tau_v < least or theta <= 0.0:
            samples.clear()
            self._stall_start = math.nan
            self.state = ObstacleState(False, math.nan, '')
            return self.state
        if not samples:
            self._stall_start = t
        samples.append((t, x_v))
        # Keep one sample at or before t − stall_time: the window's start.
        while len(samples) > 1 and samples[1][0] <= t - self.stall_time + 1e-9:
            samples.popleft()
        t0, x0 = samples[0]
        held = t - t0 >= self.stall_time - 1e-9
        blocked = held and abs(x_v - x0) < self.stall_speed * (t - t0)
        if not blocked:
            self.state = ObstacleState(False, math.nan, '')
            return self.state
        if not self.state.blocked:
            self.events += 1
            self.state = ObstacleState(True, self._stall_start, self._reason(x_v, theta, tau_v))
            if self.first is None:
                self.first = self.state
        return self.state

    def _reason(self, x_v: float, theta: float, tau_v: float) -> str:
        return (f'wheels blocked at x_v = {x_v:.2f} m: {tau_v:.0f} N m of drive torque '
                f'and a lean of {theta:.2f} rad forward do not move them (an obstacle); '
                f'{self.max_drive_torque:.0f} N m climbs a square edge of at most '
                f'{100.0 * self.edge_height:.1f} cm and holds the body over blocked '
                f'wheels up to a lean of {self.lean_limit:.2f} rad')
