"""The in-process runner gives the controllers only what a robot's controllers know."""

import pytest

from wip_control.core.runner import run_scenario
from wip_control.core.scenario import scenario_from_mapping


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
