"""The safety monitor (core/safety.py): e-stop, heartbeat, limits, shadow mode, position.

Every fault must zero both torques in the very update at which the monitor first sees
it (the "same tick"), and name its cause (harness: safety_harness.py).
"""

import dataclasses

from hypothesis import given, settings, strategies as st
import pytest

from safety_harness import active, assert_zeroed, Clock, ESTIMATE, H, RATE, TAU_MAX
from wip_control.core.mixer import mix
from wip_control.core.safety import (ACTIVE, ESTOP, FAULT,
                                     SafetyMonitor, SHADOW, STARTING)
from wip_control.core.safety_config import SafetyParams

#: Each test with the interpreted tick and with the compiled one (safety_kernel.py).
pytestmark = pytest.mark.usefixtures('safety_tick')


# ----------------------------------------------------------------------------- e-stop

def test_estop_latches_until_an_explicit_reset_after_release():
    config = SafetyParams(settle_time=0.02)
    monitor, clock = active(config)
    monitor.estop(clock.t, True)
    assert_zeroed(clock.tick(), ESTOP, 'e-stop engaged')
    ok, message = monitor.reset()
    assert not ok and 'still engaged' in message
    monitor.estop(clock.t, False)                    # released: still latched
    for _ in range(100):
        assert_zeroed(clock.tick(), ESTOP, 'reset required')
    ok, message = monitor.reset()
    assert ok and 'e-stop' in message
    states = [clock.tick().state for _ in range(6)]
    # Re-arming: 0.02 s = 4 ticks of settling, then ACTIVE.
    assert states == [STARTING] * 4 + [ACTIVE] * 2
    assert monitor.reset() == (True, 'nothing to reset')


def test_estop_wins_over_faults_and_reports_them_too():
    monitor, clock = active()
    monitor.estop(clock.t, True)
    clock.estimate = ESTIMATE._replace(theta=2.0)
    assert_zeroed(clock.tick(), ESTOP, 'e-stop engaged', 'fallen')


def test_latched_faults_stay_until_reset():
    config = SafetyParams(latch_faults=True, settle_time=0.0)
    monitor, clock = active(config)
    clock.estimate = ESTIMATE._replace(theta=1.0)
    assert_zeroed(clock.tick(), FAULT, 'fallen')
    clock.estimate = ESTIMATE
    for _ in range(10):
        assert_zeroed(clock.tick(), FAULT, 'latched fault', 'fallen', 'reset required')
    assert monitor.reset()[0]
    assert clock.tick().state == ACTIVE               # settle_time 0


# ----------------------------------------------------------------------------- heartbeat

def test_estop_heartbeat_when_configured():
    config = SafetyParams(max_estop_age=0.02, settle_time=0.0)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    assert_zeroed(clock.tick(), STARTING, 'no heartbeat (/wip/heartbeat or /wip/estop) yet')
    monitor.estop(clock.t, False)
    assert clock.tick().state == ACTIVE
    for _ in range(3):                               # up to 0.02 s old: still fresh
        assert clock.tick().state == ACTIVE
    assert_zeroed(clock.tick(), FAULT, 'heartbeat (/wip/heartbeat or /wip/estop) stale')


def test_the_heartbeat_topic_keeps_the_link_fresh_but_never_releases_an_estop():
    config = SafetyParams(max_estop_age=0.02, settle_time=0.0)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    assert_zeroed(clock.tick(), STARTING, 'no heartbeat (/wip/heartbeat or /wip/estop) yet')
    monitor.heartbeat(clock.t)                       # a heartbeat alone arms
    assert clock.tick().state == ACTIVE
    for _ in range(20):                              # heartbeats every tick: fresh
        monitor.heartbeat(clock.t)
        assert clock.tick().state == ACTIVE
    monitor.estop(clock.t, True)
    for _ in range(400):                             # 2 s of heartbeats: still held
        monitor.heartbeat(clock.t)
        assert_zeroed(clock.tick(), ESTOP, 'e-stop engaged')
    assert not monitor.reset(clock.t)[0]
    for _ in range(5):                               # heartbeat stops: stale, and ESTOP wins
        clock.tick()
    assert_zeroed(clock.tick(), ESTOP, 'e-stop engaged',
                  'heartbeat (/wip/heartbeat or /wip/estop) stale')


def test_a_held_estop_blocks_the_reset_whatever_else_publishes():
    # A button that repeats true every 0.1 s, and another publisher's false between two
    # of its messages: the reset is refused until no true came for estop_hold_time.
    config = SafetyParams(settle_time=0.0, estop_hold_time=0.5)
    monitor, clock = active(config)
    for _ in range(10):
        monitor.estop(clock.t, True)
        for _ in range(20):                          # 0.1 s at 200 Hz
            assert_zeroed(clock.tick(), ESTOP, 'e-stop engaged')
    monitor.estop(clock.t, True)
    clock.tick()
    monitor.estop(clock.t, False)                    # someone else's release
    ok, message = monitor.reset(clock.t)
    assert not ok and 'e-stop held' in message and '< estop_hold_time 0.5 s' in message
    for _ in range(98):                              # 0.49 s after the last true: held
        clock.tick()
    assert not monitor.reset(clock.t)[0]
    for _ in range(2):                               # 0.5 s: released
        clock.tick()
    ok, message = monitor.reset(clock.t)
    assert ok and 'e-stop' in message
    assert clock.tick().state == ACTIVE


# ----------------------------------------------------------------------------- limits

def test_zeroing_is_immediate_and_torque_comes_back_rate_limited_from_zero():
    rate = 200.0                                     # [N m/s]: 1 N m per tick
    config = SafetyParams(settle_time=0.0)
    monitor, clock = active(config, rate=rate)
    clock.tau_v, clock.tau_omega = 20.0, 0.0         # 10 N m per wheel
    for _ in range(12):
        d = clock.tick()
    assert (d.tau_left, d.tau_right) == (10.0, 10.0)
    clock.estimate = ESTIMATE._replace(theta=1.0)
    assert_zeroed(clock.tick(), FAULT)               # 10 -> 0 in one tick, not rate limited
    clock.estimate = ESTIMATE
    # The fault clears: re-armed at once (settle_time 0), ramping up from zero.
    lefts = [clock.tick().tau_left for _ in range(12)]
    # 1e-9: Δt is a difference of float times near 100 s (ulp 1.4e-14 s) times 200 N m/s.
    assert lefts == pytest.approx([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 10, 10], abs=1e-9)


commands = st.lists(st.tuples(st.floats(0.0, 0.05),               # dt [s]
                              st.floats(-100.0, 100.0),            # tau_v [N m]
                              st.floats(-100.0, 100.0)),           # tau_omega [N m]
                    min_size=1, max_size=60)


@settings(max_examples=150, deadline=None)
@given(commands=commands, rate=st.floats(1.0, 1e4), tau_max=st.floats(0.1, 50.0))
def test_rate_and_torque_limits_hold_for_any_command_sequence(commands, rate, tau_max):
    config = SafetyParams(settle_time=0.0)
    monitor = SafetyMonitor(config, tau_max, rate, H, timing_checks=False)
    t = 0.0
    previous = (0.0, 0.0)
    for dt, tau_v, tau_omega in commands:
        t_before, t = t, t + dt
        monitor.yaw_torque(t, tau_omega)
        monitor.drive_torque(t, tau_v)
        d = monitor.update(t)
        assert d.state == ACTIVE
        # Δt of the monitor: the nominal period at the first update, then the difference
        # of the times it was given (not dt: t + 1e-38 rounds to t, a step of 0).
        step = rate * (H if monitor.ticks == 1 else t - t_before)
        target = mix(tau_v, tau_omega, tau_max)
        for now, before, goal in zip((d.tau_left, d.tau_right), previous, target):
            # One rounding of previous +- step: 1e-12 relative.
            assert abs(now - before) <= step * (1 + 1e-12) + 1e-12
            assert abs(now) <= tau_max
            # Toward the target, and exactly on it when it is within reach.
            assert abs(now - goal) <= abs(before - goal) + 1e-12
            if abs(goal - before) <= step:
                assert now == goal
        previous = (d.tau_left, d.tau_right)


# ----------------------------------------------------------------------------- shadow

def test_shadow_mode_reports_the_torques_but_commands_zero():
    config = SafetyParams(shadow_mode=True)
    monitor, clock = active(config)
    d = clock.tick()
    assert (d.state, d.zeroed, d.shadow) == (SHADOW, False, True)
    assert (d.tau_left, d.tau_right) == mix(clock.tau_v, clock.tau_omega, TAU_MAX)
    assert d.command == (0.0, 0.0)
    clock.estimate = ESTIMATE._replace(theta=1.0)
    assert_zeroed(clock.tick(), FAULT, 'fallen')
    # Not in shadow mode: the command is the torques.
    monitor, clock = active(dataclasses.replace(config, shadow_mode=False))
    d = clock.tick()
    assert d.command == (d.tau_left, d.tau_right) != (0.0, 0.0)


def test_a_stall_of_the_layer_itself_past_the_bridge_is_a_fault_even_with_fresh_inputs():
    """A stall of the layer itself past the bridge is a fault, even with fresh inputs.

    The whole controller process frozen: on waking up fresh inputs may be taken before
    the layer's own tick; the gap since its previous tick still makes it a fault (the
    base held the last command, blind, for that long).
    """
    config = SafetyParams()
    bound = config.max_estimate_age + config.bridge_time
    monitor, clock = active(config)
    clock.t += bound - H                    # within the bound: ridden through
    clock.feed()
    assert monitor.update(clock.t).state == ACTIVE
    clock.t += bound + 0.01                 # past it: fresh inputs, yet a fault
    clock.feed()
    assert_zeroed(monitor.update(clock.t), FAULT, 'stalled', 'not scheduled')
    assert clock.tick().state == STARTING   # then re-armed through STARTING


# ------------------------------------------------------------ position source and runaway

def test_no_position_fix_yet_holds_the_start_and_a_refused_source_is_a_fault():
    from wip_control.core.position import FAULT as POSITION_FAULT, NO_FIX, TRACKING
    monitor = SafetyMonitor(SafetyParams(), TAU_MAX, RATE, H)
    clock = Clock(monitor)
    for _ in range(100):
        monitor.estimate(clock.t, ESTIMATE, True, NO_FIX, 0.0, 0.0)
        clock.t += H
        monitor.yaw_torque(clock.t, 0.6)
        monitor.drive_torque(clock.t, 4.0)
        decision = monitor.update(clock.t)
    assert_zeroed(decision, STARTING, 'no position fix yet', 'position_source: wheels')
    # Engaged on a tracking source, then the ESO refuses it: zero torque at once.
    monitor, clock = active()
    monitor.estimate(clock.t + H, ESTIMATE, True, POSITION_FAULT, 0.0, 0.0)
    clock.t += H
    assert_zeroed(monitor.update(clock.t), FAULT, 'position source refused', 'datum')
    # Lockstep (no timing checks) ignores the position status: the simulation's is right.
    monitor, clock = active(timing_checks=False)
    monitor.estimate(clock.t + H, ESTIMATE, True, NO_FIX, 0.0, 0.0)
    clock.t += H
    assert monitor.update(clock.t).state == ACTIVE
    assert TRACKING != NO_FIX


def test_a_runaway_is_a_latched_fault_until_reset():
    # The estimate is frozen at the origin while the wheels (υ̂ = 1 m/s) roll and the
    # reference moves 0.3 m/s: the guard's verdict zeroes the torque and stays.
    from wip_control.core.position import TRACKING
    monitor, clock = active()
    moving = ESTIMATE._replace(v=1.0, phi=0.0)
    verdict_at = None
    for k in range(2000):
        clock.t += H
        monitor.reference(clock.t, 0.3 * k * H, 0.0)
        monitor.estimate(clock.t, moving, True, TRACKING, 0.0, 0.0)
        monitor.yaw_torque(clock.t, 0.6)
        monitor.drive_torque(clock.t, 4.0)
        decision = monitor.update(clock.t)
        if decision.state == FAULT:
            verdict_at = k * H
            break
    assert verdict_at is not None and verdict_at < 4.0
    assert_zeroed(decision, FAULT, 'runaway', 'position estimate is likely wrong')
    # Stays latched with everything healthy again, until an explicit reset.
    for _ in range(100):
        decision = clock.tick()
    assert_zeroed(decision, FAULT, 'runaway', 'reset required')
    ok, message = monitor.reset()
    assert ok and 'runaway' in message
    for _ in range(int(SafetyParams().settle_time / H) + 3):
        decision = clock.tick()
    assert decision.state == ACTIVE
