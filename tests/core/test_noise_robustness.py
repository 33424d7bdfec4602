"""Sensor noise does not drop the robot (the default design): IMU pitch noise 0.002 rad and
gyro noise 0.01 rad/s, on the paper plant and on the full plant, 10 seeds each.

The paper scenario up to 33 s (start-up with θ(0) = 0.05 rad and the pose error, the yaw
sine, the collision pulse at 30 s and 3 s after it). The 100-seed check of the issue is a
campaign, not a unit test.

Measured on this branch (35 s runs, seeds 0-9): paper plant no fall, |θ| ≤ 0.097 rad
outside the pulse window; full plant no fall, |θ| ≤ 0.104 rad outside the pulse window,
the largest values during the start-up transient (t < 3 s); after it 0.06 rad at most.
Before (main, the paper's ESOs): 0.002 rad of pitch noise alone falls within 0.6 s.
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
        # 0.1 rad after the start-up transient (measured ≤ 0.06: 40 % margin); during it
        # the initial tilt and pose error dominate (measured ≤ 0.104 on the full plant,
        # 0.084 without noise on the paper plant): bound 0.12.
        assert settled <= 0.1, (seed, settled)
        assert whole <= 0.12, (seed, whole)
