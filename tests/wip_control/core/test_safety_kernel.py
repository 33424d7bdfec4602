"""The safety layer's compiled steady tick (core/safety_kernel.py) against the interpreter.

Two monitors of the same settings take the same random inputs, one of them with the
kernel: every decision (torques, state, reasons) and every state array must be the same to
the bit, tick by tick, through every condition the monitor knows (late, stale, missing and
invalid inputs, fall and divergence, the MPC's statuses and fallbacks, the e-stop and its
reset, a wiring verdict, stalls, no fix); and the kernel must have taken the steady ticks.
"""

import math

import numpy as np
import pytest

from safety_harness import H, RATE, TAU_MAX
from wip_control.core import safety_kernel
from wip_control.core.runaway import RunawayParams
from wip_control.core.safety import ACTIVE, DriveStatus, SafetyMonitor, SHADOW
from wip_control.core.safety_config import SafetyParams
from wip_control.core.safety_rules import RUNAWAY_FOUND, TICK_TAKEN

CONFIGS = {
    'defaults': SafetyParams(),
    'heartbeat required, faults latched': SafetyParams(max_estop_age=0.1, latch_faults=True),
    'shadow mode, no bridge': SafetyParams(shadow_mode=True, bridge_time=0.0),
}


def _compiled_and_counted(monitor) -> list[int]:
    """Give ``monitor`` the compiled tick; return the list of what each of its calls did."""
    assert monitor.use_compiled() == ''
    statuses = []
    kernel = monitor._kernel

    def counted(*args):
        out = kernel(*args)
        statuses.append(out[0])
        return out
    monitor._kernel = counted
    return statuses


def _random_inputs(monitor, rng, t, k):
    """Feed ``monitor`` one tick's inputs: mostly a healthy graph, now and then not."""
    roll = rng.uniform(size=13)
    if roll[12] < 0.9:                  # the reference: 15 m off for a while (a runaway)
        monitor.reference(t, 15.0 if k % 1500 > 1000 else 0.0, 0.0)
    if roll[0] > 0.01:                  # the estimate, sometimes absurd or fallen
        values = rng.normal(scale=0.05, size=10)
        if roll[1] < 0.002:
            values[6] = 0.5             # θ̂ beyond the fall threshold
        if roll[1] > 0.998:
            values[4] = 9.0             # υ̂ beyond its bound: a diverged observer
        if roll[2] < 0.002:
            values[0] = math.nan        # invalid: refused
        status = 0 if roll[3] > 0.003 else int(rng.integers(1, 4))   # tracking or not
        monitor.estimate(t, values, roll[4] > 0.003, status, 0.001 * (k % 1500), 0.0)
    if roll[5] > 0.01:
        monitor.yaw_torque(t, rng.normal(scale=2.0) if roll[6] > 0.002 else math.inf)
    if roll[7] < 0.1:                   # the MPC: a plan, mostly solved
        status = DriveStatus.SOLVED if roll[8] > 0.05 else int(rng.integers(1, 6))
        plan = list(rng.normal(scale=10.0, size=int(rng.integers(0, 12))))
        monitor.drive_torque(t, rng.normal(scale=10.0), status, plan,
                             H * int(rng.integers(1, 25)))
    if roll[9] > 0.02:
        monitor.heartbeat(t)
    if roll[10] < 0.001:
        monitor.estop(t, True)
    elif roll[10] < 0.02:
        monitor.estop(t, False)         # released (or never engaged): a reset may follow
    if roll[10] > 0.9995:
        monitor.wiring_fault('wiring: a wheel backwards')
    if roll[11] < 0.02:
        monitor.reset(t)


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('timing_checks', [True, False], ids=['real time', 'lockstep'])
@pytest.mark.parametrize('config', list(CONFIGS.values()), ids=list(CONFIGS))
def test_the_kernel_decides_every_tick_as_the_interpreter_to_the_bit(config, timing_checks,
                                                                      seed):
    pair = [SafetyMonitor(config, TAU_MAX, RATE, H, timing_checks, RunawayParams())
            for _ in range(2)]
    taken = _compiled_and_counted(pair[0])
    rngs = [np.random.default_rng(seed), np.random.default_rng(seed)]
    t = 100.0
    for k in range(3000):
        # Ticks on time, now and then late or a stall of the process (past the bridge).
        t += H * (1.0 if k % 97 else 12.0) * (1.0 if k % 1009 else 90.0)
        decisions = []
        for monitor, rng in zip(pair, rngs):
            _random_inputs(monitor, rng, t, k)
            decisions.append(monitor.update(t + 0.3 * H))
        assert decisions[0] == decisions[1], k
        for a, b in ((pair[0].numbers, pair[1].numbers),
                     (pair[0].guard.state, pair[1].guard.state),
                     (pair[0].guard.history, pair[1].guard.history)):
            assert a.tobytes() == b.tobytes(), k
    steady = taken.count(TICK_TAKEN)
    # The kernel took the steady ticks, and only those.
    print(f'kernel took {steady} of {len(taken)} ticks')
    assert steady > 100, steady
    assert steady < len(taken)


def test_a_tick_the_kernel_leaves_is_not_changed_by_it():
    monitor = SafetyMonitor(SafetyParams(), TAU_MAX, RATE, H)
    monitor.estimate(1.0, [0.0] * 10, True)
    before = monitor.numbers.tobytes()
    guard = monitor.guard
    taken, _, _ = safety_kernel.tick(1.0, monitor.numbers, monitor.constants, monitor.plan,
                                     guard.state, guard.history, guard.constants)
    assert taken == 0 and monitor.numbers.tobytes() == before    # STARTING: not its tick


def test_the_use_time_comparison_finds_a_kernel_a_last_bit_off(monkeypatch):
    tick = safety_kernel.tick

    def off_by_a_bit(now, n, c, plan, *guard):
        taken, left, right = tick(now, n, c, plan, *guard)
        return taken, left, math.nextafter(right, math.inf) if taken else right
    monkeypatch.setattr(safety_kernel, 'tick', off_by_a_bit)
    monkeypatch.setattr(safety_kernel, 'refresh', lambda: None)
    monitor = SafetyMonitor(SafetyParams(), TAU_MAX, RATE, H)
    warning = monitor.use_compiled()
    assert 'differs from the interpreted one at tick' in warning
    assert monitor._kernel is None            # interpreted, with the warning logged
    for k in range(200):                      # and it still balances as before
        t = 1.0 + k * H
        monitor.estimate(t, [0.0] * 10, True)
        monitor.yaw_torque(t, 0.5)
        monitor.drive_torque(t, 2.0)
        decision = monitor.update(t)
    assert decision.state == ACTIVE and decision.tau_right == 1.25


def test_shadow_mode_in_the_kernel_sends_nothing_and_reports_the_torques():
    monitor = SafetyMonitor(SafetyParams(shadow_mode=True, settle_time=0.0), TAU_MAX, RATE, H)
    assert monitor.use_compiled() == ''
    for k in range(3):
        t = 1.0 + k * H
        monitor.estimate(t, [0.0] * 10, True)
        monitor.yaw_torque(t, 0.5)
        monitor.drive_torque(t, 2.0)
        decision = monitor.update(t)
    assert decision.state == SHADOW and decision.command == (0.0, 0.0)
    assert (decision.tau_left, decision.tau_right) == (0.75, 1.25)


def test_the_guard_s_window_grows_in_the_kernel_as_in_the_interpreter():
    # The error grows steadily for 10 s in a 30 s window: every sample stays a candidate
    # for the window's least, more than the history's first ring holds.
    config = RunawayParams(growth_window=30.0, max_error_growth=100.0)
    pair = [SafetyMonitor(SafetyParams(settle_time=0.0), TAU_MAX, RATE, H, True, config)
            for _ in range(2)]
    assert pair[0].use_compiled() == ''
    first = len(pair[0].guard.history)
    for k in range(2000):
        t = 1.0 + k * H
        decisions = []
        for monitor in pair:
            # Driving away at 0.2 m/s by the wheels and the position alike.
            monitor.estimate(t, [0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0], True, 0,
                             0.001 * k, 0.0)
            monitor.reference(t, 0.0, 0.0)
            monitor.yaw_torque(t, 0.5)
            monitor.drive_torque(t, 2.0)
            decisions.append(monitor.update(t))
        assert decisions[0] == decisions[1], k
        assert pair[0].guard.state.tobytes() == pair[1].guard.state.tobytes(), k
    assert decisions[0].state == ACTIVE
    assert len(pair[0].guard.history) > 16 * first
    assert pair[0].guard.largest_growth == pytest.approx(0.001 * 1998, abs=0.002)
    assert pair[0].guard.history.tobytes() == pair[1].guard.history.tobytes()


@pytest.mark.parametrize('speed, offset, words', [(1.0, 0.0, 'by its own motion'),
                                                  (0.0, 15.0, 'tracking error')])
def test_a_runaway_found_in_the_kernel_is_the_interpreter_s(speed, offset, words):
    # Driving away at 1 m/s by the wheels and the position (the growth verdict), or the
    # reference 15 m off (the absurd tracking error): the same tick, text and state.
    pair = [SafetyMonitor(SafetyParams(settle_time=0.0), TAU_MAX, RATE, H, True,
                          RunawayParams()) for _ in range(2)]
    statuses = _compiled_and_counted(pair[0])
    found = []
    for k in range(1000):
        t = 1.0 + k * H
        decisions = []
        for monitor in pair:
            monitor.estimate(t, [0.0, 0.0, 0.0, 0.0, speed, 0.0, 0.0, 0.0, 0.0, 0.0], True, 0,
                             speed * k * H, 0.0)
            monitor.reference(t, offset, 0.0)
            monitor.yaw_torque(t, 0.5)
            monitor.drive_torque(t, 2.0)
            decisions.append(monitor.update(t))
        assert decisions[0] == decisions[1], k
        assert pair[0].numbers.tobytes() == pair[1].numbers.tobytes(), k
        if decisions[0].zeroed:
            found.append(k)
    assert found, 'no runaway found'
    assert RUNAWAY_FOUND in statuses       # by the kernel's step of the guard
    assert words in pair[0].runaway
    assert decisions[0].state == 'FAULT' and pair[0].runaway in decisions[0].reason
