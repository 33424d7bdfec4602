"""The in-process runner gives the controllers only what a robot's controllers know."""

import numpy as np
import pytest

from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import scenario_from_mapping


def test_wheel_odometry_uses_the_nominal_wheel_radius_not_the_true_one():
    # The controllers think the wheels are 10 % larger than they are: the distance rolled
    # that they measure, x_v = r_nominal * (wheel angle), is 10 % longer than the true one
    # (as for the eso node and scripts/rerun, which know only the nominal model).
    true_radius, nominal_radius = 0.20, 0.22
    scenario = scenario_from_mapping({
        'duration': 10.0, 'reference': {'kind': 'line'},
        'plant': {'parameters': {'wheel_radius': true_radius}},
        'controller_model': {'parameters': {'wheel_radius': nominal_radius}}})
    result = run_scenario(scenario)
    assert not result.fell
    truth, estimate = result.record['truth'], result.record['estimate']
    # After 10 s the vehicle has rolled ~5 m; the initial x_v(0) = 0.1 m is measured
    # with the same scale, so the ratio is r_nominal / r_true to the ESO's lag.
    assert estimate['x_v'][-1] / truth['x_v'][-1] == pytest.approx(
        nominal_radius / true_radius, rel=2e-3)


def test_the_recorded_columns_are_the_named_tuples_fields_in_order():
    # The runner records (t, *ref[:5]), (t, *estimate[:9], x, y), (t, *command) and
    # (t, *arc): that relies on the fields being in the record's column order.
    from wip_control.core.arc import ArcOutput
    from wip_control.core.eso import StateEstimate
    from wip_sim.core.record import GROUPS
    from wip_control.core.references import ReferenceState
    from wip_control.core.trajectory_generator import VelocityCommand
    assert GROUPS['reference'] == ('t', *ReferenceState._fields[:5])
    assert GROUPS['estimate'] == ('t', *StateEstimate._fields[:9], 'x', 'y')
    assert StateEstimate._fields[9:] == ('epsilon',)
    assert GROUPS['command'] == ('t', *VelocityCommand._fields)
    assert GROUPS['arc'] == ('t', *ArcOutput._fields)


def test_the_record_does_not_depend_on_where_its_blocks_end(monkeypatch):
    # The runner turns its rows into numpy blocks every BLOCK_ROWS ticks: with blocks of
    # 7 rows (flushes at ticks that are not MPC ticks, and a partial last block) the
    # record is the same as with one block, value for value.
    from wip_sim.core.record import RecordBuffer
    scenario = scenario_from_mapping({'duration': 0.6, 'mpc': {'backend': 'daqp'}})
    whole = run_scenario(scenario).record
    monkeypatch.setattr(RecordBuffer, 'BLOCK_ROWS', 7)
    blocked = run_scenario(scenario).record
    for group, columns in whole.groups.items():
        assert columns.keys() == blocked.groups[group].keys()
        for name, values in columns.items():
            if name != 'solve_time':
                assert np.array_equal(blocked.groups[group][name], values,
                                      equal_nan=True), (group, name)
    assert len(whole['truth']['t']) == 121 and len(whole['mpc']['t']) == 6
