"""The MPC node and the torque mixer run with one ride-through, or the run is refused.

Both judge lateness by ``core.safety_config.lateness`` with ``safety.max_estimate_age`` and
``safety.bridge_time``, each from its own params-file sections; a file that sets them for one
node only would give the graph two rules. Criterion: every way a params file can reach one
node and not the other (its name's section, ``/name``, ``/**/name``) is refused in one line
that names both values; every way that reaches both (``/**``, both sections alike, nothing
set) passes; a run without both nodes is not judged (each node alone has no peer).
"""

import pathlib
import subprocess
import sys

import pytest
import yaml

from wip_bringup.hardware_params import hardware_parameters
from wip_bringup.params_check import check_params_files, ParamsFileError
from wip_bringup.params_files import CONTROLLER_NODES
from wip_control.core.safety_config import SafetyParams
from wip_sim.core.scenario import Scenario

GENERATED = hardware_parameters(Scenario())
AGE, BRIDGE = SafetyParams.max_estimate_age, SafetyParams.bridge_time


def section(key, **safety):
    return {key: {'ros__parameters': {'safety': safety}}}


def check(data, nodes=CONTROLLER_NODES):
    return check_params_files([('base.yaml', data)], nodes, GENERATED)


@pytest.mark.parametrize('data, message', [
    (section('torque_mixer', max_estimate_age=0.1),
     f"safety.max_estimate_age: mpc {AGE:g} s (default) but torque_mixer 0.1 s (base.yaml, "
     "section 'torque_mixer')"),
    (section('/mpc', bridge_time=0.2),
     f"safety.bridge_time: mpc 0.2 s (base.yaml, section '/mpc') but torque_mixer "
     f'{BRIDGE:g} s (default)'),
    (section('/**/torque_mixer', max_estimate_age=0.1, bridge_time=0.1),
     f'safety.max_estimate_age: mpc {AGE:g} s (default) but torque_mixer 0.1 s'),
    # Both set, to different values: the later file's section decides each node's.
    ({**section('mpc', bridge_time=0.2), **section('torque_mixer', bridge_time=0.25)},
     "safety.bridge_time: mpc 0.2 s (base.yaml, section 'mpc') but torque_mixer 0.25 s "
     "(base.yaml, section 'torque_mixer')"),
    # The wildcard first, then one node's own section overrides it for that node only.
    ({**section('/**', bridge_time=0.2), **section('torque_mixer', bridge_time=0.1)},
     "safety.bridge_time: mpc 0.2 s (base.yaml, section '/**') but torque_mixer 0.1 s"),
])
def test_two_ride_throughs_are_refused_in_one_line_naming_both(data, message):
    with pytest.raises(ParamsFileError) as refused:
        check(data)
    text = str(refused.value)
    assert message in text and '\n' not in text
    assert 'one lateness rule' in text


@pytest.mark.parametrize('data', [
    {},
    section('/**', max_estimate_age=0.1, bridge_time=0.2),
    {**section('mpc', max_estimate_age=0.1), **section('torque_mixer', max_estimate_age=0.1)},
    # rclpy applies a file's matching sections in their order, the later one winning (as
    # a node of rclpy 7 shows): a /** section after the mixer's own gives both nodes its.
    {**section('torque_mixer', bridge_time=0.1), **section('/**', bridge_time=0.2)},
    # The mixer's own safety values that the MPC does not share are the mixer's alone.
    section('torque_mixer', max_estop_age=0.5, fall_threshold=0.3),
])
def test_one_ride_through_passes(data):
    assert check(data) == []


def test_under_a_namespace_only_the_sections_rcl_gives_each_node_count():
    # 'mpc' is the root namespace's node (rcl): under /robot the MPC keeps its default
    # while the mixer's own section sets 0.1, a mismatch a last-name match would miss.
    data = {**section('mpc', max_estimate_age=0.1),
            **section('/robot/torque_mixer', max_estimate_age=0.1)}
    with pytest.raises(ParamsFileError, match=f'mpc {AGE:g} s .default. but torque_mixer 0.1'):
        check_params_files([('base.yaml', data)], CONTROLLER_NODES, GENERATED, 'robot')
    both = {**section('/*/mpc', max_estimate_age=0.1),
            **section('/robot/torque_mixer', max_estimate_age=0.1)}
    assert check_params_files([('base.yaml', both)], CONTROLLER_NODES, GENERATED,
                              'robot') == []


def test_a_run_without_both_nodes_is_not_judged():
    assert check(section('torque_mixer', max_estimate_age=0.1), nodes=['torque_mixer']) == []


def test_run_graph_refuses_two_ride_throughs_before_any_process_starts(tmp_path):
    params = tmp_path / 'base.yaml'
    params.write_text(yaml.safe_dump(section('torque_mixer', max_estimate_age=0.1)),
                      encoding='utf-8')
    out = tmp_path / 'run'
    done = subprocess.run([sys.executable, '-m', 'wip_bringup.graph', '--mode', 'hardware',
                           '--params-file', str(params), '--out', str(out)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=180,
                          stdin=subprocess.DEVNULL)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f'mpc {AGE:g} s (default) but torque_mixer 0.1 s' in lines[0]
    assert not out.exists() or {p.name for p in pathlib.Path(out).iterdir()} <= {
        '.run_graph.lock'}
