"""The safety monitor (core/safety.py): configuration, start-up and the fault triggers.

Every fault must zero both torques in the very update at which the monitor first sees
it (the "same tick"), and name its cause (harness: safety_harness.py; e-stop, limits,
shadow mode and position: test_safety_latching.py).
"""

import math

import pytest

from safety_harness import active, assert_zeroed, Clock, ESTIMATE, H, RATE, TAU_MAX
from wip_runtime.config import ParamError, from_mapping
from wip_control.core.eso import StateEstimate
from wip_control.core.mixer import mix
from wip_description.params import ModelParams
from wip_control.core.safety import (ACTIVE, DEGRADED, DriveStatus, FAULT,
                                     SafetyMonitor, STARTING, TIME_TOLERANCE,
                                     tilt_divergence_rate)
from wip_control.core.safety_config import FRESH, LATE, lateness, SafetyParams, STALE

#: Each test with the interpreted tick and with the compiled one (safety_kernel.py).
pytestmark = pytest.mark.usefixtures('safety_tick')


# ----------------------------------------------------------------------------- config

def test_config_defaults_load_and_bad_values_name_the_key():
    assert from_mapping(SafetyParams, {}, 'safety') == SafetyParams()
    with pytest.raises(ParamError, match=r'safety\.fall_threshold: must be > 0'):
        from_mapping(SafetyParams, {'fall_threshold': 0.0}, 'safety')
    with pytest.raises(ParamError, match=r'safety\.max_estimate_age: must be finite'):
        from_mapping(SafetyParams, {'max_estimate_age': math.nan}, 'safety')
    with pytest.raises(ParamError, match=r'safety\.shadow_mode: expected true or false'):
        from_mapping(SafetyParams, {'shadow_mode': 1}, 'safety')


def test_limits_and_period_must_be_finite_and_positive():
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='max_wheel_torque'):
            SafetyMonitor(SafetyParams(), bad, RATE, H)
        with pytest.raises(ValueError, match='max_wheel_torque_rate'):
            SafetyMonitor(SafetyParams(), TAU_MAX, bad, H)
        with pytest.raises(ValueError, match='period'):
            SafetyMonitor(SafetyParams(), TAU_MAX, RATE, bad)


# ----------------------------------------------------------------------------- start-up

def test_no_torque_until_every_input_arrived_the_eso_settled_and_settle_time_passed():
    config = SafetyParams(settle_time=0.1)
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
    config = SafetyParams(settle_time=0.05)
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
    monitor = SafetyMonitor(SafetyParams(), TAU_MAX, RATE, H, timing_checks=False)
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

@pytest.mark.parametrize('bridge', [0.0, SafetyParams().bridge_time])
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
    monitor, clock = active(SafetyParams(bridge_time=bridge))
    max_age = getattr(SafetyParams(), age_field)
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
    states = [clock.tick().state for _ in range(int(SafetyParams().settle_time / H) + 2)]
    assert states[0] == STARTING and states[-1] == ACTIVE


def test_a_late_input_that_resumes_within_the_bridge_returns_to_active_without_a_gap():
    monitor, clock = active()
    gap = SafetyParams().max_estimate_age + 0.5 * SafetyParams().bridge_time   # 0.2 s
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
    monitor, clock = active(SafetyParams(max_drive_torque_age=0.25, bridge_time=0.2))
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
    config = SafetyParams(settle_time=0.05)
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
    params = ModelParams()
    lam = tilt_divergence_rate(params)
    eps = 1e-6                      # d f3 / d θ at the upright equilibrium, numerically
    slope = (nominal_terms(params, eps, 0.0, 0.0).f3
             - nominal_terms(params, -eps, 0.0, 0.0).f3) / (2 * eps)
    assert lam == pytest.approx(math.sqrt(slope), rel=1e-6)
    assert 4.0 < lam < 5.0          # the default robot: 4.6 rad/s
    assert SafetyParams().bridge_time == pytest.approx(math.log(4.0) / lam, abs=0.005)


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
    config = SafetyParams(max_mpc_fallbacks=3)
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


def test_lateness_is_fresh_within_the_age_limit_late_within_the_bridge_then_stale():
    # The defaults: 0.05 s age limit, 0.3 s bridge; the boundaries belong to the milder side.
    assert [lateness(age, 0.05, 0.3) for age in (0.0, 0.05, 0.0501, 0.35, 0.3501)] == [
        FRESH, FRESH, LATE, LATE, STALE]
    assert lateness(0.0501, 0.05, 0.0) == STALE   # no bridge: late is stale at once
