"""Commanded references (core/commanded.py): velocity commands and paths."""

import math

import pytest
from hypothesis import given, settings, strategies as st

from wip_control.core.commanded import (_cumulative, _point_on, _point_within, _polyline,
                                        CmdVelReference, MAX_PATH_COORDINATE,
                                        PATH_END_TOLERANCE, PathReference, UnicycleLimits)
from wip_control.core.references import make_reference, ReferenceParams

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
    config = ReferenceParams(kind='cmd_vel', line_start=(1.0, -1.0), line_heading=0.3)
    ref = make_reference(config)
    assert isinstance(ref, CmdVelReference)
    assert tuple(ref.sample(5.0))[:4] == (1.0, -1.0, 0.3, 0.0)
    assert isinstance(make_reference(ReferenceParams(kind='path')), PathReference)


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
    assert ref.set_path([(0.0, 2e6)]) == 'invalid'     # 2000 km from the map origin
    state = ref.update(10.0)
    assert (state.x, state.y, state.v) == (1.0, 1.0, 0.0)


# A new path is taken up where the reference is (as Nav2's controllers prune a new plan
# to the robot): the route below is the 3 m x 2 m rectangle of a route publisher.
RECTANGLE = [(0.0, 0.0), (3.0, 0.0), (3.0, 2.0), (0.0, 2.0), (0.0, 0.0)]


def drive_with(ref, t0, t1, every=None, path=None):
    """Drive from t0 to t1; with ``every`` [s], call ``path(t)`` and send what it returns."""
    def on_tick(t):
        if every is not None and round(t / DT) % round(every / DT) == 0:
            assert ref.set_path(path(t)) is None
    samples = run(ref, t0, t1, on_tick)
    assert_within_limits(samples)
    return samples


def test_a_route_published_again_changes_nothing_bit_for_bit():
    once = PathReference(LIMITS, speed=0.3)
    assert once.set_path(RECTANGLE) is None
    expected = drive_with(once, 0.0, 70.0)
    again = PathReference(LIMITS, speed=0.3)
    assert again.set_path(RECTANGLE) is None
    # Once a second, and as tuples of other types (a message's floats), mid-run.
    got = drive_with(again, 0.0, 70.0, every=1.0, path=lambda t: [list(p) for p in RECTANGLE])
    assert got == expected
    assert again.joined == 'same' and again.done
    final = got[-1][1]
    assert math.hypot(final.x, final.y) < 2 * PATH_END_TOLERANCE and final.v == 0.0
    # It went round the rectangle (each far corner passed within 0.35 m) in the time
    # of one lap at 0.3 m/s plus the turns, not on the spot at its start.
    for cx, cy in RECTANGLE[1:4]:
        assert min(math.hypot(r.x - cx, r.y - cy) for _, r in got) < 0.35


def test_a_path_overlapping_the_old_one_continues_it_within_1e_9():
    # The same route with its driven part cut off (a replan from the robot's progress),
    # sent when the reference is at about x = 1.3 on the first side.
    route = [(0.0, 0.0), (4.0, 0.0), (4.0, 3.0)]
    once = PathReference(LIMITS, speed=0.3)
    once.set_path(route)
    expected = drive_with(once, 0.0, 40.0)
    ref = PathReference(LIMITS, speed=0.3)
    ref.set_path(route)
    before = drive_with(ref, 0.0, 6.0)
    assert 1.0 < before[-1][1].x < 2.0
    assert ref.set_path([(1.0, 0.0), (4.0, 0.0), (4.0, 3.0)]) is None
    assert ref.joined == 'continued'
    got = before + drive_with(ref, 6.0, 40.0)
    assert len(got) == len(expected)
    worst = max(max(abs(a - b) for a, b in zip(r1, r2)) for (_, r1), (_, r2) in zip(got, expected))
    assert worst < 1e-9
    assert ref.done and math.hypot(got[-1][1].x - 4.0, got[-1][1].y - 3.0) < 2 * PATH_END_TOLERANCE


def test_a_replanned_path_from_the_robot_continues_smoothly_to_its_goal():
    # Every second a planner sends a straight path from the robot to the goal; the robot
    # lags the reference by 0.15 m and is 0.03 m to its left (a tracking error).
    goal = (6.0, 1.0)
    ref = PathReference(LIMITS, speed=0.3)

    def replan(_t):
        state = ref.update(ref.unicycle.t)
        lag_x, lag_y = -0.15 * math.cos(state.phi), -0.15 * math.sin(state.phi)
        side_x, side_y = -0.03 * math.sin(state.phi), 0.03 * math.cos(state.phi)
        return [(state.x + lag_x + side_x, state.y + lag_y + side_y), goal]
    ref.set_path([(0.0, 0.0), goal])
    samples = drive_with(ref, 0.0, 40.0, every=1.0, path=replan)
    assert ref.joined in ('continued', 'same')
    final = samples[-1][1]
    assert math.hypot(final.x - goal[0], final.y - goal[1]) < 2 * PATH_END_TOLERANCE
    assert final.v == 0.0
    # Smooth: once at speed, it never slows by more than 0.01 m/s before the final brake
    # (a path restarted behind the reference would turn it round every second), and it
    # stays within 0.1 m of the straight line (each replan starts 3 cm to its left).
    cruise = [r for t, r in samples if 2.0 < t and r.x < goal[0] - 0.6]
    assert cruise and min(r.v for r in cruise) > 0.29
    norm = math.hypot(*goal)
    assert max(abs(r.y * goal[0] - r.x * goal[1]) / norm for _, r in samples) < 0.1


def test_a_far_path_is_joined_at_its_closest_point():
    ref = PathReference(LIMITS, speed=0.3)
    assert ref.set_path([(-3.0, 2.0), (5.0, 2.0)]) is None   # closest point: (0, 2)
    assert ref.joined == 'joined'
    assert ref.points[:2] == [(0.0, 0.0), (0.0, 2.0)]
    samples = drive_with(ref, 0.0, 60.0)
    assert min(math.hypot(r.x, r.y - 2.0) for _, r in samples) < 0.35
    assert min(r.x for _, r in samples) > -0.05        # it never went to the path's start
    final = samples[-1][1]
    assert ref.done and math.hypot(final.x - 5.0, final.y - 2.0) < 2 * PATH_END_TOLERANCE


def test_a_closed_route_from_the_robot_is_driven_from_its_start_not_its_end():
    # The reference 5 cm nearer the route's end than its start: still driven round.
    ref = PathReference(LIMITS, speed=0.3, start=(-0.03, 0.04, 0.0))
    assert ref.set_path(RECTANGLE) is None
    assert ref.joined == 'closest' and ref.length > 9.0
    # A path behind the reference's progress is not driven back to: a copy of the
    # rectangle sent again once its end is reached leaves it at rest there.
    drive_with(ref, 0.0, 70.0)
    assert ref.done
    shifted = [(x + 1e-3, y) for x, y in RECTANGLE]      # not the same points
    assert ref.set_path(shifted) is None
    samples = drive_with(ref, 70.0, 80.0)
    assert max(math.hypot(r.x - samples[0][1].x, r.y - samples[0][1].y) for _, r in samples) < 0.02


coordinates = st.floats(allow_nan=True, allow_infinity=True, min_value=None, max_value=None)
paths = st.lists(st.tuples(st.one_of(coordinates, st.floats(-20.0, 20.0)),
                           st.one_of(coordinates, st.floats(-20.0, 20.0))), max_size=12)


@settings(max_examples=300, deadline=None)
@given(st.lists(paths, min_size=1, max_size=4))
def test_any_sequence_of_paths_is_refused_or_followed_within_the_limits(sequence):
    # Whatever a planner sends (huge, tiny, repeated, crossing, non-finite points), a path
    # is refused with a reason or taken up; the reference stays finite, within its limits
    # and never jumps (a step moves it at most max_speed * dt).
    ref = PathReference(LIMITS, speed=0.3)
    samples, t = [], 0.0
    for points in sequence:
        reason = ref.set_path(points)
        finite = all(abs(c) <= MAX_PATH_COORDINATE for p in points for c in p)
        assert reason in ((None,) if finite and points else ('invalid', 'empty')), reason
        step = run(ref, t, t + 0.5)
        samples += step
        t = step[-1][0]
    assert_within_limits(samples)
    for (_, a), (_, b) in zip(samples, samples[1:]):
        assert all(math.isfinite(v) for v in b)
        assert math.hypot(b.x - a.x, b.y - a.y) <= LIMITS.max_speed * DT + 1e-9


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)), min_size=2,
                max_size=12),
       st.lists(st.floats(0.0, 1.0), min_size=1, max_size=6))
def test_a_point_within_a_segment_is_the_searched_one_to_the_bit(points, fractions):
    # The path's projection finds the point on a segment directly: the same floats as
    # the search along the whole path (_point_on), so a route is driven bit for bit as
    # before; at a segment's end the search may take the next segment (None: searched).
    polyline = _polyline(points)
    if len(polyline) < 2:
        return
    cumulative = _cumulative(polyline)
    for i in range(len(polyline) - 1):
        (x0, y0), (x1, y1) = polyline[i], polyline[i + 1]
        s0, s1 = cumulative[i], cumulative[i + 1]
        for s in (s0, s1, s0 + (s1 - s0), *(s0 + f * (s1 - s0) for f in fractions)):
            direct = _point_within(s, s0, s1, x0, y0, x1 - x0, y1 - y0)
            if s == s0 or s0 < s < s1:
                assert direct == _point_on(polyline, cumulative, s)
            else:
                assert direct is None
