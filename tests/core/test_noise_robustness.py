"""Sensor noise does not drop the robot (the default design): IMU pitch noise 0.002 rad and
gyro noise 0.01 rad/s, on the paper plant and on the full plant, 10 seeds each.

The paper scenario up to 33 s (start-up with θ(0) = 0.05 rad and the pose error, the yaw
sine, the collision pulse at 30 s and 3 s after it). The 100-seed check of the issue is a
campaign, not a unit test.

Measured on this branch (33 s, seeds 0-9): paper plant no fall, |θ| ≤ 0.097 rad
outside the pulse window, ≤ 0.086 after the start-up (t ≥ 3 s); full plant no fall,
|θ| ≤ 0.104 rad. On the full plant the noise is not what limits |θ|: without noise it
reaches 0.100 too, from the speed oscillation (−0.8 to 1.2 m/s) of the MPC on the
full plant (the MPC's part of the issue). Before (the paper's ESOs, `design: paper`):
0.002 rad pitch and 0.01 rad/s gyro noise fall at 0.69 s (seed 0).
"""

import numpy as np
import pytest

from wip_control.core.runner import run_scenario
from wip_control.core.scenario import scenario_from_mapping

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
        # Paper plant: 0.1 rad after the start-up transient (measured ≤ 0.086); during it
        # the initial tilt and pose error dominate (0.084 without noise): bound 0.12.
        # Full plant: 0.12 throughout (measured 0.104; 0.100 without noise, see above).
        if model == 'paper':
            assert settled <= 0.1, (seed, settled)
        assert whole <= 0.12, (seed, whole)
