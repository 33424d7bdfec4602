r"""Closed-form reference curves of [1]_: trifolium, circle, straight line, figure eight.

Every curve is p(t) = (x_r(t), y_r(t)) with analytic derivatives up to the third order,
from which

.. math::

    \upsilon_r = |\dot p|, \quad
    \omega_r = \frac{\dot x \ddot y - \dot y \ddot x}{\dot x^2 + \dot y^2}, \quad
    \dot\omega_r = \frac{\dot x \dddot y - \dot y \dddot x}{\upsilon_r^2}
        - 2 \omega_r \frac{\dot x \ddot x + \dot y \ddot y}{\upsilon_r^2}

and ϕ_r = atan2(ẏ_r, ẋ_r) given by a closed form on a continuous branch (never
jumping by 2π). ``sample`` uses floats and ``math`` only.

``trifolium`` (Section V): x_r = κ cos(3Ω t) cos(Ω t), y_r = κ cos(3Ω t) sin(Ω t),
κ = 3 m, Ω = π/45 rad/s. Its speed is κΩ √(1 + 8 sin²(3Ω t)) ∈ [κΩ, 3κΩ] =
[0.21, 0.63] m/s, never zero, and |ω_r| peaks at 0.70 rad/s at the petal tips.
``figure_eight``: the lemniscate of Gerono x = a sin τ, y = (a/2) sin 2τ, τ = 2π t/P.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import math
from typing import Sequence

from .reference_state import Reference, ReferenceState

_HALF_PI = 0.5 * math.pi


# The closed forms are module functions of a parameter tuple ``p`` and t, with ``math``
# only, so that the time scaling's compiled kernel (retiming_kernel.py) compiles these very
# functions: one home for each formula, the same floats interpreted or compiled.

def state_from_derivatives(x: float, y: float, phi: float, xd: float, yd: float, xdd: float,
                           ydd: float, xddd: float, yddd: float) -> tuple[float, ...]:
    """(x, y, ϕ, υ, ω, ω̇) from position derivatives (speed must be > 0)."""
    v2 = xd * xd + yd * yd
    omega = (xd * ydd - yd * xdd) / v2
    omega_dot = ((xd * yddd - yd * xddd) - 2.0 * omega * (xd * xdd + yd * ydd)) / v2
    return x, y, phi, math.sqrt(v2), omega, omega_dot


def speed_and_yaw_rate_from_derivatives(xd: float, yd: float, xdd: float,
                                        ydd: float) -> tuple[float, float]:
    """(υ_r, ω_r) from the derivatives.

    The expressions of :func:`state_from_derivatives`, so the same floats.
    """
    v2 = xd * xd + yd * yd
    return math.sqrt(v2), (xd * ydd - yd * xdd) / v2


def trifolium_derivatives(p: tuple, t: float) -> tuple[float, ...]:
    """(ẋ, ẏ, ẍ, ÿ, x⃛, y⃛) of the trifolium p = (κ, Ω) at t."""
    a_half, w = 0.5 * p[0], p[1]
    angle_a, angle_b = 4.0 * w * t, 2.0 * w * t
    ca, sa = math.cos(angle_a), math.sin(angle_a)
    cb, sb = math.cos(angle_b), math.sin(angle_b)
    w2, w3 = w * w, w * w * w
    return (a_half * w * (-4.0 * sa - 2.0 * sb), a_half * w * (4.0 * ca - 2.0 * cb),
            -a_half * w2 * (16.0 * ca + 4.0 * cb), -a_half * w2 * (16.0 * sa - 4.0 * sb),
            a_half * w3 * (64.0 * sa + 8.0 * sb), a_half * w3 * (-64.0 * ca + 8.0 * cb))


def trifolium_state(p: tuple, t: float) -> tuple[float, ...]:
    """(x, y, ϕ, υ, ω, ω̇) of the trifolium p = (κ, Ω) at t."""
    w = p[1]
    u = 3.0 * w * t
    r = p[0] * math.cos(u)
    su = math.sin(u)
    wt = w * t
    phi = 4.0 * w * t + _HALF_PI + math.atan2(math.sin(6.0 * w * t), 1.0 + 2.0 * su * su)
    xd, yd, xdd, ydd, xddd, yddd = trifolium_derivatives(p, t)
    return state_from_derivatives(r * math.cos(wt), r * math.sin(wt), phi, xd, yd, xdd, ydd,
                                  xddd, yddd)


def trifolium_speed_and_yaw_rate(p: tuple, t: float) -> tuple[float, float]:
    """(υ_r, ω_r): the first two derivatives of :func:`trifolium_derivatives`, the same floats."""
    a_half, w = 0.5 * p[0], p[1]
    angle_a, angle_b = 4.0 * w * t, 2.0 * w * t
    ca, sa = math.cos(angle_a), math.sin(angle_a)
    cb, sb = math.cos(angle_b), math.sin(angle_b)
    w2 = w * w
    return speed_and_yaw_rate_from_derivatives(
        a_half * w * (-4.0 * sa - 2.0 * sb), a_half * w * (4.0 * ca - 2.0 * cb),
        -a_half * w2 * (16.0 * ca + 4.0 * cb), -a_half * w2 * (16.0 * sa - 4.0 * sb))


def circle_state(p: tuple, t: float) -> tuple[float, ...]:
    """(x, y, ϕ, υ, ω, ω̇) of the circle p = (cx, cy, R, υ, start angle, ±1, ω) at t."""
    beta = p[4] + p[6] * t
    return (p[0] + p[2] * math.cos(beta), p[1] + p[2] * math.sin(beta),
            beta + p[5] * _HALF_PI, p[3], p[6], 0.0)


def circle_speed_and_yaw_rate(p: tuple, t: float) -> tuple[float, float]:
    """(υ_r, ω_r) of the circle: constant."""
    return p[3], p[6]


def line_state(p: tuple, t: float) -> tuple[float, ...]:
    """(x, y, ϕ, υ, ω, ω̇) of the line p = (x0, y0, heading, υ, cos heading, sin heading)."""
    d = p[3] * t
    return p[0] + d * p[4], p[1] + d * p[5], p[2], p[3], 0.0, 0.0


def line_speed_and_yaw_rate(p: tuple, t: float) -> tuple[float, float]:
    """(υ_r, ω_r) of the line: constant."""
    return p[3], 0.0


def figure_eight_derivatives(p: tuple, t: float) -> tuple[float, ...]:
    """(ẋ, ẏ, ẍ, ÿ, x⃛, y⃛) of the figure eight p = (cx, cy, a, 2π/P) at t."""
    a, w = p[2], p[3]
    tau = w * t
    c1, s1 = math.cos(tau), math.sin(tau)
    c2, s2 = math.cos(2.0 * tau), math.sin(2.0 * tau)
    return (a * w * c1, a * w * c2, -a * w * w * s1, -2.0 * a * w * w * s2,
            -a * w ** 3 * c1, -4.0 * a * w ** 3 * c2)


def figure_eight_state(p: tuple, t: float) -> tuple[float, ...]:
    """(x, y, ϕ, υ, ω, ω̇) of the figure eight p = (cx, cy, a, 2π/P) at t."""
    tau = p[3] * t
    c = math.cos(tau)
    phi = -_HALF_PI + math.atan2(c, 1.0 - 2.0 * c * c)
    xd, yd, xdd, ydd, xddd, yddd = figure_eight_derivatives(p, t)
    return state_from_derivatives(p[0] + p[2] * math.sin(tau),
                                  p[1] + 0.5 * p[2] * math.sin(2.0 * tau), phi,
                                  xd, yd, xdd, ydd, xddd, yddd)


def figure_eight_speed_and_yaw_rate(p: tuple, t: float) -> tuple[float, float]:
    """(υ_r, ω_r) of the figure eight, the same floats as its state."""
    xd, yd, xdd, ydd, _, _ = figure_eight_derivatives(p, t)
    return speed_and_yaw_rate_from_derivatives(xd, yd, xdd, ydd)


class ClosedFormCurve(Reference):
    """A curve whose closed forms are the module functions of its ``parameters``.

    ``KERNEL_KIND`` names it for the compiled time scaling (retiming_kernel.py).
    """

    KERNEL_KIND = -1
    parameters: tuple = ()

    def sample(self, t: float) -> ReferenceState:
        return ReferenceState(*self._state(self.parameters, t))

    def speed_and_yaw_rate(self, t: float) -> tuple[float, float]:
        return self._speed_and_yaw_rate(self.parameters, t)


class Trifolium(ClosedFormCurve):
    """The paper's trifolium, Section V of [1]_: r = κ cos(3Ω t) at polar angle Ω t.

    Written as p = (κ/2)(e^{i4Ωt} + e^{−i2Ωt}) (complex plane), so every derivative is a
    sum of two phasors. Heading on a continuous branch: with u = 3Ω t,
    ϕ_r = 4Ω t + π/2 + atan2(sin 2u, 1 + 2 sin² u) (the atan2 argument has a positive
    real part, so it never jumps); ϕ_r grows by 4π per figure (π/Ω = 45 s).

    Parameters
    ----------
    size : κ [m], > 0.
    angular_frequency : Ω [rad/s], > 0.
    """

    KERNEL_KIND = 0
    _state = staticmethod(trifolium_state)
    _speed_and_yaw_rate = staticmethod(trifolium_speed_and_yaw_rate)

    def __init__(self, size: float = 3.0, angular_frequency: float = math.pi / 45.0) -> None:
        if not (size > 0.0 and angular_frequency > 0.0):
            raise ValueError('Trifolium: size and angular_frequency must be > 0')
        self.size = size
        self.angular_frequency = angular_frequency
        self.parameters = (float(size), float(angular_frequency))

    def derivatives(self, t: float) -> tuple[float, ...]:
        return trifolium_derivatives(self.parameters, t)


class Circle(ClosedFormCurve):
    """Uniform motion on a circle.

    Parameters
    ----------
    center : (x, y) [m].
    radius : R [m], > 0.
    speed : υ_r [m/s], > 0.
    direction : ``'ccw'`` (ω_r = υ/R) or ``'cw'`` (ω_r = −υ/R).
    start_angle : polar angle of the start point about the centre [rad].
    """

    KERNEL_KIND = 1
    _state = staticmethod(circle_state)
    _speed_and_yaw_rate = staticmethod(circle_speed_and_yaw_rate)

    def __init__(self, center: Sequence[float] = (0.0, 0.0), radius: float = 2.0,
                 speed: float = 0.5, direction: str = 'ccw', start_angle: float = 0.0) -> None:
        if not (radius > 0.0 and speed > 0.0):
            raise ValueError('Circle: radius and speed must be > 0')
        if direction not in ('ccw', 'cw'):
            raise ValueError(f"Circle: direction must be 'ccw' or 'cw', got {direction!r}")
        self.cx, self.cy = center
        self.radius, self.speed, self.start_angle = radius, speed, start_angle
        self.sign = 1.0 if direction == 'ccw' else -1.0
        self.rate = self.sign * speed / radius
        self.parameters = tuple(float(v) for v in (self.cx, self.cy, radius, speed,
                                                   start_angle, self.sign, self.rate))

    def derivatives(self, t: float) -> tuple[float, ...]:
        beta = self.start_angle + self.rate * t
        c, s = math.cos(beta), math.sin(beta)
        r, w = self.radius, self.rate
        return (-r * w * s, r * w * c, -r * w * w * c, -r * w * w * s, r * w ** 3 * s,
                -r * w ** 3 * c)


class StraightLine(ClosedFormCurve):
    """Uniform motion on a straight line.

    The motion starts at ``start`` [m] and goes along ``heading`` [rad] at ``speed``
    [m/s] (≥ 0).
    """

    KERNEL_KIND = 2
    _state = staticmethod(line_state)
    _speed_and_yaw_rate = staticmethod(line_speed_and_yaw_rate)

    def __init__(self, start: Sequence[float] = (0.0, 0.0), heading: float = 0.0,
                 speed: float = 0.5) -> None:
        if not speed >= 0.0:
            raise ValueError('StraightLine: speed must be >= 0')
        self.x0, self.y0 = start
        self.heading, self.speed = heading, speed
        self._c, self._s = math.cos(heading), math.sin(heading)
        self.parameters = tuple(float(v) for v in (self.x0, self.y0, heading, speed,
                                                   self._c, self._s))

    def derivatives(self, t: float) -> tuple[float, ...]:
        return (self.speed * self._c, self.speed * self._s, 0.0, 0.0, 0.0, 0.0)


class FigureEight(ClosedFormCurve):
    """Lemniscate of Gerono: x = cx + a sin τ, y = cy + (a/2) sin 2τ, τ = 2π t/P.

    Starts at the centre heading 45°, first lobe to the right (counter-clockwise), the
    second clockwise. ẋ ∝ cos τ and ẏ ∝ 2cos²τ − 1 depend on τ only through c = cos τ, so
    ϕ_r = −π/2 + atan2(c, 1 − 2c²), continuous for c ∈ [−1, 1] (range [−5π/4, π/4]).
    The speed a(2π/P)√(4c⁴ − 3c² + 1) lies in [0.66, 1.41]·a 2π/P, never zero.

    Parameters
    ----------
    center : (x, y) [m].
    size : half-width a [m], > 0.
    period : P, time for the whole figure [s], > 0.
    """

    KERNEL_KIND = 3
    _state = staticmethod(figure_eight_state)
    _speed_and_yaw_rate = staticmethod(figure_eight_speed_and_yaw_rate)

    def __init__(self, center: Sequence[float] = (0.0, 0.0), size: float = 3.0,
                 period: float = 60.0) -> None:
        if not (size > 0.0 and period > 0.0):
            raise ValueError('FigureEight: size and period must be > 0')
        self.cx, self.cy = center
        self.size, self.period = size, period
        self.rate = 2.0 * math.pi / period
        self.parameters = tuple(float(v) for v in (self.cx, self.cy, size, self.rate))

    def derivatives(self, t: float) -> tuple[float, ...]:
        return figure_eight_derivatives(self.parameters, t)
