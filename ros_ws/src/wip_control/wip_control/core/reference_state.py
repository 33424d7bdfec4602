"""The reference's sample and the interface of every reference.

:class:`ReferenceState` and :class:`Reference` have a module of their own so that the
closed-form curves, the waypoint paths, the time scaling and the commanded references
(``commanded.py``) all build on them, and ``references.make_reference`` builds any of them
without an import cycle.
"""

from __future__ import annotations

from typing import NamedTuple


class ReferenceState(NamedTuple):
    """Reference pose and velocities at one time."""

    x: float          #: x_r in the map frame [m]
    y: float          #: y_r in the map frame [m]
    phi: float        #: ϕ_r, heading, continuous (not wrapped) [rad]
    v: float          #: υ_r, speed [m/s]
    omega: float      #: ω_r, yaw rate [rad/s]
    omega_dot: float  #: ω̇_r, yaw acceleration [rad/s²]


class Reference:
    """A reference trajectory: :meth:`sample` gives the state at time t [s]."""

    #: Whether :meth:`sample` is a pure function of t (the same float for the same t,
    #: whatever was sampled before), so that a loop may sample ahead of its ticks.
    #: False for the references commanded at run time.
    pure = True

    def sample(self, t: float) -> ReferenceState:  # pragma: no cover - interface
        raise NotImplementedError

    def derivatives(self, t: float) -> tuple[float, ...]:  # pragma: no cover - interface
        """(ẋ, ẏ, ẍ, ÿ, x⃛, y⃛) at t, where defined analytically."""
        raise NotImplementedError

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        """(υ_r, ω_r) at t, the same floats as :meth:`sample`'s ``v`` and ``omega``.

        :class:`TimeScaled` needs only these at its lead times; curves defined by their
        derivatives override this to skip the pose (its trigonometry is most of a
        sample's cost).
        """
        ref = self.sample(t)
        return ref.v, ref.omega
