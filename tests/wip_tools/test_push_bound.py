"""The clairvoyant push-recovery bound (wip_tools.analysis.push_bound) against closed forms.

Model (1) linearised about upright: with w = u + J_θ θ̇ / (mp l), ẇ = g θ + d, so a push of
Δv is absorbed only by leaning, ∫ θ dt = −Δv / g. With the tilt the only limit (torque and
torque rate unbounded), the least peak e lies within J_θ θmax / (mp l) of
E1 = ∫ (P(t) − g θmax t) dt up to the time that integrand reaches 0 (P(t) the push's speed
so far): leaning back at once by θmax reaches it with the lean's own +J_θ θmax/(mp l);
no sequence can do better than E1 less that lean. The full plant also puts the motors'
reaction torque on the body: then ẇ = k θ + d with k = g mp l / (mv r + mp l) and the lean
term (J_θ + mp l r) θmax / (mv r + mp l) (the elimination of τυ from its two equations).
"""

import dataclasses
import math

import numpy as np
import pytest

from wip_description.params import ModelParams
from wip_tools.analysis.push_bound import absorption_rate, push_excursion_bound
from wip_tools.analysis.push_recovery import (measured_excursion, state_at_push,
                                              torques_before_push)

PARAMS = ModelParams()
FAST = dict(horizon=6.0)
UNLIMITED = dict(max_torque=1e5, max_delta_torque=1e5)


def _tilt_only_integral(delta_v, push_time, max_tilt, g):
    """E1 of the module docstring, by quadrature on a fine grid."""
    t = np.linspace(0.0, 5.0 * delta_v / (g * max_tilt) + push_time, 200001)
    speed = np.minimum(t / push_time, 1.0) * delta_v - g * max_tilt * t
    return float(np.trapezoid(np.clip(speed, 0.0, None), t))


@pytest.mark.parametrize('body_mass, com_height', [(25.0, 0.6), (30.0, 0.66), (10.0, 1.2)])
def test_a_lean_absorbs_speed_at_g_per_radian_whatever_the_body(body_mass, com_height):
    params = dataclasses.replace(PARAMS, body_mass=body_mass, com_height=com_height)
    assert absorption_rate(params) == pytest.approx(params.gravity, rel=1e-12)


def _full_rate_and_lean(params, max_tilt):
    """Return (k, the lean term) of the full plant, from its equations of motion."""
    mp_l, r = params.body_mass * params.com_height, params.wheel_radius
    inertia = params.effective_mass * r + mp_l
    return (params.gravity * mp_l / inertia,
            (params.pitch_inertia + mp_l * r) / inertia * max_tilt)


@pytest.mark.parametrize('body_mass, com_height', [(25.0, 0.6), (30.0, 0.66), (10.0, 1.2)])
def test_with_the_reaction_torque_a_lean_absorbs_less_than_g(body_mass, com_height):
    # m_v υ̇ + mp l θ̈ = τ/r and mp l υ̇ + J_θ θ̈ − mp g l θ = −τ: r times the first plus the
    # second has no τ, (mv r + mp l) υ̇ + (J_θ + mp l r) θ̈ = mp g l θ.
    params = dataclasses.replace(PARAMS, body_mass=body_mass, com_height=com_height)
    rate, _ = _full_rate_and_lean(params, 0.1)
    assert absorption_rate(params, 'full') == pytest.approx(rate, rel=1e-12)
    assert rate < params.gravity


def test_no_push_needs_no_excursion():
    bound = push_excursion_bound(PARAMS, 0.0)
    assert bound.excursion == 0.0 and not np.any(bound.torque)


def test_with_the_tilt_the_only_limit_the_bound_is_the_closed_forms():
    g, theta_max = PARAMS.gravity, 0.1
    lean = PARAMS.pitch_inertia / (PARAMS.body_mass * PARAMS.com_height) * theta_max
    e1 = _tilt_only_integral(1.0, 0.1, theta_max, g)
    assert e1 == pytest.approx(0.4597, abs=1e-3)       # 1 / (2 g θmax) less the push's ramp
    bound = push_excursion_bound(PARAMS, 1.0, **UNLIMITED, **FAST)
    assert e1 - lean - 1e-3 <= bound.excursion <= e1 + lean + 0.01
    assert np.max(np.abs(bound.tilt)) <= theta_max + 1e-6


def test_with_the_reaction_torque_the_tilt_only_bound_is_its_closed_form():
    theta_max = 0.1
    rate, lean = _full_rate_and_lean(PARAMS, theta_max)
    e1 = _tilt_only_integral(1.0, 0.1, theta_max, rate)
    bound = push_excursion_bound(PARAMS, 1.0, **UNLIMITED, **FAST, model='full')
    assert e1 - lean - 1e-3 <= bound.excursion <= e1 + lean + 0.01
    # And with the torque limits it needs more than model (1) (0.70 m).
    limited = push_excursion_bound(PARAMS, 1.0, **FAST, model='full').excursion
    assert limited > push_excursion_bound(PARAMS, 1.0, **FAST).excursion + 0.1


def test_the_torque_limits_cost_excursion_and_the_paper_plant_needs_0_70_m():
    unlimited = push_excursion_bound(PARAMS, 1.0, **UNLIMITED, **FAST).excursion
    bound = push_excursion_bound(PARAMS, 1.0, step=0.02, **FAST)
    assert bound.excursion > unlimited + 0.1
    assert bound.excursion == pytest.approx(0.70, abs=0.01)
    # The optimal sequence keeps every limit and ends at rest.
    assert np.max(np.abs(bound.torque)) <= 30.0 + 1e-6
    lag = 5                                               # 0.1 s on the 0.02 s grid
    torque = np.concatenate([np.zeros(lag), bound.torque])
    assert np.max(np.abs(torque[lag:] - torque[:-lag])) <= 10.0 + 1e-6
    assert abs(bound.tilt[-1]) < 1e-6 and np.max(bound.error) == pytest.approx(
        bound.excursion, abs=1e-6)


def test_scaling_the_push_and_every_limit_together_scales_the_bound():
    # The LP is homogeneous: (Δv, θmax, τmax, Δτmax) → λ (…) scales every feasible
    # sequence, and so the optimum, by λ.
    limits = dict(max_tilt=0.1, max_torque=30.0, max_delta_torque=10.0)
    full = push_excursion_bound(PARAMS, 1.0, **limits, **FAST).excursion
    half = push_excursion_bound(PARAMS, 0.5, **{k: 0.5 * v for k, v in limits.items()},
                                **FAST).excursion
    assert half == pytest.approx(0.5 * full, rel=1e-5)


def test_the_bound_grows_with_the_push_convexly_and_is_symmetric():
    values = [push_excursion_bound(PARAMS, dv, **FAST).excursion for dv in (0.25, 0.5, 1.0)]
    assert 0.0 < values[0] < values[1] < values[2]
    # An LP's value is convex in a right-hand side linear in Δv, and 0 at Δv = 0.
    assert values[1] >= 2.0 * values[0] - 1e-6 and values[2] >= 2.0 * values[1] - 1e-6
    backward = push_excursion_bound(PARAMS, -0.5, **FAST).excursion
    assert backward == pytest.approx(values[1], rel=1e-6)


@pytest.mark.parametrize('delay', [0.04, 0.06, 0.1])
def test_a_late_reaction_costs_at_most_the_push_times_the_delay(delay):
    # Fewer choices: not less. The zero-delay optimum applied `delay` late is feasible,
    # and e then exceeds its peak by at most what the push adds meanwhile, Δv · delay.
    on_time = push_excursion_bound(PARAMS, 1.0, **FAST).excursion
    late = push_excursion_bound(PARAMS, 1.0, **FAST, reaction_delay=delay)
    assert on_time - 1e-6 <= late.excursion <= on_time + 1.0 * delay + 1e-6
    assert not np.any(late.torque[:int(round(delay / 0.02))])


def test_the_grid_is_fine_enough():
    coarse = push_excursion_bound(PARAMS, 1.0, step=0.02, **FAST).excursion
    fine = push_excursion_bound(PARAMS, 1.0, step=0.01, **FAST).excursion
    assert fine == pytest.approx(coarse, rel=0.005)


@pytest.mark.parametrize('kwargs, message', [
    (dict(delta_v=math.nan), 'delta_v must be a finite number'),
    (dict(delta_v=1.0, max_tilt=0.0), 'max_tilt must be > 0'),
    (dict(delta_v=1.0, step=0.5), 'need step <='),
    (dict(delta_v=20.0, horizon=1.0), 'no torque sequence within the limits'),
    (dict(delta_v=1.0, model='mujoco'), 'model must be one of'),
    (dict(delta_v=1.0, reaction_delay=-0.1), 'reaction_delay must be in'),
])
def test_bad_arguments_and_impossible_pushes_are_one_line_errors(kwargs, message):
    with pytest.raises(ValueError, match=message) as error:
        push_excursion_bound(PARAMS, **kwargs)
    assert '\n' not in str(error.value)


def test_the_measured_excursion_is_the_along_track_peak_after_the_push():
    # A reference on the circle of radius 2 at 0.5 m/s; the vehicle on it, then 0.3 m
    # ahead along its tangent between 11 and 12 s (a push at 10 s), 0.1 m ahead before.
    t = np.arange(0.0, 20.0, 0.005)
    beta = 0.25 * t
    ahead = np.where((t >= 11.0) & (t < 12.0), 0.3, 0.1)
    ref = {'t': t, 'x': 2 * np.cos(beta), 'y': 2 * np.sin(beta), 'phi': beta + math.pi / 2}
    truth = {'t': t, 'x': ref['x'] + ahead * np.cos(ref['phi']),
             'y': ref['y'] + ahead * np.sin(ref['phi'])}
    assert measured_excursion({'truth': truth, 'reference': ref}, 10.0) == pytest.approx(0.2)


def test_the_state_at_the_push_is_the_speed_error_tilt_and_rate_interpolated_there():
    # The vehicle 0.1 m/s faster than a 0.5 m/s reference, leaning 0.02 rad at 0.002
    # rad/s at 10 s, all varying linearly in time between the samples.
    t = np.arange(0.0, 20.0, 0.01)
    truth = {'t': t, 'v': 0.5 + 0.01 * t, 'theta': 0.002 * t, 'theta_dot': 0.0002 * t}
    ref = {'t': t, 'v': np.full_like(t, 0.5)}
    state = state_at_push({'truth': truth, 'reference': ref}, 10.0)
    assert state == pytest.approx((0.1, 0.02, 0.002), abs=1e-12)


def test_the_torques_before_the_push_are_those_in_force_on_the_bounds_grid():
    # A truth row at t holds the torques applied over the 5 ms that end at t: a torque
    # that is 1 N m per wheel until 9.95 s and 3 N m after is recorded from 9.955 s on.
    t = np.round(np.arange(0.0, 20.0, 0.005), 9)
    per_wheel = np.where(t <= 9.95 + 1e-9, 1.0, 3.0)
    record = {'truth': {'t': t, 'tau_left': per_wheel, 'tau_right': per_wheel}}
    # In force at 9.90, 9.92, 9.94 (2 N m), then 9.96, 9.98 (6 N m).
    assert torques_before_push(record, 0.1, 0.02, 10.0) == pytest.approx([2, 2, 2, 6, 6])


def test_from_a_state_on_the_optimal_path_the_bound_is_the_rest_of_its_peak():
    # Bellman: the optimum's tail from its state at 0.1 s (the push over) is optimal for
    # the problem that starts there, with the torques of the last 0.1 s as the rate
    # limit's past and the time left as the horizon; its peak is the rest, P − e(0.1).
    whole = push_excursion_bound(PARAMS, 1.0, horizon=6.0)
    k = 5                                                   # 0.1 s on the 0.02 s grid
    state = (whole.speed[k], whole.tilt[k], whole.tilt_rate[k])

    def tail(earlier):
        return push_excursion_bound(PARAMS, 0.0, horizon=6.0 - 0.1, initial_state=state,
                                    earlier_torques=earlier).excursion

    assert whole.error[k] > 0.05 and np.all(np.diff(whole.error[:k + 1]) > 0.0)
    assert tail(whole.torque[:k]) == pytest.approx(whole.excursion - whole.error[k], abs=1e-4)
    # The past torques (+10 N m) bind the first windows: a past of 0 lets the torque
    # reverse sooner (less run-on), a past of −10 N m holds it back (more).
    assert tail(()) < tail(whole.torque[:k]) - 3e-3
    assert tail(-whole.torque[:k]) > tail(whole.torque[:k]) + 3e-3


def test_from_a_state_a_push_back_is_the_mirror_of_one_ahead():
    start, earlier = (0.08, 0.015, -0.05), (1.0, 2.0, 3.0, 2.5, 2.0)
    ahead = push_excursion_bound(PARAMS, 1.0, initial_state=start, earlier_torques=earlier,
                                 **FAST)
    back = push_excursion_bound(PARAMS, -1.0, initial_state=[-v for v in start],
                                earlier_torques=[-v for v in earlier], **FAST)
    assert back.excursion == pytest.approx(ahead.excursion, rel=1e-6)
    assert back.tilt == pytest.approx(-ahead.tilt, abs=1e-6)
    # Met moving ahead already, the push needs more run-on than from rest (0.70 m).
    assert ahead.excursion > push_excursion_bound(PARAMS, 1.0, **FAST).excursion + 0.05


def test_a_row_is_the_median_and_percentiles_of_its_runs_ratios():
    from wip_tools.analysis.push_recovery import _summary
    # Ten runs, ratios 1.0 .. 1.9 against their own bounds (1 m), excursions 1.0 .. 1.9 m.
    runs = [{'excursion': 1.0 + 0.1 * i, 'bound': 1.0, 'state': (0.0, 0.0, 0.0),
             'rate_kept': i != 3} for i in range(10)]
    row = _summary(runs, 0.5, 1.3)
    assert row['ratio'] == pytest.approx(1.45) and row['ratio_rest'] == pytest.approx(2.9)
    assert (row['ratio_p10'], row['ratio_p90']) == pytest.approx((1.09, 1.81))
    assert row['halves'] == pytest.approx([1.2, 1.7]) and not row['met']
    assert row['halves_rest'] == pytest.approx([2.4, 3.4]) and row['rate_kept'] == 9
    fell = _summary(runs[:9] + [{**runs[9], 'excursion': math.inf}], 0.5, 2.0)
    assert fell['fell'] and fell['falls'] == 1 and not fell['met']


def test_a_case_runs_and_its_excursion_is_above_the_bound():
    from wip_tools.analysis.push_recovery import push_recovery_rows
    (row,) = push_recovery_rows([('line', 'paper', False, False)])
    assert not row['fell']
    # Without noise the push finds the vehicle at rest on its reference: the bound's start.
    assert row['at_rest'] and row['speed_error_at_push'] < 1e-3
    assert row['bound_m'] == pytest.approx(0.70, abs=0.01)
    # At rest, the bound from the state the push found is the one from rest.
    assert row['bound_m'] == pytest.approx(row['bound_rest_m'], abs=1e-3)
    # No controller beats the clairvoyant one on its own model (the paper plant is it).
    assert 1.0 < row['ratio'] == pytest.approx(row['measured_m'] / row['bound_m'])
    # A push along the motion never lifts the rate limit: the bound's limit is the run's.
    assert row['rate_kept'] == row['runs'] == 1


def test_the_largest_change_within_a_period_counts_the_torque_in_force_before_it():
    from wip_tools.analysis.push_recovery import largest_change_within
    # Solves every 0.05 s (the re-solve grid), Ts = 0.1 s: 0 -> 6 -> 10 -> 16 -> 16. The 0
    # is in force until 0.05 s, so within 0.1 s of the 10 applied at 0.1 s: 10, as the
    # 6 -> 16 of 0.05 -> 0.15 s; over 0.2 s the whole 0 -> 16.
    group = {'t': [0.0, 0.05, 0.1, 0.15, 0.2], 'tau_v': [0.0, 6.0, 10.0, 16.0, 16.0]}
    assert largest_change_within(group, 0.1) == pytest.approx(10.0)
    assert largest_change_within(group, 0.2) == pytest.approx(16.0)
    # Two re-solves of 6 N m within Ts move the torque by 12 N m in it.
    assert largest_change_within({'t': [0.0, 0.05, 0.1], 'tau_v': [0.0, 6.0, 12.0]},
                                 0.1) == pytest.approx(12.0)
    assert largest_change_within({'t': [], 'tau_v': []}, 0.1) == 0.0


def test_the_full_plant_is_measured_against_its_own_equations():
    from wip_sim.core.scenario import scenario_from_mapping
    from wip_tools.analysis.push_recovery import push_scenario_mapping, scenario_bound
    scenario = scenario_from_mapping(push_scenario_mapping('line', 'full', mismatch=True))
    rate, _ = _full_rate_and_lean(scenario.plant.parameters, 0.1)
    bound = scenario_bound(scenario, 1.0, 0.1)
    model_one = push_excursion_bound(scenario.plant.parameters, 1.0)
    # The run-on Δv²/(2 k θmax) grows as 1/k; the torque limits' share stays about the same.
    assert bound.excursion - model_one.excursion == pytest.approx(
        0.5 / (0.1 * rate) - 0.5 / (0.1 * scenario.plant.parameters.gravity), rel=0.35)


def test_the_bench_names_the_runs_set_against_the_impact_rate():
    from wip_tools.bench import _impact_note
    assert _impact_note({'runs': 40, 'rate_kept': 40}) == ''
    assert _impact_note({'runs': 40, 'rate_kept': 38}) == ' (2 of 40 runs at the impact rate)'


def test_a_state_where_highs_stops_without_a_status_is_solved_by_another_method():
    """Solve a state where HiGHS stops without a status (paper plant's noisy push, seed 23).

    Its automatic choice, dual simplex and interior point stop with 'model status Unknown';
    without presolve it solves, as do the states 1e-6 m/s beside it, within 1e-5 m.
    """
    state = (-0.02653194694638844, 0.005628279822642661, 0.017383473416211992)
    earlier = [0.056235950275114244] * 5
    bound = push_excursion_bound(PARAMS, 1.0, initial_state=state, earlier_torques=earlier)
    for du in (-1e-6, 1e-6):
        beside = push_excursion_bound(PARAMS, 1.0, initial_state=(state[0] + du, *state[1:]),
                                      earlier_torques=earlier)
        assert bound.excursion == pytest.approx(beside.excursion, abs=1e-5)
