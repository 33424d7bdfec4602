"""The tests' reference integrator, written once.

The classic fourth-order Runge–Kutta step, on numpy arrays (the plant's own stepper is
hand-inlined on floats, see ``wip_sim/core/plant.py``; the tests integrate with this textbook
form to check against it).
"""


def rk4_step(f, t, x, h):
    """x(t + h) of x' = f(t, x) by one classic RK4 step of ``h``."""
    k1 = f(t, x)
    k2 = f(t + h / 2, x + h / 2 * k1)
    k3 = f(t + h / 2, x + h / 2 * k2)
    k4 = f(t + h, x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
