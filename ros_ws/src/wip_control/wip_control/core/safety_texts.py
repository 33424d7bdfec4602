"""The reasons of the safety layer's conditions, one line each, from their bits.

``safety_rules.condition_codes`` decides which conditions hold; this module says each of
them in words, with its figures, in the order of the bits: (faults, not-yet conditions,
late inputs within the bridge). Made only for a tick that has a condition.
"""

from __future__ import annotations

import math

from .safety_rules import (ARRIVAL, BRIDGE, CONSECUTIVE_FALLBACKS, DIVERGED_BITS,
                           DIVERGENCE_CHECKS, DRIVE_STATUS, ESTIMATE_VALUES, ESTOP_INDEX,
                           FAILED_ZERO, FALLEN_BIT, HEARTBEAT_AT, INPUT_BITS, INPUT_INVALID,
                           INPUTS, INVALID_BIT, LATE_BIT, MAX_AGE, MISSING_BIT,
                           MPC_FAILED_BIT, MPC_FALLBACKS_BIT, MPC_NOT_READY_BIT,
                           MPC_UNKNOWN_BIT, NO_FIX_BIT, NOT_SETTLED_BIT,
                           POSITION_FAULT_BIT, RUNAWAY_BIT, STALE_BIT, STALLED_BIT,
                           WIRING_BIT)
from .eso import StateEstimate

_LINK = 'heartbeat (/wip/heartbeat or /wip/estop)'
#: Each divergence check's label and unit in its reason, in DIVERGENCE_CHECKS' order.
_DIVERGENCE_LABELS = (('v_hat', 'm/s'), ('omega_hat', 'rad/s'), ('theta_dot_hat', 'rad/s'),
                      ('f1_hat', 'rad/s^2'), ('f2_hat', 'm/s^2'), ('f3_hat', 'rad/s^2'))
_FIELD = {name: ESTIMATE_VALUES + i for i, name in enumerate(StateEstimate._fields)}
_STATUS_NAMES = {FAILED_ZERO: 'FAILED_ZERO', INPUT_INVALID: 'INPUT_INVALID'}


def condition_texts(monitor, codes: int, now: float, dt: float, n: list[float],
                    c: list[float]) -> tuple[list[str], list[str], list[str]]:
    """(faults, not-yet conditions, late inputs within the bridge) of ``codes`` at ``now``.

    ``monitor``: the ``SafetyMonitor`` (its verdict texts, invalid reasons, config); ``n``,
    ``c``: its state and constants as floats; ``dt`` [s]: the time since its last tick.
    """
    faults: list[str] = []
    waiting: list[str] = []
    late: list[str] = []
    if codes >> WIRING_BIT & 1:
        faults.append(monitor.wiring)
    if codes >> RUNAWAY_BIT & 1:
        faults.append(monitor.runaway + ' (latched: reset required)')
    for i, name in enumerate(INPUTS):
        bits = codes >> (INPUT_BITS + 4 * i) & 0b1111
        if not bits:
            continue
        label = _LINK if i == ESTOP_INDEX else name
        arrival = n[ARRIVAL + i]
        if i == ESTOP_INDEX and not math.isnan(n[HEARTBEAT_AT]):
            arrival = max(n[HEARTBEAT_AT], -math.inf if math.isnan(arrival) else arrival)
        max_age, bridge = c[MAX_AGE + i], (c[BRIDGE] if i != ESTOP_INDEX else 0.0)
        if bits >> INVALID_BIT & 1:
            faults.append(f'{name} invalid: {monitor.invalid_reasons[i]}')
        elif bits >> MISSING_BIT & 1:
            waiting.append(f'no {label} yet')
        elif bits >> LATE_BIT & 1:
            late.append(f'{name} late: {now - arrival:.3f} s old > {max_age:g} s, '
                        f'bridged up to {max_age + bridge:g} s')
        elif bits >> STALE_BIT & 1:
            faults.append(f'{label} stale: {now - arrival:.3f} s old > '
                          f'{max_age + bridge:g} s (age limit {max_age:g} s + bridge '
                          f'{bridge:g} s; publisher stopped?)')
    _estimate_texts(monitor.config, codes, n, faults, waiting)
    _drive_texts(monitor.config, codes, n, faults, waiting)
    if codes >> STALLED_BIT & 1:
        bound = monitor.config.max_estimate_age + monitor.config.bridge_time
        faults.append(f'stalled: no safety tick for {dt:.3f} s > {bound:g} s (estimate age '
                      'limit + bridge; this process was not scheduled)')
    return faults, waiting, late


def _estimate_texts(config, codes: int, n: list[float], faults: list[str],
                    waiting: list[str]) -> None:
    if codes >> FALLEN_BIT & 1:
        faults.append(f'fallen: |theta_hat| {abs(n[_FIELD["theta"]]):.3f} rad > '
                      f'fall_threshold {config.fall_threshold:g} rad')
    for j, ((field, bound), (label, unit)) in enumerate(zip(DIVERGENCE_CHECKS,
                                                            _DIVERGENCE_LABELS)):
        if codes >> (DIVERGED_BITS + j) & 1:
            faults.append(f'ESO diverged: |{label}| {abs(n[_FIELD[field]]):.4g} {unit} > '
                          f'{getattr(config, bound):g}')
    if codes >> NOT_SETTLED_BIT & 1:
        waiting.append('ESO not settled')
    if codes >> POSITION_FAULT_BIT & 1:
        faults.append('position source refused by the ESO (its /diagnostics says why): '
                      'check datum.* and position_source')
    elif codes >> NO_FIX_BIT & 1:
        waiting.append('no position fix yet (position_source gps or odometry; without GPS '
                       'set position_source: wheels)')


def _drive_texts(config, codes: int, n: list[float], faults: list[str],
                 waiting: list[str]) -> None:
    status = int(n[DRIVE_STATUS])
    if codes >> MPC_NOT_READY_BIT & 1:
        waiting.append('MPC not ready (NOT_READY)')
    elif codes >> MPC_FALLBACKS_BIT & 1:
        faults.append(f'MPC failed: {int(n[CONSECUTIVE_FALLBACKS])} consecutive '
                      f'FALLBACK_SHIFTED_PLAN outputs > {config.max_mpc_fallbacks}')
    elif codes >> MPC_FAILED_BIT & 1:
        faults.append(f'MPC failed: status {_STATUS_NAMES[status]}')
    elif codes >> MPC_UNKNOWN_BIT & 1:
        faults.append(f'MPC failed: unknown status {status}')
