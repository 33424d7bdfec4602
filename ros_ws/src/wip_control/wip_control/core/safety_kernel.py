"""The safety layer's steady tick, compiled with numba (``cache=True``).

:meth:`SafetyMonitor.update <.safety.SafetyMonitor.update>` decides, every control tick,
which of some thirty conditions hold, the state, and the wheel torques: lists, texts and
about a hundred attribute reads in the interpreter, though nearly every tick of a healthy
robot has no condition at all. Compiled, that tick is one call on the monitor's state array
(``SafetyMonitor.numbers``), so the interpreter and the kernel share one state and either
may take the next tick.

Nothing is written twice: numba compiles the rules themselves
(``safety_rules.condition_codes``, ``drive_torque_now``, ``toward``, ``mixer.mixed``;
``register_jitable``). The kernel takes only the steady tick: a torque state (ACTIVE,
DEGRADED or SHADOW), no e-stop or fault latched, and no condition; the state then stays
ACTIVE (SHADOW in shadow mode) and the mix (24), rate limited, is sent. Anything else, it
returns before changing a thing, and the interpreter takes the tick (and writes the
reasons). The runaway guard steps before either (``SafetyMonitor._guard_step``).

numba's cache knows only this file's date, not theirs: :func:`warm_up` compiles afresh when
a digest of the sources differs from the one kept beside the cache, and
:meth:`SafetyMonitor.use_compiled <.safety.SafetyMonitor.use_compiled>` compares the kernel
with the interpreter (:func:`difference`) before using it.
"""

from __future__ import annotations

import math
from typing import Callable

import numba
import numpy as np
from numba.extending import register_jitable

from . import (compiled, eso, mixer, numba_math, position, runaway, safety_config,
               safety_rules)
from .safety_rules import (ACTIVE_CODE, DEGRADED_CODE, ESTOP_LATCHED, FAULT_LATCHED,
                           LAST_UPDATE, MAX_WHEEL_TORQUE, MAX_WHEEL_TORQUE_RATE, READY_SINCE,
                           RUNAWAY_FOUND, SHADOW_CODE, SHADOW_MODE, STATE, TAU_LEFT,
                           TAU_RIGHT, TICK_LEFT, TICK_TAKEN, TICKS, TIMING_CHECKS, YAW_TAU)

#: The interpreter's functions the kernel compiles; their files make its sources' digest.
COMPILED_FUNCTIONS = (safety_config.lateness_code, safety_rules.condition_codes,
                      safety_rules._estimate_codes, safety_rules._drive_codes,
                      safety_rules.drive_torque_now, safety_rules.toward,
                      safety_rules.guard_due, safety_rules.step_guard, mixer.mixable,
                      mixer.mixed, runaway.guard_step, runaway._norm, runaway._push,
                      runaway._growth, runaway._absurd)
for _function in COMPILED_FUNCTIONS:
    register_jitable(_function)
#: Modules whose constants the rules read (the estimate's field order, the position
#: statuses) or whose code it compiles too (math.remainder): in the digest.
ALSO_COMPILED = (eso, position, numba_math)

#: What :func:`tick` returns for a tick it leaves to the interpreter.
_LEFT = (TICK_LEFT, math.nan, math.nan)
_ARRAY = numba.float64[::1]
#: One signature, compiled once: arguments of another type are converted (an int time) or
#: refused, never compiled anew in a control tick.
_SIGNATURE = numba.types.Tuple((numba.int64, numba.float64, numba.float64))(
    numba.float64, *(_ARRAY,) * 6)


@numba.njit(_SIGNATURE, cache=True, nogil=True, boundscheck=True)
def tick(now, n, c, plan, guard_state, guard_history, guard_constants):
    """Take the steady tick at ``now`` [s] on the state ``n`` in place: (TICK_TAKEN, τl, τr).

    ``c``: the constants (``safety_rules.constants``); ``plan``: the MPC's planned τυ; the
    runaway guard's state, history and constants (``RunawayGuard``). Or (TICK_LEFT, …):
    the interpreter's tick (the guard may have stepped), (RUNAWAY_FOUND, …): the guard
    found a runaway, the interpreter words it and takes the tick.
    """
    state = n[STATE]
    if (not (state == ACTIVE_CODE or state == DEGRADED_CODE or state == SHADOW_CODE)
            or n[ESTOP_LATCHED] != 0.0 or n[FAULT_LATCHED] != 0.0
            or math.isnan(n[LAST_UPDATE]) or not math.isfinite(now)):
        return _LEFT
    # SafetyMonitor.update: the runaway guard first (a torque state, real time).
    if c[TIMING_CHECKS] != 0.0 and safety_rules.guard_due(n, c):
        if guard_state[runaway.COUNT] * runaway.HISTORY_FIELDS >= len(guard_history):
            return _LEFT    # its history full: the interpreter makes room
        if safety_rules.step_guard(n, guard_state, guard_history, guard_constants) != 0:
            return (RUNAWAY_FOUND, math.nan, math.nan)
    dt = max(0.0, now - n[LAST_UPDATE])
    ticks = n[TICKS] + 1.0
    if safety_rules.condition_codes(now, dt, ticks, n, c) != 0:
        return _LEFT
    tau_v = safety_rules.drive_torque_now(now, n, plan)
    tau_omega = n[YAW_TAU]
    if not mixer.mixable(tau_v, tau_omega, c[MAX_WHEEL_TORQUE]):
        return _LEFT
    left, right = mixer.mixed(tau_v, tau_omega, c[MAX_WHEEL_TORQUE])
    step = c[MAX_WHEEL_TORQUE_RATE] * dt
    tau_left = safety_rules.toward(n[TAU_LEFT], left, step)
    tau_right = safety_rules.toward(n[TAU_RIGHT], right, step)
    n[TICKS] = ticks
    n[LAST_UPDATE] = now
    n[STATE] = SHADOW_CODE if c[SHADOW_MODE] != 0.0 else ACTIVE_CODE
    n[READY_SINCE] = math.nan
    n[TAU_LEFT] = tau_left
    n[TAU_RIGHT] = tau_right
    return (TICK_TAKEN, tau_left, tau_right)


def difference(make_monitor: Callable) -> str:
    """Where :func:`tick` differs from the interpreter on a made-up drive ('' nowhere).

    Two monitors of ``make_monitor()`` are driven alike, one with the kernel, through
    engaging, the plan followed and the rate limit, a late input bridged and one stale,
    a fault and its recovery: every decision and state array compared to the bit.
    """
    pair = [make_monitor(), make_monitor()]
    pair[0]._kernel = tick
    for k in range(500):
        decisions = [_drive(monitor, k) for monitor in pair]
        if decisions[0] != decisions[1] or (pair[0].numbers.tobytes()
                                            != pair[1].numbers.tobytes()):
            return f'at tick {k}: {decisions[0]} != {decisions[1]}'
    return ''


def _drive(monitor, k: int):
    """Feed ``monitor`` the inputs of tick ``k`` of :func:`difference`'s drive, and tick it."""
    period = monitor.period
    t = 100.0 + k * period
    late = 150 <= k < 150 + int(round(0.1 / period))      # the yaw torque 0.1 s late
    stale = 250 <= k < 250 + int(round(0.5 / period))     # the estimate 0.5 s late: stale
    wave = math.sin(0.05 * k)
    if not stale:
        monitor.estimate(t, (0.1 * wave, 0.2, 0.01, 0.3, 0.4 * wave, -0.2, 0.02 * wave, 0.1,
                             0.3, 0.0), True, 0, 0.01 * k, 0.0)
        monitor.reference(t, 0.01 * k, 0.0)
    if not late:
        monitor.yaw_torque(t, 0.3 * wave)
    if k % 20 == 0:
        plan = [5.0 * wave + 0.7 * j for j in range(10)]
        monitor.drive_torque(t, plan[0], 0, plan, 4 * period)   # followed past its end
    monitor.heartbeat(t)
    if k % 40 == 0:
        monitor.estop(t, False)
    return monitor.update(t + 0.25 * period)


def warm_up() -> None:
    """Load :func:`tick` from numba's cache (or compile it).

    Compiled afresh if the sources it compiles changed since numba's cache was filled
    (:data:`SOURCES_STAMP` beside the cache holds their digest).
    """
    tick(0.0, np.zeros(safety_rules.SIZE), np.zeros(safety_rules.CONSTANTS), np.zeros(0),
         np.zeros(runaway.STATE_SIZE), np.zeros(runaway.HISTORY_FIELDS), np.zeros(7))
    compiled.refresh_if_sources_changed(tick.stats.cache_path, SOURCES_STAMP, sources_digest(),
                                        refresh)


#: The file beside numba's cache with the digest of the sources the kernel was compiled from.
SOURCES_STAMP = 'safety_kernel.sources'


def sources_digest() -> str:
    """SHA-256 of the files whose functions or constants the kernel compiles, and of this one."""
    return compiled.sources_digest(COMPILED_FUNCTIONS, __name__, ALSO_COMPILED)


def refresh() -> None:
    """Compile :func:`tick` afresh, replacing numba's cache of it (stale, say)."""
    tick.recompile()
