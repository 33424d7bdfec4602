"""Sensor noise does not drop the robot (the default design).

IMU pitch noise 0.002 rad and gyro noise 0.01 rad/s, on the paper plant and on the full plant, 10
seeds each.

The paper scenario up to 33 s (start-up with θ(0) = 0.05 rad and the pose error, the yaw
sine, the collision pulse at 30 s and 3 s after it). The 100-seed check of the issue is a
campaign, not a unit test.

Measured on this branch (33 s, seeds 0-9): no fall; |θ| ≤ 0.083 rad (paper plant) and
≤ 0.079 rad (full plant) outside the pulse window, the largest during the start-up
(after 3 s: 0.045 and 0.079). 90 s runs, same seeds: no fall, ≤ 0.083 / 0.089 rad.
Before (the paper's design, `design: paper`): 0.002 rad pitch and 0.01 rad/s gyro
noise fall at 0.69 s (seed 0).
"""

import numpy as np
import pytest

from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import scenario_from_mapping

NOISE = {'imu_pitch_noise_std': 0.002, 'gyro_noise_std': 0.01}
PULSE_START, PULSE_WINDOW = 30.0, 3.0
START_UP = 3.0


def tilt_outside_pushes(model, seed):
    scenario = scenario_from_mapping({'duration': 33.0, 'seed': seed, 'sensors': NOISE,
                                      'plant': {'model': model}})
    result = run_scenario(scenario)
    truth = result.record.groups['truth']
    t, theta = truth['t'], np.abs(truth['theta'])
    outside = ~((t >= PULSE_START) & (t < PULSE_START + PULSE_WINDOW))
    return result.fell, theta[outside].max(), theta[outside & (t >= START_UP)].max()


@pytest.mark.slow
@pytest.mark.parametrize('model', ['paper', 'full'])
def test_no_fall_and_small_tilt_under_imu_and_gyro_noise(model):
    for seed in range(10):
        fell, whole, settled = tilt_outside_pushes(model, seed)
        assert not fell, seed
        # The bound, 0.1 rad outside the pushes, start-up included (measured
        # ≤ 0.083: 17 % margin); after the start-up 0.09 (measured ≤ 0.079).
        assert whole <= 0.1, (seed, whole)
        assert settled <= 0.09, (seed, settled)


def speed_wander(model, seed, average_time):
    """Std of υ − 0.5 m/s [m/s] over 10-30 s of a line at 0.5 m/s with the default noise."""
    scenario = scenario_from_mapping({
        'duration': 30.0, 'seed': seed, 'sensors': NOISE, 'plant': {'model': model},
        'reference': {'kind': 'line', 'line_speed': 0.5},
        'disturbances': {'yaw': [], 'longitudinal': [], 'tilt': []},
        'mpc': {'disturbance_average_time': average_time}})
    truth = run_scenario(scenario).record.groups['truth']
    return float(np.std(truth['v'][truth['t'] >= 10.0] - 0.5))


@pytest.mark.slow
@pytest.mark.parametrize('model, largest_ratio', [('paper', 0.4), ('full', 0.7)])
def test_the_mean_drift_of_a_solve_narrows_the_speed_wander(model, largest_ratio):
    """The gyro noise folded into the solves' sampled f̂ made the speed wander.

    Sampled once per Ts, the noise of f̂2, f̂3 (up to the ESOs' 40-60 rad/s) folds into the
    band of the position loop; the mean over the period (mpc.disturbance_average_time, the
    default) filters it first. Measured (seeds 0-3): std 0.099 → 0.019 m/s on the paper
    plant (0.20×), 0.083 → 0.043 on the full plant (0.52×), whose position loop is the less
    damped (docs/history/mpc.md §27).
    """
    for seed in (0, 1):
        sampled, averaged = speed_wander(model, seed, 0.0), speed_wander(model, seed, 0.1)
        assert averaged <= largest_ratio * sampled, (seed, sampled, averaged)
