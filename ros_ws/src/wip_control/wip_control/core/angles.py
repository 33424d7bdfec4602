"""Angle helpers shared by the estimators and the generator."""

from __future__ import annotations

import math

_TWO_PI = 2.0 * math.pi


def wrap_to_pi(angle: float) -> float:
    """Angle [rad] mapped to (−π, π]."""
    wrapped = math.fmod(angle + math.pi, _TWO_PI)
    if wrapped <= 0.0:
        wrapped += _TWO_PI
    return wrapped - math.pi


def unwrap_next(previous_unwrapped: float, new_wrapped: float) -> float:
    """Continuous angle [rad] closest to ``previous_unwrapped`` equal to ``new_wrapped`` mod 2π.

    Sensors report yaw in (−π, π]; the ESO of eq. (4) needs the continuous ϕ, so each
    sample is moved to the branch nearest the previous one. Correct as long as the yaw
    changes by less than π between samples (ω < 628 rad/s at 200 Hz).
    """
    return previous_unwrapped + wrap_to_pi(new_wrapped - previous_unwrapped)
