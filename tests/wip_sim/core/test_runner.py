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
    from wip_control.core.reference_state import ReferenceState
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


def test_each_tick_row_lands_in_its_groups_columns():
    # The loop appends one wide row per tick; the record splits it into the groups of
    # TICK_GROUPS. Every field of the tick's named tuples, each a distinct value, must
    # come back in its own group and column.
    from itertools import count
    from wip_control.core.arc import ArcOutput
    from wip_control.core.control_step import ControlOutputs
    from wip_control.core.eso import StateEstimate
    from wip_control.core.reference_state import ReferenceState
    from wip_control.core.state_estimation import PoseEstimate
    from wip_control.core.trajectory_generator import VelocityCommand
    from wip_sim.core import runner
    from wip_sim.core.record import GROUPS
    from wip_sim.core.simulation import SensorReading

    values = count(1.0)

    def fill(cls, n):
        return cls(*(next(values) for _ in range(n)))

    rec = runner._Recorder()
    rows = []
    for k in range(3):
        t = 0.005 * k
        reading = SensorReading((next(values), next(values)), None,
                                (next(values), next(values)), (next(values), next(values)),
                                False, None)
        ref = fill(ReferenceState, 6)
        pose = PoseEstimate(fill(StateEstimate, 10), next(values), next(values))
        out = ControlOutputs(fill(VelocityCommand, 6), fill(ArcOutput, 3), None,
                             next(values), next(values))
        runner._record_tick(rec, t, reading, ref, pose, out)
        rows.append(dict(
            encoders=(t, *reading.encoders), imu=(t, *reading.imu, *reading.imu_rates),
            reference=(t, *ref[:5]), estimate=(t, *pose.estimate[:9], pose.x, pose.y),
            command=(t, *out.command), arc=(t, *out.arc),
            wheels=(t, out.tau_left, out.tau_right)))
    groups = rec.arrays()
    assert tuple(groups) == runner.RECORDED_GROUPS
    assert set(runner.TICK_GROUPS) | {'truth', 'mpc'} == set(runner.RECORDED_GROUPS)
    for group in runner.TICK_GROUPS:
        assert tuple(groups[group]) == GROUPS[group]
        for k, row in enumerate(rows):
            assert tuple(groups[group][name][k] for name in GROUPS[group]) == row[group]
    assert len(groups['truth']['t']) == 0 and len(groups['mpc']['t']) == 0


def test_the_reference_sampled_in_blocks_is_the_reference_sampled_at_each_tick():
    # The runner samples a pure reference ahead, a block of ticks at a time: the same
    # calls at the same float times, so the same values, across the blocks' ends too. A
    # commanded reference (its sample depends on the commands so far) is not pure.
    from wip_control.core.references import ReferenceParams, make_reference
    from wip_sim.core import runner
    dt = 0.005
    for kind in ('trifolium', 'waypoints', 'figure_eight'):
        blocks = runner._ReferenceBlocks(make_reference(ReferenceParams(kind=kind)), dt,
                                         ticks=7)
        fresh = make_reference(ReferenceParams(kind=kind))
        assert fresh.pure
        for k in range(40):
            assert blocks.at(k) == fresh.sample(k * dt), (kind, k)
    for kind in ('cmd_vel', 'path'):
        assert not make_reference(ReferenceParams(kind=kind)).pure
