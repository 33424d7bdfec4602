"""Runaway guard: the motion by the wheels and IMU against the reference's (core/runaway.py)."""

import math

import pytest

from wip_control.core.runaway import RunawayParams, RunawayGuard

DT = 0.005   # [s] 200 Hz, the estimate's rate


def drive(guard, seconds, vehicle, reference, estimate=None, t0=0.0):
    """Feed the guard; returns (time of the first verdict or None, the verdict).

    ``vehicle(t)`` -> (x, y, phi, v) of the true motion (what the wheels and IMU say),
    ``reference(t)`` -> (x_r, y_r), ``estimate(t)`` -> (x̂, ŷ) (default: the truth).
    """
    steps = int(round(seconds / DT))
    for k in range(steps + 1):
        t = t0 + k * DT
        x, y, phi, v = vehicle(t)
        xe, ye = estimate(t) if estimate is not None else (x, y)
        verdict = guard.update(t, xe, ye, phi, v, *reference(t))
        if verdict:
            return t, verdict
    return None, ''


def test_a_vehicle_on_its_reference_is_never_judged_a_runaway():
    guard = RunawayGuard()
    when, _ = drive(guard, 60.0, lambda t: (0.5 * t, 0.0, 0.0, 0.5), lambda t: (0.5 * t, 0.0))
    assert when is None and guard.largest_growth < 1e-9


def test_driving_against_the_reference_is_caught_when_the_growth_passes_the_bound():
    # The estimate agrees with the wheels (a wrong sign somewhere downstream): the wheels
    # roll backwards at 0.9 m/s while the reference goes forward at 0.3 m/s. ε_w grows at
    # 1.2 m/s, pulled back by (e − ε_w)/T_a = 0 (the estimate is the truth): the verdict
    # comes when 1.2 t > 2 m, at t = 1.667 s, 1.5 m driven.
    config = RunawayParams(max_error_growth=2.0, growth_window=4.0)
    guard = RunawayGuard(config)
    when, verdict = drive(guard, 10.0, lambda t: (-0.9 * t, 0.0, 0.0, -0.9),
                          lambda t: (0.3 * t, 0.0))
    assert when == pytest.approx(2.0 / 1.2, abs=2 * DT)
    assert 'runaway' in verdict and 'max_error_growth 2 m' in verdict


def test_a_frozen_position_estimate_is_caught_by_the_wheels():
    # The position source froze at the origin; the generator, seeing no progress, drives
    # at 1 m/s while the reference goes 0.3 m/s. The estimated error e = −0.3 t looks
    # modest; by the wheels ε_w' = 1 − 0.3 + (e − ε_w)/T_a, ε_w(0) = 0, whose solution is
    # ε_w = T_a (1 − exp(−t/T_a)) − 0.3 t. The verdict comes when it reaches the bound.
    anchor, bound = 10.0, 2.0
    guard = RunawayGuard(RunawayParams(max_error_growth=bound, anchor_time=anchor))
    when, verdict = drive(guard, 20.0, lambda t: (1.0 * t, 0.0, 0.0, 1.0),
                          lambda t: (0.3 * t, 0.0), estimate=lambda t: (0.0, 0.0))
    low, high = 0.0, 20.0
    for _ in range(60):   # bisection of the closed form
        mid = 0.5 * (low + high)
        if anchor * (1 - math.exp(-mid / anchor)) - 0.3 * mid < bound:
            low = mid
        else:
            high = mid
    # The guard's explicit Euler pull differs from the exact exponential by O(dt/T_a).
    assert when == pytest.approx(low, abs=0.02)
    assert 'position estimate is likely wrong' in verdict


def test_a_vehicle_held_at_an_obstacle_while_the_reference_goes_on_is_not_a_runaway():
    # Wheels stopped at an edge it cannot climb, the reference going on at 1 m/s: ε_w
    # grows by 4 m every 4 s, twice the bound, all of it the reference's; the vehicle's
    # own share is 0. (Cutting the torque of a balancing vehicle that stands still would
    # tip it over.) The error stays under max_tracking_error (10 m) for the 9 s.
    guard = RunawayGuard()
    when, _ = drive(guard, 9.0, lambda t: (0.0, 0.0, 0.0, 0.0), lambda t: (1.0 * t, 0.0))
    assert when is None
    assert guard.largest_growth == pytest.approx(2.0 * RunawayParams().max_error_growth,
                                                 abs=0.01)


@pytest.mark.parametrize('backwards, caught', [(0.2, False), (0.6, True)])
def test_the_growth_counts_when_the_vehicle_makes_its_share_of_it(backwards, caught):
    # The reference goes on at 0.5 m/s while the wheels roll backwards: ε_w grows at
    # 0.5 + b m/s, the vehicle's share is b / (0.5 + b): 0.29 at 0.2 m/s (below
    # min_own_share 0.5: it lags), 0.55 at 0.6 m/s (it runs away, caught when
    # 1.1 t > 2 m, at t = 1.818 s).
    guard = RunawayGuard(RunawayParams(max_error_growth=2.0, min_own_share=0.5))
    when, verdict = drive(guard, 8.0, lambda t: (-backwards * t, 0.0, 0.0, -backwards),
                          lambda t: (0.5 * t, 0.0))
    if caught:
        assert when == pytest.approx(2.0 / (0.5 + backwards), abs=2 * DT)
        assert 'by its own motion' in verdict
    else:
        assert when is None


def test_odometry_drift_is_not_a_runaway_over_a_long_run():
    # The wheels read 5 % fast (a wheel radius off) on a 10-minute circle of radius 5 m at
    # 0.5 m/s, the estimate (GPS) exact: ε_w's drift is bounded by 0.05 v T_a = 0.25 m.
    radius, speed = 5.0, 0.5
    rate = speed / radius

    def truth(t):
        return (radius * math.sin(rate * t), radius * (1 - math.cos(rate * t)),
                rate * t, 1.05 * speed)
    guard = RunawayGuard()
    when, _ = drive(guard, 600.0, truth, lambda t: truth(t)[:2])
    assert when is None and guard.largest_growth < 0.3


def test_an_absurd_tracking_error_is_caught_after_its_time():
    # A datum 1 km off: the estimate is 1 km from the reference, and the generator
    # drives "back" toward it (ε_w shrinks: no growth), yet the error is absurd.
    config = RunawayParams(max_tracking_error=10.0, tracking_error_time=1.0)
    guard = RunawayGuard(config)
    when, verdict = drive(guard, 5.0, lambda t: (1000.0 - 1.5 * t, 0.0, math.pi, 1.5),
                          lambda t: (0.3 * t, 0.0))
    assert when == pytest.approx(1.0, abs=DT / 2)
    assert 'max_tracking_error 10 m' in verdict and 'datum' in verdict


def test_a_replaced_reference_reanchors_instead_of_counting_as_growth():
    # A new path moves the reference 5 m in one step: not motion of the vehicle.
    guard = RunawayGuard()
    when, _ = drive(guard, 20.0, lambda t: (0.0, 0.0, 0.0, 0.0),
                    lambda t: (0.0, 0.0) if t < 5.0 else (5.0, 0.0))
    assert when is None


@pytest.mark.parametrize('bad', [math.nan, math.inf])
def test_non_finite_input_gives_no_verdict_and_leaves_the_state(bad):
    guard = RunawayGuard()
    guard.update(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert guard.update(0.005, bad, 0.0, 0.0, 0.0, 0.0, 0.0) == ''
    assert guard.wheel_error == 0.0


def test_the_same_sample_twice_changes_nothing():
    guard = RunawayGuard()
    guard.update(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    guard.update(0.005, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    before = guard.wheel_error
    assert guard.update(0.005, 50.0, 0.0, 0.0, 0.0, 0.0, 0.0) == ''
    assert guard.wheel_error == before


def test_absurd_positions_are_a_runaway_said_with_finite_figures():
    # Positions near the largest float (a datum in the wrong unit, garbage): the squares
    # of the norm would overflow; the verdict still comes, with its figures.
    guard = RunawayGuard()
    verdict = ''
    for k in range(400):
        verdict = guard.update(k * DT, 1e200 * (k % 3), 1e300, 0.1, 1.0, -1e300, 0.0)
        if verdict:
            break
    assert verdict.startswith('runaway') and 'nan' not in verdict and 'inf' not in verdict
    assert math.isfinite(guard.largest_growth)
