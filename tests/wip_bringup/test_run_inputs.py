"""What a user gives run_graph and check_base is checked before anything starts.

Params files against the one declaration of each node parameter, --remap rules, every numeric
option, the scenario's duration. Each refusal is one line on stderr, exit 2, and the run's output
folder holds no logs (no node process was started).
"""

import pathlib
import re
import subprocess
import sys

import pytest
import yaml

from wip_bringup.hardware_params import hardware_parameters
from wip_bringup.params_check import (check_params_files, check_remap, ParamsFileError,
                                      unmatched_remaps)
from wip_bringup.params_files import CONTROLLER_NODES
from wip_sim.core.scenario import Scenario

REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
GENERATED = hardware_parameters(Scenario())


def readme_params_file():
    """Return the base's params file the README shows (its yaml block with ros__parameters)."""
    text = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    (block,) = [b for b in re.findall(r'```yaml\n(.*?)```', text, re.S)
                if 'ros__parameters' in b]
    return yaml.safe_load(block)


def check(data, nodes=CONTROLLER_NODES, namespace=''):
    return check_params_files([('base.yaml', data)], nodes, GENERATED, namespace)


def section(parameters, key='/**'):
    return {key: {'ros__parameters': parameters}}


def test_the_readme_params_file_passes():
    assert check(readme_params_file()) == []


@pytest.mark.parametrize('data, message', [
    (section({'left_wheel_sing': 1}, 'torque_mixer'),
     "--params-file base.yaml: unknown parameter 'left_wheel_sing' for node torque_mixer "
     "(did you mean 'left_wheel_sign'?)"),
    (section({'max_tilt': 0.2}, 'mpc'),
     "unknown parameter 'max_tilt' for node mpc (did you mean 'mpc.max_tilt'?)"),
    (section({'model.wheel_radius': 'abc'}),
     "node eso: model.wheel_radius: expected a number, got 'abc'"),
    (section({'model.wheel_radius': -1.0}),
     'node eso: model.wheel_radius: must be > 0.0, got -1.0'),
    (section({'model.wheel_radius': 1}),
     'node eso: model.wheel_radius: expected a floating-point number (ROS reads 1 as an '
     'integer: write 1.0), got 1'),
    (section({'imu_mounting_rpy': [0, 0, 0]}), 'imu_mounting_rpy[0]: expected a floating'),
    (section({'left_wheel_sign': 2}), 'left_wheel_sign: must be 1 or -1, got 2'),
    (section({'position_source': 'gsp'}), "position_source: 'gsp' is not one of"),
    (section({'joints': ['a', 'b']}), 'joints: must list left_joint'),
    (section({'left_wheel_sign': 1}, 'torque_mixr'),
     "unknown node section 'torque_mixr' (did you mean 'torque_mixer'?)"),
    (section({'use_sim_time': 'yes'}), 'use_sim_time: expected true or false'),
])
def test_a_bad_params_file_is_refused_in_one_line(data, message):
    with pytest.raises(ParamsFileError) as refused:
        check(data)
    assert message in str(refused.value) and '\n' not in str(refused.value)


def test_sections_by_node_name_namespace_and_wildcard_apply():
    assert check(section({'mpc.max_tilt': 0.2}, 'mpc')) == []
    assert check(section({'mpc.max_tilt': 0.2}, '/**/mpc')) == []
    assert check(section({'mpc.max_tilt': 0.2}, '/robot/mpc'), namespace='robot') == []
    assert check(section({'mpc.max_tilt': 0.2}, '/*/mpc'), namespace='/robot') == []
    assert check(section({'use_sim_time': False, 'qos_overrides./x.depth': 5})) == []
    # A node of the project that this run does not start: a warning, not an error.
    assert check(section({'output': '/tmp/x'}, 'recorder')) == [
        "--params-file base.yaml: section 'recorder': no such node in this run (ignored)"]
    # rcl gives a section to the node of that namespace only: 'mpc' is /mpc.
    assert check(section({'mpc.max_tilt': 0.2}, '/robot/mpc')) == [
        "--params-file base.yaml: section '/robot/mpc': no such node in this run (ignored)"]
    assert check(section({'mpc.max_tilt': 0.2}, 'mpc'), namespace='robot') == [
        "--params-file base.yaml: section 'mpc': no such node in this run under /robot "
        '(ignored)']
    # ... and its values are not checked against that node (rcl never gives them to it).
    assert check(section({'mpc.max_tilt': -5.0}, '/other/mpc'), namespace='robot') != []
    with pytest.raises(ParamsFileError, match='max_tilt'):
        check(section({'mpc.max_tilt': -5.0}, '/**/mpc'), namespace='robot')


@pytest.mark.parametrize('rule, message', [
    ('/imu/data:=/my imu', "'/my imu' is not a valid ROS topic name"),
    ('/imu/data:=/base/1imu', "'/base/1imu' is not a valid ROS topic name"),
    ('/imu/data=/base/imu', '--remap: expected FROM:=TO'),
    ('/imu/data:=', '--remap: expected FROM:=TO'),
])
def test_a_bad_remap_rule_is_refused(rule, message):
    with pytest.raises(ParamsFileError, match=re.escape(message)):
        check_remap(rule)


def test_a_remap_that_matches_no_topic_warns():
    assert check_remap('imu/data:=/base/imu') == ('/imu/data', '/base/imu')
    (line,) = unmatched_remaps([('/imu/dta', '/base/imu'), ('/imu/data', '/b')],
                               ['/imu/data', '/joint_states'])
    assert line.startswith('--remap /imu/dta:=/base/imu: no topic /imu/dta')
    assert "did you mean '/imu/data'?" in line


def run(tmp_path, *args, module='wip_bringup.graph'):
    return subprocess.run([sys.executable, '-m', module, *map(str, args)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=180,
                          stdin=subprocess.DEVNULL)


def no_logs(out):
    """No node was started: the run's folder holds no logs (at most the lock file)."""
    return not out.exists() or {p.name for p in out.iterdir()} <= {'.run_graph.lock'}


@pytest.fixture
def files(tmp_path):
    made = {}
    for name, data in {'typo': section({'left_wheel_sing': 1}, 'torque_mixer'),
                       'type': section({'model.wheel_radius': 'abc'}),
                       'range': section({'model.wheel_radius': -1.0}),
                       'node': section({'left_wheel_sign': 1}, 'torque_mixr')}.items():
        made[name] = tmp_path / f'{name}.yaml'
        made[name].write_text(yaml.safe_dump(data), encoding='utf-8')
    made['zero_ticks'] = tmp_path / 'zero_ticks.yaml'
    made['zero_ticks'].write_text('duration: 1e-9\n', encoding='utf-8')
    return made


@pytest.mark.parametrize('args, message', [
    (['--mode', 'hardware', '--params-file', '{typo}'],
     "unknown parameter 'left_wheel_sing' for node torque_mixer (did you mean "
     "'left_wheel_sign'?)"),
    (['--mode', 'hardware', '--params-file', '{type}'], 'model.wheel_radius: expected a number'),
    (['--mode', 'hardware', '--params-file', '{range}'], 'model.wheel_radius: must be > 0.0'),
    (['--mode', 'hardware', '--params-file', '{node}'], "unknown node section 'torque_mixr'"),
    (['--mode', 'hardware', '--remap', '/imu/data:=/my imu'],
     "'/my imu' is not a valid ROS topic name"),
    (['--discovery-timeout', '0'], '--discovery-timeout: must be > 0'),
    (['--stall-timeout', '0'], '--stall-timeout: must be > 0'),
    (['--startup-retries', '-1'], '--startup-retries: must be >= 0'),
    (['--duration', '36000'], 'more than the 1e+06 one run may have'),
    (['--mode', 'hardware', '--duration', '-1'], '--duration: must be > 0'),
    (['--mode', 'hardware', '--rt-priority', '100'], '--rt-priority: must be >= 0 and <= 99'),
    (['--mode', 'hardware', '--arm-delay', 'nan'], "--arm-delay: 'nan' is not a finite"),
    (['--scenario', '{zero_ticks}'], 'the run would have no control tick'),
])
def test_run_graph_refuses_bad_input_before_any_process_starts(tmp_path, files, args,
                                                               message):
    out = tmp_path / 'run'
    done = run(tmp_path, *[a.format(**files) for a in args], '--out', out)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], done.stderr
    assert 'Traceback' not in done.stderr + done.stdout
    assert no_logs(out)


def test_check_base_refuses_a_bad_params_file_before_it_listens(tmp_path, files):
    done = run(tmp_path, '--params-file', files['typo'], '--auto', '--timeout', '1',
               module='wip_bringup.check_base')
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"check_base: error: --params-file {files['typo']}: unknown parameter "
        "'left_wheel_sing' for node torque_mixer (did you mean 'left_wheel_sign'?)"]
    assert 'ROS network' not in done.stderr   # refused before it joined the network
