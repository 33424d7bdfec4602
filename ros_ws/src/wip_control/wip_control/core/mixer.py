r"""Wheel-torque mixer, eq. (24) in [1]_, with REP 103 signs and per-wheel limits.

.. math::

    \tau_l = (\tau_\upsilon - \tau_\omega)/2, \quad
    \tau_r = (\tau_\upsilon + \tau_\omega)/2

the inverse of τυ = τl + τr, τω = τr − τl (``model.wheel_to_body_torques``). The paper
writes τω = τl − τr (clockwise yaw); with REP 103 (yaw counter-clockwise positive) and
g1 > 0, a positive τω pushes the right wheel forward and turns the vehicle
counter-clockwise.

Limits, yaw first (docs/paper.md §5): τω is clipped to ±2 τmax, then τυ to
±(2 τmax − |τω|) (:func:`drive_torque_limit`, which the MPC also receives as its input
bound), so that |τl|, |τr| ≤ (|τυ| + |τω|)/2 ≤ τmax. When a wheel would saturate the
yaw torque is kept and the drive torque gives way: with the default limits the yaw share
is at most τω,max = 0.8 N·m of the 30 N·m drive range, so balance loses at most 3 % of
its authority, while clipping each wheel separately would change τω, and so the heading,
by up to the whole clipped excess. Inside the limits the mix is exact.

:class:`WheelTorqueRateLimiter` bounds the change of each wheel torque per period; it is
for the safety layer (the torque_mixer node) and is not part of the paper.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math

from wip_runtime.config import param


@dataclasses.dataclass(frozen=True)
class MixerParams:
    """Per-wheel limits of the mixer (defaults: Section V, τmax = 15 N·m)."""

    max_wheel_torque: float = param(15.0, 'N m', 'tau_max: limit of each wheel torque '
                                    '(|tau_v| <= 2 tau_max - |tau_omega|)', minimum=0.0,
                                    exclusive_minimum=True)
    max_wheel_torque_rate: float = param(
        1.0e4, 'N m/s', 'limit of the change of each wheel torque (safety layer); the '
        'default allows 50 N m per 5 ms period, i.e. no limit', minimum=0.0,
        exclusive_minimum=True)


def drive_torque_limit(tau_omega: float, max_wheel_torque: float) -> float:
    """Bound on |τυ| [N·m] that keeps both wheels within ±τmax: 2 τmax − |τω| (≥ 0)."""
    return max(0.0, 2.0 * max_wheel_torque - abs(tau_omega))


def mix(tau_v: float, tau_omega: float, max_wheel_torque: float) -> tuple[float, float]:
    """(τl, τr) [N·m] from (τυ, τω) [N·m], eq. (24) with REP 103 signs, yaw preserved.

    Raises
    ------
    ValueError
        on non-finite torques or a non-positive limit.
    """
    if not mixable(tau_v, tau_omega, max_wheel_torque):
        raise ValueError(f'mix: need finite torques and max_wheel_torque > 0, got '
                         f'tau_v={tau_v!r}, tau_omega={tau_omega!r}, '
                         f'max_wheel_torque={max_wheel_torque!r}')
    return mixed(tau_v, tau_omega, max_wheel_torque)


def mixable(tau_v: float, tau_omega: float, max_wheel_torque: float) -> bool:
    """Whether :func:`mix` takes these: finite torques and a positive limit."""
    return math.isfinite(tau_v + tau_omega + max_wheel_torque) and max_wheel_torque > 0.0


def mixed(tau_v: float, tau_omega: float, max_wheel_torque: float) -> tuple[float, float]:
    """:func:`mix` of values it takes (:func:`mixable`); compiled too (``safety_kernel``)."""
    yaw_limit = 2.0 * max_wheel_torque
    tau_omega = max(-yaw_limit, min(yaw_limit, tau_omega))
    drive_limit = yaw_limit - abs(tau_omega)
    tau_v = max(-drive_limit, min(drive_limit, tau_v))
    tau_left = 0.5 * (tau_v - tau_omega)                                  # Eq. (24) in [1]
    tau_right = 0.5 * (tau_v + tau_omega)
    # Rounding guard: (|τυ| + |τω|)/2 ≤ τmax holds exactly in reals.
    tau_left = max(-max_wheel_torque, min(max_wheel_torque, tau_left))
    tau_right = max(-max_wheel_torque, min(max_wheel_torque, tau_right))
    return tau_left, tau_right


class WheelTorqueRateLimiter:
    """Limit the change of each wheel torque to ``max_rate`` · Δt per step.

    Parameters
    ----------
    max_rate : [N·m/s], > 0.
    initial : (τl, τr) [N·m] the limiter starts from (normally zero torque).
    """

    def __init__(self, max_rate: float, initial: tuple[float, float] = (0.0, 0.0)) -> None:
        if not (math.isfinite(max_rate) and max_rate > 0.0):
            raise ValueError(f'max_rate must be finite and > 0, got {max_rate!r}')
        self.max_rate = float(max_rate)
        self.reset(*initial)

    def reset(self, tau_left: float = 0.0, tau_right: float = 0.0) -> None:
        """Set the torques [N·m] the next step is measured from."""
        if not math.isfinite(tau_left + tau_right):
            raise ValueError(f'reset: non-finite torques ({tau_left!r}, {tau_right!r})')
        self.tau_left, self.tau_right = float(tau_left), float(tau_right)

    def step(self, dt: float, tau_left: float, tau_right: float) -> tuple[float, float]:
        """Rate-limited (τl, τr) [N·m] toward the requested torques over ``dt`` [s] > 0."""
        if not (math.isfinite(dt + tau_left + tau_right) and dt > 0.0):
            raise ValueError(f'WheelTorqueRateLimiter.step: need finite torques and dt > 0, '
                             f'got dt={dt!r}, tau_left={tau_left!r}, tau_right={tau_right!r}')
        d = self.max_rate * dt
        self.tau_left += max(-d, min(d, tau_left - self.tau_left))
        self.tau_right += max(-d, min(d, tau_right - self.tau_right))
        return self.tau_left, self.tau_right
