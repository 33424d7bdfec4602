r"""The paper's WIP model, eq. (1) in [1]_, and the state layout shared by the project.

.. math::

    \dot\omega = f_{\omega 1} + g_1 \tau_\omega + \tau_{d1}, \quad
    \dot\upsilon = f_{\upsilon 2} + g_2 \tau_\upsilon + \tau_{d2}, \quad
    \ddot\theta = f_{\theta 3} + g_3 \tau_\upsilon + \tau_{d3}

with τυ = τl + τr and, following REP 103 (yaw counter-clockwise positive),
τω = τr − τl. The paper writes τω = τl − τr (clockwise yaw); see docs/paper.md §1.

These terms are the controllers' nominal model and the right-hand side of the
"paper" plant. Scalars are plain floats and ``math`` functions on purpose: the plant
evaluates them 4000 times per simulated second and numpy's per-call overhead on
scalars would dominate.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from wip_description.params import ModelParams

# Layout of the plant state vector, used everywhere a full state is an array:
# planar position (REP 103 world frame, x east / y north in the simulator's map frame),
# yaw, distance rolled, tilt, then the three generalised velocities.
X, Y, PHI, XV, THETA, OMEGA, V, THETA_DOT = range(8)
STATE_SIZE = 8
STATE_NAMES = ('x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot')
STATE_UNITS = ('m', 'm', 'rad', 'm', 'rad', 'rad/s', 'm/s', 'rad/s')


class ModelTerms(NamedTuple):
    """Drift and input gains of eq. (1) at one state."""

    f1: float  #: f_ω1 [rad/s²]
    f2: float  #: f_υ2 [m/s²]
    f3: float  #: f_θ3 [rad/s²]
    g1: float  #: g_1 [rad/s² per N·m of τω]
    g2: float  #: g_2 [m/s² per N·m of τυ]
    g3: float  #: g_3 [rad/s² per N·m of τυ]


def input_gains(params: ModelParams, theta: float) -> tuple[float, float, float]:
    """(g1, g2, g3) of eq. (1) at tilt ``theta`` [rad]."""
    p = params
    return input_gains_of(p.body_mass, p.com_height, p.wheel_radius, p.track_width,
                          p.effective_mass, p.pitch_inertia, p.yaw_inertia_total, theta)


def input_gains_of(mp: float, l: float, r: float, d: float, mv: float, jt: float,  # noqa: E741 - the paper's symbol
                   j_yaw: float, theta: float, square: float = 2) -> tuple[float, float, float]:
    """(g1, g2, g3) of eq. (1) at tilt ``theta`` [rad], from the model's terms.

    ``square`` is the exponent 2, an argument so that compiled code (``estimator_kernel``)
    calls the C library's ``pow`` as CPython's ``x ** 2`` does: LLVM turns a constant
    exponent 2 into ``x * x``, a last bit apart now and then.
    """
    s, c = math.sin(theta), math.cos(theta)
    big_omega = mv * jt - (mp * l * c) ** square
    g1 = d / (r * (j_yaw + mp * l * l * s * s))
    g2 = jt / (big_omega * r)
    g3 = -mp * l * c / (big_omega * r)
    return g1, g2, g3


def nominal_terms(params: ModelParams, theta: float, omega: float,
                  theta_dot: float) -> ModelTerms:
    """All terms of eq. (1) at (θ [rad], ω [rad/s], θ̇ [rad/s])."""
    p = params
    mp, l, g = p.body_mass, p.com_height, p.gravity  # noqa: E741 - the paper's symbol
    mv, jt = p.effective_mass, p.pitch_inertia
    s, c = math.sin(theta), math.cos(theta)
    s2 = 2.0 * s * c  # sin 2θ
    big_omega = mv * jt - (mp * l * c) ** 2
    yaw_inertia = p.yaw_inertia_total + mp * l * l * s * s
    f1 = -mp * l * l * omega * theta_dot * s2 / yaw_inertia
    f2 = (jt * mp * l * theta_dot ** 2 * s
          - mp * mp * l ** 3 * omega ** 2 * s * c * c
          - 0.5 * mp * mp * l * l * g * s2) / big_omega
    f3 = (mv * mp * g * l * s
          + 0.5 * mv * mp * l * l * omega ** 2 * s2
          - 0.5 * mp * mp * l * l * theta_dot ** 2 * s2) / big_omega
    g1 = p.track_width / (p.wheel_radius * yaw_inertia)
    g2 = jt / (big_omega * p.wheel_radius)
    g3 = -mp * l * c / (big_omega * p.wheel_radius)
    return ModelTerms(f1, f2, f3, g1, g2, g3)


def wheel_to_body_torques(tau_left: float, tau_right: float) -> tuple[float, float]:
    """(τυ, τω) from wheel torques [N·m]: τυ = τl + τr, τω = τr − τl (REP 103)."""
    return tau_left + tau_right, tau_right - tau_left
