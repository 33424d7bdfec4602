"""The loop's two core objects.

StateEstimator's start and restart rules, the stages' overflow handling and the drive stage's hold
(core/state_estimation.py, core/control_step.py; the three drivers are cross-checked in
tests/wip_tools/test_single_loop.py).
"""

import dataclasses
import math

import pytest

from wip_control.core.control_step import (ControlOverflow, ControlStep, DriveControllerStage,
                                           TrajectoryGeneratorStage, YawControllerStage)
from wip_control.core.eso import EsoParams
from wip_control.core.mpc_config import MpcParams
from wip_description.params import ModelParams
from wip_control.core.position import PositionParams
from wip_control.core.reference_state import ReferenceState
from wip_sim.core.scenario import Scenario
from wip_description.sensors import wheel_odometry
from wip_control.core.state_estimation import EstimatorOverflow, StateEstimator
from wip_control.core.trajectory_generator import VelocityCommand

MODEL = ModelParams()
H = 0.005


def estimator(**eso):
    return StateEstimator(MODEL, EsoParams(**eso), encoders_relative_to_body=True)


def test_the_estimator_starts_at_the_first_measurements_and_the_position_at_the_first_fix():
    est = estimator(estimator='paper')
    pose = est.update(0.0, 0.4, 0.6, 0.02, 3.0, 0.0, 0.0)
    x_v, _ = wheel_odometry(0.4, 0.6, 0.02, MODEL, 0.0, True)
    assert (pose.estimate.phi, pose.estimate.x_v, pose.estimate.theta) == (3.0, x_v, 0.02)
    assert (pose.estimate.omega, pose.estimate.v, pose.estimate.f2) == (0.0, 0.0, 0.0)
    assert (pose.x, pose.y) == (0.0, 0.0) and not est.has_fix    # dead reckoning from (0, 0)
    # The IMU yaw wraps from +pi to -pi: the estimate stays on the continuous branch.
    pose = est.update(H, 0.4, 0.6, 0.02, 3.0 - 2.0 * math.pi + 0.01, 0.0, 0.0)
    assert pose.estimate.phi == pytest.approx(3.0, abs=0.02)
    # The first fix moves the position to it exactly; later fixes are blended.
    pose = est.update(2 * H, 0.4, 0.6, 0.02, 3.0, 0.0, 0.0, fix=(5.0, -2.0))
    assert (pose.x, pose.y) == (5.0, -2.0) and est.has_fix
    pose = est.update(3 * H, 0.4, 0.6, 0.02, 3.0, 0.0, 0.0, fix=(5.2, -2.0))
    gain = PositionParams().gps_blend_gain    # no odometry motion: the blend alone
    assert pose.x == pytest.approx(5.0 + gain * 0.2, abs=1e-12)


def test_non_finite_input_raises_and_leaves_the_estimator_as_it_was():
    a, b = estimator(), estimator()
    for est in (a, b):
        est.update(0.0, 0.0, 0.0, 0.01, 0.1, 0.0, 0.0, (0.0, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError) as info:
        a.update(H, math.nan, 0.0, 0.01, 0.1, 0.0, 0.0, (0.0, 0.0))
    assert not isinstance(info.value, EstimatorOverflow)
    with pytest.raises(ValueError):
        a.update(H, 0.0, 0.0, 0.01, 0.1, math.inf, 0.0, (0.0, 0.0))
    assert a.update(H, 0.1, 0.1, 0.01, 0.1, 1.0, 0.5, (0.1, 0.0)) == \
        b.update(H, 0.1, 0.1, 0.01, 0.1, 1.0, 0.5, (0.1, 0.0))


def test_an_overflow_raises_and_restarts_the_estimator_from_the_next_sample():
    est = estimator(estimator='paper')
    est.update(0.0, 0.0, 0.0, 0.01, 0.1, 0.0, 0.0, fix=(1.0, 1.0))
    with pytest.raises(EstimatorOverflow, match='overflow'):
        est.update(H, 5e307, 5e307, 0.01, 0.1, 0.0, 0.0)
    assert not est.started and not est.has_fix and est.restarts == 1
    # Restarted as at the first sample: from the measured positions, at this time.
    pose = est.update(2 * H, 0.001, 0.001, 0.01, 0.2, 0.0, 0.0)
    assert pose.estimate.x_v == wheel_odometry(0.001, 0.001, 0.01, MODEL, 0.0, True)[0]
    assert (pose.estimate.phi, pose.x, pose.y) == (0.2, 0.0, 0.0)


def test_the_guidance_and_yaw_stages_keep_their_state_on_overflow():
    guidance = TrajectoryGeneratorStage()
    guidance.step(0.0, ReferenceState(0.0, 0.0, 0.0, 0.5, 0.0, 0.0), 0.0, 0.0, 0.0)
    saved = dict(vars(guidance.generator))
    with pytest.raises(ControlOverflow):
        guidance.step(H, ReferenceState(1e308, 0.0, 0.0, 0.5, 0.0, 0.0), -1e308, 0.0, 0.0)
    assert dict(vars(guidance.generator)) == saved
    yaw = YawControllerStage(None, 0.4, H)
    alpha = yaw.controller.alpha_hat
    # eω = ω̂ − ωd overflows to inf and (13) would give α̂ = inf·0 = NaN.
    with pytest.raises(ControlOverflow):
        yaw.step(1.7e308, 0.0, VelocityCommand(0.0, -1.7e308, 0.0, 0.0, 0.0, 0.0))
    assert yaw.controller.alpha_hat == alpha
    assert yaw.step(0.0, 0.0, VelocityCommand(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)).tau_omega == 0.0


def test_the_generators_state_is_everything_its_step_changes():
    # The guidance stage restores generator.state() after an overflow: every attribute
    # that step() changes (filter, saturation flags) must be in it.
    guidance = TrajectoryGeneratorStage()
    generator = guidance.generator
    reference = ReferenceState(0.0, 0.0, 0.0, 0.5, 0.0, 0.0)
    flags = set()
    for t, ref_y in ((0.0, 0.0), (H, 40.0), (2 * H, -40.0), (3 * H, 0.1)):
        ref = reference._replace(y=ref_y, phi=ref_y / 16.0, v=0.5 + 3.0 * abs(ref_y))
        before, state = dict(vars(generator)), generator.state()
        generator.step(t, ref, 0.0, 0.0, 0.0)
        assert dict(vars(generator)) != before     # the step changed something
        generator.restore(state)
        assert dict(vars(generator)) == before
        generator.step(t, ref, 0.0, 0.0, 0.0)
        flags.add((generator.saturated_speed, generator.saturated_yaw_rate))
    assert {(False, False), (True, True)} <= flags  # the flags were exercised both ways


def test_the_drive_stage_solves_at_its_ticks_and_holds_its_torque():
    # Without the MPC's start-up rule (its first tick acts on no speed error; tested in
    # test_mpc.py): this test asks the first tick for a torque.
    drive = DriveControllerStage(MODEL, MpcParams(backend='daqp', disturbance_startup_time=0.0),
                                 15.0, decimation=4)
    assert [k for k in range(9) if drive.is_tick(k)] == [0, 4, 8]
    # Standing, asked for 0.5 m/s: a torque, held.
    result = drive.step(0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0)
    assert abs(result.tau_v) > 1e-3 and drive.tau_v == result.tau_v
    again = drive.step(0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0, hold=False)
    assert drive.tau_v == result.tau_v and math.isfinite(again.tau_v)
    # The bound 2 τmax − |τω|; a NaN τω gives a NaN bound (the controller's INPUT_INVALID).
    assert drive.limit(10.0) == 20.0 and math.isnan(drive.limit(math.nan))


def _drive_ticks(drive, f2_of_k, ticks, v_d=0.0):
    """(k, result) of the ticks at which ``drive`` solves, standing, f̂2 = f2_of_k(k)."""
    out = []
    for k in range(ticks):
        f2 = f2_of_k(k)
        if drive.is_tick(k) and drive.solves(k, 0.0, f2, 0.0):
            out.append((k, drive.step(0.0, 0.0, 0.0, f2, 0.0, v_d, 0.0, k=k)))
    return out


@pytest.mark.parametrize('trigger', [False, True])
def test_without_a_push_re_solving_changes_nothing(trigger):
    """Without a push, re-solving changes nothing.

    fast_resolve_period on: the stage takes inputs at the finer grid (every control tick
    with push_trigger) but, without a push, solves at the MPC's ticks only, with the same
    floats as with it off. (The drift's mean over the period is off: the two take their
    inputs at different ticks, tests/wip_control/core/test_mpc_drift_mean.py.)
    """
    config = MpcParams(backend='daqp', push_trigger=trigger, disturbance_average_time=0.0)
    fast = DriveControllerStage(MODEL, config, 15.0, decimation=20, fast_decimation=10)
    off = DriveControllerStage(MODEL, dataclasses.replace(config, fast_resolve_period=0.0), 15.0,
                     decimation=20, fast_decimation=None)
    assert ([k for k in range(41) if fast.is_tick(k)]
            == (list(range(41)) if trigger else [0, 10, 20, 30, 40]))
    assert [k for k in range(41) if off.is_tick(k)] == [0, 20, 40]

    def f2(k):   # a slow drift, within the dead zone
        return 0.3 * math.sin(0.01 * k)
    a = _drive_ticks(fast, f2, 400, v_d=0.5)
    b = _drive_ticks(off, f2, 400, v_d=0.5)
    assert [k for k, _ in a] == [k for k, _ in b] == list(range(0, 400, 20))
    assert [r.tau_v for _, r in a] == [r.tau_v for _, r in b]


@pytest.mark.parametrize('trigger', [False, True])
def test_after_a_push_the_stage_re_solves_within_the_torque_rate_limit(trigger):
    """After a push the stage re-solves within the torque rate limit.

    A 10 m/s² push seen by the ESO from tick 413, between two ticks of the finer grid:
    with push_trigger the stage solves at once and the finer grid runs from there (413,
    423, ...), without it from the grid's next tick (420, 430, ...); either way at every
    tick of that grid for fast_resolve_time, each increment at most Δτmax ·
    push_resolve_share, and the increments within any MPC period sum to at most Δτmax
    (the limit (19) holds however the solves fall); then back to the MPC's ticks.
    """
    config = MpcParams(backend='daqp', push_trigger=trigger)
    drive = DriveControllerStage(MODEL, config, 15.0, decimation=20, fast_decimation=10)
    dmax = config.max_delta_torque

    def f2(k):   # the push from tick 413 (2.065 s) to 433
        return 10.0 if 413 <= k < 433 else 0.0
    ticks = _drive_ticks(drive, f2, 2000)
    solved = [k for k, _ in ticks]
    first = 413 if trigger else 420
    assert min(k for k in solved if k > 400) == first
    # Re-solving lasts fast_resolve_time (4 s = 800 ticks) after the last push seen (the
    # estimate's drop back below the slow estimate, after the push, is seen too), and
    # ends: the MPC's ticks only in the last second.
    hold = round(config.fast_resolve_time / H)
    assert set(range(first, first + hold, 10)) <= set(solved)
    assert all(k % 20 == 0 or (k - first) % 10 == 0 for k in solved)
    assert all(k % 20 == 0 for k in solved if k >= 1800)
    fast = [k for k in solved if k % 20]
    moves = {k: abs(r.delta_tau) for k, r in ticks}
    share = dmax * config.push_resolve_share
    assert max(moves[k] for k in solved if first <= k <= max(fast)) <= share + 1e-9
    assert max(moves.values()) > 1.0           # it did act
    assert _largest_window_move(ticks) <= dmax + 1e-9


def _largest_window_move(ticks, decimation=20):
    """Return the largest sum of |Δτ| of the solves within one MPC period [N m]."""
    moves = {k: abs(r.delta_tau) for k, r in ticks}
    return max(sum(m for j, m in moves.items() if k - decimation < j <= k) for k in moves)


def test_an_obstacle_stopping_the_base_lifts_the_rate_to_the_impact_limit():
    """A drift against the motion lifts the limit (19) to impact_delta_torque, no other.

    Driven at υd = 0.5 m/s, a 10 m/s² drift of f̂2 backwards (a wheel stopped by an edge)
    from tick 413: the torque then moves by more than max_delta_torque within one MPC
    period, and by at most impact_delta_torque. The same drift forwards (a push along the
    motion, the push bench's) keeps max_delta_torque, as does a standing vehicle (υd = 0);
    impact_delta_torque at max_delta_torque is the paper's limit alone.
    """
    config = MpcParams(backend='daqp')
    assert config.impact_delta_torque > config.max_delta_torque
    dmax, relieved = config.max_delta_torque, config.largest_delta_torque()

    def run(sign, v_d, **changes):
        drive = DriveControllerStage(MODEL, dataclasses.replace(config, **changes), 15.0,
                                     decimation=20, fast_decimation=10)
        return _drive_ticks(drive, lambda k: sign * 10.0 if 413 <= k < 433 else 0.0, 1200,
                            v_d=v_d)
    for sign, v_d in ((-1.0, 0.5), (1.0, -0.5)):   # against the motion, either way
        assert dmax + 1.0 < _largest_window_move(run(sign, v_d)) <= relieved + 1e-9
    for sign, v_d, changes in ((1.0, 0.5, {}), (-1.0, -0.5, {}), (-1.0, 0.0, {}),
                               (-1.0, 0.5, {'impact_delta_torque': dmax})):
        assert _largest_window_move(run(sign, v_d, **changes)) <= dmax + 1e-9, (sign, v_d)
    assert MpcParams(impact_delta_torque=0.0).largest_delta_torque() == dmax
    assert MpcParams(fast_resolve_period=0.0).largest_delta_torque() == dmax


def test_the_impact_limit_ends_impact_hold_after_the_drift():
    """impact_hold after the last solve that saw the drift, the limit is Δτmax again."""
    config = MpcParams(backend='daqp', impact_hold=1.0)
    drive = DriveControllerStage(MODEL, config, 15.0, decimation=20, fast_decimation=10)
    _drive_ticks(drive, lambda k: -10.0 if 413 <= k < 433 else 0.0, 433, v_d=0.5)
    assert drive.rate == config.impact_delta_torque    # what the MPC's /diagnostics shows
    drive = DriveControllerStage(MODEL, config, 15.0, decimation=20, fast_decimation=10)
    ticks = _drive_ticks(drive, lambda k: -10.0 if 413 <= k < 433 else 0.0, 1200, v_d=0.5)
    assert drive.rate == config.max_delta_torque
    last_seen = max(k for k, _ in ticks if k < 433)
    after = [(k, r) for k, r in ticks if k >= last_seen + round(1.0 / H) + 20]
    assert after and _largest_window_move(after) <= config.max_delta_torque + 1e-9


def test_fast_resolve_period_must_divide_the_sampling_period():
    from wip_runtime.config import ParamError
    MpcParams(fast_resolve_period=0.025).validate()
    MpcParams(fast_resolve_period=0.1).validate()      # not shorter: off
    MpcParams(sampling_period=0.01).validate()         # (the default 0.05 then off)
    for bad in (0.03, 0.07):
        with pytest.raises(ParamError, match='fast_resolve_period'):
            MpcParams(fast_resolve_period=bad).validate()


def test_the_paper_design_holds_the_torque_for_the_mpc_period():
    from wip_sim.core.scenario import scenario_from_mapping
    paper = scenario_from_mapping({'design': 'paper'})
    assert paper.mpc.fast_resolve_period == 0.0 and paper.mpc_fast_decimation is None
    assert paper.drive_decimation == paper.mpc_decimation == 20
    # The robust design looks for a push at every control tick (mpc.push_trigger), and
    # without it takes its inputs at the re-solve grid's ticks.
    robust = scenario_from_mapping({})
    assert robust.mpc_fast_decimation == 10 and robust.drive_decimation == 1
    grid = scenario_from_mapping({'mpc': {'push_trigger': False}})
    assert grid.drive_decimation == 10
    assert ControlStep.from_scenario(paper).drive.every == 20
    for scenario in (paper, robust, grid):
        assert ControlStep.from_scenario(scenario).drive.every == scenario.drive_decimation


def test_the_control_step_mixes_the_held_drive_torque_between_mpc_ticks():
    scenario = Scenario()
    control = ControlStep.from_scenario(scenario)
    est = estimator()
    pose = est.update(0.0, 0.0, 0.0, 0.03, 0.0, 0.0, 0.0, (0.0, 0.0), (0.0, 0.0))
    ref = ReferenceState(0.0, 0.0, 0.0, 0.5, 0.0, 0.0)
    first = control.step(0.0, ref, pose, True)
    between = control.step(H, ref, pose, False)
    assert first.mpc is not None and between.mpc is None
    # Eq. (24): τυ = τl + τr is the held MPC torque (no clipping at these magnitudes).
    for out in (first, between):
        assert out.tau_left + out.tau_right == pytest.approx(first.mpc.tau_v, abs=1e-12)
        assert out.tau_right - out.tau_left == pytest.approx(out.arc.tau_omega, abs=1e-12)
