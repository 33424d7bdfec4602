"""Hardware mode's network settings and how its runs end (no ROS graph: fast).

Hardware mode and check_base use the user's ROS environment, with ROS's defaults where it
sets nothing (domain 0, SUBNET), not the private defaults scripts/_env.sh gives
simulations; and a hardware run exits 0 only when the controllers engaged and no fall or
safety FAULT followed.
"""

import re

import pytest

from wip_runtime import cli
from wip_bringup import graph, hardware
from wip_bringup.hardware_outcome import format_result, hardware_outcome, HardwareResult
from wip_bringup.hardware_runner import HardwareOptions, HardwareRunner
from wip_bringup.launcher import (EXIT_FELL, EXIT_NOT_ENGAGED, ROS_DEFAULTS_VARIABLE,
                                  ros_network, use_user_ros_environment)
from wip_bringup.processes import graph_environment

ENGAGED = [{'t': 1.0, 'state': 'STARTING', 'reasons': 'waiting: ESO not settled'},
           {'t': 3.0, 'state': 'ACTIVE', 'reasons': 'none'}]
FALL = {'t': 4.5, 'state': 'FAULT',
        'reasons': 'fallen: |theta_hat| 0.412 rad > fall_threshold 0.35 rad'}


# ------------------------------------------------------------------------------ network

def test_scripts_env_defaults_are_dropped_and_ros_defaults_apply():
    env = {'ROS_DOMAIN_ID': '51', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
           ROS_DEFAULTS_VARIABLE: 'ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=51'}
    network = use_user_ros_environment(env)
    assert env == {}
    assert (network.domain_id, network.discovery_range) == (0, 'SUBNET')
    assert network.describe() == 'ROS_DOMAIN_ID=0, ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET'


def test_the_users_own_ros_settings_are_kept():
    # Set by the user before scripts/_env.sh (no record), or changed after it (a harness).
    env = {'ROS_DOMAIN_ID': '12', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
           'ROS_STATIC_PEERS': '192.168.1.7',
           ROS_DEFAULTS_VARIABLE: 'ROS_DOMAIN_ID=51'}
    network = use_user_ros_environment(env)
    assert ROS_DEFAULTS_VARIABLE not in env and env['ROS_DOMAIN_ID'] == '12'
    assert (network.domain_id, network.discovery_range) == (12, 'LOCALHOST')
    assert network.describe().endswith(', ROS_STATIC_PEERS=192.168.1.7')
    assert ros_network({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT'}
                       ).discovery_range == 'SYSTEM_DEFAULT'


def test_hardware_mode_with_nothing_exported_uses_domain_0_and_subnet(tmp_path, monkeypatch):
    # What scripts/run_graph's shell leaves when the user exported nothing.
    monkeypatch.setenv('ROS_DOMAIN_ID', '51')
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.setenv(ROS_DEFAULTS_VARIABLE,
                       'ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=51')
    runner = HardwareRunner(HardwareOptions(out=str(tmp_path / 'run')))
    assert runner.domain_id == 0
    env = graph_environment(runner.domain_id, private=runner.PRIVATE_NETWORK)
    assert env['ROS_DOMAIN_ID'] == '0'
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in env       # ROS's default: SUBNET
    assert runner.network.describe() == ('ROS_DOMAIN_ID=0, '
                                         'ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET')
    # A simulation's nodes stay on this host.
    assert graph_environment(7)['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


# ------------------------------------------------------------------------------ outcome

def test_engaged_and_no_fault_is_success():
    assert hardware_outcome(ENGAGED, 'stopped by SIGINT') == (0, 'stopped by SIGINT')
    # An e-stop of the user's is a stop, not a fault.
    estop = ENGAGED + [{'t': 9.0, 'state': 'ESTOP', 'reasons': 'e-stop'}]
    assert hardware_outcome(estop, 'the duration of 40 s was reached')[0] == cli.EXIT_OK


def test_a_fall_after_engaging_exits_1_with_the_mixers_reason():
    code, message = hardware_outcome(ENGAGED + [FALL], 'the duration of 40 s was reached')
    assert code == cli.EXIT_FAILED == 1
    assert message.startswith('safety FAULT 1.5 s after the controllers engaged: fallen: '
                              '|theta_hat| 0.412 rad')
    assert message.endswith('(then the duration of 40 s was reached)')


def test_a_stand_in_bases_planned_end_is_not_a_fault():
    stale = {'t': 12.8, 'state': 'FAULT', 'reasons': 'stale: /joint_states 0.2 s'}
    assert hardware_outcome(ENGAGED + [stale], 'base exited (0)', base_end_after=10.0)[0] == 0
    assert hardware_outcome(ENGAGED + [FALL], 'base exited (3)', base_end_after=10.0)[0] == 1


def test_never_engaged_exits_5_with_the_reason():
    events = [{'t': 1.0, 'state': 'STARTING', 'reasons': 'waiting: /joint_states missing'}]
    code, message = hardware_outcome(events, 'stopped by SIGINT',
                                     missing=['/joint_states', '/imu/data'])
    assert code == cli.EXIT_NOT_ENGAGED == 5
    assert message == ('the controllers never engaged (stopped by SIGINT); the safety layer '
                       'stayed STARTING: waiting: /joint_states missing; no inputs from the '
                       'base: nothing on /joint_states, /imu/data')
    # A FAULT before engaging (an estimate that never settles) is "never engaged" too.
    settle = [{'t': 5.0, 'state': 'FAULT', 'reasons': 'ESO not settled'}]
    assert hardware_outcome(settle, 'x')[0] == 5
    assert 'no safety state came from the mixer' in hardware_outcome([], 'x')[1]


# -------------------------------------------------------------------- the exit-code table

def test_every_exit_code_is_in_the_table_and_the_docs_that_list_codes():
    codes = {value for name, value in vars(cli).items()
             if name.startswith('EXIT_') and isinstance(value, int)}   # not EXIT_CODES
    assert codes == set(cli.EXIT_CODES)
    rows = {int(code) for code in re.findall(r'^(\d+) {2,}\S', cli.__doc__, re.MULTILINE)}
    assert codes <= rows, codes - rows
    assert EXIT_NOT_ENGAGED == cli.EXIT_NOT_ENGAGED
    assert EXIT_FELL == cli.EXIT_FAILED
    # The codes hardware mode and a real-time simulation end with, in their --help.
    hardware_help = ' '.join(hardware.build_parser().format_help().split())
    for text in ('0 the controllers engaged and the run ended without a safety fault',
                 '1 the vehicle fell or the safety layer went to FAULT after engaging',
                 '5 the controllers never engaged'):
        assert text in hardware_help
    # scripts/run_graph --help (either mode) shows them too.
    graph_help = ' '.join(graph.build_parser().format_help().split())
    for text in ('5 (with --clock realtime) the controllers never engaged',
                 'Hardware mode: 0 the controllers engaged and the run ended without a safety '
                 'fault', '1 the vehicle fell or the safety layer went to FAULT after engaging',
                 '5 the controllers never engaged (no inputs from the base'):
        assert text in graph_help


@pytest.mark.parametrize('code, word', [(0, 'OK'), (1, 'FELL OR FAULT'),
                                        (5, 'NEVER ENGAGED'), (3, 'FAILED')])
def test_the_result_line_names_the_outcome(tmp_path, code, word):
    result = HardwareResult(code, 'why', tmp_path, None, 0)
    assert format_result(result).splitlines()[0] == f'{word}: why'
