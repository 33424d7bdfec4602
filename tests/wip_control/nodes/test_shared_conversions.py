"""Conversions done once per message or per layout give what the per-call ones give.

``hardware_inputs.body_attitude`` (the ESO's IMU conversion, kept for the mixer's wiring
checks on the same decoded message; interpreted and compiled) and
``conversions.EffortCommandCdr`` (the mixer's effort command with its layout worked out
once). Criterion: bit for bit the values and bytes of the functions they stand for, and a
message object of rclpy's classes, which a sender may fill again, never served from what an
earlier content gave.
"""

import math

from hypothesis import given, settings, strategies as st
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('rosbags')

from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import Imu  # noqa: E402

from wip_control.nodes.conversions import EffortCommandCdr, effort_command_cdr  # noqa: E402
from wip_control.nodes import hardware_inputs  # noqa: E402
from wip_control.nodes.hardware_inputs import (body_attitude, body_pitch_yaw,  # noqa: E402
                                               body_pitch_yaw_rates, mounting_inverse)
from wip_runtime.messages import decode_serialized, InvalidMessage  # noqa: E402
from wip_runtime.rotations import quaternion_from_euler  # noqa: E402

IMU = 'sensor_msgs/msg/Imu'
MOUNTINGS = [None, mounting_inverse((math.pi, 0.0, 0.0)), mounting_inverse((0.1, -0.2, 1.5))]


@pytest.fixture(scope='module', params=['interpreted', 'compiled'], autouse=True)
def attitude_reading(request):
    """Every test of the module twice: the attitude read interpreted, then compiled."""
    last = hardware_inputs._last_attitude
    kept = last.kernel
    last.kernel = None
    if request.param == 'compiled':
        assert hardware_inputs.use_compiled_attitude() == ''
    yield request.param
    last.kernel, last.msg = kept, None


def _imu(pitch: float, yaw: float, rates: tuple[float, float, float]) -> Imu:
    msg = Imu()
    o = msg.orientation
    o.x, o.y, o.z, o.w = quaternion_from_euler(0.0, pitch, yaw)
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = rates
    return msg


def _expected(msg, mount, with_rates: bool):
    pitch, yaw = body_pitch_yaw(msg, mount)
    return pitch, yaw, body_pitch_yaw_rates(msg, mount, pitch) if with_rates else None


angles = st.floats(-1.4, 1.4)
rates = st.tuples(*[st.floats(-5.0, 5.0)] * 3)


@settings(max_examples=60, deadline=None)
@given(pitch=angles, yaw=angles, w=rates, mount=st.sampled_from(MOUNTINGS),
       other=st.sampled_from(MOUNTINGS), first_rates=st.booleans())
def test_the_attitude_of_a_decoded_imu_is_the_per_call_one_for_each_reader(
        pitch, yaw, w, mount, other, first_rates):
    # The ESO reads first (rates or not, as its estimator), the mixer second (always the
    # rates), each with its own mounting tuple: equal values, or another mounting.
    decoded = decode_serialized(serialize_message(_imu(pitch, yaw, w)), IMU)
    reference = _imu(pitch, yaw, w)
    assert body_attitude(decoded, mount, first_rates) == _expected(reference, mount, first_rates)
    assert body_attitude(decoded, other, True) == _expected(reference, other, True)
    assert body_attitude(decoded, tuple(mount) if mount else None, True) == _expected(
        reference, mount, True)


def test_an_rclpy_imu_filled_again_gives_its_new_attitude():
    msg = _imu(0.1, 0.2, (0.0, 0.3, 0.0))
    first = body_attitude(msg, None, True)
    o = msg.orientation
    o.x, o.y, o.z, o.w = quaternion_from_euler(0.0, -0.2, 0.5)
    msg.angular_velocity.y = -0.4
    assert body_attitude(msg, None, True) == _expected(msg, None, True) != first


def test_an_imu_without_rates_is_refused_for_every_reader_that_needs_them():
    msg = _imu(0.1, 0.2, (0.0, 0.0, 0.0))
    msg.angular_velocity_covariance[0] = -1.0
    decoded = decode_serialized(serialize_message(msg), IMU)
    assert body_attitude(decoded, None, False)[2] is None
    for _ in range(2):
        with pytest.raises(InvalidMessage, match='angular velocity'):
            body_attitude(decoded, None, True)


@settings(max_examples=100, deadline=None)
@given(left=st.floats(width=64), right=st.floats(width=64),
       joints=st.sampled_from([('l', 'r'), ('r', 'l'), ('l', 'l', 'r'), ('r',)]))
def test_the_effort_command_of_a_fixed_layout_is_the_per_call_bytes(left, right, joints):
    assert EffortCommandCdr(joints, 'l', 'r')(left, right) == effort_command_cdr(
        left, right, joints, 'l', 'r')


def test_an_effort_layout_naming_another_joint_is_refused():
    with pytest.raises(KeyError, match='arm'):
        EffortCommandCdr(('l', 'arm'), 'l', 'r')
