"""The body's attitude read compiled (core/attitude_kernel.py) is the interpreter's, bit for bit.

Criterion: for any IMU sample, the compiled reading gives the floats of
``hardware_inputs.body_pitch_yaw`` and ``body_pitch_yaw_rates``, or leaves the sample to the
interpreter exactly where a check of theirs refuses it (which then raises its error); a
kernel that disagrees (a stale numba cache) is not used, and the reason is given.
"""

import math

from hypothesis import given, settings, strategies as st
import pytest

pytest.importorskip('rclpy')

from sensor_msgs.msg import Imu  # noqa: E402

from compiled_harness import stale_kernel_module  # noqa: E402
from wip_control.core import attitude_kernel  # noqa: E402
from wip_control.nodes import hardware_inputs  # noqa: E402
from wip_control.nodes.hardware_inputs import (_compiled_attitude, attitude_difference,  # noqa: E402
                                               body_pitch_yaw, body_pitch_yaw_rates,
                                               mounting_inverse)
from wip_runtime.messages import InvalidMessage  # noqa: E402

KERNEL = attitude_kernel.attitude


def _interpreted(msg, mount, with_rates):
    try:
        pitch, yaw = body_pitch_yaw(msg, mount)
        return pitch, yaw, body_pitch_yaw_rates(msg, mount, pitch) if with_rates else None
    except InvalidMessage:
        return None


def _imu(q, w, orientation_known=True, rates_known=True) -> Imu:
    msg = Imu()
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = q
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = w
    if not orientation_known:
        msg.orientation_covariance[0] = -1.0
    if not rates_known:
        msg.angular_velocity_covariance[0] = -1.0
    return msg


def test_the_kernel_agrees_on_the_samples_it_is_checked_with():
    # The check's own samples take both paths, many times each.
    assert attitude_difference(attitude_kernel) == ''
    read = [_compiled_attitude(KERNEL, *sample) is not None
            for sample in hardware_inputs._attitude_samples()]
    assert sum(read) >= 100 and len(read) - sum(read) >= 60


component = st.one_of(st.floats(-1.0, 1.0), st.floats(width=64),
                      st.sampled_from([0.0, -0.0, 1.0, 1e-300, 1e300]))
rate = st.one_of(st.floats(-50.0, 50.0), st.floats(width=64))
mounting = st.one_of(st.none(), st.tuples(*[st.floats(-7.0, 7.0)] * 3).map(mounting_inverse))


@settings(max_examples=400, deadline=None)
@given(q=st.tuples(*[component] * 4), angles=st.tuples(*[st.floats(-3.2, 3.2)] * 3),
       unit=st.booleans(), w=st.tuples(*[rate] * 3), mount=mounting, with_rates=st.booleans(),
       orientation_known=st.booleans(), rates_known=st.booleans())
def test_any_sample_reads_the_interpreters_bits_or_is_left_to_it(
        q, angles, unit, w, mount, with_rates, orientation_known, rates_known):
    if unit:    # most samples of a real IMU: a unit quaternion
        q = hardware_inputs.quaternion_from_euler(*angles)
    msg = _imu(q, w, orientation_known or unit, rates_known or unit)
    expected = _interpreted(msg, mount, with_rates)
    got = _compiled_attitude(KERNEL, msg, mount, with_rates)
    assert repr(got) == repr(expected)


def test_a_sample_the_kernel_leaves_raises_the_interpreters_error():
    last = hardware_inputs._last_attitude
    kept, last.kernel = last.kernel, KERNEL
    try:
        msg = _imu((0.0, 0.0, 0.0, 1.0), (0.0, math.nan, 0.0))
        assert hardware_inputs.body_attitude(msg, None, False)[:2] == (0.0, 0.0)
        with pytest.raises(InvalidMessage, match='angular_velocity: non-finite y=nan'):
            hardware_inputs.body_attitude(msg, None, True)
        with pytest.raises(InvalidMessage, match='quaternion norm 2.0 is not 1'):
            hardware_inputs.body_attitude(_imu((0.0, 0.0, 0.0, 2.0), (0.0, 0.0, 0.0)),
                                          mounting_inverse((math.pi, 0.0, 0.0)), True)
    finally:
        last.kernel = kept


def test_a_kernel_that_disagrees_is_not_used(monkeypatch):
    # A stale numba cache (a formula changed in rotations.py, the kernel's file not) gives
    # other floats: the reading says why and stays interpreted.
    from wip_control.core import compiled as compiled_module

    # One ulp off in ϕ until compiled afresh twice.
    stale = stale_kernel_module('attitude', KERNEL, lambda out: (
        out[0], out[1], math.nextafter(out[2], math.inf), *out[3:]))
    monkeypatch.setattr(compiled_module, 'load_compiled', lambda name: stale)
    monkeypatch.setattr(hardware_inputs._last_attitude, 'kernel', None)
    why_not = hardware_inputs.use_compiled_attitude()
    assert stale.refreshed == 1
    assert why_not.startswith('the compiled attitude differs from the interpreted one at '
                              'sample 0: ')
    assert hardware_inputs._last_attitude.kernel is None
    stale.refreshed, stale.fixed_by = 0, 1
    assert hardware_inputs.use_compiled_attitude() == '' and stale.refreshed == 1
    assert hardware_inputs._last_attitude.kernel == stale.attitude
