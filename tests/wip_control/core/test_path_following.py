"""Path following by time scaling (time_scaling.TimeScaled, the default).

The reference slows where the path would exceed υmax or ωmax, every kind, and the trifolium goal.
"""

import dataclasses
import math

import numpy as np
import pytest

from wip_runtime.config import ParamError
from wip_control.core.reference_curves import Trifolium
from wip_control.core.references import distance_to_path, make_reference, ReferenceParams
from wip_control.core.time_scaling import TimeScaled
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import scenario_from_mapping

KIND_OPTIONS = {
    'trifolium': {},
    'circle': {'circle_radius': 1.0, 'circle_speed': 0.6},     # ω = 0.6 rad/s
    'line': {'line_speed': 1.4},
    'figure_eight': {'figure_eight_period': 20.0},
    'waypoints': {'waypoints_speed': 1.0, 'waypoints_max_yaw_rate': 0.5},
}


@pytest.mark.parametrize('kind', sorted(KIND_OPTIONS))
def test_every_kind_respects_the_limits_on_the_same_path(kind):
    # The re-timing itself: without the speed lead (which makes υ the speed ahead, so
    # ẋ = υ cos ϕ holds only where the speed is constant; tested below).
    config = ReferenceParams(kind=kind, time_scaling=True, path_max_speed=0.8,
                             path_max_yaw_rate=0.2, path_speed_lead_time=0.0,
                             path_speed_lead_time_accelerating=0.0, **KIND_OPTIONS[kind])
    timed = make_reference(config)
    assert isinstance(timed, TimeScaled)
    times = np.arange(0.0, 60.0, 0.05)
    states = [timed.sample(t) for t in times]
    speeds = np.array([s.v for s in states])
    rates = np.array([s.omega for s in states])
    assert speeds.max() <= 0.8 + 1e-9
    assert np.abs(rates).max() <= 0.2 + 1e-9
    progress = np.array([timed.progress(t) for t in times])
    assert np.all(np.diff(progress) >= 0.0)   # never runs backwards
    # The same curve: every timed point is on the base path, traced over the progress.
    distance = distance_to_path(timed.base, [s.x for s in states], [s.y for s in states],
                                float(progress[-1]) + 0.1, resolution=0.001)
    assert distance.max() < 1e-3
    # Pose and rates are consistent: ẋ = υ cos ϕ, ẏ = υ sin ϕ (central differences).
    x, y = np.array([s.x for s in states]), np.array([s.y for s in states])
    phi = np.array([s.phi for s in states])
    dx, dy = np.gradient(x, times), np.gradient(y, times)
    # (99 %: the waypoints' fillets and stops change the curvature abruptly.)
    inner = slice(2, -2)
    err = np.hypot(dx - speeds * np.cos(phi), dy - speeds * np.sin(phi))[inner]
    assert np.quantile(err, 0.99) < 0.01 and err.max() < 0.1


@pytest.mark.parametrize('kind', sorted(KIND_OPTIONS))
def test_the_speed_lead_is_the_speed_ahead_and_changes_nothing_else(kind):
    """The speed lead is the speed ahead and changes nothing else.

    path_speed_lead_time: υ(t) is the lead-free reference's υ at t + T where that is
    not faster (braking, cruising), at t + T_a where it is (speeding up); pose, ω and ω̇
    are those at t. Every kind (docs/history/mpc.md §8).
    """
    common = dict(kind=kind, time_scaling=True, path_max_speed=0.8, path_max_yaw_rate=0.2,
                  **KIND_OPTIONS[kind])
    plain = make_reference(ReferenceParams(**common, path_speed_lead_time=0.0,
                                           path_speed_lead_time_accelerating=0.0))
    lead, lead_up = 0.75, 0.6
    led = make_reference(ReferenceParams(**common, path_speed_lead_time=lead,
                                         path_speed_lead_time_accelerating=lead_up))
    changed = 0
    for t in np.arange(0.0, 40.0, 0.37):
        a, b = plain.sample(t), led.sample(t)
        assert (b.x, b.y, b.phi, b.omega, b.omega_dot) == (a.x, a.y, a.phi, a.omega,
                                                            a.omega_dot)
        ahead = plain.sample(t + lead).v
        expected = plain.sample(t + lead_up).v if abs(ahead) > abs(a.v) else ahead
        assert b.v == expected   # the same floats (TimeScaled._speed_at)
        changed += abs(b.v - a.v) > 1e-6
    # Where the path speed changes, the lead changes υ (the check above is not vacuous);
    # the line and the circle run at one speed.
    if kind not in ('line', 'circle'):
        assert changed > 5


def test_unconstrained_reference_is_unchanged():
    # Limits that never bind: σ = 1, the timed reference is the base, to rounding.
    base = Trifolium()
    timed = TimeScaled(base, 10.0, 10.0)
    for t in (0.0, 3.3, 27.1, 61.05):
        # (s(t) = t to the rounding of the RK4 sums on the 0.01 s grid.)
        assert tuple(timed.sample(t)) == pytest.approx(tuple(base.sample(t)), abs=1e-9)


def test_trifolium_slows_at_its_petal_tips_only():
    # |ω_r| = 0.70 rad/s at the tips (r = κ cos(3Ωt) = ±κ: t = 0, 15, 30 s) against 0.2:
    # progress 0.2/0.70 there, full speed where |ω_r| ≤ 0.2 (the petals' straight
    # parts); the yaw-rate limit is met with equality at the tips.
    base = Trifolium()
    timed = TimeScaled(base, 1.2, 0.2)
    for tip in (0.0, 15.0):
        assert abs(base.sample(tip).omega) == pytest.approx(0.70, abs=0.005)
        assert timed.rate_at(tip) == pytest.approx(0.2 / abs(base.sample(tip).omega))
    straight = [s for s in np.arange(0.0, 45.0, 0.1) if abs(base.sample(s).omega) < 0.19]
    assert len(straight) > 50
    assert all(timed.rate_at(s) == 1.0 for s in straight)
    t = np.arange(0.0, 90.0, 0.05)
    omega = np.abs([timed.sample(ti).omega for ti in t])
    assert omega.max() == pytest.approx(0.2, abs=1e-9)
    assert timed.progress(90.0) < 90.0


def test_references_of_one_configuration_share_their_tables_and_values():
    # make_reference shares the re-timing tables among the TimeScaled of one path and
    # limits (every run of a campaign re-times the same path once): the samples are those
    # of a TimeScaled with tables of its own, whatever the order of the queries.
    config = ReferenceParams(kind='figure_eight', figure_eight_period=20.0,
                             path_max_speed=0.8, path_max_yaw_rate=0.2)
    own = make_reference(dataclasses.replace(config, path_max_speed=0.7))
    first, second = make_reference(config), make_reference(config)
    assert second._s is first._s and second._sigma is first._sigma
    other_lead = make_reference(dataclasses.replace(config, path_speed_lead_time=0.3))
    assert other_lead._s is first._s            # the tables do not depend on the lead
    assert own._s is not first._s               # other limits: other tables
    alone = TimeScaled(first.base, 0.8, 0.2, config.path_progress_rate_limit,
                       speed_lead_time=config.path_speed_lead_time,
                       speed_lead_time_accelerating=config.path_speed_lead_time_accelerating)
    assert alone._s is not first._s
    times = np.arange(0.0, 60.0, 0.37)
    late = [second.sample(t) for t in times[::-1]]       # far ahead first
    assert [first.sample(t) for t in times] == late[::-1] == [alone.sample(t) for t in times]


#: A reference with a speed lead, shorter while accelerating (the memo's tests).
LEAD_CONFIG = ReferenceParams(path_speed_lead_time=0.75, path_speed_lead_time_accelerating=0.6)


def sampled_afresh(t: float):
    """Return the lead's definition at ``t``, on a time-scaled reference that sampled nothing."""
    config = LEAD_CONFIG
    timed = TimeScaled(Trifolium(), config.path_max_speed, config.path_max_yaw_rate,
                       config.path_progress_rate_limit)
    state = timed.sample(t)
    ahead = timed.sample(t + config.path_speed_lead_time).v
    if abs(ahead) > abs(state.v):
        ahead = timed.sample(t + config.path_speed_lead_time_accelerating).v
    return state._replace(v=ahead)


def test_remembered_states_give_the_same_samples_in_any_order():
    # With a speed lead, sample(t) remembers the re-timed states by their time (the lead
    # asks for times sampled again later): the samples are those computed afresh, for a
    # loop running forward at 200 Hz (where most are remembered), backwards, at random
    # times and repeated times; and what is remembered stays bounded.
    config = LEAD_CONFIG

    timed = make_reference(config)
    forward = [k * 0.005 for k in range(6001)]
    samples = [timed.sample(t) for t in forward]
    assert len(timed._memo) <= 2 * max(TimeScaled.MEMO_MIN_SIZE, 400)
    rng = np.random.default_rng(3)
    checked = list(rng.choice(6001, 40, replace=False))
    assert [samples[k] for k in checked] == [sampled_afresh(forward[k]) for k in checked]
    others = [29.999, 0.0, 12.345, 12.345, 3.0, -0.2] + list(rng.uniform(0.0, 40.0, 20))
    assert [timed.sample(t) for t in others] == [sampled_afresh(t) for t in others]
    assert [timed.sample(t) for t in forward[::-97]] == [samples[k] for k in range(6000, -1, -97)]
    # Running backwards nothing is behind t to forget: bounded all the same.
    for t in forward[::-1]:
        timed.sample(t)
        assert len(timed._memo) <= 2 * TimeScaled.MEMO_MAX_SIZE + 3


def test_rate_at_is_the_interpolated_sigma_to_the_bit():
    # rate_at (the RK4 of s(t) and the lead speeds) and _sigma_and_slope (the sample's
    # ω̇) interpolate σ separately: the same floats, on and between the grid nodes.
    timed = TimeScaled(Trifolium(), 1.2, 0.2)
    for s in [-0.5, 0.0, 1e-9, 0.01, 0.015, 7.3, 15.0] + list(np.arange(0.0, 50.0, 0.0037)):
        assert timed.rate_at(s) == timed._sigma_and_slope(s)[0]


def test_shared_tables_are_bounded_per_thread(monkeypatch):
    import threading
    from wip_control.core import time_scaling
    config = ReferenceParams(kind='circle')
    tables = time_scaling.shared_tables(('test', config))
    assert time_scaling.shared_tables(('test', config)) is tables
    # Only the last MAX_SHARED_CONFIGURATIONS configurations are kept.
    for i in range(time_scaling.MAX_SHARED_CONFIGURATIONS):
        time_scaling.shared_tables(('test', i))
    assert time_scaling.shared_tables(('test', config)) is not tables
    # Another thread has tables of its own.
    seen = []
    thread = threading.Thread(target=lambda: seen.append(
        time_scaling.shared_tables(('test', config))))
    thread.start()
    thread.join(timeout=10.0)
    assert seen and seen[0] is not time_scaling.shared_tables(('test', config))
    # Tables grown beyond MAX_SHARED_NODES are no longer offered (nor kept for sharing).
    monkeypatch.setattr(time_scaling.RetimingTables, 'MAX_SHARED_NODES', 500)
    long_run = make_reference(config)
    long_run.sample(4.0)                                  # 400 nodes: still shared
    assert make_reference(config)._s is long_run._s
    long_run.sample(6.0)                                  # 600 nodes
    assert make_reference(config)._s is not long_run._s


def test_omega_dot_is_the_derivative_of_omega():
    timed = make_reference(ReferenceParams())
    t = np.arange(0.0, 60.0, 0.01)
    samples = [timed.sample(ti) for ti in t]
    omega = np.array([s.omega for s in samples])
    omega_dot = np.array([s.omega_dot for s in samples])
    numeric = np.gradient(omega, t)
    # σ = min(…) has kinks where a limit starts to bind: compare away from the few
    # samples where the numerical derivative straddles one.
    err = np.abs(numeric - omega_dot)
    assert np.quantile(err, 0.99) < 1e-3
    assert err.max() < 0.05


def test_path_limits_above_the_generator_limits_are_rejected():
    with pytest.raises(ParamError, match=r'^reference\.path_max_yaw_rate: must not exceed'):
        scenario_from_mapping({'reference': {'path_max_yaw_rate': 0.5}})
    with pytest.raises(ParamError, match=r'^reference\.path_max_speed: must not exceed'):
        scenario_from_mapping({'reference': {'path_max_speed': 2.0}})
    # Without time scaling the path limits are unused.
    scenario_from_mapping({'reference': {'time_scaling': False, 'path_max_speed': 2.0}})


def path_errors(scenario):
    result = run_scenario(scenario)
    assert not result.fell
    truth = result.record.groups['truth']
    reference = make_reference(scenario.reference)
    base = reference.base if isinstance(reference, TimeScaled) else reference
    # One trifolium is 45 s of its own time: the whole path.
    distance = distance_to_path(base, truth['x'], truth['y'], 45.0, resolution=0.002)
    return truth['t'], distance


@pytest.mark.slow
def test_trifolium_goal_with_path_following():
    # The paper's claim, on distance to the path: ≤ 0.1 m within 8 s and RMS ≤ 0.1 m
    # afterwards (the collision pulse at 30 s and the yaw sine included). Measured:
    # first within 0.1 m at 6.8 s, RMS after 8 s 0.049 m (max 0.145 m, after the pulse;
    # 0.081 m before it); the paper's design on the same path: 7.8 s, RMS 0.33 m.
    t, distance = path_errors(scenario_from_mapping({}))
    assert distance[t <= 8.0].min() <= 0.1
    assert math.sqrt(np.mean(distance[t >= 8.0] ** 2)) <= 0.1


def test_a_loop_whose_times_never_repeat_gives_up_the_memo_with_the_same_states():
    # A node in real time samples at sensor stamps, off any grid: no time is asked twice,
    # so remembering states is in vain. A memo that serves fewer than half of the samples
    # over MEMO_TRIAL_TIME from the first lead on is dropped; the states are the
    # definition's, to the bit, before and after (the lead's speeds from _speed_at, the
    # same floats as a re-timed state's υ).
    config, lead = LEAD_CONFIG, LEAD_CONFIG.path_speed_lead_time
    rng = np.random.default_rng(5)
    # Waiting at t = 0 first (a node before the safety layer engages: the same t, hits).
    jittered = [0.0] * 100 + np.cumsum(0.005 + rng.uniform(-2e-4, 2e-4, 6000)).tolist()
    timed = make_reference(config)
    samples = [timed.sample(t) for t in jittered]
    assert timed._memo is None
    given_up = next(k for k, t in enumerate(jittered)
                    if t > lead + TimeScaled.MEMO_TRIAL_TIME)
    checked = sorted({0, 150, given_up - 1, given_up, given_up + 1, 6099,
                      *rng.choice(6100, 30, replace=False).tolist()})
    assert [samples[k] for k in checked] == [sampled_afresh(jittered[k]) for k in checked]
    # A loop on a grid keeps it (its times come back at t + lead).
    grid = make_reference(config)
    for k in range(2000):
        grid.sample(k * 0.005)
    assert grid._memo is not None and grid._memo_kept
