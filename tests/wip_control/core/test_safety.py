"""The safety monitor (core/safety.py): triggers, latching, limits, shadow mode, start-up.

Every fault must zero both torques in the very update at which the monitor first sees
it (the "same tick"), and name its cause. Times are seconds of a fake monotonic clock
advanced by the tests: H = 5 ms ticks, as the mixer's 200 Hz timer.
"""

import dataclasses
import math

from hypothesis import given, settings, strategies as st
import pytest

from wip_control.core.config import ConfigError, from_mapping
from wip_control.core.eso import StateEstimate
from wip_control.core.mixer import mix
from wip_control.core.params import WipParameters
from wip_control.core.safety import (ACTIVE, DEGRADED, DriveStatus, ESTOP, FAULT,
                                     SafetyMonitor, SHADOW, STARTING, TIME_TOLERANCE,
                                     tilt_divergence_rate)
from wip_control.core.safety_config import SafetyConfig

H = 0.005                   # tick period [s]
TAU_MAX = 15.0              # [N m], the default MixerConfig
RATE = 1.0e4                # [N m/s], the default MixerConfig: 50 N m per tick, no limit
ESTIMATE = StateEstimate(phi=0.1, omega=0.2, f1=0.3, x_v=1.0, v=0.5, f2=-0.4, theta=0.02,
                         theta_dot=-0.1, f3=0.5, epsilon=0.01)


class Clock:
    """Drives a monitor: feeds every input every tick, like a healthy graph."""

    def __init__(self, monitor, t=100.0):
        self.monitor, self.t = monitor, t
        self.tau_v, self.tau_omega, self.status = 4.0, 0.6, DriveStatus.SOLVED
        self.estimate, self.settled = ESTIMATE, True

    def feed(self):
        m = self.monitor
        m.estimate(self.t, self.estimate, self.settled)
        m.yaw_torque(self.t, self.tau_omega)
        m.drive_torque(self.t, self.tau_v, self.status)

    def tick(self, feed=True):
        self.t += H
        if feed:
            self.feed()
        return self.monitor.update(self.t)


def active(config=SafetyConfig(), rate=RATE, **kwargs):
    """Return a monitor driven to ACTIVE, with its clock."""
    monitor = SafetyMonitor(config, TAU_MAX, rate, H, **kwargs)
    clock = Clock(monitor)
    for _ in range(int(config.settle_time / H) + 3):
        decision = clock.tick()
    assert decision.state in (ACTIVE, SHADOW), decision
    return monitor, clock


def assert_zeroed(decision, state, *words):
    assert (decision.tau_left, decision.tau_right, decision.zeroed) == (0.0, 0.0, True)
    assert decision.command == (0.0, 0.0)
    assert decision.state == state, decision
    for word in words:
        assert word in decision.reason, (word, decision.reasons)


# ----------------------------------------------------------------------------- config

def test_config_defaults_load_and_bad_values_name_the_key():
    assert from_mapping(SafetyConfig, {}, 'safety') == SafetyConfig()
    with pytest.raises(ConfigError, match=r'safety\.fall_threshold: must be > 0'):
        from_mapping(SafetyConfig, {'fall_threshold': 0.0}, 'safety')
    with pytest.raises(ConfigError, match=r'safety\.max_estimate_age: must be finite'):
        from_mapping(SafetyConfig, {'max_estimate_age': math.nan}, 'safety')
    with pytest.raises(ConfigError, match=r'safety\.shadow_mode: expected true or false'):
        from_mapping(SafetyConfig, {'shadow_mode': 1}, 'safety')


def test_limits_and_period_must_be_finite_and_positive():
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='max_wheel_torque'):
            SafetyMonitor(SafetyConfig(), bad, RATE, H)
        with pytest.raises(ValueError, match='max_wheel_torque_rate'):
            SafetyMonitor(SafetyConfig(), TAU_MAX, bad, H)
        with pytest.raises(ValueError, match='period'):
            SafetyMonitor(SafetyConfig(), TAU_MAX, RATE, bad)


# ----------------------------------------------------------------------------- start-up

def test_no_torque_until_every_input_arrived_the_eso_settled_and_settle_time_passed():
    config = SafetyConfig(settle_time=0.1)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    d = clock.tick(feed=False)
    assert_zeroed(d, STARTING, 'no state_estimate yet', 'no yaw_torque yet',
                  'no drive_torque yet')
    clock.t += H
    monitor.yaw_torque(clock.t, 0.5)
    monitor.drive_torque(clock.t, 3.0)
    assert_zeroed(monitor.update(clock.t), STARTING, 'no state_estimate yet')
    clock.settled = False
    assert_zeroed(clock.tick(), STARTING, 'ESO not settled')
    clock.status = DriveStatus.NOT_READY
    assert_zeroed(clock.tick(), STARTING, 'ESO not settled', 'NOT_READY')
    clock.settled, clock.status = True, DriveStatus.SOLVED
    start = clock.t + H
    d = clock.tick()
    assert_zeroed(d, STARTING, 'settling')
    while clock.t - start < config.settle_time - 1e-9:
        assert_zeroed(d, STARTING, 'settling')
        d = clock.tick()
    # settle_time after everything was first present and valid, torque starts.
    assert clock.t - start == pytest.approx(config.settle_time, abs=1e-9)
    assert d.state == ACTIVE and not d.zeroed and d.reasons == ()
    assert (d.tau_left, d.tau_right) == mix(clock.tau_v, clock.tau_omega, TAU_MAX)


def test_a_fault_during_start_up_restarts_the_settle_time():
    config = SafetyConfig(settle_time=0.05)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    for _ in range(5):                 # 4 ticks of settling: not yet ACTIVE
        d = clock.tick()
    assert d.state == STARTING
    clock.estimate = ESTIMATE._replace(theta=1.0)
    assert_zeroed(clock.tick(), FAULT, 'fallen')
    clock.estimate = ESTIMATE
    states = [clock.tick().state for _ in range(12)]
    # 0.05 s = 10 ticks of settling from the first healthy tick, then ACTIVE.
    assert states == [STARTING] * 10 + [ACTIVE] * 2


def test_without_timing_checks_torque_flows_from_the_first_tick_as_in_lockstep():
    monitor = SafetyMonitor(SafetyConfig(), TAU_MAX, RATE, H, timing_checks=False)
    monitor.yaw_torque(0.0, 0.5)
    monitor.drive_torque(0.0, 3.0)
    d = monitor.update(0.0)            # no estimate at all, never settled, t = 0
    assert (d.state, d.zeroed) == (ACTIVE, False)
    assert (d.tau_left, d.tau_right) == mix(3.0, 0.5, TAU_MAX)
    # Ages are not checked: 1000 s later with the same inputs.
    assert not monitor.update(1000.0).zeroed
    # Values are: a paper_ramp ESO (settled = False) is fine, a fall is not.
    monitor.estimate(1000.0, ESTIMATE, settled=False)
    assert not monitor.update(1000.005).zeroed
    monitor.estimate(1000.01, ESTIMATE._replace(theta=-0.5), settled=False)
    assert_zeroed(monitor.update(1000.01), FAULT, 'fallen')
    # The fault clears: back at once (no settle time), like the in-process runner.
    monitor.estimate(1000.015, ESTIMATE, settled=False)
    assert monitor.update(1000.015).state == ACTIVE


# ----------------------------------------------------------------------------- triggers

@pytest.mark.parametrize('bridge', [0.0, SafetyConfig().bridge_time])
@pytest.mark.parametrize('name, age_field', [
    ('state_estimate', 'max_estimate_age'), ('yaw_torque', 'max_yaw_torque_age'),
    ('drive_torque', 'max_drive_torque_age')])
def test_an_input_older_than_its_age_is_bridged_then_zeroes_at_the_first_tick_past_it(
        name, age_field, bridge):
    """An input older than its age is bridged, then zeroes at the first tick past it.

    ACTIVE up to the age limit, DEGRADED (torque flowing, the late input named) for
    bridge_time more, zero torque at the first tick past age + bridge (bridge 0: at the
    first tick past the age, the strict behaviour).
    """
    monitor, clock = active(SafetyConfig(bridge_time=bridge))
    max_age = getattr(SafetyConfig(), age_field)
    last = clock.t
    degraded = 0
    while True:
        clock.t += H
        # Every input but one keeps coming.
        if name != 'state_estimate':
            monitor.estimate(clock.t, ESTIMATE, True)
        if name != 'yaw_torque':
            monitor.yaw_torque(clock.t, 0.6)
        if name != 'drive_torque':
            monitor.drive_torque(clock.t, 4.0)
        d = monitor.update(clock.t)
        age = clock.t - last
        if age <= max_age + TIME_TOLERANCE:
            assert d.state == ACTIVE, (age, d)
        elif age <= max_age + bridge + TIME_TOLERANCE:
            assert d.state == DEGRADED and not d.zeroed, (age, d)
            assert (d.tau_left, d.tau_right) == mix(4.0, 0.6, TAU_MAX)
            assert f'{name} late' in d.reason and 'bridged' in d.reason
            degraded += 1
        else:
            # The first tick at which the age exceeds the bridge: zero in this tick.
            assert_zeroed(d, FAULT, f'{name} stale', 'publisher stopped')
            break
    assert degraded == round(bridge / H)
    # It recovers through STARTING once the stream resumes.
    states = [clock.tick().state for _ in range(int(SafetyConfig().settle_time / H) + 2)]
    assert states[0] == STARTING and states[-1] == ACTIVE


def test_a_late_input_that_resumes_within_the_bridge_returns_to_active_without_a_gap():
    monitor, clock = active()
    gap = SafetyConfig().max_estimate_age + 0.5 * SafetyConfig().bridge_time   # 0.2 s
    t_last = clock.t
    states = []
    while clock.t - t_last < gap:
        clock.t += H
        monitor.yaw_torque(clock.t, 0.6)
        monitor.drive_torque(clock.t, 4.0)
        states.append(monitor.update(clock.t))
    assert all(not d.zeroed for d in states)
    assert {d.state for d in states} == {ACTIVE, DEGRADED}
    d = clock.tick()                      # the estimate is back: no settle time, no step
    assert d.state == ACTIVE and (d.tau_left, d.tau_right) == mix(4.0, 0.6, TAU_MAX)


def test_a_late_mpc_output_is_followed_along_its_plan_then_held_at_its_end():
    period = 0.1
    plan = (4.0, 6.0, 7.0, 7.5)
    monitor, clock = active(SafetyConfig(max_drive_torque_age=0.25, bridge_time=0.2))
    clock.t += H
    monitor.drive_torque(clock.t, plan[0], DriveStatus.SOLVED, plan=plan,
                         plan_period=period)
    t0 = clock.t
    seen = {}
    while True:
        clock.t += H
        monitor.estimate(clock.t, ESTIMATE, True)
        monitor.yaw_torque(clock.t, 0.0)
        d = monitor.update(clock.t)
        if d.zeroed:
            break
        elapsed = clock.t - t0
        expected = plan[min(len(plan) - 1, int(elapsed / period + 1e-9))]
        assert d.tau_left + d.tau_right == pytest.approx(expected), elapsed
        seen.setdefault(expected, set()).add(d.state)
    assert clock.t - t0 == pytest.approx(0.25 + 0.2 + H, abs=1e-9)
    # Late after 0.25 s (during the plan's third period), zero after 0.45 s.
    assert seen == {4.0: {ACTIVE}, 6.0: {ACTIVE}, 7.0: {ACTIVE, DEGRADED}, 7.5: {DEGRADED}}
    # A plan that is not finite is ignored: τυ is held.
    monitor, clock = active()
    monitor.drive_torque(clock.t + H, 3.0, plan=(3.0, math.nan), plan_period=period)
    clock.t += 0.3
    monitor.estimate(clock.t, ESTIMATE, True)
    monitor.yaw_torque(clock.t, 0.0)
    d = monitor.update(clock.t)
    assert d.state == DEGRADED and d.tau_left + d.tau_right == pytest.approx(3.0)


def test_late_inputs_before_engaging_are_never_bridged():
    config = SafetyConfig(settle_time=0.05)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    clock.tick()
    clock.t += config.max_estimate_age + 0.01          # stale before ever being ACTIVE
    monitor.yaw_torque(clock.t, 0.6)
    monitor.drive_torque(clock.t, 4.0)
    assert_zeroed(monitor.update(clock.t), STARTING, 'state_estimate late')


def test_the_default_bridge_is_ln4_over_the_unstable_tilt_pole_of_the_nominal_model():
    """The default bridge is ln 4 over the unstable tilt pole of the nominal model.

    The stated bound: with the torque held the tilt error grows like exp(λ t); bridging
    ln 4 / λ at most quadruples it. λ from the linearised model (1), checked here against the
    eigenvalues of the tilt dynamics integrated numerically from the model's own terms.
    """
    from wip_control.core.model import nominal_terms
    params = WipParameters()
    lam = tilt_divergence_rate(params)
    eps = 1e-6                      # d f3 / d θ at the upright equilibrium, numerically
    slope = (nominal_terms(params, eps, 0.0, 0.0).f3
             - nominal_terms(params, -eps, 0.0, 0.0).f3) / (2 * eps)
    assert lam == pytest.approx(math.sqrt(slope), rel=1e-6)
    assert 4.0 < lam < 5.0          # the default robot: 4.6 rad/s
    assert SafetyConfig().bridge_time == pytest.approx(math.log(4.0) / lam, abs=0.005)


def test_non_finite_or_wrong_size_estimate_zeroes_in_the_same_tick():
    for field in StateEstimate._fields:
        if field == 'epsilon':
            continue                    # inf at the start of the paper's ramp: not checked
        for bad in (math.nan, math.inf, -math.inf):
            monitor, clock = active()
            clock.estimate = ESTIMATE._replace(**{field: bad})
            assert_zeroed(clock.tick(), FAULT, 'state_estimate invalid', f'{field}=')
            clock.estimate = ESTIMATE
            assert clock.tick().state == STARTING          # valid again: re-arming
    monitor, clock = active()
    clock.estimate = ESTIMATE._replace(epsilon=math.inf)
    assert clock.tick().state == ACTIVE
    for wrong in (ESTIMATE[:9], (*ESTIMATE, 0.0), (), 'abcdefghij', None):
        monitor, clock = active()
        monitor.estimate(clock.t + H, wrong, True)
        clock.t += H
        assert_zeroed(monitor.update(clock.t), FAULT, 'state_estimate invalid')


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf, None, '1.0', True])
def test_non_finite_or_non_numeric_torques_zero_in_the_same_tick(bad):
    monitor, clock = active()
    clock.tau_omega = bad
    assert_zeroed(clock.tick(), FAULT, 'yaw_torque invalid', 'non-finite yaw torque')
    monitor, clock = active()
    clock.tau_v = bad
    assert_zeroed(clock.tick(), FAULT, 'drive_torque invalid', 'non-finite drive torque')


def test_invalid_input_reported_by_the_node_zeroes_until_a_valid_one_arrives():
    monitor, clock = active()
    monitor.invalid_input('yaw_torque', clock.t, 'wrong type')
    assert_zeroed(monitor.update(clock.t + H), FAULT, 'yaw_torque invalid: wrong type')
    clock.t += H
    assert clock.tick().state == STARTING


@pytest.mark.parametrize('theta', [0.3501, -0.3501, 1.4, -3.0])
def test_tilt_past_the_fall_threshold_zeroes_in_the_same_tick(theta):
    monitor, clock = active()
    clock.estimate = ESTIMATE._replace(theta=0.35 * math.copysign(1.0, theta))
    assert clock.tick().state == ACTIVE                    # at the threshold: still fine
    clock.estimate = ESTIMATE._replace(theta=theta)
    assert_zeroed(clock.tick(), FAULT, 'fallen', 'fall_threshold 0.35 rad')


@pytest.mark.parametrize('field, bound, label', [
    ('v', 5.0, 'v_hat'), ('omega', 10.0, 'omega_hat'), ('theta_dot', 10.0, 'theta_dot_hat'),
    ('f1', 50.0, 'f1_hat'), ('f2', 50.0, 'f2_hat'), ('f3', 100.0, 'f3_hat')])
def test_eso_divergence_zeroes_in_the_same_tick(field, bound, label):
    for sign in (1.0, -1.0):
        monitor, clock = active()
        clock.estimate = ESTIMATE._replace(**{field: sign * bound})
        assert clock.tick().state == ACTIVE                # at the bound: fine
        clock.estimate = ESTIMATE._replace(**{field: sign * bound * 1.001})
        assert_zeroed(clock.tick(), FAULT, 'ESO diverged', f'|{label}|')


@pytest.mark.parametrize('status', [DriveStatus.FAILED_ZERO, DriveStatus.INPUT_INVALID, 7])
def test_mpc_failure_status_zeroes_in_the_same_tick(status):
    monitor, clock = active()
    clock.status = status
    d = clock.tick()
    assert_zeroed(d, FAULT, 'MPC failed')
    assert (getattr(status, 'name', None) or 'unknown status 7') in d.reason


def test_mpc_not_ready_after_start_is_a_fault():
    monitor, clock = active()
    clock.status = DriveStatus.NOT_READY
    assert_zeroed(clock.tick(), FAULT, 'NOT_READY')
    assert clock.tick().state == FAULT              # stays FAULT while it lasts
    clock.status = DriveStatus.SOLVED
    assert clock.tick().state == STARTING


def test_mpc_fallbacks_are_tolerated_for_max_mpc_fallbacks_consecutive_outputs():
    config = SafetyConfig(max_mpc_fallbacks=3)
    monitor, clock = active(config)
    for episode in range(2):
        # The MPC publishes at 10 Hz: one fallback output every 20 ticks.
        for n in range(1, 5):
            monitor.drive_torque(clock.t, 4.0, DriveStatus.FALLBACK_SHIFTED_PLAN)
            for _ in range(20):
                clock.t += H
                monitor.estimate(clock.t, ESTIMATE, True)
                monitor.yaw_torque(clock.t, 0.6)
                d = monitor.update(clock.t)
                if n <= 3:
                    assert d.state == ACTIVE, (n, d)
                else:
                    assert_zeroed(d, FAULT, 'MPC failed', '4 consecutive FALLBACK')
                    break
        # A SOLVED output resets the count.
        while d.state != ACTIVE:
            d = clock.tick()


# ----------------------------------------------------------------------------- e-stop

def test_estop_latches_until_an_explicit_reset_after_release():
    config = SafetyConfig(settle_time=0.02)
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
    config = SafetyConfig(latch_faults=True, settle_time=0.0)
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
    config = SafetyConfig(max_estop_age=0.02, settle_time=0.0)
    monitor = SafetyMonitor(config, TAU_MAX, RATE, H)
    clock = Clock(monitor)
    assert_zeroed(clock.tick(), STARTING, 'no heartbeat (/wip/heartbeat or /wip/estop) yet')
    monitor.estop(clock.t, False)
    assert clock.tick().state == ACTIVE
    for _ in range(3):                               # up to 0.02 s old: still fresh
        assert clock.tick().state == ACTIVE
    assert_zeroed(clock.tick(), FAULT, 'heartbeat (/wip/heartbeat or /wip/estop) stale')


def test_the_heartbeat_topic_keeps_the_link_fresh_but_never_releases_an_estop():
    config = SafetyConfig(max_estop_age=0.02, settle_time=0.0)
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
    config = SafetyConfig(settle_time=0.0, estop_hold_time=0.5)
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
    config = SafetyConfig(settle_time=0.0)
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
    config = SafetyConfig(settle_time=0.0)
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
    config = SafetyConfig(shadow_mode=True)
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
    config = SafetyConfig()
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
    monitor = SafetyMonitor(SafetyConfig(), TAU_MAX, RATE, H)
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
    for _ in range(int(SafetyConfig().settle_time / H) + 3):
        decision = clock.tick()
    assert decision.state == ACTIVE
