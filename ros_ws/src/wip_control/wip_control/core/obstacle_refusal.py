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
obstacle (a timed path) stays refused. A new refusal needs a new blocking (the monitor's
blocked going from false to true), so a resumed vehicle that is still held is not caught
again at once.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from .reference_state import ReferenceState


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
    """

    def __init__(self, back_off: float) -> None:
        if not (math.isfinite(back_off) and back_off > 0.0):
            raise ValueError(f'ObstacleRefusal: back_off must be finite and > 0, '
                             f'got {back_off!r}')
        self.back_off = back_off
        self.reset()

    def reset(self) -> None:
        """Forget everything: no refusal, no blocking seen."""
        self.refusal: Refusal | None = None   #: the refusal in force (None if none)
        self.refusals = 0                     #: refusals since the start
        self._blocked = False

    @property
    def refusing(self) -> bool:
        return self.refusal is not None

    def state(self) -> tuple:
        """Everything :meth:`update` changes, for :meth:`restore`."""
        return self.refusal, self.refusals, self._blocked

    def restore(self, state: tuple) -> None:
        """Go back to a :meth:`state` (the guidance stage does when its step fails)."""
        self.refusal, self.refusals, self._blocked = state

    def leads_past(self, reference: ReferenceState) -> bool:
        """Whether ``reference`` is ahead of where the axle stopped, along its heading then."""
        r = self.refusal
        return (reference.x - r.x) * math.cos(r.phi) + (reference.y - r.y) * math.sin(r.phi) > 0.0

    def update(self, t: float, blocked: bool, reference: ReferenceState, x: float, y: float,
               phi: float) -> ReferenceState:
        """Return the reference to follow at ``t`` [s].

        ``reference`` itself, or the held point while refusing; ``blocked``: the obstacle
        monitor's verdict on this sample; (x, y, ϕ): the estimated pose [m, m, rad].
        """
        start = blocked and not self._blocked
        self._blocked = blocked
        if start and all(map(math.isfinite, (t, x, y, phi))):
            self.refusal = Refusal(t, x, y, phi, back_off_point(x, y, phi, self.back_off))
            self.refusals += 1
        if self.refusal is None:
            return reference
        if not self.leads_past(reference):
            self.refusal = None
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
