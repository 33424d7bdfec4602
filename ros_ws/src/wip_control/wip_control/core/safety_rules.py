"""The safety layer's rules as numbers: which conditions hold at a tick, and the torque sent.

Pure Python on the monitor's state array (``SafetyMonitor.numbers``, the slots below) and
its constants (:func:`constants`), written so that numba compiles the same functions
(``register_jitable``, ``safety_kernel.py``): the interpreter and the kernel decide by one
text of the rules. :func:`condition_codes` gives each condition as a bit, in the order in
which the monitor lists their reasons (``safety_texts.py`` writes them); the state machine
and the reasons: ``safety.py`` and docs/decisions/safety-layer.md.

Not part of the paper [1]_.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import math

from . import runaway
from .eso import StateEstimate
from .position import FAULT as POSITION_FAULT, NO_FIX
from .safety_config import lateness_code, LATE_CODE, STALE_CODE, TIME_TOLERANCE

#: The states, by their code in the state array (``STATES[code]``).
STARTING, ACTIVE, DEGRADED, SHADOW, FAULT, ESTOP = (
    'STARTING', 'ACTIVE', 'DEGRADED', 'SHADOW', 'FAULT', 'ESTOP')
STATES = (STARTING, ACTIVE, DEGRADED, SHADOW, FAULT, ESTOP)
STARTING_CODE, ACTIVE_CODE, DEGRADED_CODE, SHADOW_CODE, FAULT_CODE, ESTOP_CODE = range(6)

#: What the compiled tick did (``safety_kernel.tick``): left the tick to the interpreter
#: (having stepped the runaway guard or not), took it, or found a runaway (the guard
#: stepped, its verdict to be worded: the rest is the interpreter's).
TICK_LEFT, TICK_TAKEN, RUNAWAY_FOUND = 0, 1, 2

#: The watched inputs, by their index in the state array's per-input slots.
ESTIMATE, YAW_TORQUE, DRIVE_TORQUE, ESTOP_INPUT = ('state_estimate', 'yaw_torque',
                                                   'drive_torque', 'estop')
INPUTS = (ESTIMATE, YAW_TORQUE, DRIVE_TORQUE, ESTOP_INPUT)
ESTIMATE_INDEX, YAW_INDEX, DRIVE_INDEX, ESTOP_INDEX = range(4)

#: Statuses of a drive torque: the values of the ``wip_msgs/DriveTorque`` constants.
SOLVED, FALLBACK_SHIFTED_PLAN, FAILED_ZERO, INPUT_INVALID, NOT_READY = range(5)

#: The slots of the monitor's state array. NaN stands for "none yet" in the times.
(TICKS, LAST_UPDATE, STATE, READY_SINCE, TAU_LEFT, TAU_RIGHT, SETTLED, POSITION_STATUS,
 CONSECUTIVE_FALLBACKS, ESTOP_LATCHED, FAULT_LATCHED, WIRING, RUNAWAY, HEARTBEAT_AT,
 YAW_TAU, DRIVE_TAU, DRIVE_STATUS, PLAN_PERIOD, PLAN_LENGTH) = range(19)
# The runaway guard's inputs: the estimate's planar position, the reference's and whether
# it is new since the guard's step, and the estimate's arrival at that step.
POSE_X, POSE_Y, REFERENCE_X, REFERENCE_Y, REFERENCE_FRESH, GUARD_ESTIMATE_TIME = range(19, 25)
ARRIVAL = 25          # 4 slots, one per input: when its last valid value arrived [s]
INVALID = 29          # 4 slots: 1 when its last message was unusable
ESTIMATE_VALUES = 33  # the last valid estimate, in StateEstimate's field order
SIZE = ESTIMATE_VALUES + len(StateEstimate._fields)

#: The estimate values whose bound is a divergence of the observer, in the order of the
#: reasons, with the name of their bound among the constants.
DIVERGENCE_CHECKS = (('v', 'max_speed_estimate'), ('omega', 'max_yaw_rate_estimate'),
                     ('theta_dot', 'max_tilt_rate_estimate'),
                     ('f1', 'max_yaw_disturbance_estimate'),
                     ('f2', 'max_longitudinal_disturbance_estimate'),
                     ('f3', 'max_tilt_disturbance_estimate'))
_DIVERGENCE_SLOTS = tuple(ESTIMATE_VALUES + StateEstimate._fields.index(field)
                          for field, _ in DIVERGENCE_CHECKS)
_THETA_SLOT = ESTIMATE_VALUES + StateEstimate._fields.index('theta')
_PHI_SLOT = ESTIMATE_VALUES + StateEstimate._fields.index('phi')
_V_SLOT = ESTIMATE_VALUES + StateEstimate._fields.index('v')

#: The slots of the constants array (:func:`constants`).
MAX_AGE = 0           # 4 slots, one per input
(BRIDGE, FALL_THRESHOLD) = (4, 5)
BOUNDS = 6            # 6 slots, DIVERGENCE_CHECKS' bounds
(MAX_MPC_FALLBACKS, TIMING_CHECKS, SHADOW_MODE, WATCH_LINK, MAX_WHEEL_TORQUE,
 MAX_WHEEL_TORQUE_RATE, GUARD_ENABLED) = range(12, 19)
CONSTANTS = 19

#: The conditions' bits (:func:`condition_codes`), in the order of the reasons.
WIRING_BIT, RUNAWAY_BIT = 0, 1
INPUT_BITS = 2        # 4 per input: invalid, missing, late, stale
INVALID_BIT, MISSING_BIT, LATE_BIT, STALE_BIT = range(4)
FALLEN_BIT = INPUT_BITS + 4 * len(INPUTS)
DIVERGED_BITS = FALLEN_BIT + 1     # one per DIVERGENCE_CHECKS
(NOT_SETTLED_BIT, POSITION_FAULT_BIT, NO_FIX_BIT, MPC_NOT_READY_BIT, MPC_FALLBACKS_BIT,
 MPC_FAILED_BIT, MPC_UNKNOWN_BIT, STALLED_BIT) = range(DIVERGED_BITS + 6,
                                                        DIVERGED_BITS + 14)


def constants(config, max_wheel_torque: float, max_wheel_torque_rate: float,
              timing_checks: bool, guard_enabled: bool) -> list[float]:
    """Return the constants (the slots above) of a ``SafetyParams``, the limits, the guard's."""
    return [config.max_estimate_age, config.max_yaw_torque_age, config.max_drive_torque_age,
            config.max_estop_age, config.bridge_time, config.fall_threshold,
            *(getattr(config, bound) for _, bound in DIVERGENCE_CHECKS),
            float(config.max_mpc_fallbacks), float(timing_checks), float(config.shadow_mode),
            float(config.max_estop_age > 0.0), max_wheel_torque, max_wheel_torque_rate,
            float(guard_enabled)]


def guard_due(n, c) -> bool:
    """Whether the runaway guard takes a step now: a new valid estimate and a new reference.

    Not once it has found a runaway (latched), nor twice on one estimate (a watchdog tick).
    """
    arrival = n[ARRIVAL + ESTIMATE_INDEX]
    return (c[GUARD_ENABLED] != 0.0 and n[RUNAWAY] == 0.0 and n[REFERENCE_FRESH] != 0.0
            and not math.isnan(arrival) and n[INVALID + ESTIMATE_INDEX] == 0.0
            and arrival != n[GUARD_ESTIMATE_TIME])


def step_guard(n, guard_state, guard_history, guard_constants) -> int:
    """Feed the runaway guard the newest estimate and reference (``runaway.guard_step``).

    Return its verdict. The guard's history must have room (``RunawayGuard.make_room``).
    """
    arrival = float(n[ARRIVAL + ESTIMATE_INDEX])
    n[REFERENCE_FRESH] = 0.0
    n[GUARD_ESTIMATE_TIME] = arrival
    return runaway.guard_step(guard_state, guard_history, guard_constants, arrival,
                              float(n[POSE_X]), float(n[POSE_Y]), float(n[_PHI_SLOT]),
                              float(n[_V_SLOT]), float(n[REFERENCE_X]),
                              float(n[REFERENCE_Y]))


def condition_codes(now: float, dt: float, ticks: float, n, c) -> int:
    """Return the conditions that hold at ``now`` [s], one bit each (0: none).

    ``dt``: the time since the last tick [s]; ``ticks``: this tick's count (from 1); ``n``,
    ``c``: the state and the constants.
    """
    codes = 0
    if n[WIRING] != 0.0:    # a wiring verdict first: a fall that follows is its effect
        codes |= 1 << WIRING_BIT
    if n[RUNAWAY] != 0.0:
        codes |= 1 << RUNAWAY_BIT
    timing = c[TIMING_CHECKS] != 0.0
    for i in range(4 if c[WATCH_LINK] != 0.0 else 3):
        arrival = n[ARRIVAL + i]
        if i == ESTOP_INDEX and not math.isnan(n[HEARTBEAT_AT]):
            # The link is alive if either the heartbeat or an e-stop message came.
            arrival = max(n[HEARTBEAT_AT], -math.inf if math.isnan(arrival) else arrival)
        bit = INPUT_BITS + 4 * i
        if n[INVALID + i] != 0.0:
            codes |= 1 << (bit + INVALID_BIT)
        elif math.isnan(arrival):
            if timing or i == YAW_INDEX or i == DRIVE_INDEX:
                codes |= 1 << (bit + MISSING_BIT)
        elif timing:
            verdict = lateness_code(now - arrival, c[MAX_AGE + i],
                                    c[BRIDGE] if i != ESTOP_INDEX else 0.0)
            if verdict == LATE_CODE:
                codes |= 1 << (bit + LATE_BIT)
            elif verdict == STALE_CODE:
                codes |= 1 << (bit + STALE_BIT)
    if not math.isnan(n[ARRIVAL + ESTIMATE_INDEX]) and n[INVALID + ESTIMATE_INDEX] == 0.0:
        codes |= _estimate_codes(n, c, timing)
    if not math.isnan(n[ARRIVAL + DRIVE_INDEX]) and n[INVALID + DRIVE_INDEX] == 0.0:
        codes |= _drive_codes(n, c)
    # The layer itself not run for longer than the bridge covers (its process frozen or
    # starved): the base held the last command that long, blind.
    if timing and ticks > 1 and dt > c[MAX_AGE + ESTIMATE_INDEX] + c[BRIDGE] + TIME_TOLERANCE:
        codes |= 1 << STALLED_BIT
    return codes


def _estimate_codes(n, c, timing: bool) -> int:
    """Return the conditions of a valid estimate: fall, divergence, not settled, no fix."""
    codes = 0
    if abs(n[_THETA_SLOT]) > c[FALL_THRESHOLD]:
        codes |= 1 << FALLEN_BIT
    for j in range(len(_DIVERGENCE_SLOTS)):
        if abs(n[_DIVERGENCE_SLOTS[j]]) > c[BOUNDS + j]:
            codes |= 1 << (DIVERGED_BITS + j)
    if timing and n[SETTLED] == 0.0:
        codes |= 1 << NOT_SETTLED_BIT
    if timing and n[POSITION_STATUS] == POSITION_FAULT:
        codes |= 1 << POSITION_FAULT_BIT
    elif timing and n[POSITION_STATUS] == NO_FIX:
        codes |= 1 << NO_FIX_BIT
    return codes


def _drive_codes(n, c) -> int:
    """Return the condition of the MPC's status: not ready, too many fallbacks, failed."""
    status = n[DRIVE_STATUS]
    if status == NOT_READY:
        return 1 << MPC_NOT_READY_BIT
    if status == FALLBACK_SHIFTED_PLAN:
        return 1 << MPC_FALLBACKS_BIT if n[CONSECUTIVE_FALLBACKS] > c[MAX_MPC_FALLBACKS] else 0
    if status == FAILED_ZERO or status == INPUT_INVALID:
        return 1 << MPC_FAILED_BIT
    return 0 if status == SOLVED else 1 << MPC_UNKNOWN_BIT


def drive_torque_now(now: float, n, plan) -> float:
    """τυ of the MPC's last output at ``now``.

    Its plan's entry for the periods elapsed since it arrived (the last entry after the
    plan), or τυ itself without a plan.
    """
    length = n[PLAN_LENGTH]
    if length == 0.0:
        return n[DRIVE_TAU]
    elapsed = max(0.0, now - n[ARRIVAL + DRIVE_INDEX])
    k = elapsed / n[PLAN_PERIOD] + TIME_TOLERANCE
    return plan[int(length) - 1 if k >= length - 1.0 else int(k)]


def toward(previous: float, target: float, step: float) -> float:
    """``target`` if within ``step`` of ``previous`` (exactly), else previous ± step."""
    if abs(target - previous) <= step:
        return target
    return previous + math.copysign(step, target - previous)
