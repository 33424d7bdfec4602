"""The bag tools on a bag recorded from the node graph (``scripts/run_graph --record``).

A short lockstep run of the paper scenario through the whole graph; then ``bag_info``,
``bag_repair`` and the open-loop re-run on its bag, as a user would chain them.
"""

import json
import pathlib
import subprocess

import pytest
import yaml

from bagtools_helpers import child_environment, REPO_ROOT
from wip_bag.bag_info import bag_information
from wip_bag.bag_repair import repair_bag
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

RUN_GRAPH = REPO_ROOT / 'scripts' / 'run_graph'
DURATION = 2.0  # [s] of simulation: 400 control ticks, 20 MPC ticks
# The graph's controller nodes and the re-run call the same core objects with the same
# inputs (the graph in lockstep is bit-for-bit the runner, see tests/graph); only the MPC's
# QP solver may differ between two solver instances in two processes: ProxSuite stops at
# its tolerance eps_abs = 1e-6, and a solve that takes one iteration more or less lands
# elsewhere within it. Measured: mostly 0 on the estimates and 1e-11 N m on the torques,
# but 2.6e-8 and 1.6e-7 N m in 2 of about 10 runs (1e-9 failed then, CI included). The
# bound is the solver's tolerance.
TOLERANCE = 1e-6


@pytest.fixture(scope='module')
def graph_bag(tmp_path_factory):
    if not RUN_GRAPH.is_file():
        pytest.skip('scripts/run_graph does not exist yet')
    out = tmp_path_factory.mktemp('graph')
    env = child_environment()
    env['ROS_DOMAIN_ID'] = str(take_private_domain())
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    result = subprocess.run(
        [str(RUN_GRAPH), '--duration', str(DURATION), '--record', str(out / 'bag'),
         '--out', str(out / 'run')], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    return out / 'bag'


def test_bag_info_and_repair_of_a_graph_bag(graph_bag, tmp_path):
    info = bag_information(graph_bag)
    assert info['problems'] == []
    counts = {t['name']: t['count'] for t in info['topics']}
    ticks = int(round(DURATION * 200))
    assert counts['/joint_states'] == counts['/imu/data'] == ticks
    assert counts['/wip/ground_truth'] == ticks + 1
    # In lockstep the MPC node answers every control tick, where it looks for a push (a
    # solve, or its held torque between solves: docs/history/mpc.md §10, §14).
    assert counts['/wip/drive_torque'] == ticks
    before = yaml.safe_load((graph_bag / 'metadata.yaml').read_text())
    # A healthy bag: its file copied as it is, the same metadata, the original untouched.
    result = repair_bag(graph_bag, out=tmp_path / 'repaired')
    assert [f.action for f in result.files] == ['copied'] and not result.lost
    assert yaml.safe_load((tmp_path / 'repaired' / 'metadata.yaml').read_text()) == before
    assert yaml.safe_load((graph_bag / 'metadata.yaml').read_text()) == before


def test_rerun_reproduces_the_graph_run(graph_bag, tmp_path):
    out = tmp_path / 'rerun'
    result = subprocess.run(
        [str(REPO_ROOT / 'scripts' / 'rerun'), str(graph_bag), '--out', str(out),
         '--no-figures', '--quiet'], env=child_environment(), capture_output=True, text=True,
        timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    comparison = json.loads((out / 'comparison.json').read_text())
    for key, entry in comparison.items():
        assert entry['compared'] > 0, key
        for field, figures in entry['fields'].items():
            assert figures['max_abs_difference'] <= TOLERANCE, (key, field, figures)
    metrics = json.loads((out / 'metrics.json').read_text())
    assert pathlib.Path(metrics['rerun']['scenario_source']).name == 'scenario.yaml'
