"""``scripts/estop``: the e-stop of a running graph without ros2cli.

A test node stands in for the mixer (a /wip/estop subscription and a
/torque_mixer/reset_estop service); the front door runs as its own process in the test's
domain.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest

rclpy = pytest.importorskip('rclpy')
from ros_harness import spinning_in_background  # noqa: E402

pytestmark = pytest.mark.ros

REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]


def front_door(*args, domain=None, timeout=60):
    env = dict(os.environ)
    if domain is not None:
        env['ROS_DOMAIN_ID'] = str(domain)
    else:
        env.pop('ROS_DOMAIN_ID', None)
    return subprocess.run([sys.executable, '-m', 'wip_bringup.estop', *args], env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def mixer(test_node):
    from std_msgs.msg import Bool
    from std_srvs.srv import Trigger
    received = []
    state = {'refuse': True}
    # A node named as the mixer: scripts/estop waits for the mixer's own subscription.
    mixer_node = rclpy.create_node('torque_mixer', context=test_node.context)
    test_node.executor_for_test.add_node(mixer_node)
    mixer_node.create_subscription(Bool, '/wip/estop', lambda m: received.append(m.data), 10)

    def reset(request, response):
        response.success = not state['refuse']
        response.message = 'refused: /wip/estop still says true' if state['refuse'] else 'ok'
        return response
    test_node.create_service(Trigger, '/torque_mixer/reset_estop', reset)
    with spinning_in_background(test_node.executor_for_test):
        yield received, state
    mixer_node.destroy_node()


def test_engage_release_and_reset_reach_the_mixer(domain, mixer):
    received, state = mixer
    engage = front_door('engage', '--domain', str(domain))
    assert engage.returncode == 0, engage.stderr
    release = front_door('release', domain=domain)  # from $ROS_DOMAIN_ID
    assert release.returncode == 0, release.stderr
    assert received == [True] * 4 + [False]     # an engage is sent four times
    refused = front_door('reset', '--domain', str(domain))
    assert refused.returncode == 1
    assert 'reset refused: refused: /wip/estop still says true' in refused.stdout
    state['refuse'] = False
    done = front_door('reset', '--domain', str(domain))
    assert done.returncode == 0 and 'reset done' in done.stdout


def test_bad_arguments_are_one_line_errors(domain):
    for args, text in ((('stop', '--domain', '3'), "invalid choice: 'stop'"),
                       (('engage', '--domain', '999'), 'not in 0..232')):
        result = front_door(*args)
        assert result.returncode == 2, result
        assert text in result.stderr and 'Traceback' not in result.stderr
    # Nothing there: a clear message, not a hang.
    lonely = front_door('engage', '--domain', str(domain), '--timeout', '1')
    assert lonely.returncode == 1
    assert '/torque_mixer does not subscribe to /wip/estop' in lonely.stderr


def test_scripts_estop_drops_the_private_defaults_of_scripts_env_as_hardware_mode_does():
    # scripts/_env.sh gives a shell without ROS settings a pid-derived domain and
    # localhost-only discovery, and lists them in WIP_ROS_DEFAULTS: the e-stop must go to
    # the robot's network instead, ROS's defaults (domain 0, SUBNET), as hardware mode.
    env = {k: v for k, v in os.environ.items()
           if k not in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'WIP_ROS_DEFAULTS')}
    script = REPO_ROOT / 'scripts' / 'estop'
    result = subprocess.run([str(script), 'engage', '--timeout', '0.5'], env=env,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result
    assert 'in domain 0 (discovery range SUBNET)' in result.stderr, result.stderr
    # A domain the user set is theirs (kept), whatever scripts/_env.sh would choose.
    env['ROS_DOMAIN_ID'] = '0'
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    mine = subprocess.run([str(script), 'engage', '--timeout', '0.5'], env=env,
                          capture_output=True, text=True, timeout=60)
    assert 'in domain 0 (discovery range LOCALHOST)' in mine.stderr, mine.stderr
