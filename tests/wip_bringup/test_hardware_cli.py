"""``scripts/run_graph --no-plant`` (hardware mode) from the command line, with no base.

Without a base the controllers come up, say which of the base's topics are missing, and
the safety layer never engages: every effort command sent on the (remapped) command topic
is zero, and the runner sends zeros again when it stops the nodes.
"""

import json
import os
import subprocess
import sys
import time

import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from std_msgs.msg import Float64MultiArray  # noqa: E402

from ros_harness import spinning_in_background  # noqa: E402

from wip_bringup.hardware_params import (load_params_file, node_parameters,  # noqa: E402
                                     parse_remap, remapped)
from wip_bringup.launcher import GraphError  # noqa: E402
from wip_bringup.standin_run import SHORT_ARM_DELAY  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

EFFORT = '/base/effort_controller/commands'


def test_remap_and_params_file_helpers():
    assert parse_remap('joint_states:=/base/joint_states') == ('/joint_states',
                                                               '/base/joint_states')
    for bad in ('/a', '/a:=', ':=/b', '/a:=/b:=/c'):
        with pytest.raises(GraphError, match='--remap: expected FROM:=TO'):
            parse_remap(bad)
    rules = [('/imu/data', '/base/imu'), ('/imu/data', '/other')]
    assert remapped('/imu/data', rules) == '/base/imu'     # the first rule wins, as in ROS
    assert remapped('/gps/fix', rules) == '/gps/fix'
    generated = {'eso': {'ros__parameters': {'left_joint': 'a', 'model': {'wheel_radius': 0.2}}}}
    extra = [{'/**': {'ros__parameters': {'left_joint': 'b'}}},
             {'eso': {'ros__parameters': {'model': {'wheel_radius': 0.1}}}},
             {'mpc': {'ros__parameters': {'left_joint': 'c'}}}]
    assert node_parameters('eso', generated, extra) == {'left_joint': 'b',
                                                        'model.wheel_radius': 0.1}


def test_a_malformed_params_file_is_refused(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump({'eso': {'left_joint': 'x'}}))
    with pytest.raises(GraphError, match='has no ros__parameters'):
        load_params_file(path)


def test_the_single_process_layout_is_refused_in_hardware_mode(tmp_path):
    # 'single' puts the plant in the controllers' process: there is no plant on a robot.
    done = subprocess.run([sys.executable, '-m', 'wip_bringup.graph', '--mode', 'hardware',
                           '--layout', 'single', '--out', str(tmp_path / 'out')],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == (
        "run_graph: error: --layout: 'single' is not one of ['separate', 'composed'] "
        '(single holds the plant: simulation only)')
    assert not (tmp_path / 'out').exists()


# Wall clock: a 3 s real-time run whose zero commands this process must take in time.
@pytest.mark.wallclock
def test_no_plant_without_a_base_never_commands_torque(tmp_path, test_node):
    params = tmp_path / 'base.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'left_joint': 'wheel_l', 'right_joint': 'wheel_r', 'joints': ['wheel_r', 'wheel_l'],
        'left_wheel_sign': -1}}}))
    received = []
    test_node.create_subscription(Float64MultiArray, EFFORT,
                                  lambda m: received.append(list(m.data)), 100)
    out = tmp_path / 'run'
    # The run inherits the test's DDS domain (conftest's private_dds_domain). Armed after
    # the tests' short delay (the arming is not under test here): the 3 s of --duration
    # count from the arming, armed and without a base.
    with spinning_in_background(test_node.executor_for_test):
        result = subprocess.run(
            [sys.executable, '-m', 'wip_bringup.graph', '--no-plant', '--duration', '3',
             '--arm-delay', str(SHORT_ARM_DELAY),
             '--out', str(out), '--params-file', str(params), '--remap',
             '/joint_states:=/base/joint_states', '--remap',
             f'/effort_controller/commands:={EFFORT}', '--foxglove', '0'],
            capture_output=True, text=True, timeout=120)
        time.sleep(0.5)
    # The controllers never engaged: exit 5, with the reason (no inputs from the base).
    assert result.returncode == 5, result.stdout + result.stderr
    assert result.stdout.startswith('NEVER ENGAGED: the controllers never engaged (the '
                                    'duration of 3 s was reached)'), result.stdout
    assert 'no inputs from the base: nothing on /base/joint_states' in result.stdout
    # The network in use, and what the graph shows when no base topic appears.
    domain = os.environ['ROS_DOMAIN_ID']
    assert (f'ROS network: ROS_DOMAIN_ID={domain}, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST'
            in result.stderr)
    (missing,) = [line for line in result.stderr.splitlines() if 'no base topic' in line]
    assert ('expected publishers on /base/joint_states, /imu/data, /gps/fix and a '
            f'subscription on {EFFORT}; the graph shows ') in missing
    assert 'may be on another ROS_DOMAIN_ID or discovery range' in missing
    # The test's own listener is the one node besides the run's own.
    assert f'the graph shows {EFFORT} of other nodes' in missing
    run = json.loads((out / 'run.json').read_text())
    assert run['mode'] == 'hardware'
    # The base's topics under their remapped names, none present.
    assert run['base_topics']['/base/joint_states'] == {'publishers': 0}
    assert run['base_topics'][EFFORT] == {'subscriptions': 1}     # the test's listener
    assert 'no publisher on /base/joint_states' in result.stderr
    assert {e['state'] for e in run['safety_events']} <= {'STARTING', 'FAULT'}
    # The default layout: the six controller nodes in one process; the viewer (on by
    # default) and the Foxglove bridge (--foxglove 0) in their own.
    assert set(run['node_exit_codes']) == {'controllers', 'viewer', 'foxglove_bridge'}
    assert run['node_exit_codes']['foxglove_bridge'] == 0
    assert 'live view: open ws://127.0.0.1:' in result.stderr
    # No plant in the generated parameters; the reference starts with the engagement.
    generated = yaml.safe_load((out / 'params.yaml').read_text())
    assert 'plant' not in generated
    assert generated['reference']['ros__parameters']['realtime_start'] == 'engaged'
    assert generated['eso']['ros__parameters']['clock_mode'] == 'realtime'
    # Every command the base would have got: zero, two joints (the mixer's ticks and the
    # runner's zeros at the stop).
    assert received and all(c == [0.0, 0.0] for c in received)
    assert run['zero_commands_sent'] >= 1
