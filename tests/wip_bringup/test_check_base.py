"""scripts/check_base against a base whose motions are played by the test.

A helper in this process publishes a base's /base/joint_states and /base/imu at 100 Hz
from a kinematic state (wheel rolling angles, body pitch and yaw) with the base's own
conventions (``wip_sim.base_conventions.BaseConventions``, what the stand-in base publishes
with: joints ``wheel_r``, ``wheel_l`` in that order, the left joint's sign −1, an IMU
upside down and turned a quarter turn, encoders measuring against the body). The
tool runs as its own process (``python -m wip_bringup.check_base``); in ``--script`` mode the
helper answers each ``CHECK_BASE WAIT <step> <phase>`` prompt after performing the
motion a person would, in ``--auto`` mode it plays the motions on a schedule.
"""

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from sensor_msgs.msg import Imu, JointState  # noqa: E402

from wip_description.params import ModelParams  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402
from wip_sim.base_conventions import BaseConventions  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.wallclock]

BASE = {
    'left_joint': 'wheel_l', 'right_joint': 'wheel_r', 'joints': ['wheel_r', 'wheel_l'],
    'left_wheel_sign': -1, 'right_wheel_sign': 1,
    'imu_mounting_rpy': [math.pi, 0.0, math.pi / 2],
}
REMAPS = ['/joint_states:=/base/joint_states', '/imu/data:=/base/imu']
PARAMS = ModelParams()
TILT = math.radians(10.0)       # what the person does: 0.1745 rad
HOLD = 0.45                     # [s] held still before confirming (> the 0.3 s window)
MOTION = 0.3                    # [s] of a motion


class PlayedBase:
    """Publishes the base's topics from a kinematic state that the test moves."""

    def __init__(self, domain_id, conventions=BASE):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id, args=[])
        self.node = rclpy.create_node('played_base', context=self.context)
        self.joint_pub = self.node.create_publisher(JointState, '/base/joint_states', 10)
        self.imu_pub = self.node.create_publisher(Imu, '/base/imu', 10)
        self.conventions = BaseConventions(
            conventions['joints'], conventions['left_joint'], conventions['right_joint'],
            conventions['left_wheel_sign'], conventions['right_wheel_sign'],
            conventions['imu_mounting_rpy'])
        # Rolling angles of the wheels [rad], body pitch and yaw [rad].
        self.state = {'left': 0.0, 'right': 0.0, 'pitch': 0.0, 'yaw': 0.4}
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._publish_loop, daemon=True)
        self.thread.start()

    def _publish_loop(self):
        joint, imu = JointState(), Imu()
        while not self.stop.is_set():
            with self.lock:
                s = dict(self.state)
            # Encoders measure the wheel against the body: joint = rolling angle - pitch.
            wheels = (s['left'] - s['pitch'], s['right'] - s['pitch'])
            self.conventions.fill(joint, imu, wheels, (0.0, 0.0), (0.0, 0.0), s['pitch'],
                                  s['yaw'], 0.0, 0.0, PARAMS.gravity)
            stamp = self.node.get_clock().now().to_msg()
            joint.header.stamp = imu.header.stamp = stamp
            self.joint_pub.publish(joint)
            self.imu_pub.publish(imu)
            time.sleep(0.01)

    def move(self, seconds=MOTION, **deltas):
        """Change the state by ``deltas`` smoothly over ``seconds``, then hold still."""
        with self.lock:
            start = dict(self.state)
        steps = max(1, int(seconds / 0.01))
        for k in range(1, steps + 1):
            with self.lock:
                for key, delta in deltas.items():
                    self.state[key] = start[key] + delta * k / steps
            time.sleep(seconds / steps)

    def hold(self, seconds=HOLD):
        time.sleep(seconds)

    # The person's motions.
    def upright(self):
        with self.lock:
            pitch = self.state['pitch']
        if pitch:
            self.move(pitch=-pitch)
        self.hold()

    def perform(self, step):
        half_turn = 0.5 * PARAMS.track_width * (math.pi / 2) / PARAMS.wheel_radius
        motions = {'upright': {}, 'tilt': {'pitch': TILT},
                   'left_wheel': {'left': 2 * math.pi}, 'right_wheel': {'right': 2 * math.pi},
                   'turn': {'yaw': math.pi / 2, 'right': half_turn, 'left': -half_turn}}
        if motions[step]:
            self.move(**motions[step])
        self.hold()

    def close(self):
        self.stop.set()
        self.thread.join(timeout=2)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def start_tool(tmp_path, domain_id, params, mode):
    params_file = tmp_path / 'base.yaml'
    params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
    command = [sys.executable, '-m', 'wip_bringup.check_base', f'--{mode}', '--params-file',
               str(params_file), '--json', str(tmp_path / 'report.json'), '--timeout', '20']
    for remap in REMAPS:
        command += ['--remap', remap]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    return subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)


def run_script_mode(tmp_path, params):
    domain_id = take_private_domain()
    base = PlayedBase(domain_id)
    tool = start_tool(tmp_path, domain_id, params, 'script')
    output = []
    try:
        for line in tool.stdout:
            output.append(line)
            words = line.split()
            if words[:2] != ['CHECK_BASE', 'WAIT']:
                continue
            step, phase = words[2], words[3]
            if phase == 'ready':
                base.upright()
            else:
                base.perform(step)
            tool.stdin.write('\n')
            tool.stdin.flush()
        code = tool.wait(timeout=30)
    finally:
        if tool.poll() is None:
            tool.kill()
            tool.wait()
        base.close()
    report = json.loads((tmp_path / 'report.json').read_text())
    return code, report, ''.join(output)


def checks_by_name(report):
    return {f'{c["step"]}/{c["name"]}': c for c in report['checks']}


def test_a_correct_configuration_passes_every_check_with_the_expected_numbers(tmp_path):
    code, report, output = run_script_mode(tmp_path, BASE)
    assert code == 0, output
    checks = checks_by_name(report)
    assert all(c['status'] == 'OK' for c in report['checks']), output
    assert set(checks) >= {'connect/left_joint', 'connect/right_joint', 'upright/body_level',
                           'upright/gravity', 'tilt/pitch', 'tilt/encoders_relative_to_body',
                           'left_wheel/sign', 'right_wheel/sign', 'turn/imu_yaw',
                           'turn/odometry'}
    # The played motions come back exactly (noise-free; 1e-6 rad: means of float angles).
    assert checks['tilt/pitch']['measured'] == pytest.approx(TILT, abs=1e-6)
    assert checks['left_wheel/sign']['measured'] == pytest.approx(2 * math.pi, abs=1e-6)
    assert checks['right_wheel/sign']['measured'] == pytest.approx(2 * math.pi, abs=1e-6)
    assert checks['turn/imu_yaw']['measured'] == pytest.approx(math.pi / 2, abs=1e-6)
    assert checks['turn/odometry']['measured'] == pytest.approx(math.pi / 2, abs=1e-6)
    assert checks['tilt/encoders_relative_to_body']['measured'] == pytest.approx(0.0,
                                                                                abs=1e-6)
    # An upside-down IMU: gravity along its -z, as its mounting predicts.
    assert checks['upright/gravity']['measured'] == pytest.approx([0.0, 0.0, -1.0], abs=1e-6)
    assert 'ALL OK' in output


def test_a_flipped_wheel_sign_is_detected_with_the_right_advice(tmp_path):
    code, report, output = run_script_mode(tmp_path, dict(BASE, left_wheel_sign=1))
    assert code == 1, output
    checks = checks_by_name(report)
    left = checks['left_wheel/sign']
    assert left['status'] == 'FAIL'
    assert left['measured'] == pytest.approx(-2 * math.pi, abs=1e-6)
    assert 'sign wrong: set left_wheel_sign to -1' in left['message']
    assert checks['right_wheel/sign']['status'] == 'OK'
    # The turn sees the wheels disagree with the IMU; the IMU checks still pass.
    assert checks['turn/odometry']['status'] == 'FAIL'
    assert checks['turn/imu_yaw']['status'] == 'OK'
    assert checks['tilt/pitch']['status'] == 'OK'
    # While tilting, the wheel joints (measured against the body) turned in opposite
    # directions: blamed on a sign, not on encoders_relative_to_body.
    assert 'a wheel sign is wrong' in checks['tilt/encoders_relative_to_body']['message']


def test_a_wrong_mounting_and_swapped_joints_are_named(tmp_path):
    params = dict(BASE, imu_mounting_rpy=[0.0, 0.0, 0.0], left_joint='wheel_r',
                  right_joint='wheel_l', left_wheel_sign=1, right_wheel_sign=-1)
    code, report, output = run_script_mode(tmp_path, params)
    assert code == 1, output
    checks = checks_by_name(report)
    assert checks['upright/body_level']['status'] == 'FAIL'
    assert checks['upright/gravity']['status'] == 'FAIL'
    assert checks['tilt/pitch']['status'] == 'FAIL'
    swapped = checks['left_wheel/joint_name']
    assert swapped['status'] == 'FAIL'
    assert "set left_joint: 'wheel_l', right_joint: 'wheel_r'" in swapped['message']


def test_auto_mode_detects_the_motions_without_confirmations(tmp_path):
    domain_id = take_private_domain()
    base = PlayedBase(domain_id)
    tool = start_tool(tmp_path, domain_id, BASE, 'auto')
    lines = []

    def wait_for_line(text, timeout=30.0):
        deadline = time.monotonic() + timeout
        while not any(text in line for line in lines):
            assert time.monotonic() < deadline, f'no {text!r} in {lines}'
            time.sleep(0.02)

    reader = threading.Thread(target=lambda: lines.extend(tool.stdout), daemon=True)
    reader.start()
    try:
        for number, step in enumerate(('tilt', 'left_wheel', 'right_wheel', 'turn'), start=2):
            # The tool announces the step, then waits for an upright, still robot (0.5 s)
            # before it looks for the motion: no confirmation is sent.
            wait_for_line(f'step {number}/5 ({step})')
            base.upright()
            base.hold(1.0)
            base.perform(step)
        tool.wait(timeout=30)
        reader.join(timeout=5)
    finally:
        if tool.poll() is None:
            tool.kill()
            tool.wait()
        base.close()
    output = ''.join(lines)
    assert tool.returncode == 0, output
    checks = checks_by_name(json.loads((tmp_path / 'report.json').read_text()))
    assert checks['tilt/pitch']['measured'] == pytest.approx(TILT, abs=1e-6)
    assert checks['left_wheel/sign']['measured'] == pytest.approx(2 * math.pi, abs=1e-6)
    assert checks['turn/imu_yaw']['measured'] == pytest.approx(math.pi / 2, abs=1e-6)


def test_ros_arguments_from_ros2_run_are_split_off_and_remaps_kept():
    from wip_bringup.check_base import split_ros_arguments
    own, remaps = split_ros_arguments(
        ['--auto', '--ros-args', '-r', '/imu/data:=/base/imu', '-p', 'x:=1',
         '--remap', 'a:=b', '--', '--timeout', '5'])
    assert own == ['--auto', '--timeout', '5']
    assert remaps == ['/imu/data:=/base/imu', 'a:=b']
    assert split_ros_arguments(['--script']) == (['--script'], [])


#: Runs check_base with an interrupt (what SIGINT raises) at the worst moment of its
#: start: the listener thread is spinning, the constructor has not returned.
INTERRUPTED_START = """
import sys, threading
from wip_bringup import check_base
real_start = threading.Thread.start
def start_then_interrupt(thread):
    real_start(thread)
    if thread._target.__name__ == '_spin':
        raise KeyboardInterrupt
threading.Thread.start = start_then_interrupt
sys.exit(check_base.main(['--script', '--timeout', '5', '--json', sys.argv[1]]))
"""


def test_an_interrupt_while_the_listener_starts_exits_cleanly(tmp_path):
    # The ros2 run contract test sends SIGINT as soon as the node's subscriptions are
    # visible, which is before BaseListener's constructor returns. The thread then kept
    # spinning into interpreter shutdown, where rclpy's C++ aborted the process
    # ('terminate called without an active exception', exit -6) under load.
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    for _ in range(2):
        done = subprocess.run([sys.executable, '-c', INTERRUPTED_START,
                               str(tmp_path / 'report.json')], env=env, timeout=60,
                              capture_output=True, text=True, stdin=subprocess.DEVNULL)
        assert done.returncode == 130, done.stdout + done.stderr
        assert 'terminate' not in done.stderr and 'Traceback' not in done.stderr, done.stderr
        assert json.loads((tmp_path / 'report.json').read_text())['status'] == 130


def test_sigint_stops_the_check_even_when_it_was_started_with_sigint_ignored(tmp_path):
    # A background job of a non-interactive shell (`scripts/test ... &`, a CI step) starts
    # with SIGINT ignored, and so does every process it starts: the check then waited for
    # data until its timeout instead of stopping (the ros2 run contract test's failure).
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    ignoring = ('import os, signal, sys\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n'
                'os.execv(sys.executable, [sys.executable, "-m", "wip_bringup.check_base", '
                '"--script", "--timeout", "60"])\n')
    tool = subprocess.Popen([sys.executable, '-c', ignoring], env=env, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    try:
        first = tool.stdout.readline()            # the conventions line: it is running
        assert first.startswith('check_base:'), first
        tool.send_signal(signal.SIGINT)
        output, _ = tool.communicate(timeout=20)
    finally:
        if tool.poll() is None:
            tool.kill()
            tool.communicate()
    assert tool.returncode == 130, output
