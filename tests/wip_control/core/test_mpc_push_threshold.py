"""Tests of ``mpc.push_threshold``: what the MPC calls a push, apart from the decay's zone.

A push is a transient disturbance estimate (f̂ against the offset-free target's slow
estimate) beyond the threshold; the prediction's ``disturbance_decay_dead_zone`` is a
separate band. Upright, at rest, with the model's gains and the slow estimate at 0 after
one tick, the transient is (f̂2, f̂3) itself, so the criterion is exact.
"""

import dataclasses

import numpy as np
import pytest

from wip_control.core.mpc import LongitudinalMpc
from wip_control.core.mpc_config import MpcParams
from wip_description.params import ModelParams

PARAMS = ModelParams()
CONFIG = MpcParams(disturbance_startup_time=0.0)


def _mpc(threshold) -> LongitudinalMpc:
    mpc = LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, push_threshold=threshold))
    mpc.step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # the slow estimate starts at 0
    assert mpc.tau_previous == pytest.approx(0.0, abs=1e-9)
    return mpc


def test_the_default_threshold_is_the_decay_s_dead_zone():
    # The behaviour before the threshold had a parameter of its own.
    assert CONFIG.push_threshold == CONFIG.disturbance_decay_dead_zone


@pytest.mark.parametrize('threshold', [(1.0, 1.0), (0.3, 0.3), (0.3, 2.0)])
def test_a_transient_is_a_push_beyond_the_threshold_on_either_axis(threshold):
    mpc = _mpc(threshold)
    for f2, f3 in ((0.25, 0.0), (0.0, 0.25), (0.5, 0.0), (0.0, 0.5), (1.2, 0.0),
                   (0.0, -1.2), (-2.5, 0.0), (0.0, 2.5)):
        expected = abs(f2) > threshold[0] or abs(f3) > threshold[1]
        assert mpc.push_detected(0.0, f2, f3) == expected, (f2, f3)


def test_the_threshold_leaves_the_prediction_alone():
    # Same estimates, thresholds apart: the same torques and predictions to the bit (the
    # decay over the horizon follows disturbance_decay_dead_zone only).
    rng = np.random.default_rng(5)
    inputs = [(rng.uniform(-0.3, 0.3), rng.uniform(-0.05, 0.05), rng.uniform(-0.3, 0.3),
               rng.uniform(-3, 3), rng.uniform(-3, 3), 0.3) for _ in range(30)]
    runs = []
    for threshold in ((1.0, 1.0), (0.2, 0.2)):
        mpc = _mpc(threshold)
        runs.append([(r.tau_v, r.predicted.copy()) for r in (mpc.step(*x) for x in inputs)])
    for (tau_a, pred_a), (tau_b, pred_b) in zip(*runs):
        assert tau_a == tau_b
        assert np.array_equal(pred_a, pred_b)


def _solved_ticks(drive):
    """Control ticks 0-599 of a push (10 m/s² at 413-432) and noise (0.5 at 100-139): solves."""
    solved = []
    for k in range(600):
        f2 = 10.0 if 413 <= k < 433 else 0.5 if 100 <= k < 140 else 0.0
        if drive.is_tick(k) and drive.solves(k, 0.0, f2, 0.0):
            drive.step(0.0, 0.0, 0.0, f2, 0.0, 0.0, 0.0, k=k)
            solved.append(k)
    return solved


@pytest.mark.parametrize('restart', [False, True])
def test_a_fresh_push_restarts_the_re_solve_grid_with_push_restart(restart):
    """While re-solving on a small transient, a push solves at once with ``push_restart``.

    Threshold 0.3: a transient of 0.5 m/s² from tick 100 (within the decay's dead zone
    of 1) starts the 50 ms grid there (100, 110, ...). A 10 m/s² push from tick 413, off
    that grid: with ``push_restart`` the stage solves at 413 and the grid runs from there
    (423, 433); without it the push waits for the old grid's 420.
    """
    from wip_control.core.control_step import DriveControllerStage
    config = dataclasses.replace(CONFIG, backend='daqp', push_threshold=(0.3, 0.3),
                                 push_restart=restart)
    drive = DriveControllerStage(PARAMS, config, 15.0, decimation=20, fast_decimation=10)
    solved = _solved_ticks(drive)
    assert {100, 110, 120, 400, 410, 420} <= set(solved)
    after = [k for k in solved if 410 < k < 450]
    assert after == ([413, 420, 423, 433, 440, 443] if restart else [420, 430, 440])


class _ReportedSlack:
    """The MPC, reporting a chosen tilt slack sθ of (20) for every plan."""

    def __init__(self, mpc, slack):
        self._mpc, self.slack = mpc, slack

    def __getattr__(self, name):
        return getattr(self._mpc, name)

    def step(self, **inputs):
        return self._mpc.step(**inputs)._replace(slack_theta=self.slack)


@pytest.mark.parametrize('slack, restarts', [(0.0, True), (0.25, True), (0.2501, False),
                                             (1.5, False), (float('nan'), False)])
def test_a_fresh_push_restarts_the_grid_only_within_the_tilt_margin(slack, restarts):
    """The restart moves the grid only if the plan solved there has sθ ≤ the margin.

    The setting of the test above with ``push_restart_max_slack`` 0.25: the push at 413
    is solved at once either way; a plan leaning past (1 + 0.25)·θmax (or no plan)
    leaves the grid where it was (420, 430, 440), since the next solve would come later.
    """
    from wip_control.core.control_step import DriveControllerStage
    config = dataclasses.replace(CONFIG, backend='daqp', push_threshold=(0.3, 0.3),
                                 push_restart=True, push_restart_max_slack=0.25)
    drive = DriveControllerStage(PARAMS, config, 15.0, decimation=20, fast_decimation=10)
    drive.controller = _ReportedSlack(drive.controller, slack)
    solved = _solved_ticks(drive)
    after = [k for k in solved if 410 < k < 450]
    assert after == ([413, 420, 423, 433, 440, 443] if restarts else [413, 420, 430, 440])
