"""The outcome at an obstacle and the refusal criterion (wip_tools/analysis/criteria.py).

Synthetic records of a line along x into a kerb at x = 5 m, at 200 Hz: the axle stops
with its centre 0.12 m before the edge (a = √(r² − (r − h)²) for r = 0.2 m, h = 4 cm),
is named blocked, and the generator's reference steps back to 0.2 m
(``obstacle_back_off``) behind where it stopped; or the axle rolls past the edge.
"""

import numpy as np
import pytest

from wip_control.core.obstacle import ObstacleState
from wip_sim.core.record import RunRecord
from wip_sim.core.scenario import scenario_from_mapping
from wip_tools.analysis.criteria import Criteria, evaluate, obstacle_outcome

KERB = scenario_from_mapping({'plant': {'model': 'mujoco', 'terrain': {
    'step_position': 5.0, 'step_height': 0.04}}})
H = 0.005
STOP = 5.0 - 0.12
NAMED = ObstacleState(True, 17.0, 'wheels blocked ...')


def _record(x, x_e):
    t = np.arange(len(x)) * H
    zeros = np.zeros_like(t)
    v = np.gradient(x, H)
    return RunRecord({
        'truth': {'t': t, 'x': x, 'y': zeros, 'v': v},
        'estimate': {'t': t, 'x': x, 'y': zeros, 'phi': zeros},
        'command': {'t': t, 'x_e': x_e}})


def refused_run(end_offset=0.0, creep=0.0):
    """Return a run stopped at STOP, refused at 18 s, backed off by 18.5 s, held to 30 s."""
    t = np.arange(0.0, 30.0 + H / 2, H)
    x = np.minimum(0.3 * t, STOP)
    back = np.clip((t - 18.0) / 0.5, 0.0, 1.0) * (0.2 + end_offset) + creep * np.maximum(
        t - 18.5, 0.0)
    x = x - back
    x_e = np.where(t < 18.0, 0.3 * t - x, (STOP - 0.2) - x)   # the hold point from 18 s
    return _record(x, x_e)


def final(record, window=3.0):
    t = record['truth']['t']
    return t >= t[-1] - window


def test_a_run_refused_balanced_is_refused_and_holds_the_back_off_point():
    record = refused_run()
    out = obstacle_outcome(record, KERB, False, NAMED, final(record))
    assert out['outcome'] == 'refused' and out['refused_at'] == pytest.approx(18.0, abs=H)
    assert out['refusal_hold_error'] == pytest.approx(0.0, abs=1e-9)
    assert out['final_speed'] == pytest.approx(0.0, abs=1e-9)
    creeping = refused_run(-0.92, 0.08)
    assert obstacle_outcome(creeping, KERB, False, NAMED, final(creeping))['final_speed'] == (
        pytest.approx(0.08, rel=1e-6))


def test_the_outcomes_are_told_apart():
    record = refused_run()
    # Not named: the step of the reference alone is not a refusal; the axle stayed
    # before the edge: stopped. A fall is a fall whatever came before.
    assert obstacle_outcome(record, KERB, False, None, final(record))['outcome'] == 'stopped'
    assert obstacle_outcome(record, KERB, True, NAMED, final(record))['outcome'] == 'fell'
    t = np.arange(0.0, 30.0, H)
    crossed = _record(0.3 * t, np.zeros_like(t))
    assert obstacle_outcome(crossed, KERB, False, None, final(crossed))['outcome'] == 'crossed'
    flat = scenario_from_mapping({})
    assert obstacle_outcome(crossed, flat, False, None, final(crossed))['outcome'] == ''


def test_a_refusal_the_vehicle_went_on_past_is_a_crossing():
    # Refused at 18 s as the wheels start over the kerb (the reference steps back to the
    # hold point), the axle goes on past the edge (core/obstacle_refusal.py ends the
    # refusal): past it over the whole final window, it crossed and is judged on the path
    # and its end; back before the edge for one sample of that window, it is refused.
    t = np.arange(0.0, 30.0 + H / 2, H)
    x = np.where(t < 18.0, np.minimum(0.3 * t, STOP), STOP + 0.3 * (t - 18.0))
    x_e = np.where(t < 18.0, 0.3 * t - x, (STOP - 0.2) - x)
    went_on = _record(x, x_e)
    out = obstacle_outcome(went_on, KERB, False, NAMED, final(went_on))
    assert out['outcome'] == 'crossed' and out['refused_at'] == pytest.approx(18.0, abs=H)
    x[-1] = 4.99
    back = _record(x, x_e)
    assert obstacle_outcome(back, KERB, False, NAMED, final(back))['outcome'] == 'refused'


def _measured(outcome_values, **overrides):
    values = {'fell': False, 'end_time': 30.0, 'max_wheel_torque': 15.0,
              'max_delta_tau_v': 10.0, 'qp_failures': 0, 'final_position_error': 4.3,
              'max_path_error_after_settle': 0.02, 'max_abs_theta_outside_pulses': 0.09,
              **outcome_values}
    values.update(overrides)
    return values


@pytest.mark.parametrize('end_offset, creep, failed', [
    (0.0, 0.0, set()),                       # at the point, at rest
    (0.19, 0.0, set()),                      # 0.19 m beyond it: within 0.2 m
    (0.22, 0.0, {'refusal_hold_radius'}),    # 0.22 m beyond it
    (-0.92, 0.08, {'refusal_hold_radius'}),  # at the point at the end, creeping at 0.08 m/s:
])                                           # 0.24 m from it 3 s before
def test_with_refusal_passes_a_refused_run_is_judged_on_the_refusal(end_offset, creep, failed):
    record = refused_run(end_offset, creep)
    criteria = Criteria(max_abs_theta_outside_pulses=0.15, max_final_position_error=0.15,
                        final_window=3.0, refusal_passes=True)
    measured = _measured(obstacle_outcome(record, KERB, False, NAMED, final(record)))
    failures = evaluate(measured, criteria, 30.0)
    assert set(failures) == failed, failures
    # The end of the reference is out of reach whether it passes or not; without the
    # option it fails on it, and a refused run keeps every other criterion (the tilt).
    assert 'max_final_position_error' not in failures
    strict = Criteria(max_abs_theta_outside_pulses=0.15, max_final_position_error=0.15)
    assert 'max_final_position_error' in evaluate(measured, strict, 30.0)
    tilted = dict(measured, max_abs_theta_outside_pulses=0.16)
    assert 'max_abs_theta_outside_pulses' in evaluate(tilted, criteria, 30.0)


def test_refusal_passes_does_not_excuse_a_run_that_crossed_or_stopped():
    criteria = Criteria(max_final_position_error=0.15, refusal_passes=True)
    for outcome in ('crossed', 'stopped', ''):
        failures = evaluate(_measured({'outcome': outcome}), criteria, 30.0)
        assert 'max_final_position_error' in failures, outcome
