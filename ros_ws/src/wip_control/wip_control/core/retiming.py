"""The time scaling's formulas: progress s(t), σ(s), the re-timed state and speed.

Module functions of floats and indexable node tables (lists in
:class:`~.time_scaling.TimeScaled`, numpy arrays in the compiled kernel,
``retiming_kernel.py``, which compiles these very functions): one home for each formula,
the same floats interpreted or compiled. The callers make sure that the tables reach the
nodes indexed. Arithmetic on floats only, no import.
"""

from __future__ import annotations


def hermite_progress(t: float, h: float, s_nodes, rate_nodes) -> float:
    """s(t): cubic Hermite between the nodes s(n h), ṡ(n h); σ(0) t before t = 0."""
    if t <= 0.0:
        return rate_nodes[0] * t
    n = int(t / h)
    u = t / h - n
    s0, s1, r0, r1 = s_nodes[n], s_nodes[n + 1], rate_nodes[n], rate_nodes[n + 1]
    u2, u3 = u * u, u * u * u
    return ((2 * u3 - 3 * u2 + 1) * s0 + (u3 - 2 * u2 + u) * h * r0
            + (-2 * u3 + 3 * u2) * s1 + (u3 - u2) * h * r1)


def interpolated_sigma(s: float, h: float, sigma_nodes) -> tuple[float, float]:
    """σ(s), linear between the nodes σ(i h), and dσ/ds; s ≤ 0 takes σ(0), slope 0."""
    if s <= 0.0:
        return sigma_nodes[0], 0.0
    u = s / h
    i = int(u)
    a, b = sigma_nodes[i], sigma_nodes[i + 1]
    return a + (b - a) * (u - i), (b - a) / h


def interpolated_rate(s: float, h: float, sigma_nodes) -> float:
    """σ(s) of :func:`interpolated_sigma`, without the slope."""
    if s <= 0.0:
        return sigma_nodes[0]
    u = s / h
    i = int(u)
    a = sigma_nodes[i]
    return a + (sigma_nodes[i + 1] - a) * (u - i)


def raw_rate(v: float, omega: float, max_speed: float, max_yaw_rate: float) -> float:
    """σ0 for the base's speed ``v`` and yaw rate ``omega``."""
    sigma = 1.0
    if v > max_speed:
        sigma = max_speed / v
    if abs(omega) * sigma > max_yaw_rate:
        sigma = max_yaw_rate / abs(omega)
    return sigma


def retimed_state(x: float, y: float, phi: float, v: float, omega: float, omega_dot: float,
                  sigma: float, d_sigma: float, max_speed: float,
                  max_yaw_rate: float) -> tuple[float, ...]:
    """Re-time the base's state at s by σ(s): pose, υ_r σ, ω_r σ, σ (ω̇_r σ + ω_r dσ/ds)."""
    # Between grid nodes the linear σ may exceed σ0 by O(step²): never above it.
    sigma = min(sigma, raw_rate(v, omega, max_speed, max_yaw_rate))
    return x, y, phi, v * sigma, omega * sigma, sigma * (omega_dot * sigma + omega * d_sigma)


def retimed_speed(v: float, omega: float, sigma: float, max_speed: float,
                  max_yaw_rate: float) -> float:
    """υ_r σ of :func:`retimed_state`, the same float."""
    return v * min(sigma, raw_rate(v, omega, max_speed, max_yaw_rate))


def speeding_up(v_ahead: float, v: float, lead: float, lead_accelerating: float) -> bool:
    """Whether the lead of the accelerations replaces the speed lead's υ ``v_ahead``."""
    return abs(v_ahead) > abs(v) and lead_accelerating != lead
