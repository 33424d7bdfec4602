"""Wiring checks at engage against the stand-in base: the controllers' params WRONG for it.

The stand-in base (``wip_sim.standin_base``, harness :mod:`wip_bringup.standin_run`) has
joints ``wheel_l``/``wheel_r`` listed right first, the left joint's sign −1 and an IMU
mounted ``[pi, 0, pi/2]``; :data:`~wip_bringup.standin_run.BASE` is what the controllers
need. Each test gives them one mistake:

- ``right_wheel_sign`` −1 instead of 1 (a mirrored motor the params do not know of);
- ``left_joint``/``right_joint`` swapped (with their signs: the sides exchanged);
- ``imu_mounting_rpy`` off by pi about z (the tilt read with the wrong sign);
- ``left_joint``/``right_joint`` swapped with the signs left as they were: to every
  sensor this looks like the IMU turned by pi (the wheels and the IMU disagree on which
  way is forward, nothing else knows): the verdict names ``imu_mounting_rpy`` and the
  swapped joints as the alternative.

Each must end with zero torque applied by the base within 0.5 s of engaging (measured
from the torques the base applied, its ground truth every 5 ms; the bound is the control's
need: without the check a wrong right_wheel_sign dropped the base 0.57 s after engaging,
and torque cut later than that is no longer a choice), the parameter named in the run's
last line, and exit status 1 (a fault while engaged). The verdict's timing is set by the
base's physics (its clock is real time), not by the machine's speed: only the sensor ->
command chain's latency (milliseconds) adds to it.
"""

import pytest

pytest.importorskip('rclpy')

from wip_bringup.standin_run import (BASE, line_scenario, run_against_standin,  # noqa: E402
                                     SHORT_ARM_DELAY)

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.wallclock]

RUN_TIME = 3.0        # [s] after the release; the base falls within it
ZERO_WITHIN = 0.5     # [s] after engaging (see the module docstring)
TRUTH_PERIOD = 0.005  # [s]: the base's torque log, one per control period

MISTAKES = {
    'right_wheel_sign': dict(BASE, right_wheel_sign=-1),
    'left_joint/right_joint': dict(BASE, left_joint=BASE['right_joint'],
                                   right_joint=BASE['left_joint'],
                                   left_wheel_sign=BASE['right_wheel_sign'],
                                   right_wheel_sign=BASE['left_wheel_sign']),
    'imu_mounting_rpy': dict(BASE, imu_mounting_rpy=[
        BASE['imu_mounting_rpy'][0], BASE['imu_mounting_rpy'][1],
        BASE['imu_mounting_rpy'][2] - 3.141592653589793]),
    'joint names only': dict(BASE, left_joint=BASE['right_joint'],
                             right_joint=BASE['left_joint']),
}
#: case -> (the parameter the verdict names, a text the message must hold too).
EXPECTED = {
    'right_wheel_sign': ('right_wheel_sign', 'set right_wheel_sign to 1'),
    'left_joint/right_joint': ('left_joint/right_joint', "left_joint: 'wheel_l'"),
    'imu_mounting_rpy': ('imu_mounting_rpy', 'imu_mounting_rpy: [3.142, 0, 1.571]'),
    'joint names only': ('imu_mounting_rpy', 'left_joint/right_joint swapped'),
}


def zero_torque_from(stats) -> float | None:
    """Time after the release [s] from which every torque the base applied was zero.

    None: torque to the end of its log.
    """
    truth = stats['truth']
    samples = list(zip(truth['t'], truth['tau_left'], truth['tau_right']))
    last_nonzero = max((i for i, (_, left, right) in enumerate(samples)
                        if left != 0.0 or right != 0.0), default=-1)
    if last_nonzero + 1 >= len(samples):
        return None
    return samples[last_nonzero + 1][0]


@pytest.mark.parametrize('case', list(MISTAKES))
def test_a_wiring_mistake_zeroes_the_torque_within_half_a_second_and_names_it(
        tmp_path, case):
    parameter, advice = EXPECTED[case]
    run = run_against_standin(tmp_path / case.replace('/', '_').replace(' ', '_'),
                              MISTAKES[case],
                              RUN_TIME, exit_after_fall=1.0,
                              base_extra={'truth_period': TRUTH_PERIOD}, arm_delay=SHORT_ARM_DELAY)
    result, stats = run.result, run.stats
    assert stats['released'], result.message          # the controllers engaged
    zero_at = zero_torque_from(stats)
    assert zero_at is not None and zero_at <= ZERO_WITHIN, (zero_at, result.message)
    print(f'{case}: zero torque {zero_at:.3f} s after engaging')
    # Nothing but zero afterwards, to the end (the fault is latched).
    assert stats['nonzero_commands_after_fall'] == 0
    assert stats['last_command'] == [0.0, 0.0]          # (-0.0 == 0.0)
    # The run's last line: a fault while engaged, the parameter named first.
    assert result.exit_code == 1, result.message
    assert result.message.startswith('safety FAULT '), result.message
    assert f'wiring: {parameter}: ' in result.message, result.message
    assert advice in result.message, result.message
    engaged_at = next(i for i, e in enumerate(result.safety_events) if e['state'] == 'ACTIVE')
    first = next(e for e in result.safety_events[engaged_at:] if e['state'] == 'FAULT')
    assert first['reasons'].startswith(f'wiring: {parameter}: '), first
    assert all(c == 0 for c in result.node_exit_codes.values()), result.node_exit_codes


def test_correct_wiring_with_sensor_noise_gyro_bias_and_pushes_gives_no_wiring_fault(tmp_path):
    """Correct wiring with sensor noise, gyro bias and pushes gives no wiring fault.

    No false alarm: the base's own conventions (BASE), noisy sensors with gyro biases
    (a consumer IMU's: noise 0.01 rad/s, biases 0.01 and 0.02 rad/s; 4096-count encoders)
    and pushes on the tilt, one while the tilt check runs (2 rad/s^2 for 0.2 s from 0.1 s)
    and one later (a longitudinal 3 m/s^2 for 0.2 s at 3 s): the base stays up, no verdict.
    """
    scenario = line_scenario()
    scenario['sensors'] = {'imu_pitch_noise_std': 0.002, 'imu_yaw_noise_std': 0.002,
                           'gyro_noise_std': 0.01, 'gyro_pitch_bias': 0.01,
                           'gyro_yaw_bias': 0.02, 'encoder_counts_per_rev': 4096}
    scenario['disturbances'] = {
        'yaw': [], 'tilt': [{'kind': 'pulse', 'amplitude': 2.0, 'start_time': 0.1,
                             'width': 0.2}],
        'longitudinal': [{'kind': 'pulse', 'amplitude': 3.0, 'start_time': 3.0,
                          'width': 0.2}]}
    run = run_against_standin(tmp_path / 'noisy', BASE, 8.0, scenario=scenario,
                              arm_delay=SHORT_ARM_DELAY)
    result, stats = run.result, run.stats
    assert not any('wiring' in e['reasons'] for e in result.safety_events), \
        result.safety_events
    assert stats['released'] and not stats['fell'], result.message
    assert result.exit_code == 0, result.message
    mixer = next(v for k, v in result.node_diagnostics.items()
                 if k.startswith('/torque_mixer'))
    print('wiring check:', mixer['wiring check'])
    assert mixer['wiring check'].startswith('no contradiction: tilt Y/X ')
