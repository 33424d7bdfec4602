"""The time-scaled sample of a closed-form curve, compiled with numba (``cache=True``).

A node in real time samples the time-scaled reference at sensor stamps, off any grid, so
:class:`~.time_scaling.TimeScaled` cannot remember its states and re-times two or three
curve samples per call: about fifteen Python calls, which cost several times more inside the
control tick than alone (the tick's working set evicts them). Compiled, the call is one; on
a time grid (the in-process runner, lockstep) it also costs less than remembering states.

Nothing is written twice: numba compiles the module functions of ``retiming`` and
``reference_curves`` themselves (``register_jitable``), and :func:`sample` composes them as
``TimeScaled._interpreted_sample`` does (tests check the two agree to the bit). numba's
cache knows only this file's date, not theirs: :func:`warm_up` compiles afresh when a digest
of the three files differs from the one kept beside the cache, and
:meth:`TimeScaled.use_compiled` compares the kernel with the interpreted sample before using
it, compiles it afresh once (:func:`refresh`) if they differ, and samples interpreted if
they still do.
"""

from __future__ import annotations

import numba
import numpy as np
from numba.extending import register_jitable

from . import compiled
from . import reference_curves as curves
from . import retiming

#: The interpreter's functions the kernel compiles; their files make its sources' digest.
COMPILED_FUNCTIONS = (retiming.hermite_progress, retiming.interpolated_sigma,
                      retiming.interpolated_rate, retiming.raw_rate, retiming.retimed_state,
                      retiming.retimed_speed, retiming.speeding_up,
                      curves.state_from_derivatives,
                      curves.speed_and_yaw_rate_from_derivatives,
                      curves.trifolium_derivatives, curves.trifolium_state,
                      curves.trifolium_speed_and_yaw_rate, curves.circle_state,
                      curves.circle_speed_and_yaw_rate, curves.line_state,
                      curves.line_speed_and_yaw_rate, curves.figure_eight_derivatives,
                      curves.figure_eight_state, curves.figure_eight_speed_and_yaw_rate)
for _function in COMPILED_FUNCTIONS:
    register_jitable(_function)

#: The curves by ``KERNEL_KIND``; a curve's parameters are its ``parameters`` as an array.
TRIFOLIUM, CIRCLE, LINE, FIGURE_EIGHT = (curves.Trifolium.KERNEL_KIND,
                                         curves.Circle.KERNEL_KIND,
                                         curves.StraightLine.KERNEL_KIND,
                                         curves.FigureEight.KERNEL_KIND)


@register_jitable
def _curve_state(kind, p, t):
    if kind == TRIFOLIUM:
        return curves.trifolium_state(p, t)
    if kind == CIRCLE:
        return curves.circle_state(p, t)
    if kind == LINE:
        return curves.line_state(p, t)
    return curves.figure_eight_state(p, t)


# The dispatch of _curve_state again, on purpose: the lead's speeds need no pose (its
# trigonometry), as Reference.speed_and_yaw_rate says.
@register_jitable
def _curve_speed(kind, p, t):
    if kind == TRIFOLIUM:
        return curves.trifolium_speed_and_yaw_rate(p, t)
    if kind == CIRCLE:
        return curves.circle_speed_and_yaw_rate(p, t)
    if kind == LINE:
        return curves.line_speed_and_yaw_rate(p, t)
    return curves.figure_eight_speed_and_yaw_rate(p, t)


@register_jitable
def _speed_at(t, h, s_nodes, rate_nodes, sigma_nodes, max_speed, max_yaw_rate, kind, p):
    s = retiming.hermite_progress(t, h, s_nodes, rate_nodes)
    v, omega = _curve_speed(kind, p, s)
    return retiming.retimed_speed(v, omega, retiming.interpolated_rate(s, h, sigma_nodes),
                                  max_speed, max_yaw_rate)


# boundscheck: a node beyond the tables raises IndexError instead of reading memory.
@numba.njit(cache=True, nogil=True, boundscheck=True)
def sample(t, lead, lead_accelerating, h, s_nodes, rate_nodes, sigma_nodes, max_speed,
           max_yaw_rate, kind, p):
    """``TimeScaled._interpreted_sample(t)`` of a curve ``kind`` with parameters ``p``.

    The tables must reach t + either lead (``TimeScaled._cover``).
    """
    s = retiming.hermite_progress(t, h, s_nodes, rate_nodes)
    x, y, phi, v, omega, omega_dot = _curve_state(kind, p, s)
    sigma, d_sigma = retiming.interpolated_sigma(s, h, sigma_nodes)
    x, y, phi, v, omega, omega_dot = retiming.retimed_state(
        x, y, phi, v, omega, omega_dot, sigma, d_sigma, max_speed, max_yaw_rate)
    v_ahead = _speed_at(t + lead, h, s_nodes, rate_nodes, sigma_nodes, max_speed,
                        max_yaw_rate, kind, p)
    if retiming.speeding_up(v_ahead, v, lead, lead_accelerating):
        v_ahead = _speed_at(t + lead_accelerating, h, s_nodes, rate_nodes, sigma_nodes,
                            max_speed, max_yaw_rate, kind, p)
    return x, y, phi, v_ahead, omega, omega_dot


def warm_up() -> None:
    """Load the kernel from numba's cache (or compile it) for every curve at once.

    Compiled afresh if the sources it compiles changed since numba's cache was filled
    (:data:`SOURCES_STAMP` beside the cache holds their digest).
    """
    nodes = np.array([0.0, 0.01, 0.02])
    for kind in (TRIFOLIUM, CIRCLE, LINE, FIGURE_EIGHT):
        sample(0.005, 0.0, 0.0, 0.01, nodes, np.ones(3), np.ones(3), 1.0, 1.0, kind,
               np.ones(7))
    compiled.refresh_if_sources_changed(sample.stats.cache_path, SOURCES_STAMP,
                                        sources_digest(), refresh)


#: The file beside numba's cache with the digest of the sources the kernel was compiled from.
SOURCES_STAMP = 'retiming_kernel.sources'


def sources_digest() -> str:
    """SHA-256 of the files whose functions the kernel compiles, and of this one."""
    return compiled.sources_digest(COMPILED_FUNCTIONS, __name__)


def refresh() -> None:
    """Compile :func:`sample` afresh, replacing numba's cache of it (stale, say)."""
    sample.recompile()
