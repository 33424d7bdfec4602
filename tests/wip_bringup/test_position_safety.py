"""The position is checked before it is believed, and a runaway is stopped (hardware mode).

Against the stand-in base (wip_bringup.standin_run: its own process, real time, a real
robot's conventions), whose position outputs can be given a fault (``position_fault.*``):

1. A datum copied from elsewhere (hundreds of km from the fixes): refused before engaging,
   the message names ``datum`` and the fix's latitude/longitude; the base is never
   released. A datum 2 km off (believed): the runaway guard stops it within 1 s.
2. A receiver that jumps 50 m for half a second mid-run: the fixes are rejected (counted),
   the run goes on, and the base moves less than 1 m off its course because of it.
3. A receiver that jumps 50 m for good: a position fault (zero torque, exit 1) within
   ``max_rejection_time`` plus a tick or two, naming the cause.
4. A position source that freezes while the wheels roll: the runaway guard faults
   within the time and distance derived in docs/safety.md.
5. Dead reckoning (``position_source: wheels``): engages without any GPS and drives a
   teleop square; its drift against the truth is measured.

Criteria are on the base's ground truth (its stats file), never on wall-clock timings.
"""

from __future__ import annotations

import math

import pytest

pytest.importorskip('rclpy')

from wip_bringup.standin_run import (BASE, line_scenario, run_against_standin,  # noqa: E402
                                     SHORT_ARM_DELAY)
from wip_description.sensors import SensorParams  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.wallclock]

SPEED = 0.5          # [m/s] the line's
FAULT_START = 4.0    # [s] after the release


def truth(stats):
    """Return the base's ground truth samples as dicts (t, x, y, phi, theta, v)."""
    samples = stats['truth']
    if isinstance(samples, dict):
        keys = list(samples)
        return [dict(zip(keys, values)) for values in zip(*samples.values())]
    return samples


def at(samples, t):
    return min(samples, key=lambda s: abs(s['t'] - t))


def fault_event(result):
    return next((e for e in result.safety_events if e['state'] == 'FAULT'), None)


@pytest.mark.parametrize('kind', ['line', 'cmd_vel'])
def test_a_datum_hundreds_of_km_off_is_refused_before_engaging(tmp_path, kind):
    # A path and a teleop alike: the controllers never engage on a position 490 km away.
    wrong = dict(BASE, **{'datum.latitude': SensorParams().gps_datum_latitude + 4.4})

    def refused(runner):
        return (runner is not None and runner.position_error
                and any(e['state'] == 'FAULT' for e in runner.safety_events)
                and 'the datum was refused')
    run = run_against_standin(tmp_path / 'datum', wrong, 5.0, stop_when=refused,
                              runner_duration=90.0, scenario=line_scenario(SPEED, kind=kind),
                              arm_delay=SHORT_ARM_DELAY)
    result = run.result
    assert result.exit_code == 5, result.message          # never engaged
    assert not run.stats['released']                        # no torque ever reached it
    assert 'datum' in result.message and 'latitude 38.88' in result.message, result.message
    assert 'km from the datum' in result.message, result.message


def test_a_datum_2_km_off_is_stopped_by_the_runaway_guard_before_the_base_runs_away(tmp_path):
    # Under max_datum_distance, so the fixes are believed: the line's start is then 2 km
    # from the estimate, and the generator drives at its limit toward it. The guard's
    # absurd-error rule cuts the torque 1 s after the engagement.
    wrong = dict(BASE, **{'datum.latitude': SensorParams().gps_datum_latitude + 0.018})
    run = run_against_standin(tmp_path / 'datum2km', wrong, 10.0, arm_delay=SHORT_ARM_DELAY)
    result = run.result
    assert result.exit_code == 1, result.message
    assert 'max_tracking_error' in result.message and 'datum' in result.message
    samples = truth(run.stats)
    first = samples[0]
    cut = at(samples, 1.0 + 0.2)        # the verdict, and a tick or so of transport
    assert math.hypot(cut['x'] - first['x'], cut['y'] - first['y']) < 1.5


def test_a_brief_50_m_jump_is_rejected_and_does_not_move_the_base(tmp_path):
    fault = {'position_fault.kind': 'offset', 'position_fault.start': FAULT_START,
             'position_fault.duration': 0.5, 'position_fault.offset': [50.0, 0.0]}
    run = run_against_standin(tmp_path / 'jump', BASE, 10.0, base_extra=fault,
                              arm_delay=SHORT_ARM_DELAY)
    result, stats = run.result, run.stats
    assert result.exit_code == 0, result.message
    assert stats['released'] and not stats['fell']
    eso = next(v for k, v in result.node_diagnostics.items() if k.startswith('/eso'))
    assert int(eso['GPS fixes rejected']) >= 4, eso    # 5 fixes at 10 Hz, all refused
    # The base's course: from just before the jump, along the line at the line's speed.
    samples = truth(stats)
    before = at(samples, FAULT_START - 0.1)
    worst = 0.0
    for s in samples:
        if FAULT_START - 0.1 <= s['t'] <= FAULT_START + 3.0:
            dt = s['t'] - before['t']
            expected = (before['x'] + SPEED * dt * math.cos(before['phi']),
                        before['y'] + SPEED * dt * math.sin(before['phi']))
            worst = max(worst, math.hypot(s['x'] - expected[0], s['y'] - expected[1]))
    assert worst < 1.0, worst


def test_a_persistent_50_m_jump_is_a_position_fault_with_its_cause(tmp_path):
    fault = {'position_fault.kind': 'offset', 'position_fault.start': FAULT_START,
             'position_fault.offset': [50.0, 0.0]}
    run = run_against_standin(tmp_path / 'jump_for_good', BASE, 12.0, base_extra=fault,
                              arm_delay=SHORT_ARM_DELAY)
    result = run.result
    assert result.exit_code == 1, result.message
    assert 'position source refused' in result.message, result.message
    assert 'from the odometry' in result.message, result.message
    # Zero torque by the base's clock: it fell (torque cut) no sooner than the rejection
    # time after the jump, and it had not been driven away before that.
    samples = truth(run.stats)
    start = at(samples, FAULT_START)
    cut = run.stats['fall_time_s'] if run.stats['fell'] else samples[-1]['t']
    assert cut > FAULT_START + 1.0 - 0.05
    lost = at(samples, FAULT_START + 1.0)
    dt = lost['t'] - start['t']
    course = (start['x'] + SPEED * dt * math.cos(start['phi']),
              start['y'] + SPEED * dt * math.sin(start['phi']))
    assert math.hypot(lost['x'] - course[0], lost['y'] - course[1]) < 1.0


def test_a_frozen_position_is_a_runaway_stopped_within_its_bound(tmp_path):
    fault = {'position_fault.kind': 'freeze', 'position_fault.start': FAULT_START}
    run = run_against_standin(tmp_path / 'freeze', BASE, 16.0, base_extra=fault,
                              arm_delay=SHORT_ARM_DELAY)
    result = run.result
    assert result.exit_code == 1, result.message
    assert 'runaway' in result.message, result.message
    samples = truth(run.stats)
    # The torque is cut at the verdict; the base falls after it. Where it fell bounds where
    # it was at the verdict: ahead of its reference by the guard's growth bound (2 m) plus
    # what it rolls while it falls (about 1 s at up to the 1.5 m/s speed limit).
    assert run.stats['fell'], 'zero torque makes a balancing robot fall'
    end = at(samples, run.stats['fall_time_s'])
    reference = (SPEED * end['t'], 0.0)   # the line from the map origin, from the release
    ahead = math.hypot(end['x'] - reference[0], end['y'] - reference[1])
    assert ahead < 2.0 + 1.5 * 1.5, (ahead, end, reference)
    # docs/safety.md: the frozen estimate first holds the robot back (its reference runs
    # on), then the generator drives it past: the verdict within 10 s of the freeze.
    assert run.stats['fall_time_s'] - FAULT_START < 10.0


class OpenLoopTeleop:
    """A person with a joystick: a 5 m square, timed on the wall clock (real time).

    Forward at 1 m/s for SIDE / SPEED s, a left turn at TURN rad/s for π/2 / TURN s (with a
    pause between), four times, then zero; it keeps the newest state estimate.
    """

    SIDE, SPEED, TURN, PAUSE = 5.0, 1.0, 0.3, 1.0   # TURN: the limit of the reference

    def __init__(self) -> None:
        import os

        import rclpy
        import rclpy.executors
        from geometry_msgs.msg import TwistStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from wip_msgs.msg import StateEstimate
        self.rclpy, self.TwistStamped = rclpy, TwistStamped
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(os.environ['ROS_DOMAIN_ID']))
        self.node = rclpy.create_node('teleop_square', context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.publisher = self.node.create_publisher(TwistStamped, 'cmd_vel', 10)
        self.estimate = None
        self.node.create_subscription(
            StateEstimate, '/wip/state_estimate', self._on_estimate,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))

    def _on_estimate(self, msg) -> None:
        self.estimate = msg

    def _hold(self, seconds: float, v: float, omega: float) -> None:
        import time
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = self.TwistStamped()
            msg.header.stamp = self.node.get_clock().now().to_msg()
            msg.twist.linear.x, msg.twist.angular.z = v, omega
            self.publisher.publish(msg)
            self.executor.spin_once(timeout_sec=0.05)

    def drive_square(self) -> None:
        for _ in range(4):
            self._hold(self.SIDE / self.SPEED, self.SPEED, 0.0)
            self._hold(self.PAUSE, 0.0, 0.0)
            self._hold(0.5 * math.pi / self.TURN, 0.0, self.TURN)
            self._hold(self.PAUSE, 0.0, 0.0)
        self._hold(3.0, 0.0, 0.0)   # at rest: the last estimate is where it stopped

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def test_dead_reckoning_drives_a_20_m_teleop_square_with_its_drift_measured(tmp_path):
    # No GPS at all: position_source wheels (the ESO subscribes no position topic, and
    # hardware mode looks for none), a cmd_vel reference, a teleop square.
    wheels = dict(BASE, position_source='wheels')
    # The teleop's speed and turn rate within the commanded reference's limits.
    scenario = line_scenario(OpenLoopTeleop.SPEED, kind='cmd_vel',
                             commanded_max_speed=OpenLoopTeleop.SPEED,
                             commanded_max_acceleration=1.0,
                             commanded_max_yaw_rate=OpenLoopTeleop.TURN,
                             commanded_max_yaw_acceleration=1.0)
    final = {}
    # The teleop joins the DDS graph before the run, as a user starts it before arming:
    # a participant that appears while the robot balances can stall the controllers for a
    # third of a second (docs/driving.md), which made the robot fall at the release.
    # (The run uses this test session's domain, as the teleop does.)
    driver = OpenLoopTeleop()

    def teleop(_runner, _processes):
        driver.drive_square()
        final['estimate'] = driver.estimate
    try:
        run = run_against_standin(tmp_path / 'square', wheels, 200.0, scenario=scenario,
                                  during=teleop, end_after_during=0.5, arm_delay=SHORT_ARM_DELAY)
    finally:
        driver.close()
    stats = run.stats
    assert run.result.exit_code == 0, run.result.message
    assert stats['released'] and not stats['fell']
    samples = truth(stats)
    first, last = samples[0], samples[-1]
    perimeter = sum(math.hypot(b['x'] - a['x'], b['y'] - a['y'])
                    for a, b in zip(samples, samples[1:]))
    assert perimeter > 15.0, perimeter       # the square was driven (about 20 m)
    est = final['estimate']
    # Dead reckoning's frame starts where the robot stood, with the IMU's (absolute) yaw.
    drift = math.hypot(est.x - (last['x'] - first['x']), est.y - (last['y'] - first['y']))
    (tmp_path / 'drift.txt').write_text(f'{drift:.4f} m over {perimeter:.2f} m\n')
    # docs/safety.md states the measured drift; the bound is 2 % of the distance driven.
    assert drift < 0.02 * perimeter, (drift, perimeter)
