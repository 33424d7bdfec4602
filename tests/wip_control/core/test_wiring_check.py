"""Wiring checks (core/wiring_check.py) on synthetic signals.

A small balancing loop of model (1) closed through a base whose wiring differs from what the check
is told.

The loop: a PD tilt controller on the MEASURED tilt (gains stabilise the nominal
linearised tilt dynamics: 150 N m/rad > a/|g3| = 74), a yaw-rate loop toward
0.5 rad/s on the gyro; the base applies the torques through its real wiring and reports
its wheels through it. Sensor noise and gyro biases as a consumer IMU's.
"""

import math

import numpy as np
import pytest

from wip_control.core.model import nominal_terms
from wip_description.params import ModelParams
from wip_control.core.wiring_check import (JOINTS, LEFT_SIGN, mirrored_tilt_band, MOUNTING,
                                           RIGHT_SIGN, WiringCheck, WiringCheckParams)

PERIOD = 0.005
PARAMS = ModelParams()
CONFIGURED = {'left_joint': 'wheel_l', 'right_joint': 'wheel_r', 'left_wheel_sign': 1,
              'right_wheel_sign': 1, 'imu_mounting_rpy': (0.0, 0.0, 0.0)}


def _wired(mistake, left, right):
    """(left, right) of a base wired with ``mistake``: its sensors and its torques alike."""
    if mistake == 'right_sign':
        return left, -right
    if mistake == 'left_sign':
        return -left, right
    if mistake == 'swap':
        return right, left
    return left, right


def run(mistake=None, *, seconds=1.5, rest=0.5, noise=0.01, gyro_bias=0.05, push=0.0,
        push_at=0.3, yaw_rate_ref=0.5, config=WiringCheckParams(), seed=1, g3_scale=1.0):
    """Feed a check ``rest`` s at rest (held, not engaged), then ``seconds`` engaged.

    Return the verdict and the time after engaging it came (None, None without one).
    """
    rng = np.random.default_rng(seed)
    check = WiringCheck(config, PARAMS, PERIOD, configured=CONFIGURED)
    p = PARAMS
    r, d = p.wheel_radius, p.track_width
    theta, theta_dot, v, yaw_rate = 0.05, 0.0, 0.0, 0.0
    tau_l = tau_r = 0.0
    n_rest = int(round(rest / PERIOD))
    for k in range(n_rest + int(round(seconds / PERIOD))):
        t = k * PERIOD
        engaged = k >= n_rest
        # The base's sensors, through its real wiring.
        wl, wr = _wired(mistake, (v - 0.5 * d * yaw_rate) / r, (v + 0.5 * d * yaw_rate) / r)
        wl += noise * rng.standard_normal()
        wr += noise * rng.standard_normal()
        pitch, pitch_rate = theta, theta_dot + gyro_bias
        if mistake == 'imu_yaw_pi':
            pitch, pitch_rate = -pitch, -pitch_rate
        pitch_rate += noise * rng.standard_normal()
        gyro_yaw = yaw_rate + gyro_bias + noise * rng.standard_normal()
        g = p.gravity
        accel = (g * math.sin(theta), 0.0, g * math.cos(theta))
        if mistake == 'upside_down':
            accel = (accel[0], 0.0, -accel[2])
        check.wheels(t, wl, wr)
        verdict = check.imu(t, pitch, pitch_rate, gyro_yaw, accel)
        if verdict is not None:
            return verdict, t - rest
        # The controller (measured values as configured) and the torque sent.
        if engaged:
            tau_v = 150.0 * pitch + 40.0 * pitch_rate
            tau_w = 20.0 * (yaw_rate_ref - gyro_yaw)
            tau_l, tau_r = 0.5 * (tau_v - tau_w), 0.5 * (tau_v + tau_w)
        check.torque(t, tau_l + tau_r, engaged, tau_r - tau_l)
        # The real plant: what the wheels really get.
        phys_l, phys_r = _wired(mistake, tau_l, tau_r)
        if engaged:
            terms = nominal_terms(p, theta, yaw_rate, theta_dot)
            disturbance = push if push_at <= t - rest < push_at + 0.2 else 0.0
            theta_ddot = terms.f3 + g3_scale * terms.g3 * (phys_l + phys_r) + disturbance
            v += (terms.f2 + terms.g2 * (phys_l + phys_r)) * PERIOD
            yaw_rate += (terms.f1 + terms.g1 * (phys_r - phys_l)) * PERIOD
            theta_dot += theta_ddot * PERIOD
            theta += theta_dot * PERIOD
    return None, None


@pytest.mark.parametrize('mistake, parameter', [
    ('right_sign', RIGHT_SIGN), ('left_sign', LEFT_SIGN), ('swap', JOINTS),
    ('imu_yaw_pi', MOUNTING)])
def test_a_wiring_mistake_is_named_within_half_a_second_of_engaging(mistake, parameter):
    verdict, after = run(mistake)
    assert verdict is not None, mistake
    assert verdict.parameter == parameter, verdict.reason
    assert 0.0 <= after <= 0.5, (after, verdict.reason)
    assert verdict.reason.startswith(f'wiring: {parameter}: ')
    assert verdict.evidence


def reaction_factor(params):
    """g3 with the motors' reaction torque over model (1)'s, upright: (m_v r + m_p l)/(m_p l)."""
    return (params.effective_mass * params.wheel_radius + params.body_mass
            * params.com_height) / (params.body_mass * params.com_height)


def test_the_tilt_band_holds_the_mirrored_response_with_and_without_reaction_torque():
    low, high = mirrored_tilt_band(PARAMS)
    k = reaction_factor(PARAMS)
    assert k > 1.2                      # the default model: 1.5
    # Model (1) mirrored gives -1, a base whose motors push back on the body -k; each
    # with 0.5 of model error to spare, and correct wiring (+1) far outside.
    assert low <= -k - 0.5 + 1e-12 and -1.0 + 0.5 <= high + 1e-12 and high < 0.0


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_a_mirrored_drive_is_named_on_a_base_whose_motors_push_back_on_the_body(seed):
    # The stand-in base's full plant has g3 = k times model (1)'s: the mirrored response
    # is then -k X, which a band ending at -1.5 caught only some of the time.
    verdict, after = run('imu_yaw_pi', g3_scale=reaction_factor(PARAMS), seed=seed)
    assert verdict is not None and verdict.parameter == MOUNTING
    assert 0.0 <= after <= 0.3, (after, verdict.reason)


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_correct_wiring_on_a_base_whose_motors_push_back_gives_no_verdict(seed):
    verdict, _ = run(None, seconds=3.0, push=3.0, push_at=0.05, seed=seed,
                     g3_scale=reaction_factor(PARAMS))
    assert verdict is None, verdict.reason


def test_the_advice_names_the_value_to_set():
    verdict, _ = run('right_sign')
    assert 'set right_wheel_sign to -1' in verdict.message
    verdict, _ = run('swap')
    assert "left_joint: 'wheel_r', right_joint: 'wheel_l'" in verdict.message
    verdict, _ = run('imu_yaw_pi')
    assert 'imu_mounting_rpy: [0, 0, 3.142]' in verdict.message


def test_an_upside_down_imu_is_named_before_engaging():
    verdict, after = run('upside_down')
    assert verdict is not None and verdict.parameter == MOUNTING
    assert after < 0.0                 # at rest, before any torque
    assert 'along base_link -z' in verdict.message and 'upside down' in verdict.message


@pytest.mark.parametrize('seed', [1, 2, 3])
@pytest.mark.parametrize('push, push_at', [(0.0, 0.0), (3.0, 0.05), (-3.0, 0.05),
                                           (8.0, 0.4), (-8.0, 0.4)])
def test_correct_wiring_with_noise_bias_and_a_push_gives_no_verdict(seed, push, push_at):
    # Pushes on the tilt for 0.2 s: 3 rad/s^2 during the tilt check (a jolt as the hand
    # lets go), 8 rad/s^2 after it (a hard shove); yaw motion throughout.
    verdict, _ = run(None, seconds=3.0, push=push, push_at=push_at, seed=seed)
    assert verdict is None, verdict.reason


def test_no_verdict_without_excitation_and_when_disabled():
    # Held at rest, never engaged: no motion, nothing to compare.
    verdict, _ = run('swap', rest=1.0, seconds=0.0)
    assert verdict is None
    verdict, _ = run('right_sign', seconds=0.5, config=WiringCheckParams(enabled=False))
    assert verdict is None


def test_non_finite_samples_are_skipped():
    check = WiringCheck(WiringCheckParams(), PARAMS, PERIOD)
    check.wheels(0.0, math.nan, 1.0)
    assert check.imu(0.0, math.nan, 0.0, 0.0, (0.0, 0.0, 9.8)) is None
    with pytest.raises(ValueError):
        WiringCheck(WiringCheckParams(), PARAMS, 0.0)


def test_a_wiring_fault_zeroes_the_torque_at_once_is_latched_and_listed_first():
    from wip_control.core.eso import StateEstimate
    from wip_control.core.safety import ACTIVE, FAULT, SafetyMonitor, STARTING
    from wip_control.core.safety_config import SafetyParams
    monitor = SafetyMonitor(SafetyParams(), 10.0, 1e6, PERIOD, timing_checks=False)
    estimate = [0.0] * len(StateEstimate._fields)

    def tick(t):
        monitor.estimate(t, estimate, True)
        monitor.yaw_torque(t, 1.0)
        monitor.drive_torque(t, 4.0)
        return monitor.update(t)

    assert tick(0.0).state == ACTIVE
    verdict, _ = run('right_sign')
    monitor.wiring_fault(verdict.reason)
    for k in range(1, 4):      # the next tick and every one after: zero, latched
        decision = tick(k * PERIOD)
        assert decision.state == FAULT and decision.zeroed
        assert decision.command == (0.0, 0.0)
        assert decision.reasons[0].startswith('wiring: right_wheel_sign: ')
    ok, message = monitor.reset()
    assert ok and 'wiring: right_wheel_sign' in message
    assert monitor.update(4 * PERIOD).state in (STARTING, ACTIVE)


def _open_loop(mistake, tau_v, tau_omega, seconds=0.3):
    """Feed a check ``seconds`` of constant commanded torques on a base that yaws slowly.

    The base's tilt follows eq. (1) with the drive torque it really gets; its yaw rate stays
    at 0.1 rad/s (below min_yaw_rate: the yaw check has no excitation). Returns the verdict.
    """
    check = WiringCheck(WiringCheckParams(), PARAMS, PERIOD, configured=CONFIGURED)
    theta, theta_dot, yaw_rate = 0.0, 0.0, 0.1
    tau_l, tau_r = 0.5 * (tau_v - tau_omega), 0.5 * (tau_v + tau_omega)
    physical = {'left_sign': -tau_l + tau_r, 'imu_yaw_pi': tau_l + tau_r}[mistake]
    for k in range(int(round(seconds / PERIOD))):
        t = k * PERIOD
        pitch, pitch_rate = theta, theta_dot
        if mistake == 'imu_yaw_pi':
            pitch, pitch_rate = -pitch, -pitch_rate
        wheel = yaw_rate * PARAMS.track_width / (2.0 * PARAMS.wheel_radius)
        check.wheels(t, -wheel if mistake != 'left_sign' else wheel, wheel)
        verdict = check.imu(t, pitch, pitch_rate, yaw_rate)
        if verdict is not None:
            return verdict
        check.torque(t, tau_l + tau_r, True, tau_r - tau_l)
        terms = nominal_terms(PARAMS, theta, yaw_rate, theta_dot)
        theta_dot += (terms.f3 + terms.g3 * physical) * PERIOD
        theta += theta_dot * PERIOD
    return None


def test_a_wrong_wheel_sign_is_not_named_as_the_imu_mounting_before_the_yaw_check():
    # One wheel mirrored: the base's drive torque is the commanded yaw torque. With
    # τω = −0.8 τυ the pitch responds like −0.8 X, inside the tilt check's band, long
    # before the slow yaw gives the yaw check its excitation: the tilt check must leave
    # the verdict to it (±X' = ±∫ g3 τω dt explains the response, −X does not as well).
    assert _open_loop('left_sign', tau_v=5.0, tau_omega=-4.0) is None
    # The IMU turned by π with the same torques: the response is −X, and it is named.
    verdict = _open_loop('imu_yaw_pi', tau_v=5.0, tau_omega=-4.0)
    assert verdict is not None and verdict.parameter == MOUNTING, verdict


def test_fall_pick_up_reset_and_engage_again_gives_no_gravity_fault():
    # A correctly mounted IMU: at rest upright, engaged and balancing, a fall (torque cut,
    # the body rotates to 1.4 rad onto its bumper and lies there still, gravity 1.4 rad
    # from +z: past max_gravity_angle 1.0), a reset while lying, picked up, held upright
    # and still, engaged again. Lying still on the bumper is the gravity check's
    # signature of an IMU on its side: only a check limited to before the first engage
    # tells the two apart (the sensors cannot).
    check = WiringCheck(WiringCheckParams(), PARAMS, PERIOD, configured=CONFIGURED)
    g = PARAMS.gravity
    t = 0.0
    theta = 0.0

    def samples(seconds, engaged, target=None):
        nonlocal t, theta
        n = int(round(seconds / PERIOD))
        start = theta
        for k in range(n):
            previous = theta
            if target is not None:          # a smooth rotation from start to target
                theta = start + (target - start) * 0.5 * (1 - math.cos(math.pi * (k + 1) / n))
            rate = (theta - previous) / PERIOD
            check.wheels(t, 0.0, 0.0)
            verdict = check.imu(t, theta, rate, 0.0,
                                (g * math.sin(theta), 0.0, g * math.cos(theta)))
            assert verdict is None, (t, theta, verdict.reason)
            check.torque(t, 2.0 if engaged else 0.0, engaged, 0.0)
            t += PERIOD

    samples(0.5, False)                     # at rest before the first engage: checked
    samples(1.0, True)                      # balancing
    samples(0.4, False, target=1.4)         # the fall: torque cut at once
    samples(5.0, False)                     # lying still on the bumper
    check.reset()                           # the user resets the safety layer
    samples(1.0, False)
    samples(1.0, False, target=0.0)         # picked up
    samples(1.0, False)                     # held upright and still
    samples(1.0, True)                      # engaged again
    # The same lying still before any engage is a verdict: the check itself still works.
    fresh = WiringCheck(WiringCheckParams(), PARAMS, PERIOD, configured=CONFIGURED)
    lying = (g * math.sin(1.4), 0.0, g * math.cos(1.4))
    verdicts = [fresh.imu(k * PERIOD, 1.4, 0.0, 0.0, lying) for k in range(20)]
    assert verdicts[-1] is not None and 'on its side' in verdicts[-1].message
