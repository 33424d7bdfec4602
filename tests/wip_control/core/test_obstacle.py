"""Wheels blocked by an obstacle (core/obstacle.py), against closed forms.

Synthetic samples at 200 Hz: the axle's distance x_v, the lean θ and the drive torque τυ.
The default model: r = 0.2 m, M = 25 + 5 + 2 · 2.5 = 35 kg, m_p l = 25 · 0.6 kg m.
"""

import math

import pytest

from wip_description.params import ModelParams
from wip_control.core.eso import EsoParams
from wip_control.core.obstacle import (ObstacleMonitor, ObstacleRelease,
                                       climbable_edge_height,
                                       holding_lean)
from wip_control.core.state_estimation import StateEstimator

PARAMS = ModelParams()
H = 0.005
G = PARAMS.gravity


def feed(monitor, seconds, speed, theta, torque, start=0.0, x_v=0.0):
    """Feed samples of an axle at ``speed(t)``; return rows (t, state) and the last x_v."""
    rows = []
    for k in range(int(round(seconds / H)) + 1):
        t = start + k * H
        if k:
            x_v += speed(t) * H
        rows.append((t, monitor.update(t, x_v, theta, torque)))
    return rows, x_v


def test_the_highest_edge_is_where_the_torque_lifts_the_vehicle_about_it():
    # 2 x 15 N m, 35 kg: the edge a = τ/(M g) = 8.74 cm ahead of the axle; its height
    # r − √(r² − a²) = 2.0 cm (docs/mujoco-plant.md). Above M g r the torque lifts the
    # vehicle even with the edge at the axle's height: h_max = r.
    a = 30.0 / (35.0 * G)
    assert a == pytest.approx(0.0874, abs=1e-4)
    assert climbable_edge_height(0.2, 30.0, 35.0, G) == pytest.approx(
        0.2 - math.sqrt(0.04 - a * a), rel=1e-12)
    assert climbable_edge_height(0.2, 30.0, 35.0, G) == pytest.approx(0.0201, abs=1e-4)
    assert climbable_edge_height(0.2, 35.0 * G * 0.2 * 1.001, 35.0, G) == 0.2
    # The lean whose weight the torque just holds: m_p g l sin θ = τ.
    lean = holding_lean(30.0, 25.0, 0.6, G)
    assert 25.0 * G * 0.6 * math.sin(lean) == pytest.approx(30.0, rel=1e-12)
    assert holding_lean(1000.0, 25.0, 0.6, G) == math.pi / 2


def test_wheels_held_still_against_the_torque_are_blocked_after_the_stall_time():
    # 0.3 m/s with 5 N m, then an edge stops the axle at 2 s while 15 N m push and the
    # body leans 0.1 rad forward: blocked once the axle has stood still for the 0.3 s
    # stall time.
    monitor = ObstacleMonitor(PARAMS, stall_time=0.3, stall_torque=10.0)
    rows, x_v = feed(monitor, 2.0, lambda t: 0.3, 0.1, 5.0)
    assert not any(s.blocked for _, s in rows)   # moving: never blocked
    rows, _ = feed(monitor, 1.0, lambda t: 0.0, 0.1, 15.0, start=2.0 + H, x_v=x_v)
    blocked = [t for t, s in rows if s.blocked]
    assert blocked[0] == pytest.approx(2.0 + H + 0.3, abs=1.5 * H)
    assert all(s.blocked for t, s in rows if t >= blocked[0])
    state = rows[-1][1]
    assert state.since == pytest.approx(2.0 + H) and monitor.events == 1
    assert monitor.first == state
    assert '2.0 cm' in state.reason and '0.21 rad' in state.reason


def test_a_slow_climb_a_short_stall_and_no_push_are_not_blocked():
    # Creeping up at 0.06 m/s (above the 0.05 m/s stall speed), a stall of 0.2 s (a bump
    # climbed), a stand-still with 9 N m (below the 10 N m stall torque: a slope's hold)
    # or leaning back: none is an obstacle.
    for speed, seconds, theta, torque in ((0.06, 2.0, 0.1, 30.0), (0.0, 0.2, 0.1, 30.0),
                                          (0.0, 2.0, 0.1, 9.0), (0.0, 2.0, -0.01, 30.0)):
        monitor = ObstacleMonitor(PARAMS)
        rows, _ = feed(monitor, seconds, lambda t, v=speed: v, theta, torque)
        assert not any(s.blocked for _, s in rows), (speed, seconds, theta, torque)


def test_one_report_while_held_and_released_when_the_push_stops():
    monitor = ObstacleMonitor(PARAMS)
    rows, x_v = feed(monitor, 1.0, lambda t: 0.0, 0.1, 15.0)
    assert rows[-1][1].blocked
    # A held body's torque wanders about the stall torque: 7 N m (above half of it) keeps
    # the one report; 2 N m ends it.
    assert monitor.update(1.0 + H, x_v, 0.1, 7.0).blocked and monitor.events == 1
    state = monitor.update(1.0 + 2 * H, x_v, 0.1, 2.0)
    assert not state.blocked and state.reason == '' and math.isnan(state.since)


@pytest.mark.parametrize('name, value', [('stall_time', 0.0), ('stall_torque', math.nan),
                                         ('stall_speed', -1.0)])
def test_bad_settings_are_one_line_errors(name, value):
    with pytest.raises(ValueError, match=f'ObstacleMonitor: {name} must be finite and > 0'):
        ObstacleMonitor(PARAMS, **{name: value})


def test_non_finite_input_is_refused():
    monitor = ObstacleMonitor(PARAMS)
    with pytest.raises(ValueError, match='non-finite'):
        monitor.update(0.0, math.nan, 0.1, 15.0)


def test_on_by_default_in_the_estimator_and_off_with_a_zero_stall_time():
    estimator = StateEstimator(PARAMS)
    assert isinstance(estimator.obstacle, ObstacleMonitor)
    assert not estimator.obstacle_state.blocked
    off = StateEstimator(PARAMS, EsoParams(obstacle_stall_time=0.0))
    assert off.obstacle is None and off.obstacle_state is None


def test_the_disturbances_are_held_back_once_the_wheels_roll_on_from_a_stall():
    # 0.5 m/s cruising with 3 N m: nothing held. A stall (20 N m, still, leaning 0.1 rad)
    # at 1 s, the wheels roll on at 0.3 m/s from 1.2 s: f2, f3 held back for the 0.5 s
    # hold from the first rolling sample, once; a later sample without a new stall is not.
    release = ObstacleRelease(hold=0.5)
    held = []
    for k in range(400):
        t = k * H
        if t < 1.0:
            v, theta, tau = 0.5, 0.0, 3.0
        elif t < 1.2:
            v, theta, tau = 0.0, 0.1, 20.0
        else:
            v, theta, tau = 0.3, 0.05, 20.0
        held.append((t, release.update(t, v, theta, tau)))
    times = [t for t, on in held if on]
    assert times[0] == pytest.approx(1.2, abs=1e-9)
    assert times[-1] == pytest.approx(1.7 - H, abs=1e-9) and release.events == 1
    assert len(times) == round(0.5 / H)


def test_a_start_a_slope_hold_and_a_slow_creep_hold_nothing_back():
    # Speeding up from rest leaning forward with little torque, standing on a slope with
    # 6.9 N m, creeping forward at 0.15 m/s after a stall (below the 0.2 m/s of rolling on).
    for rows in ([(0.0, 0.1, 5.0), (0.5, 0.1, 5.0)], [(0.0, 0.05, 6.9), (0.5, 0.05, 6.9)],
                 [(0.0, 0.1, 20.0), (0.15, 0.1, 20.0)]):
        release = ObstacleRelease()
        assert not any(release.update(k * H, *rows[k >= 50]) for k in range(200)), rows


def test_release_hold_off_by_default_and_on_with_a_hold():
    assert StateEstimator(PARAMS).release is None
    on = StateEstimator(PARAMS, EsoParams(obstacle_release_hold=0.5))
    assert isinstance(on.release, ObstacleRelease) and on.release.hold == 0.5
    with pytest.raises(ValueError, match='ObstacleRelease: hold must be finite and > 0'):
        ObstacleRelease(hold=0.0)


def blocked_at_an_edge(monitor):
    """Stop an axle at x_v = 0 with 15 N m and a 0.1 rad lean; return (t blocked, x_v)."""
    rows, x_v = feed(monitor, 0.5, lambda t: 0.0, 0.1, 15.0)
    assert rows[-1][1].blocked and monitor.events == 1
    return rows[-1][0], x_v


def test_an_axle_rocking_on_the_edge_without_progress_stays_blocked():
    # Blocked, then the axle rocks back from the edge and up it again: x_v = −A (1 − cos
    # 2πt/T) with A = 1.5 cm, T = 0.4 s, 3 s long (peak speed 2πA/T = 0.24 m/s), then
    # 2 cm beyond where it stopped (a wheel pressed a little up the edge, the estimate's
    # creep), half of the release distance. Over any 0.3 s window the axle moves up to
    # 2A = 3 cm, twice what the 0.05 m/s stall speed allows: a speed rule would let go
    # every rocking. It gains no ground past the edge, so the one blocking holds.
    monitor = ObstacleMonitor(PARAMS)
    t0, x0 = blocked_at_an_edge(monitor)
    states = []
    for k in range(1, int(round(3.0 / H)) + 1):
        t = t0 + k * H
        x_v = x0 - 0.015 * (1.0 - math.cos(2.0 * math.pi * (t - t0) / 0.4))
        states.append(monitor.update(t, x_v, 0.1, 15.0))
    for k in range(1, 101):
        states.append(monitor.update(t + k * H, x0 + 0.02 * min(k, 50) / 50, 0.1, 15.0))
    assert all(s.blocked for s in states) and monitor.events == 1
    assert states[-1].since == 0.0


@pytest.mark.parametrize('speed', [0.13, 0.3])
def test_a_real_crossing_releases_once_past_the_edge_by_the_release_distance(speed):
    # Blocked, then the wheels climb: the axle rolls on at 0.13 m/s (the slowest roll-on
    # traced at a 2 cm bump, docs/history/mpc.md §13) or 0.3 m/s. Released on the first
    # sample at or past 4 cm (release_distance) beyond where it stopped: 0.04/υ after the
    # roll-on, 0.31 s and 0.13 s, within one sample; the torque and lean still push.
    monitor = ObstacleMonitor(PARAMS)
    t0, x0 = blocked_at_an_edge(monitor)
    rows, _ = feed(monitor, 1.0, lambda t: speed, 0.1, 15.0, start=t0, x_v=x0)
    released = next(t for t, s in rows if not s.blocked)
    assert released - t0 == pytest.approx(0.04 / speed, abs=H + 1e-9)
    assert not any(s.blocked for t, s in rows if t >= released)
