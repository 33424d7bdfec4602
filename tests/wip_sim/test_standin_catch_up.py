"""The stand-in base's physics follows the wall clock: a stalled tick catches up.

Its samples are stamped with the wall-clock instant of the state they carry; a plant that
advanced one step per tick whatever the gap would publish 5 ms of motion over a 30 ms
stamp gap after a stall of its process, which the controllers read as the robot nearly
stopping.
"""

import random
import types

import pytest

pytest.importorskip('rclpy')

from wip_sim.standin_base import MAX_CATCH_UP_STEPS, StandinBase  # noqa: E402

DT = 0.005


#: The ROS clock's reading at perf_counter 0 in these tests (any offset: stamps move with it).
ROS_AT_ZERO_NS = 1_700_000_000_000_000_000


def _drive(wall_times, stamps=None):
    """Return t after each tick, ticking at ``wall_times`` (one step per call as _tick does).

    ``stamps``, a list, gets each tick's sample stamp [ns] as _tick publishes it.
    """
    base = types.SimpleNamespace(_physics_origin=None, t=0.0, dt=DT)
    out = []
    for now in wall_times:
        base.t += DT * StandinBase._steps_due(base, now)
        out.append(base.t)
        if stamps is not None:
            stamps.append(StandinBase._sample_stamp_ns(
                base, ROS_AT_ZERO_NS + round(now * 1e9), now))
    return out


def test_on_time_and_jittered_ticks_take_one_step_each():
    rng = random.Random(1)
    walls = [k * DT + rng.uniform(0.0, 0.9 * DT) for k in range(2000)]
    walls.sort()
    ts = _drive(walls)
    assert ts == pytest.approx([(k + 1) * DT for k in range(2000)])


def test_a_stall_is_caught_up_and_the_plant_never_runs_ahead_of_the_wall_clock():
    walls = [k * DT for k in range(100)]
    walls += [walls[-1] + 0.031 + k * DT for k in range(100)]   # a 31 ms stall
    ts = _drive(walls)
    origin = walls[0]
    for now, t in zip(walls, ts):
        # After its tick the state is one step ahead of the tick's time (the torque is
        # applied over the next period), lagging at most one step after a stall.
        assert now - origin <= t + 1e-9 <= now - origin + DT + 2e-9
    # The tick after the stall took the missed steps at once.
    assert round((ts[100] - ts[99]) / DT) == 6


def test_a_very_long_stall_catches_up_at_most_the_bound():
    stamps = []
    ts = _drive([0.0, 5.0, 5.0 + DT], stamps)
    assert round((ts[1] - ts[0]) / DT) == MAX_CATCH_UP_STEPS
    # The rest of the stall is dropped: the stamps stay on the wall clock (not 4.5 s
    # behind it), and the next tick takes one step.
    assert stamps[1] == ROS_AT_ZERO_NS + 5_000_000_000
    assert round((ts[2] - ts[1]) / DT) == 1


def test_jittered_ticks_stamp_the_instants_the_states_were_read():
    # Tick k reads the state at origin + k dt whatever the timer's jitter, and stamps
    # that. Stamped with the tick's own time, successive stamps would differ by 0.1 to 1.9
    # periods while the physics advanced exactly one.
    rng = random.Random(2)
    walls = [0.0] + sorted(k * DT + rng.uniform(0.0, 0.9 * DT) for k in range(1, 2000))
    stamps = []
    ts = _drive(walls, stamps)
    for k, (now, t, stamp) in enumerate(zip(walls, ts, stamps)):
        assert stamp - ROS_AT_ZERO_NS == pytest.approx((t - DT) * 1e9, abs=2)
        assert stamp - ROS_AT_ZERO_NS == pytest.approx(k * DT * 1e9, abs=2)
        assert stamp <= ROS_AT_ZERO_NS + round(now * 1e9)


def test_a_tick_earlier_than_the_grid_stamps_its_own_time():
    stamps = []
    # The first tick (the grid's origin) 2 ms late, the next 2 ms early against it, the
    # third 0.5 ms late.
    _drive([0.002, 0.005, 0.0125], stamps)
    assert stamps[1] == ROS_AT_ZERO_NS + 5_000_000     # not 7 ms: 2 ms in the future
    assert stamps[2] == ROS_AT_ZERO_NS + 12_000_000    # the grid's 12 ms
