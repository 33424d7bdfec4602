"""The stand-in base's physics follows the wall clock: a stalled tick catches up.

Its samples are stamped with the wall clock; a plant that advanced one step per tick
whatever the gap would publish 5 ms of motion over a 30 ms stamp gap after a stall of
its process, which the controllers read as the robot nearly stopping.
"""

import random
import types

import pytest

pytest.importorskip('rclpy')

from wip_sim.standin_base import MAX_CATCH_UP_STEPS, StandinBase  # noqa: E402

DT = 0.005


def _drive(wall_times):
    """Return t after each tick, ticking at ``wall_times`` (one step per call as _tick does)."""
    base = types.SimpleNamespace(_physics_origin=None, t=0.0, dt=DT)
    out = []
    for now in wall_times:
        base.t += DT * StandinBase._steps_due(base, now)
        out.append(base.t)
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
    ts = _drive([0.0, 5.0])
    assert round((ts[1] - ts[0]) / DT) == MAX_CATCH_UP_STEPS
