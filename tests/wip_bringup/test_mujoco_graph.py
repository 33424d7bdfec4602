"""The MuJoCo plant (plant: {model: mujoco}) behind the ROS graph.

The plant node in lockstep ends where the in-process runner ends, in real time it keeps the vehicle
up, and the stand-in base simulates a robot with it against the controllers in hardware mode.
"""

import pathlib

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')
pytest.importorskip('mujoco')

from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping  # noqa: E402
from wip_bringup.graph import GraphOptions, run_graph  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402
from wip_bringup.standin_run import (BASE, line_scenario, run_against_standin,  # noqa: E402
                                     SHORT_ARM_DELAY)

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SCENARIO = pathlib.Path(__file__).resolve().parents[2] / 'scenarios' / 'mujoco_paper.yaml'
DURATION = 3.0  # [s]
CONTROL_PERIOD = 0.005  # [s]


def _graph(tmp_path, monkeypatch, **options):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(take_private_domain()))
    scenario = dict(yaml.safe_load(SCENARIO.read_text()), duration=DURATION)
    path = tmp_path / 'scenario.yaml'
    path.write_text(yaml.safe_dump(scenario))
    return run_graph(GraphOptions(scenario=str(path), out=str(tmp_path / 'run'), quiet=True,
                                  layout='single', **options))


def test_lockstep_graph_ends_where_the_in_process_runner_ends(tmp_path, monkeypatch):
    result = _graph(tmp_path, monkeypatch)
    assert result.exit_code == 0, result.message
    assert result.plant_stats['ticks'] == round(DURATION / CONTROL_PERIOD)
    scenario = scenario_from_mapping(dict(yaml.safe_load(SCENARIO.read_text()),
                                          duration=DURATION))
    assert scenario.plant.model.model == 'mujoco'
    truth = run_scenario(scenario).record['truth']
    final = result.plant_stats['final_state']
    # The same plant code on the same inputs: the graph's last state is the runner's. The
    # equation plants match to the bit (test_lockstep.py); with MuJoCo the two differ by
    # 1.3e-10 m after 3 s (measured; each is reproducible on its own, the cause of the
    # difference is not found yet), so the bound is 1e-8 in SI units: far below anything
    # physical, far above the difference.
    for name, value in final.items():
        assert value == pytest.approx(truth[name][-1], rel=0.0, abs=1e-8), name
    assert np.ptp(truth['x']) > 0.1    # it moved


@pytest.mark.wallclock
def test_real_time_graph_keeps_the_mujoco_vehicle_up(tmp_path, monkeypatch):
    result = _graph(tmp_path, monkeypatch, clock='realtime')
    assert result.exit_code == 0, result.message
    stats = result.plant_stats
    # Up for the whole run: the plant ran every tick it had time for, at the wall clock's
    # rate at most (how many it had time for is the machine's; bench measures it).
    assert stats['ticks'] * CONTROL_PERIOD == pytest.approx(stats['sim_time_s'])
    assert 0.0 < stats['real_time_factor'] <= 1.02
    assert abs(stats['final_state']['theta']) < 0.3


@pytest.mark.wallclock
def test_the_standin_base_simulates_a_mujoco_robot_for_hardware_mode(tmp_path):
    run_time = 8.0
    scenario = dict(line_scenario(), plant={'model': 'mujoco'})
    assert scenario_from_mapping(scenario).plant.model.model == 'mujoco'
    run = run_against_standin(tmp_path / 'mujoco', BASE, run_time, scenario=scenario,
                              arm_delay=SHORT_ARM_DELAY)
    result, stats, code = run.result, run.stats, run.base_code
    assert result.exit_code == 0, result.message
    assert code == 0, stats['end_reason']
    assert stats['released'] and not stats['fell']
    truth = {k: np.asarray(v) for k, v in stats['truth'].items()}
    assert np.abs(truth['theta']).max() < 0.3
    # It drove along the line: the same bound as the full-plant stand-in runs.
    assert truth['x'][-1] - truth['x'][0] > 0.6 * 0.5 * run_time
