"""Refusing an obstacle (core/obstacle_refusal.py), fed by the obstacle monitor's verdicts.

Synthetic samples at 200 Hz, as tests/wip_control/core/test_obstacle.py: the axle's
distance x_v, the lean θ and the drive torque τυ, on a heading ϕ from a start point, with
a line reference at 0.3 m/s running on ahead.
"""

import math

import pytest

from wip_description.params import ModelParams
from wip_control.core.control_step import TrajectoryGeneratorStage
from wip_control.core.obstacle import ObstacleMonitor
from wip_control.core.obstacle_refusal import back_off_point, ObstacleRefusal
from wip_control.core.reference_state import ReferenceState
from wip_control.core.trajectory_generator import TrajectoryGeneratorParams

H = 0.005
PHI = 0.7                      # heading of the run [rad]
C, S = math.cos(PHI), math.sin(PHI)
X0, Y0 = 1.0, -2.0             # where the axle starts [m]


def reference(t, speed=0.3, lead=0.1):
    """Return a line along ϕ at ``speed``, ``lead`` m ahead of an axle starting with it."""
    d = lead + speed * t
    return ReferenceState(X0 + d * C, Y0 + d * S, PHI, speed, 0.0, 0.0)


def drive(stage, monitor, phases, t=0.0, x_v=0.0):
    """Run (seconds, speed, θ, τυ) phases; return rows (t, x_v, blocked, command)."""
    rows = []
    for seconds, speed, theta, torque in phases:
        for _ in range(int(round(seconds / H))):
            t += H
            x_v += speed * H
            blocked = monitor.update(t, x_v, theta, torque).blocked
            command = stage.step(t, reference(t), X0 + x_v * C, Y0 + x_v * S, PHI, blocked)
            rows.append((t, x_v, blocked, command))
    return rows


def test_a_blocked_axle_is_refused_backing_off_to_a_point_held_at_rest():
    # 0.3 m/s for 2 s, then an edge holds the axle while 20 N m push with a 0.1 rad lean:
    # the monitor calls it blocked 0.3 s after the stop, the refusal follows 0.2 s
    # (obstacle_refuse_delay) later, and from that sample on the generator of eq. (9)
    # follows a point at rest 0.2 m behind the axle on its heading: xe = −0.2,
    # ye = ϕe = 0, so υd = λ3 tanh(−0.2) (eq. (9) with υr = 0) and ωd = 0, while the
    # reference runs on ahead.
    config = TrajectoryGeneratorParams(obstacle_back_off=0.2, obstacle_refuse_delay=0.2)
    stage = TrajectoryGeneratorStage(config)
    rows = drive(stage, ObstacleMonitor(ModelParams()),
                 [(2.0, 0.3, 0.02, 5.0), (1.0, 0.0, 0.1, 20.0)])
    stop = 2.0
    blocked = next(i for i, row in enumerate(rows) if row[2])
    assert rows[blocked][0] == pytest.approx(stop + 0.3, abs=1.5 * H)
    first = next(i for i, row in enumerate(rows) if row[3].x_e < -0.19)
    assert rows[first][0] == pytest.approx(stop + 0.3 + 0.2, abs=1.5 * H)
    assert all(cmd.v_d > 0.0 for _, _, _, cmd in rows[:first])   # pushing on before it
    x_v = rows[first][1]
    refusal = stage.refusal.refusal
    assert (refusal.x, refusal.y) == pytest.approx((X0 + x_v * C, Y0 + x_v * S), abs=1e-12)
    assert refusal.since == rows[blocked][0]
    assert refusal.hold == back_off_point(refusal.x, refusal.y, PHI, 0.2)
    assert (refusal.hold.x, refusal.hold.y) == pytest.approx(
        (refusal.x - 0.2 * C, refusal.y - 0.2 * S), abs=1e-15)
    for _, _, _, cmd in rows[first:]:
        assert cmd.x_e == pytest.approx(-0.2, abs=1e-12)
        assert cmd.y_e == pytest.approx(0.0, abs=1e-12) and cmd.phi_e == 0.0
        assert cmd.v_d == pytest.approx(config.lambda3 * math.tanh(-0.2), abs=1e-12)
        assert cmd.omega_d == pytest.approx(0.0, abs=1e-12)
    assert stage.refusal.refusals == 1
    reason = stage.refusal.reason()
    assert 'refused' in reason and 'plan around it' in reason and '0.20 m back' in reason


def test_a_stall_that_climbs_within_half_a_second_is_a_crossing_not_refused():
    # A bump's foot holds the axle for 0.2 s (the 2 cm bumps' stalls: 0.15-0.2 s) with
    # 25 N m and a 0.14 rad lean, then the wheels roll on up: shorter than the 0.3 s
    # stall time, never blocked, so every command is eq. (9) on the reference itself.
    stage = TrajectoryGeneratorStage()
    plain = TrajectoryGeneratorStage(TrajectoryGeneratorParams(obstacle_back_off=0.0))
    monitor = ObstacleMonitor(ModelParams())
    rows = drive(stage, monitor, [(1.0, 0.3, 0.02, 5.0), (0.2, 0.0, 0.14, 25.0),
                                  (1.0, 0.3, 0.05, 12.0)])
    assert not any(row[2] for row in rows) and stage.refusal.refusals == 0
    assert plain.refusal is None
    for t, x_v, _, cmd in rows:
        assert cmd == plain.step(t, reference(t), X0 + x_v * C, Y0 + x_v * S, PHI)


def test_a_stall_that_climbs_before_the_delay_is_not_refused():
    # Blocked 0.3 s after the stop, then rolling on at 0.3 m/s 0.1 s later (a bump climbed
    # after a 0.4 s stall): 0.04 m / 0.3 m/s = 0.13 s later the axle is past the edge by
    # the monitor's release distance, 0.23 s after the blocking, within the default
    # 0.3 s delay, so never refused; with no delay the same trace is refused at the
    # blocking, with 0.2 s once blocked for 0.2 s (3 cm rolled: still blocked).
    phases = [(1.0, 0.3, 0.02, 5.0), (0.4, 0.0, 0.15, 28.0), (1.0, 0.3, 0.05, 12.0)]
    for config, refusals in ((TrajectoryGeneratorParams(), 0),
                             (TrajectoryGeneratorParams(obstacle_refuse_delay=0.0), 1),
                             (TrajectoryGeneratorParams(obstacle_refuse_delay=0.2), 1)):
        stage = TrajectoryGeneratorStage(config)
        rows = drive(stage, ObstacleMonitor(ModelParams()), phases)
        assert any(row[2] for row in rows)
        assert stage.refusal.refusals == refusals, config.obstacle_refuse_delay


def test_a_refusal_ends_once_the_vehicle_has_gone_on_past_the_edge():
    # A slow climb refused as the wheels start over the edge: stopped 1.2 s against 25 N m
    # (blocked at 0.3 s, refused at 0.6 s with the default 0.3 s delay), then rolling on
    # at 0.3 m/s. The position is ahead of where it was refused by CROSSED = 0.2 m after
    # 0.2 / 0.3 s of rolling; the refusal ends
    # CROSSED_TIME = 0.15 s later, and from then on every command is eq. (9) on the
    # reference itself, as without a refusal (ω̇d aside: a difference across the switch).
    stage = TrajectoryGeneratorStage()
    plain = TrajectoryGeneratorStage(TrajectoryGeneratorParams(obstacle_back_off=0.0))
    rows = drive(stage, ObstacleMonitor(ModelParams()),
                 [(1.0, 0.3, 0.02, 5.0), (1.2, 0.0, 0.12, 25.0), (2.0, 0.3, 0.05, 12.0)])
    refused = next(i for i, row in enumerate(rows) if row[3].x_e < -0.19)
    assert rows[refused][0] == pytest.approx(1.0 + 0.6, abs=1.5 * H)
    end = 1.0 + 1.2 + 0.2 / 0.3 + 0.15
    for t, x_v, _, cmd in rows[refused:]:
        if t < end - 1.5 * H:
            assert cmd.x_e == pytest.approx(-0.2 - (x_v - rows[refused][1]), abs=1e-9)
        elif t > end + 1.5 * H:
            free = plain.step(t, reference(t), X0 + x_v * C, Y0 + x_v * S, PHI)
            assert (cmd.v_d, cmd.omega_d, cmd.x_e, cmd.y_e, cmd.phi_e) == pytest.approx(
                (free.v_d, free.omega_d, free.x_e, free.y_e, free.phi_e), abs=1e-12), t
    assert stage.refusal.refusals == 1 and stage.refusal.crossings == 1
    assert not stage.refusal.refusing


def test_a_position_pushed_ahead_between_fixes_does_not_end_a_refusal():
    # Wheels spinning at 2.5 m/s against the edge push the odometry ahead between the
    # 10 Hz fixes, 0.25 m just before each (past CROSSED = 0.2 m for 0.02 s of every
    # 0.1 s, under CROSSED_TIME), and each fix takes it back to the still axle: held.
    refusal = ObstacleRefusal(0.2, 0.0)
    ahead = reference(10.0)
    refusal.update(0.0, True, ahead, X0, Y0, PHI)
    for k in range(1, 600):
        t = k * H
        leak = 2.5 * (t % 0.1)
        held = refusal.update(t, True, ahead, X0 + leak * C, Y0 + leak * S, PHI)
        assert held == refusal.refusal.hold, t
    assert refusal.crossings == 0
    # The same 0.25 m held for 0.15 s ends it.
    for k in range(600, 631):
        held = refusal.update(k * H, True, ahead, X0 + 0.25 * C, Y0 + 0.25 * S, PHI)
    assert held is ahead and refusal.crossings == 1


def test_dead_reckoning_progress_never_ends_a_refusal():
    # position_source wheels: the position is the wheels' distance, which spinning wheels
    # move on; 0.25 m ahead for a whole second ends nothing, and the first fixed sample
    # after CROSSED_TIME does.
    refusal = ObstacleRefusal(0.2, 0.0)
    ahead = reference(10.0)
    refusal.update(0.0, True, ahead, X0, Y0, PHI, fixed=False)
    for k in range(1, 201):
        held = refusal.update(k * H, True, ahead, X0 + 0.25 * C, Y0 + 0.25 * S, PHI,
                              fixed=False)
        assert held == refusal.refusal.hold
    assert refusal.crossings == 0
    for k in range(201, 232):
        held = refusal.update(k * H, True, ahead, X0 + 0.25 * C, Y0 + 0.25 * S, PHI)
    assert held is ahead and refusal.crossings == 1


def test_a_reference_that_no_longer_leads_past_the_obstacle_resumes():
    refusal = ObstacleRefusal(0.2)
    ahead = ReferenceState(X0 + 0.5 * C, Y0 + 0.5 * S, PHI, 0.3, 0.0, 0.0)
    assert refusal.update(1.0, True, ahead, X0, Y0, PHI) == refusal.refusal.hold
    # Still blocked or not, a reference ahead stays refused (a timed path runs on).
    assert refusal.update(1.1, False, ahead, X0, Y0, PHI) == refusal.refusal.hold
    # Turned away: the reference 1 mm behind the line across the stopped axle resumes,
    # and is followed as it is.
    behind = ReferenceState(X0 - 0.001 * C + S, Y0 - 0.001 * S - C, PHI - 1.5, 0.3, 0.1, 0.0)
    assert refusal.update(1.2, False, behind, X0, Y0, PHI) is behind
    assert not refusal.refusing
    # A reference ahead again is not refused without a new blocking ...
    assert refusal.update(1.3, False, ahead, X0, Y0, PHI) is ahead
    # ... and one still in force when resumed is not one either: it must start again.
    refusal.update(1.4, True, ahead, X0, Y0, PHI)
    refusal.update(1.5, True, behind, X0, Y0, PHI)
    assert refusal.update(1.6, True, ahead, X0, Y0, PHI) is ahead
    assert refusal.update(1.7, False, ahead, X0, Y0, PHI) is ahead
    assert refusal.update(1.8, True, ahead, X0, Y0, PHI) == refusal.refusal.hold
    assert refusal.refusals == 3


def test_a_failed_step_keeps_the_refusal():
    # A non-finite reference while refusing is dropped (ValueError) and must not end the
    # refusal (a NaN reference is behind no line); a non-finite pose starts none.
    stage = TrajectoryGeneratorStage(TrajectoryGeneratorParams(obstacle_refuse_delay=0.0))
    stage.step(1.0, reference(1.0), X0, Y0, PHI, True)
    assert stage.refusal.refusing
    held = stage.refusal.state()
    nan = ReferenceState(math.nan, 0.0, 0.0, 0.3, 0.0, 0.0)
    with pytest.raises(ValueError):
        stage.step(1.1, nan, X0, Y0, PHI, True)
    assert stage.refusal.state() == held
    fresh = ObstacleRefusal(0.2)
    assert fresh.update(1.0, True, reference(1.0), math.nan, Y0, PHI) == reference(1.0)
    assert not fresh.refusing


@pytest.mark.parametrize('value', [0.0, -0.1, math.inf, math.nan])
def test_bad_settings_are_one_line_errors(value):
    with pytest.raises(ValueError, match='back_off'):
        ObstacleRefusal(value)
    if value != 0.0:
        with pytest.raises(ValueError, match='delay'):
            ObstacleRefusal(0.2, value)
        with pytest.raises(ValueError, match='crossed_time'):
            ObstacleRefusal(0.2, 0.7, 0.2, value)
    with pytest.raises(ValueError, match='crossed'):
        ObstacleRefusal(0.2, 0.7, value)
