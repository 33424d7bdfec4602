"""Commanded references (core/commanded.py): velocity commands and paths."""

import math

import pytest

from wip_control.core.commanded import (CmdVelReference, PATH_END_TOLERANCE, PathReference,
                                        UnicycleLimits)
from wip_control.core.references import make_reference, ReferenceConfig

LIMITS = UnicycleLimits(max_speed=0.5, max_acceleration=0.3, max_yaw_rate=0.25,
                        max_yaw_acceleration=0.5)
DT = 0.005


def run(reference, t0, t1, on_tick=None):
    """Return samples of reference.update on the control grid from t0 to t1."""
    out, t = [], t0
    while t < t1 - 1e-12:
        t = round(t + DT, 9)
        if on_tick is not None:
            on_tick(t)
        out.append((t, reference.update(t)))
    return out


def assert_within_limits(samples):
    previous = None
    for t, ref in samples:
        assert abs(ref.v) <= LIMITS.max_speed + 1e-12
        assert abs(ref.omega) <= LIMITS.max_yaw_rate + 1e-12
        assert abs(ref.omega_dot) <= LIMITS.max_yaw_acceleration + 1e-9
        if previous is not None:
            dt = t - previous[0]
            assert abs(ref.v - previous[1].v) <= LIMITS.max_acceleration * dt + 1e-9
            assert abs(ref.omega - previous[1].omega) <= \
                LIMITS.max_yaw_acceleration * dt + 1e-9
        previous = (t, ref)


def test_cmd_vel_clips_and_rate_limits_a_large_command():
    ref = CmdVelReference(LIMITS, timeout=0.5)
    samples = run(ref, 0.0, 4.0, lambda t: ref.command(t, t, 5.0, -3.0))
    assert_within_limits(samples)
    final = samples[-1][1]
    assert final.v == pytest.approx(LIMITS.max_speed)
    assert final.omega == pytest.approx(-LIMITS.max_yaw_rate)
    assert ref.v_command == LIMITS.max_speed


def test_cmd_vel_integrates_a_unicycle():
    ref = CmdVelReference(LIMITS, timeout=0.5, start=(1.0, 2.0, 0.5))
    run(ref, 0.0, 10.0, lambda t: ref.command(t, t, 0.3, 0.0))
    state = ref.update(10.0)
    travelled = math.hypot(state.x - 1.0, state.y - 2.0)
    # 1 s to reach 0.3 m/s (0.15 m), then 9 s at 0.3 m/s.
    assert travelled == pytest.approx(0.15 + 0.3 * 9.0, abs=1e-6)
    assert math.atan2(state.y - 2.0, state.x - 1.0) == pytest.approx(0.5)
    assert state.phi == pytest.approx(0.5)


def test_cmd_vel_timeout_brakes_smoothly_to_rest_and_stays():
    ref = CmdVelReference(LIMITS, timeout=0.5)
    samples = run(ref, 0.0, 5.0, lambda t: ref.command(t, t, 0.4, 0.2) if t <= 3.0 else None)
    samples += run(ref, 5.0, 12.0)
    assert_within_limits(samples)
    speeds = {round(t, 3): r.v for t, r in samples}
    assert speeds[3.5] == pytest.approx(0.4)          # held until the timeout
    assert 0.0 < speeds[3.9] < 0.4                    # then braking
    assert speeds[5.0] == 0.0 and samples[-1][1].omega == 0.0
    rest = [r for t, r in samples if t >= 5.0]
    assert max(abs(r.x - rest[0].x) + abs(r.y - rest[0].y) for r in rest) == 0.0
    assert ref.timed_out


def test_cmd_vel_refuses_bad_and_badly_stamped_commands():
    ref = CmdVelReference(LIMITS, timeout=0.5, max_lead=0.05)
    ref.update(2.0)
    assert ref.command(2.0, 2.0, math.nan, 0.0) == 'invalid'
    assert ref.command(2.0, 2.0, 0.1, math.inf) == 'invalid'
    assert ref.command(math.nan, 2.0, 0.1, 0.0) == 'invalid'
    assert ref.command(2.2, 2.0, 0.1, 0.0) == 'future'
    assert ref.command(1.4, 2.0, 0.1, 0.0) == 'stale'
    assert ref.command_t is None and ref.update(3.0).v == 0.0
    assert ref.command(3.0, 3.0, 0.1, 0.0) is None
    assert ref.command(2.9, 3.0, 0.2, 0.0) == 'stale'   # out of order
    assert ref.v_command == 0.1


def test_make_reference_builds_the_commanded_kinds_at_the_start_pose():
    config = ReferenceConfig(kind='cmd_vel', line_start=(1.0, -1.0), line_heading=0.3)
    ref = make_reference(config)
    assert isinstance(ref, CmdVelReference)
    assert tuple(ref.sample(5.0))[:4] == (1.0, -1.0, 0.3, 0.0)
    assert isinstance(make_reference(ReferenceConfig(kind='path')), PathReference)


def drive_path(ref, t0, t1):
    samples = run(ref, t0, t1)
    assert_within_limits(samples)
    return samples


def test_path_reaches_its_end_and_stops_there():
    ref = PathReference(LIMITS, speed=0.3, lookahead=0.5)
    square = [(2.0, 0.0), (2.0, 2.0), (0.0, 2.0), (0.0, 0.0)]
    assert ref.set_path(square) is None
    samples = drive_path(ref, 0.0, 60.0)
    assert ref.done
    final = samples[-1][1]
    assert math.hypot(final.x, final.y) < 2 * PATH_END_TOLERANCE
    assert final.v == 0.0 and final.omega == 0.0
    assert max(r.v for _, r in samples) == pytest.approx(0.3, abs=1e-9)
    # It went round: past each corner's neighbourhood.
    for cx, cy in square[:3]:
        assert min(math.hypot(r.x - cx, r.y - cy) for _, r in samples) < 0.35


def test_a_new_path_replaces_the_old_one_from_the_current_pose():
    ref = PathReference(LIMITS, speed=0.3)
    ref.set_path([(5.0, 0.0)])
    before = drive_path(ref, 0.0, 5.0)[-1][1]
    assert before.x > 0.5 and before.v > 0.2
    assert ref.set_path([(before.x, 3.0)]) is None
    assert ref.points[0] == pytest.approx((before.x, before.y))  # no jump of the reference
    samples = drive_path(ref, 5.0, 60.0)
    final = samples[-1][1]
    assert math.hypot(final.x - before.x, final.y - 3.0) < 2 * PATH_END_TOLERANCE
    assert max(r.x for _, r in samples) < before.x + 0.5  # it left the old path


def test_path_refuses_bad_paths_and_stands_still_without_one():
    ref = PathReference(LIMITS, start=(1.0, 1.0, 0.0))
    assert ref.set_path([(0.0, math.nan)]) == 'invalid'
    assert ref.set_path([]) == 'empty'
    assert ref.set_path([('a', 0.0)]) == 'invalid'
    state = ref.update(10.0)
    assert (state.x, state.y, state.v) == (1.0, 1.0, 0.0)
