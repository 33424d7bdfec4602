"""The classic fourth-order Runge–Kutta step, written once.

Every RK4 of the project is this step: the ε ramp of the ESO (``eso.py``), the progress
s(t) of a time-scaled reference (``time_scaling.py``), the MPC benchmark's plant and the
tests' reference solutions. The simulator's plant steps with a numba kernel
(``wip_sim.core.plant_rk4``) that inlines the same stages for speed; the tests check it
against this step.

The state is a float, a numpy array or a tuple of floats (component by component). The
operations and their order are the same for all three, so a scalar loop and its array
form give the same floats.
"""

from __future__ import annotations

from typing import Callable, TypeVar

State = TypeVar('State')


def _along(x, a: float, k):
    """X + a k, component by component for a tuple."""
    if isinstance(x, tuple):
        return tuple(xi + a * ki for xi, ki in zip(x, k))
    return x + a * k


def _combine(x, h6: float, k1, k2, k3, k4):
    """X + h/6 (k1 + 2 k2 + 2 k3 + k4), component by component for a tuple."""
    if isinstance(x, tuple):
        return tuple(xi + h6 * (a + 2.0 * b + 2.0 * c + d)
                     for xi, a, b, c, d in zip(x, k1, k2, k3, k4))
    return x + h6 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rk4_step(f: Callable[[float, State], State], t: float, x: State, h: float,
             k1: State | None = None) -> State:
    """x(t + h) of x' = f(t, x) by one classic RK4 step of ``h``.

    ``k1``: f(t, x) when the caller already has it (it is then not evaluated again).
    """
    hh = 0.5 * h
    if k1 is None:
        k1 = f(t, x)
    k2 = f(t + hh, _along(x, hh, k1))
    k3 = f(t + hh, _along(x, hh, k2))
    k4 = f(t + h, _along(x, h, k3))
    return _combine(x, h / 6.0, k1, k2, k3, k4)
