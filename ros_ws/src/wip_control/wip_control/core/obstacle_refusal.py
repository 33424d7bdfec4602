"""Refusing an obstacle the wheels cannot climb: back off, hold balanced, say why (no ROS).

When the estimator's obstacle monitor finds the wheels blocked (core/obstacle.py: the axle
still for 0.3 s against a forward drive torque and a forward lean), the edge is higher than
the torque lifts (h_max, docs/mujoco-plant.md): pushing on only leans the body further into
it, up to the lean the torque can no longer hold. The refusal takes the reference of the
trajectory generator over: a point at rest ``back_off`` behind where the axle stopped, on
the heading it had. Eq. (9) then gives υd = υr cos ϕe + λ3 tanh xe = λ3 tanh(−back_off) < 0,
so the drive controller stops pushing, tips the body back, rolls away from the edge and
holds the point balanced.

It lasts until the reference no longer leads past the obstacle: a reference point not
ahead of where the axle stopped, along the heading it had (a new path or goal that turns
away or goes back, a velocity command backing off; the reference node restarts a commanded
reference at the held point, docs/estimation.md §7). A reference that runs on through the
obstacle (a timed path) stays refused, unless the vehicle itself goes on past it: a
refusal that comes as the wheels start over the edge (a slow climb) must not pull back a
vehicle already crossing. Its progress is judged on the estimated position, which the
position source fixes (not on the wheels, which spin against an edge): once it has stayed
``crossed`` m ahead of where it was refused, along the heading then, for ``crossed_time`` s,
the refusal ends and the reference is followed again.

The refusal waits ``delay`` s of blocking (beyond the monitor's stall time) so that a
stall that climbs soon after is a crossing, and a new refusal needs a new blocking (the
monitor's blocked going from false to true), so a resumed vehicle that is still held is
not caught again at once.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from .reference_state import ReferenceState


#: [m] A wheel of radius r blocked by an edge up to r high has its axle at most r short of
#: the edge's line (a = √(r² − (r − h)²) ≤ r, docs/mujoco-plant.md): an axle r (0.2 m)
#: ahead of where it was refused has passed over the edge. The tip-back of a refused body
#: moves a blocked axle a few cm forward (docs/decisions/obstacle-refusal.md).
CROSSED = 0.2
#: [s] Longer than the 0.1 s between the position source's fixes (10 Hz): between two, the
#: position is odometry, which wheels spinning against the edge push ahead, and the next
#: fix takes it back (docs/decisions/obstacle-refusal.md).
CROSSED_TIME = 0.15


def back_off_point(x: float, y: float, phi: float, distance: float) -> ReferenceState:
    """Return the point at rest ``distance`` [m] behind the pose (x, y, ϕ), on its heading."""
    return ReferenceState(x - distance * math.cos(phi), y - distance * math.sin(phi), phi,
                          0.0, 0.0, 0.0)


class Refusal(NamedTuple):
    """Where the wheels were blocked and where the vehicle holds (map frame)."""

    since: float    #: time of the blocking [s]
    x: float        #: the axle's position when blocked [m]
    y: float        #: [m]
    phi: float      #: its heading then [rad]
    hold: ReferenceState   #: the point at rest it backs off to


class ObstacleRefusal:
    """See the module docstring.

    Parameters
    ----------
    back_off : [m] how far behind the blocked axle the vehicle holds, > 0.
    delay : [s] how long the wheels stay blocked before the refusal, ≥ 0: a stall that
        climbs sooner is a crossing.
    crossed : [m] how far ahead of where it was refused the vehicle is over the edge, > 0.
    crossed_time : [s] how long it must stay that far ahead, ≥ 0.
    """

    def __init__(self, back_off: float, delay: float = 0.0, crossed: float = CROSSED,
                 crossed_time: float = CROSSED_TIME) -> None:
        for name, value in (('back_off', back_off), ('crossed', crossed)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'ObstacleRefusal: {name} must be finite and > 0, '
                                 f'got {value!r}')
        for name, value in (('delay', delay), ('crossed_time', crossed_time)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'ObstacleRefusal: {name} must be finite and >= 0, '
                                 f'got {value!r}')
        self.back_off, self.delay = back_off, delay
        self.crossed, self.crossed_time = crossed, crossed_time
        self.reset()

    def reset(self) -> None:
        """Forget everything: no refusal, no blocking seen."""
        self.refusal: Refusal | None = None   #: the refusal in force (None if none)
        self.refusals = 0                     #: refusals since the start
        self._since: float | None = None      # start of the blocking in force
        self._armed = False                   # the blocking in force has not refused yet
        self._ahead: float | None = None      # since when the vehicle is `crossed` ahead
        self.crossings = 0                    #: refusals ended by the vehicle going on past

    @property
    def refusing(self) -> bool:
        return self.refusal is not None

    def state(self) -> tuple:
        """Everything :meth:`update` changes, for :meth:`restore`."""
        return (self.refusal, self.refusals, self._since, self._armed, self._ahead,
                self.crossings)

    def restore(self, state: tuple) -> None:
        """Go back to a :meth:`state` (the guidance stage does when its step fails)."""
        (self.refusal, self.refusals, self._since, self._armed, self._ahead,
         self.crossings) = state

    def leads_past(self, reference: ReferenceState) -> bool:
        """Whether ``reference`` is ahead of where the axle stopped, along its heading then."""
        r = self.refusal
        return (reference.x - r.x) * math.cos(r.phi) + (reference.y - r.y) * math.sin(r.phi) > 0.0

    def blocking(self, t: float, blocked: bool, x: float, y: float,
                 phi: float) -> Refusal | None:
        """Take the monitor's verdict at ``t`` [s] and the pose; the refusal it starts, if any."""
        if not blocked:
            self._since = None
            return None
        if self._since is None:
            self._since, self._armed = t, True
        if not (self._armed and t - self._since >= self.delay - 1e-9
                and all(map(math.isfinite, (t, x, y, phi)))):
            return None
        self.refusal = Refusal(self._since, x, y, phi, back_off_point(x, y, phi, self.back_off))
        self.refusals += 1
        self._armed, self._ahead = False, None
        return self.refusal

    def went_past(self, t: float, x: float, y: float) -> bool:
        """Whether the vehicle at (x, y) [m] has stayed ``crossed`` ahead of the refusal."""
        r = self.refusal
        ahead = (x - r.x) * math.cos(r.phi) + (y - r.y) * math.sin(r.phi)
        if not ahead >= self.crossed:
            self._ahead = None
            return False
        if self._ahead is None:
            self._ahead = t
        return t - self._ahead >= self.crossed_time - 1e-9

    def update(self, t: float, blocked: bool, reference: ReferenceState, x: float, y: float,
               phi: float, fixed: bool = True) -> ReferenceState:
        """Return the reference to follow at ``t`` [s].

        ``reference`` itself, or the held point while refusing; ``blocked``: the obstacle
        monitor's verdict on this sample; (x, y, ϕ): the estimated pose [m, m, rad];
        ``fixed``: whether a source other than the wheels fixes the position (the
        estimate's position status TRACKING), without which no progress ends a refusal.
        """
        self.blocking(t, blocked, x, y, phi)
        if self.refusal is None:
            return reference
        if not self.leads_past(reference):
            self.refusal = None
            return reference
        # Dead reckoning (position_source wheels) is the wheels' own distance, which a
        # spin against the edge moves on: it cannot tell a crossing.
        if fixed and self.went_past(t, x, y):
            self.refusal = None
            self.crossings += 1
            return reference
        return self.refusal.hold

    def reason(self) -> str:
        """Why the vehicle holds, and what resumes it ('' when not refusing)."""
        r = self.refusal
        if r is None:
            return ''
        return (f'refused: wheels blocked by an obstacle at ({r.x:.2f}, {r.y:.2f}) m '
                f'since {r.since:.2f} s, too high to climb (see the eso); holding '
                f'{self.back_off:.2f} m back at ({r.hold.x:.2f}, {r.hold.y:.2f}) m. '
                'Clear the obstacle or plan around it: a path, goal or command that does '
                'not lead past it resumes')


def make_refusal(config) -> ObstacleRefusal | None:
    """Return the refusal of a ``TrajectoryGeneratorParams`` (None: obstacle_back_off 0, off)."""
    if config.obstacle_back_off <= 0.0:
        return None
    return ObstacleRefusal(config.obstacle_back_off, config.obstacle_refuse_delay)
