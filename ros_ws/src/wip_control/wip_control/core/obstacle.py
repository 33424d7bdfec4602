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
or the lean stops pushing forward, or the axle makes progress: it passes the farthest
point it reached during the stall by ``release_distance``. Motion alone does not release
it: an axle that rocks on the edge (forward and back by a few cm, real motion) gains no
ground, and a wheel that climbs must pass the point where it met the edge.

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

from .mixer import MixerParams

#: τυ,max [N m] of the default mixer, both wheels: what h_max and the holding lean assume
#: when no limit is given.
DEFAULT_MAX_DRIVE_TORQUE = 2.0 * MixerParams().max_wheel_torque


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
    release_distance : [m] how far past the farthest point of the stall the axle must
        get to end a blocking, > 0.
    """

    def __init__(self, params: ModelParams, stall_time: float = 0.3,
                 stall_torque: float = 10.0, stall_speed: float = 0.05,
                 max_drive_torque: float = DEFAULT_MAX_DRIVE_TORQUE,
                 release_distance: float = 0.04) -> None:
        for name, value in (('stall_time', stall_time), ('stall_torque', stall_torque),
                            ('stall_speed', stall_speed),
                            ('max_drive_torque', max_drive_torque),
                            ('release_distance', release_distance)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'ObstacleMonitor: {name} must be finite and > 0, '
                                 f'got {value!r}')
        self.params = params
        self.stall_time, self.stall_torque = stall_time, stall_torque
        self.stall_speed, self.max_drive_torque = stall_speed, max_drive_torque
        # The default 4 cm: under half the 8.7 cm a wheel travels from meeting an edge of
        # h_max to standing on it, and beyond how far the axle rocks up an edge it cannot
        # climb (docs/decisions/obstacle-refusal.md).
        self.release_distance = release_distance
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
        self._farthest = -math.inf   # the farthest x_v of the stall until blocked [m]
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
        if tau_v < least or theta <= 0.0 or (
                self.state.blocked and x_v >= self._farthest + self.release_distance):
            return self._release()
        if self.state.blocked:
            # Only progress past the edge releases a blocking (above): an axle that rocks
            # on the edge moves faster than the stall speed but gains no ground.
            return self.state
        if not samples:
            self._stall_start = t
        self._farthest = max(self._farthest, x_v)
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

    def _release(self) -> ObstacleState:
        # Nothing to release (most samples: no stall under way): the state as it is.
        if self._samples or self.state.blocked:
            self._samples.clear()
            self._stall_start, self._farthest = math.nan, -math.inf
            self.state = ObstacleState(False, math.nan, '')
        return self.state

    def _reason(self, x_v: float, theta: float, tau_v: float) -> str:
        return (f'wheels blocked at x_v = {x_v:.2f} m: {tau_v:.0f} N m of drive torque '
                f'and a lean of {theta:.2f} rad forward do not move them (an obstacle); '
                f'{self.max_drive_torque:.0f} N m climbs a square edge of at most '
                f'{100.0 * self.edge_height:.1f} cm and holds the body over blocked '
                f'wheels up to a lean of {self.lean_limit:.2f} rad')


class ObstacleRelease:
    """Hold back the lumped disturbances for a while after the wheels roll on from a stall.

    While an obstacle holds the wheels, the ESOs (eqs. (4), (8)) put its force into the
    lumped disturbances f̂2, f̂3, and the offset-free MPC pushes against them. Once the
    wheels roll on (up a bump), that force shrinks to nothing at the crest and reverses
    down the far side within a few tenths of a second, while the MPC predicts it constant
    over its horizon and keeps the torque up; with the torque moving at most 10 N m per
    0.1 s the vehicle then leaves the crest too fast and tips back (docs/mujoco-plant.md).
    For ``hold`` s after the wheels roll on, f̂2 and f̂3 are handed on as zero: the
    controllers act on the measured state alone.

    A *stall*: τυ ≥ ``STALL_TORQUE``, |υ̂| < ``STALL_SPEED`` and θ̂ > ``STALL_LEAN`` (the
    motors push, the body leans into it and the axle does not move); the wheels *roll on*
    when υ̂ > ``ROLL_SPEED`` within ``WINDOW`` s of the last stalled sample. A push on the
    body that stops the wheels gives the same signature, so the estimator runs it only when
    asked (docs/estimation.md §7).
    """

    STALL_TORQUE = 8.0    #: [N m] above the 6.9 N m that hold the vehicle on a 10 % slope
    STALL_SPEED = 0.1     #: [m/s]
    STALL_LEAN = 0.06     #: [rad] 30 times the pitch noise (0.04 caught the 1 cm bump too)
    ROLL_SPEED = 0.2      #: [m/s]
    WINDOW = 1.0          #: [s]

    def __init__(self, hold: float = 0.5) -> None:
        if not (math.isfinite(hold) and hold > 0.0):
            raise ValueError(f'ObstacleRelease: hold must be finite and > 0, got {hold!r}')
        self.hold = hold
        self.reset()

    def reset(self) -> None:
        """Forget everything: no stall seen."""
        self._stalled_at: float | None = None
        self._until = -math.inf
        self.events = 0   #: releases since the start

    def update(self, t: float, v: float, theta: float, tau_v: float) -> bool:
        """Take one sample (υ̂ [m/s], θ̂ [rad], τυ [N m]); whether to hold f̂2, f̂3 at zero."""
        if not math.isfinite(t + v + theta + tau_v):
            raise ValueError('ObstacleRelease.update: non-finite input (nothing changed)')
        if (tau_v >= self.STALL_TORQUE and abs(v) < self.STALL_SPEED
                and theta > self.STALL_LEAN):
            self._stalled_at = t
        elif (self._stalled_at is not None and v > self.ROLL_SPEED
              and t - self._stalled_at < self.WINDOW and t >= self._until):
            self._until = t + self.hold
            self._stalled_at = None
            self.events += 1
        return t < self._until
