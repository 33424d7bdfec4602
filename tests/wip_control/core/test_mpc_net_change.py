"""The torque rate limit (19) as a net change per Ts, when the MPC re-solves between ticks.

What is checked, and against what:
- the drive stage's window rules (``mpc.resolve_rate_rule``; core/control_step.py
  ``net_change_box``) over random solve ticks and random increments: no two torques held
  within Ts differ by more than Δτmax, and random sequences reach Δτmax exactly;
- the box of a worked example against its arithmetic, and on the Ts grid alone (one
  torque in the window) the exact ±Δτmax of the paper;
- the QP with an asymmetric box on Δτ(k|k) (core/mpc_qp.py ``set_first_box``) against
  the projection of a one-dimensional quadratic, and its τ rows against what the box
  can reach;
- ``admissible_increment`` against clipping worked out by hand.
"""

import random

import numpy as np
import pytest

from wip_control.core.control_step import DriveControllerStage, net_change_box
from wip_control.core.model import input_gains
from wip_control.core.mpc_config import MpcParams
from wip_control.core.mpc_plan import admissible_increment
from wip_control.core.mpc_problem import MpcProblem
from wip_control.core.mpc_qp import MpcQp, TickData
from wip_control.core.mpc_reference import reference_qp
from wip_control.core.qp import make_solver, MpcStatus
from wip_description.params import ModelParams

MODEL = ModelParams()
DMAX = MpcParams().max_delta_torque
DECIMATION = 20   # control ticks per Ts (5 ms, 0.1 s)


class _Step:
    def __init__(self, tau_v, delta_tau):
        self.tau_v, self.delta_tau = tau_v, delta_tau


class RandomIncrements:
    """Stands in for the MPC: a random increment, clipped as the MPC clips its own."""

    def __init__(self, config, rng, wide):
        self.config, self.rng, self.wide = config, rng, wide
        self.tau_previous = 0.0

    def push_detected(self, theta_hat, f2_hat, f3_hat, band=None):
        # The MPC's signature: with `push_restart` the control step asks with a band too.
        return f2_hat > 0.0

    def step(self, first_box, tau_limit, **_):
        lower, upper = first_box
        delta = admissible_increment(self.rng.uniform(-self.wide, self.wide),
                                     self.tau_previous, tau_limit, upper, lower)
        self.tau_previous += delta
        return _Step(self.tau_previous, delta)


def _held_torques(seed, share, rule, ticks=4000):
    """Return the drive torque held at each control tick, random pushes and increments."""
    rng = random.Random(seed)
    config = MpcParams(push_resolve_share=share, fast_resolve_time=0.2,
                       resolve_rate_rule=rule)
    stage = DriveControllerStage(MODEL, config, 15.0, decimation=DECIMATION,
                                 fast_decimation=10)
    stage.controller = RandomIncrements(config, rng, 3.0 * DMAX)
    held = []
    for k in range(ticks):
        f2 = 1.0 if rng.random() < 0.05 else 0.0   # a push seen at about 1 tick in 20
        if stage.is_tick(k) and stage.solves(k, 0.0, f2, 0.0):
            stage.step(0.0, 0.0, 0.0, f2, 0.0, 0.0, 0.0, k=k)
        held.append(stage.tau_v)
    return held


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('share', [1.0, 0.75])
@pytest.mark.parametrize('rule', ['net', 'sum'])
def test_no_two_torques_within_ts_differ_by_more_than_the_rate_limit(seed, share, rule):
    """|τ(t) − τ(t')| ≤ Δτmax for |t − t'| ≤ Ts: the limit (19), with either rule.

    Random solve ticks (pushes restart the finer grid) and increments up to 3 Δτmax
    asked for; with these every window of Ts fills, so the bound is reached exactly
    (1e-9 N m: the sums of floats). ``net``: the solves in some window move the torque
    back and forth by more than Δτmax in all; ``sum``: never (the rule of §10).
    """
    held = _held_torques(seed, share, rule)
    spans = [max(held[k - DECIMATION:k + 1]) - min(held[k - DECIMATION:k + 1])
             for k in range(DECIMATION, len(held))]
    assert max(spans) <= DMAX + 1e-9
    assert max(spans) == pytest.approx(DMAX, abs=1e-9)
    steps = [abs(b - a) for a, b in zip(held, held[1:])]
    moved = max(sum(steps[k - DECIMATION:k]) for k in range(DECIMATION, len(held)))
    assert moved > DMAX + 1.0 if rule == 'net' else moved <= DMAX + 1e-9


def test_a_back_and_forth_leaves_the_net_change_free():
    """+1.47 then −0.68 N m within Ts: the next torque may lie in [τ0 − 8.53, τ0 + 10].

    Within Δτmax of τ0, τ0 + 1.47 and τ0 + 0.79: from τ(k−1) = τ0 + 0.79 the increment
    lies in [1.47 − 10 − 0.79, 10 − 0.79] = [−9.32, 9.21] N m (a budget on the sum of
    |Δτ| allowed ±7.85).
    """
    tau0 = 3.0
    window = [tau0, tau0 + 1.47, tau0 + 1.47 - 0.68]
    lower, upper = net_change_box(window, window[-1], DMAX)
    assert lower == pytest.approx(-9.32, abs=1e-12)
    assert upper == pytest.approx(9.21, abs=1e-12)


@pytest.mark.parametrize('tau', [0.0, -0.1, 7.3, 1e-17, -29.99])
def test_on_the_ts_grid_alone_the_box_is_the_papers(tau):
    """One torque in the window (τ(k−1)): exactly ±Δτmax, the same floats as (19)."""
    assert net_change_box([tau], tau, DMAX) == (-DMAX, DMAX)
    assert net_change_box([], tau, DMAX) == (-DMAX, DMAX)


def _one_increment_qp():
    """Return a QP with Nc = 1 (min over Δτ(k|k) only) and DAQP, an exact active-set solver."""
    config = MpcParams(control_horizon=1, backend='daqp', disturbance_startup_time=0.0)
    problem = MpcProblem(MODEL, config)
    qp = MpcQp(problem)
    solver = make_solver('daqp', problem.n_variables, problem.n_constraints,
                         config.qp_settings())
    return qp, solver


def _tick(theta, tau_prev, limit):
    """At rest, tilted by ``theta``, no disturbance, the input gains at θ = 0 of model (1)."""
    _, g2, g3 = input_gains(MODEL, 0.0)
    return TickData(0.0, theta, 0.0, 0.0, 0.0, g2, g3, g2, g3, tau_prev, limit, 0.0, 0.0,
                    0.0, 0.0, 0.0)


@pytest.mark.parametrize('theta', [0.02, -0.02])
def test_the_qp_with_an_asymmetric_box_gives_the_projected_minimiser(theta):
    """Nc = 1: with no soft row active the cost is ½ H00 Δ² + g0 Δ, minimised at −g0/H00.

    A box that cuts that minimiser on one side gives that side's end (the projection of
    a one-dimensional convex quadratic); a box that holds it gives it again.
    """
    qp, solver = _one_increment_qp()
    tick = _tick(theta, 0.0, 30.0)
    qp.update(tick)
    free = solver.solve(*qp.data)
    assert free.status == MpcStatus.SOLVED and np.all(free.z[1:] <= 1e-9)   # no slack
    minimiser = -qp.data.g[0] / qp.data.H[0, 0]
    # (Nc = 1 holds the increment over the 2 s horizon of the unstable tilt: a small one.)
    assert abs(minimiser) > 1e-4 and free.z[0] == pytest.approx(minimiser, abs=1e-9)
    cut = 0.4 * minimiser
    qp.set_first_box(*((-2.0, cut) if cut > 0 else (cut, 2.0)))
    qp.update(tick)
    assert solver.solve(*qp.data).z[0] == pytest.approx(cut, abs=1e-9)
    qp.set_first_box(-abs(minimiser) - 1.0, abs(minimiser) + 0.5)
    qp.update(tick)
    assert solver.solve(*qp.data).z[0] == pytest.approx(minimiser, abs=1e-9)


def test_the_tau_rows_follow_what_the_box_can_reach():
    """τ(k−1) = 20 N m beyond the limit 15, box [−3, 5]: τ(k) ≤ 17 is all it can reach.

    The upper τ row is max(15, 20 − (3 + j Δτmax)) − 20 and the lower one
    min(−15, 20 + 5 + j Δτmax) − 20; with Nc = 1 the one feasible increment is −3 N m.
    The compiled kernel fills the same rows as the numpy reference.
    """
    qp, solver = _one_increment_qp()
    tick = _tick(0.0, 20.0, 15.0)
    qp.set_first_box(-3.0, 5.0)
    qp.update(tick)
    assert (qp.data.u[0], qp.data.l[0]) == (-3.0, -35.0)
    assert solver.solve(*qp.data).z[0] == pytest.approx(-3.0, abs=1e-9)
    expected = reference_qp(qp, tick)
    assert np.array_equal(qp.data.u, expected[4]) and np.array_equal(qp.data.l, expected[3])
    up, down = qp.reach
    assert (up[0], down[0]) == (5.0, 3.0)


def test_admissible_increment_clips_to_the_box_and_the_reachable_limit():
    """Box [−2, 5]: 8 → 5, −9 → −2; beyond the limit 15 from 20, the box's end −2."""
    assert admissible_increment(8.0, 0.0, 30.0, 5.0, -2.0) == 5.0
    assert admissible_increment(-9.0, 0.0, 30.0, 5.0, -2.0) == -2.0
    assert admissible_increment(-10.0, 20.0, 15.0, 5.0, -2.0) == -2.0
    assert admissible_increment(0.0, -20.0, 15.0, 2.0, -5.0) == 2.0
    assert admissible_increment(1.0, 14.0, 15.0, 5.0, -2.0) == 1.0
    assert admissible_increment(3.0, 14.0, 15.0, 5.0, -2.0) == 1.0     # τ clipped to 15


def test_a_first_box_upside_down_or_nan_is_refused_and_one_beyond_the_limit_is_cut():
    """(lower, upper) with lower > upper or NaN: MpcInputError; beyond ±Δτmax: cut to it."""
    from wip_control.core.mpc import LongitudinalMpc, MpcInputError
    mpc = LongitudinalMpc(MODEL, MpcParams(backend='daqp', disturbance_startup_time=0.0))
    for box in ((1.0, -1.0), (float('nan'), 1.0), (-1.0, float('nan'))):
        with pytest.raises(MpcInputError, match='first_box'):
            mpc.step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, first_box=box)
    mpc.step(0.0, 0.05, 0.0, 0.0, 0.0, 0.0, first_box=(-50.0, 50.0))
    assert mpc.qp.first_box == (-DMAX, DMAX)
