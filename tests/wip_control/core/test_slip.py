"""Wheel slip from the wheels against the IMU (core/slip.py), against closed forms.

Synthetic samples at 200 Hz of a vehicle upright (θ = θ̇ = 0, so w = υ and ẇ = d, the
external acceleration): each wheel's r φ_i integrates its own speed. A wheel whose speed
jumps (a spin, a lost or regained grip) moves faster than any ground force allows; a push
of the paper's 10 m/s² does not.
"""

import math

import pytest

from wip_description.params import ModelParams
from wip_control.core.slip import SlipMonitor
from wip_control.core.state_estimation import StateEstimator
from wip_control.core.eso import EsoParams

PARAMS = ModelParams()
H = 0.005


def drive(monitor, speed, seconds, *, left_extra=None, right_extra=None, torque=5.0,
          start=0.0):
    """Feed ``monitor`` the vehicle at ``speed(t)`` [m/s] plus each wheel's spin.

    ``*_extra(t)`` [m/s] adds to a wheel's speed; rows (t, true x_v, wheels' x_v, state).
    """
    left = right = true = 0.0
    rows = []
    for k in range(int(round(seconds / H)) + 1):
        t = start + k * H
        if k:
            v = speed(t - 0.5 * H)
            true += v * H
            left += (v + (left_extra(t) if left_extra else 0.0)) * H
            right += (v + (right_extra(t) if right_extra else 0.0)) * H
        x_v = 0.5 * (left + right)
        state = monitor.update(t, left, right, x_v, 0.0, 0.0, 0.0, torque, torque)
        rows.append((t, true, x_v, state))
    return rows


def step(at, value):
    return lambda t: value if t >= at else 0.0


def test_rolling_wheels_and_a_push_pass_unchanged():
    # 0.5 m/s, then the paper's push (10 m/s² for 0.1 s) at 2 s: the wheels follow the
    # ground; x_v is handed on bit for bit and no wheel is called slipping.
    monitor = SlipMonitor(PARAMS)
    rows = drive(monitor, lambda t: 0.5 + (min(max(t - 2.0, 0.0), 0.1) * 10.0), 4.0)
    assert all(state.x_v == x_v and not state.slipping for _, _, x_v, state in rows)
    assert monitor.events == 0


def test_a_constant_spin_of_one_wheel_is_taken_out_of_x_v():
    # From 2 s the left wheel spins 1 m/s faster than the ground: the odometry's x_v runs
    # ahead by 0.5 m/s (the mean of the wheels); the monitor's follows the right wheel,
    # and its offset grows at 0.5 m/s while the wheels disagree.
    monitor = SlipMonitor(PARAMS, longest=1.0)
    rows = drive(monitor, lambda t: 0.5, 2.8, left_extra=step(2.0, 1.0))
    spin = [(t, true, x_v, s) for t, true, x_v, s in rows if t >= 2.01]
    assert all(s.left and not s.right for *_, s in spin)
    for t, true, x_v, s in spin:
        assert x_v - true == pytest.approx(0.5 * (t - 2.0 + H), abs=1e-9)   # from 1.995 s
        assert s.x_v == pytest.approx(true, abs=0.5 * H * 1.0 + 1e-9)
        assert s.speed == pytest.approx(0.5, abs=0.02)
    assert spin[-1][3].offset == pytest.approx(0.5 * 0.8, abs=0.01)


def test_wheels_that_spin_in_turns_stay_out_of_x_v_however_long():
    # At rest against an edge the motors push (10 N m a wheel): the left wheel spins at
    # 1 m/s from 2 s to 3.5 s, then the right one from 3.5 s to 5 s. The axle stays, so
    # the x_v to use stays where it was (the gripping wheel's distance), past ``longest``
    # (1 s) and through the hand-over: a spin of 1.5 s per wheel would add 1.5 m.
    monitor = SlipMonitor(PARAMS, longest=1.0)
    rows = drive(monitor, lambda t: 0.0, 5.0, left_extra=lambda t: 1.0 if 2.0 <= t < 3.5
                 else 0.0, right_extra=lambda t: 1.0 if 3.5 <= t < 5.0 else 0.0, torque=10.0)
    spin = [s for t, _, _, s in rows if t >= 2.01]
    assert all(s.slipping for s in spin)
    assert all(abs(s.x_v) <= H * 1.0 + 1e-9 for s in spin)    # the first sample's 5 mm
    assert spin[-1].offset == pytest.approx(3.0 * 0.5, abs=0.01)  # the odometry's mean


def test_a_later_spin_is_timed_from_its_own_start():
    # A first slip (left, 0.3 s) ends when the wheels grip again; the right wheel spins
    # 2 s later for 0.5 s: it is a slip of 0.5 s, shorter than ``longest``, taken out of
    # x_v whole (0.25 m of the odometry's mean), not believed because the first began
    # more than ``longest`` before.
    monitor = SlipMonitor(PARAMS, longest=1.0)
    rows = drive(monitor, lambda t: 0.5, 5.0, left_extra=lambda t: 1.0 if 2.0 <= t < 2.3
                 else 0.0, right_extra=lambda t: 1.0 if 4.0 <= t < 4.5 else 0.0)
    assert all(s.right for t, _, _, s in rows if 4.01 <= t < 4.5)
    true, state = rows[-1][1], rows[-1][3]
    assert state.x_v == pytest.approx(true, abs=0.01) and not state.slipping
    assert state.offset == pytest.approx(0.15 + 0.25, abs=0.01)


def test_a_roll_on_after_a_stall_with_spinning_wheels_is_believed():
    # At rest against an edge with the wheels spinning in turns (left 2-2.5 s, right
    # 2.5-3 s), then the axle rolls on: 0 to 0.3 m/s in 0.1 s from 3 s, both wheels
    # gripping. The slip has lasted ``longest`` (since 2 s) by 3 s, so the wheels that roll
    # alike are believed after ``hold`` (0.05 s) whatever ŵ says: the x_v to use then
    # advances with the wheels, and lags the truth by at most the distance rolled before
    # (0.3 m/s over 0.1 s and the hold).
    monitor = SlipMonitor(PARAMS, longest=1.0, hold=0.05)
    rows = drive(monitor, lambda t: min(max(t - 3.0, 0.0), 0.1) * 3.0, 5.0,
                 left_extra=lambda t: 1.0 if 2.0 <= t < 2.5 else 0.0,
                 right_extra=lambda t: 1.0 if 2.5 <= t < 3.0 else 0.0, torque=10.0)
    after = [(true, x_v, s) for t, true, x_v, s in rows if t >= 3.0 + 0.05 + 2 * H]
    assert all(not s.slipping for *_, s in after)
    offset = after[0][2].offset
    assert all(s.offset == offset and s.x_v == x_v - offset for _, x_v, s in after)
    assert 0.0 <= after[-1][0] - after[-1][2].x_v <= 0.3 * (0.1 + 0.05 + 2 * H)


def test_a_step_in_traction_on_both_wheels_coasts_on_the_imu_and_regrips():
    # Both wheels spin 0.8 m/s faster from 2 s to 2.3 s (ice under both, a driving
    # torque), then grip again: no wheel tells the truth meanwhile; the IMU's model
    # (ẇ = g θ + d̂ with θ = 0) carries the speed, and x_v stays the true distance.
    monitor = SlipMonitor(PARAMS)
    burst = lambda t: 0.8 if 2.0 <= t < 2.3 else 0.0       # noqa: E731
    rows = drive(monitor, lambda t: 0.5, 3.0, left_extra=burst, right_extra=burst)
    during = [s for t, _, _, s in rows if 2.01 <= t < 2.3]
    assert during and all(s.left and s.right for s in during)
    after = [(true, s) for t, true, _, s in rows if t >= 2.4]
    assert all(not s.slipping for _, s in after)
    for true, s in after:
        assert s.x_v == pytest.approx(true, abs=0.005)
    assert monitor.events == 2


def test_an_obstacle_that_stops_the_wheels_against_the_torque_is_not_slip():
    # A bump's edge stops the wheels (−0.3 m/s in 5 ms) while the motors drive forward:
    # real motion (an external force), believed.
    monitor = SlipMonitor(PARAMS)
    rows = drive(monitor, lambda t: 0.3 if t < 2.0 else 0.0, 3.0, torque=10.0)
    assert monitor.events == 0 and all(s.x_v == x_v for _, _, x_v, s in rows)


@pytest.mark.parametrize('name, value', [('max_acceleration', 0.0),
                                         ('agreement', math.nan), ('hold', -1.0)])
def test_bad_settings_are_one_line_errors(name, value):
    with pytest.raises(ValueError, match=f'SlipMonitor: {name} must be finite and > 0'):
        SlipMonitor(PARAMS, **{name: value})


def test_on_by_default_with_the_gyro_and_off_with_zero():
    assert StateEstimator(PARAMS, EsoParams(slip_max_acceleration=0.0)).slip is None
    on = StateEstimator(PARAMS)
    assert isinstance(on.slip, SlipMonitor) and on.slip.max_acceleration == 20.0
    assert StateEstimator(PARAMS, EsoParams(estimator='paper',
                                            slip_max_acceleration=20.0)).slip is None


def test_non_finite_input_is_refused_and_changes_nothing():
    monitor = SlipMonitor(PARAMS)
    drive(monitor, lambda t: 0.5, 1.0)
    before = monitor.state.copy()
    with pytest.raises(ValueError, match='non-finite input'):
        monitor.update(1.005, 0.5, 0.5, 0.5, 0.0, math.nan, 0.0)
    assert monitor.state.tobytes() == before.tobytes()
