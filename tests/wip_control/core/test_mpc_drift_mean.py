"""The drift a solve takes: the mean of f̂2, f̂3 over the MPC period, not their sample.

``mpc.disturbance_average_time`` (core/control_step.py, ``DriveControllerStage.solve_drifts``):
the ESO's drift estimates pass noise up to their bandwidth, far above the Nyquist rate of a
solve every Ts, and sampled it folds down into the position loop's band. The stage takes the
mean over the period of f̂ less its part linear in θ̂ (the gravity-aware prediction's a_υθ θ,
a_θθ θ), which it adds back at the solve's θ̂. A push, and the re-solves after it, take the
sample.
"""

import dataclasses
import math

import numpy as np
import pytest

from wip_control.core.control_step import DriveControllerStage
from wip_control.core.mpc_config import MpcParams
from wip_control.core.mpc_prediction import gravity_coefficients
from wip_description.params import ModelParams

MODEL = ModelParams()
CONFIG = MpcParams(backend='daqp')
TS = CONFIG.sampling_period
DECIMATION = 20
A_V_THETA, A_THETA_THETA = gravity_coefficients(MODEL, TS)


def _stage(**changes) -> DriveControllerStage:
    return DriveControllerStage(MODEL, dataclasses.replace(CONFIG, **changes), 15.0,
                                decimation=DECIMATION, fast_decimation=10)


def test_the_window_is_the_mpc_period_and_the_paper_design_samples():
    assert CONFIG.disturbance_average_time == TS
    from wip_sim.core.scenario import scenario_from_mapping
    assert scenario_from_mapping({'design': 'paper'}).mpc.disturbance_average_time == 0.0


def test_a_solve_takes_the_mean_drift_and_the_gravity_part_at_its_own_tilt():
    """f̂ = d + a θ̂ + n, n alternating ±0.4 (zero mean over the window), θ̂ a ramp.

    Closed form: the mean of f̂ − a θ̂ over the 20 ticks is d; the solve gets d + a θ̂(k),
    while the sample would carry the noise of tick k and the mean of f̂ the ramp's lag.
    """
    stage = _stage()
    d2, d3 = 0.07, -0.2

    def estimate(k):
        theta = 0.001 * k
        noise = 0.4 * (-1) ** k
        return theta, d2 + A_V_THETA * theta + noise, d3 + A_THETA_THETA * theta - noise

    for k in range(0, 60):
        stage.observe(k, *estimate(k))
    theta, f2, f3 = estimate(59)
    assert stage.solve_drifts(59, theta, f2, f3) == pytest.approx(
        (d2 + A_V_THETA * theta, d3 + A_THETA_THETA * theta), abs=1e-12)
    # Observing the same tick again changes nothing.
    stage.observe(59, theta, f2 + 5.0, f3)
    assert stage.solve_drifts(59, theta, f2, f3) == pytest.approx(
        (d2 + A_V_THETA * theta, d3 + A_THETA_THETA * theta), abs=1e-12)


def test_the_mean_of_white_noise_has_one_twentieth_of_its_variance():
    """White noise of σ on f̂: the solve's drift has σ/√20 (20 ticks a period), ±15 %."""
    rng = np.random.default_rng(3)
    stage = _stage()
    taken = []
    for k in range(20 * 400):
        f2, f3 = rng.normal(0.0, 0.05, 2)   # within the dead zone: no push
        stage.observe(k, 0.0, f2, f3)
        if k % DECIMATION == DECIMATION - 1:
            taken.append(stage.solve_drifts(k, 0.0, f2, f3))
    ratio = np.std(np.array(taken), axis=0) / 0.05
    assert np.all(np.abs(ratio * math.sqrt(20) - 1.0) < 0.15), ratio


def test_a_push_and_the_re_solves_after_it_take_the_sample():
    """A transient beyond push_threshold: the sample, as the re-solves until fast_resolve_time."""
    stage = _stage()
    for k in range(200):   # past disturbance_startup_time, when pushes are looked for
        stage.observe(k, 0.0, 0.0, 0.0)
        if k % DECIMATION == 0:
            stage.step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, k=k)
    assert stage.solve_drifts(200, 0.0, 0.3, 0.0) == pytest.approx((0.3 / 20, 0.0))
    assert stage.solve_drifts(201, 0.0, 6.0, 0.0) == (6.0, 0.0)     # a push
    stage.observe(201, 0.0, 6.0, 0.0)
    stage.step(0.0, 0.0, 0.0, 6.0, 0.0, 0.5, 0.0, k=201)            # starts the re-solving
    later = 201 + int(round(CONFIG.fast_resolve_time / TS * DECIMATION)) - 1
    assert stage.solve_drifts(later, 0.0, 0.3, 0.0) == (0.3, 0.0)


@pytest.mark.parametrize('changes', [{'disturbance_average_time': 0.0},
                                     {'controller': 'lqr'}])
def test_off_and_the_lqr_take_the_sample(changes):
    stage = _stage(**changes)
    for k in range(40):
        stage.observe(k, 0.0, 0.5 * (-1) ** k, 0.0)
    assert stage.solve_drifts(39, 0.0, -0.5, 0.1) == (-0.5, 0.1)


def test_a_non_finite_estimate_is_left_out_and_a_restart_clears_the_window():
    stage = _stage()
    for k in range(19):
        stage.observe(k, 0.0, 1.0 if k != 7 else math.nan, 0.0)
    assert stage.solve_drifts(19, 0.0, 0.2, 0.0) == pytest.approx((1.0 - 0.8 / 19, 0.0))
    stage.observe(3, 0.0, 0.6, 0.0)            # the ticks started again
    assert stage.solve_drifts(3, 0.0, 0.6, 0.0) == pytest.approx((0.6, 0.0))
