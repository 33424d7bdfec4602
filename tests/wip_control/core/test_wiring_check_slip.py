"""Wheel slip is not a wiring fault (core/wiring_check.py fed slipping wheels).

A vehicle on a circle (υ 0.5 m/s, ω 0.5 rad/s: twice the yaw check's excitation) whose
left wheel spins up or skids, as the MuJoCo plant's wheel does on a low-friction patch
(measured there: 1.7 m/s of slip 30 ms after a torque step beyond the cone, gone when the
torque drops). The kinematics in closed form: a wheel slipping by s reads
(υ ∓ (d/2) ω + s) / r, the gyro reads ω. The check must give no verdict; the same
numbers with the left wheel's sign flipped must still give one (so that the test can fail).
"""

import numpy as np
import pytest

from wip_description.params import ModelParams
from wip_control.core.wiring_check import LEFT_SIGN, WiringCheck, WiringCheckParams

PERIOD = 0.005
PARAMS = ModelParams()


def feed(slip, *, seconds=2.0, v=0.5, omega=0.5, left_sign=1.0, noise=0.01, seed=0):
    """Feed a check the circle with the left wheel's slip ``slip(t)`` [m/s]; its verdict."""
    rng = np.random.default_rng(seed)
    r, d = PARAMS.wheel_radius, PARAMS.track_width
    check = WiringCheck(WiringCheckParams(), PARAMS, PERIOD)
    for k in range(int(round(seconds / PERIOD))):
        t = k * PERIOD
        left = left_sign * (v - 0.5 * d * omega + slip(t)) / r
        right = (v + 0.5 * d * omega) / r
        check.wheels(t, left + noise * rng.standard_normal(),
                     right + noise * rng.standard_normal())
        check.torque(t, 0.0, True, 0.0)
        verdict = check.imu(t, 0.0, noise * rng.standard_normal(),
                            omega + noise * rng.standard_normal(), None)
        if verdict is not None:
            return verdict
    return None


def burst(peak, rise=0.03, hold=0.1, fall=0.05, start=0.5):
    """Return a slip that rises linearly to ``peak`` [m/s] in ``rise`` s, holds, falls back."""
    def slip(t):
        u = t - start
        if u < 0.0:
            return 0.0
        if u < rise:
            return peak * u / rise
        if u < rise + hold:
            return peak
        return max(0.0, peak * (1.0 - (u - rise - hold) / fall))
    return slip


@pytest.mark.parametrize('peak', [1.7, 3.0, -1.7, -3.0])
def test_a_spinning_or_skidding_wheel_is_not_a_wiring_fault(peak):
    # Spin (> 0: the wheel turns faster than the ground moves) or skid (< 0, a locked
    # or braked wheel sliding) of the MuJoCo patch's size and speed, held 0.1 s.
    assert feed(burst(peak)) is None


def test_the_same_circle_with_the_left_sign_wrong_is_named():
    verdict = feed(lambda t: 0.0, left_sign=-1.0)
    assert verdict is not None and verdict.parameter == LEFT_SIGN, verdict


def test_a_straight_run_with_one_wheel_spinning_has_no_yaw_to_judge():
    # On a straight line the gyro sees no yaw: whatever one wheel does, the check waits
    # for excitation (a spin of 2 m/s reads as 4 rad/s of encoder yaw rate at d = 0.5 m).
    assert feed(burst(2.0, hold=1.0), omega=0.0) is None
