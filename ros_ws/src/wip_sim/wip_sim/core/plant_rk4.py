"""The plant's compiled RK4 integrator (numba), apart from :mod:`.plant`.

A process that reads the plant's equations without stepping it (the metrics of a report,
the identification) does not import numba and llvmlite: about 0.2 s of import and 50 MB of
memory. :class:`~.plant.Plant` imports this module at its construction. The dynamics are
those of :func:`.plant._make_accelerations`, inlined.

The stages are those of the project's one RK4, ``wip_control.core.integration.rk4_step``,
unrolled on floats and compiled for speed (the plant steps at 1 kHz); the tests check this
kernel against that step on :meth:`.plant.Plant.derivative`
(``tests/wip_sim/core/test_plant.py``).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline='always')
def _slopes(k, tv, tw, th, om, v, thd, d1, d2, d3):
    """(ω̇, υ̇, θ̈) at one RK4 stage.

    :func:`.plant._make_accelerations` for the held wheel torques τυ = ``tv``, τω = ``tw``. Inlined
    into the caller, so the operations and their order are those of the reference step (bit for
    bit).
    """
    (mv, jt, jphi, mpl, mpl2, mpgl, mvjt, mpl_sq, inv_r, yaw_gain, k_centrifugal,
     k_coriolis, k_reaction, friction_v, friction_w) = k
    # Axle friction, state dependent (with b = 0 these leave tv and tw as they are).
    tv = tv - friction_v * (v * inv_r - thd)
    tw = tw - friction_w * om
    ytw = yaw_gain * tw
    tvr = tv * inv_r
    tvk = k_reaction * tv
    s = math.sin(th)
    c = math.cos(th)
    inv_omega = 1.0 / (mvjt - mpl_sq * c * c)
    omega_dot = ((ytw - (2.0 * mpl2 * c * thd + k_coriolis * v) * s * om)
                 / (jphi + mpl2 * s * s) + d1)
    rv = mpl * s * (thd * thd + k_centrifugal * om * om) + tvr
    rt = mpgl * s + mpl2 * s * c * om * om - tvk
    mplc = mpl * c
    v_dot = (jt * rv - mplc * rt) * inv_omega + d2
    theta_ddot = (mv * rt - mplc * rv) * inv_omega + d3
    return omega_dot, v_dot, theta_ddot


@numba.njit(cache=True, nogil=True)
def rk4_hold(k, x, y, phi, xv, th, om, v, thd, tau_left, tau_right, disturbance, h):
    """``len(disturbance)`` classic RK4 steps of ``h`` [s], wheel torques held.

    ``k``: the constants of :data:`.plant._CONSTANT_NAMES`; ``disturbance``: (n, 3) array of
    (d1, d2, d3) per step, held over it. Returns the new state as an 8-tuple.
    """
    sin, cos = math.sin, math.cos
    tw = tau_right - tau_left
    tv = tau_left + tau_right
    hh, h6 = 0.5 * h, h / 6.0

    for i in range(disturbance.shape[0]):
        d1 = disturbance[i, 0]
        d2 = disturbance[i, 1]
        d3 = disturbance[i, 2]
        # Stage 1 at (th, om, v, thd, phi).
        a1o, a1v, a1t = _slopes(k, tv, tw, th, om, v, thd, d1, d2, d3)
        cp1 = cos(phi)
        sp1 = sin(phi)

        # Stage 2 at t + h/2 along stage 1's slope.
        th2 = th + hh * thd
        om2 = om + hh * a1o
        v2 = v + hh * a1v
        thd2 = thd + hh * a1t
        phi2 = phi + hh * om
        a2o, a2v, a2t = _slopes(k, tv, tw, th2, om2, v2, thd2, d1, d2, d3)
        cp2 = cos(phi2)
        sp2 = sin(phi2)

        # Stage 3 at t + h/2 along stage 2's slope.
        th3 = th + hh * thd2
        om3 = om + hh * a2o
        v3 = v + hh * a2v
        thd3 = thd + hh * a2t
        phi3 = phi + hh * om2
        a3o, a3v, a3t = _slopes(k, tv, tw, th3, om3, v3, thd3, d1, d2, d3)
        cp3 = cos(phi3)
        sp3 = sin(phi3)

        # Stage 4 at t + h along stage 3's slope.
        th4 = th + h * thd3
        om4 = om + h * a3o
        v4 = v + h * a3v
        thd4 = thd + h * a3t
        phi4 = phi + h * om3
        a4o, a4v, a4t = _slopes(k, tv, tw, th4, om4, v4, thd4, d1, d2, d3)
        cp4 = cos(phi4)
        sp4 = sin(phi4)

        x, y, phi, xv, th, om, v, thd = (
            x + h6 * (v * cp1 + 2.0 * (v2 * cp2 + v3 * cp3) + v4 * cp4),
            y + h6 * (v * sp1 + 2.0 * (v2 * sp2 + v3 * sp3) + v4 * sp4),
            phi + h6 * (om + 2.0 * (om2 + om3) + om4),
            xv + h6 * (v + 2.0 * (v2 + v3) + v4),
            th + h6 * (thd + 2.0 * (thd2 + thd3) + thd4),
            om + h6 * (a1o + 2.0 * (a2o + a3o) + a4o),
            v + h6 * (a1v + 2.0 * (a2v + a3v) + a4v),
            thd + h6 * (a1t + 2.0 * (a2t + a3t) + a4t))
    return x, y, phi, xv, th, om, v, thd


def warm_up(constant_count: int) -> None:
    """Load or compile :func:`rk4_hold` (about 1 s when compiling; once per process).

    Zero steps: compiles (types only) without evaluating the dynamics.
    """
    rk4_hold((1.0,) * constant_count, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
             0.0, 0.0, np.zeros((0, 3)), 1e-3)
