"""The struct decoders of the two sensor streams against rosbags' (``wip_runtime.messages``).

The ESO takes /joint_states and /imu/data serialized at 200 Hz and decodes them with
hand-written decoders; rosbags' generated decoder is the reference. Criterion: every
field equal, of the same type, the float64 arrays byte for byte (the estimates are
bit-for-bit those of the messages rclpy would have built), and a truncated message
refused wherever rosbags refuses it.
"""

import math

from hypothesis import given, settings, strategies as st
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('rosbags')

import numpy as np  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

from wip_runtime import messages  # noqa: E402

JOINT_STATE, IMU = 'sensor_msgs/msg/JointState', 'sensor_msgs/msg/Imu'
messages.prepare_decoder(JOINT_STATE, IMU)


def _rosbags(data: bytes, typename: str):
    msgdef = messages._typestore.get_msgdef(typename)
    return msgdef.deserialize_cdr_le(data[4:], 0, msgdef.cls, messages._typestore)[0]


def _assert_same(a, b) -> None:
    """Field by field, recursively: same types, equal values, arrays equal byte for byte."""
    assert type(a) is type(b), (type(a), type(b))
    if hasattr(a, '__dataclass_fields__'):
        for name in a.__dataclass_fields__:
            _assert_same(getattr(a, name), getattr(b, name))
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes())
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    else:
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))


finite = st.floats(width=64)
names = st.text(alphabet='abcé_ 0', max_size=9)
stamps = st.tuples(st.integers(-2**31, 2**31 - 1), st.integers(0, 2**32 - 1))


@settings(max_examples=150, deadline=None)
@given(stamp=stamps, frame=names, joints=st.lists(names, max_size=4), data=st.data())
def test_a_joint_state_decodes_as_rosbags_decodes_it(stamp, frame, joints, data):
    n = len(joints)
    counts = st.sampled_from(sorted({0, n, 1}))
    msg = JointState(name=joints, position=data.draw(st.lists(finite, min_size=n, max_size=n)),
                     velocity=data.draw(counts.flatmap(
                         lambda k: st.lists(finite, min_size=k, max_size=k))),
                     effort=data.draw(st.lists(finite, max_size=3)))
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame
    raw = serialize_message(msg)
    decoded = messages.decode_serialized(raw, JOINT_STATE)
    _assert_same(_rosbags(raw, JOINT_STATE), decoded)
    assert messages.is_decoded(decoded) and not messages.is_decoded(msg)


@settings(max_examples=150, deadline=None)
@given(stamp=stamps, frame=names, values=st.lists(finite, min_size=37, max_size=37))
def test_an_imu_sample_decodes_as_rosbags_decodes_it(stamp, frame, values):
    msg = Imu()
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame
    o, a, g = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w = values[0:4]
    msg.orientation_covariance = values[4:13]
    a.x, a.y, a.z = values[13:16]
    msg.angular_velocity_covariance = values[16:25]
    g.x, g.y, g.z = values[25:28]
    msg.linear_acceleration_covariance = values[28:37]
    raw = serialize_message(msg)
    decoded = messages.decode_serialized(raw, IMU)
    _assert_same(_rosbags(raw, IMU), decoded)
    assert messages.is_decoded(decoded) and not messages.is_decoded(msg)


@pytest.mark.parametrize('typename, msg', [
    (JOINT_STATE, JointState(name=['left_wheel_joint', 'right_wheel_joint'],
                             position=[0.1, 0.2], velocity=[0.3, 0.4])),
    (IMU, Imu())])
def test_a_truncated_message_is_refused_wherever_rosbags_refuses_it(typename, msg):
    # Fast CDR sizes an empty trailing float64[] with its alignment: a few last bytes are
    # padding that both decoders may do without; any other cut is an InvalidMessage.
    raw = serialize_message(msg)
    for cut in range(len(raw)):
        try:
            messages.decode_serialized(raw[:cut], typename)
        except messages.InvalidMessage:
            continue
        _rosbags(raw[:cut], typename)   # raises if only the fast decoder accepted the cut


def test_a_big_endian_message_still_decodes():
    # rmw_fastrtps writes little endian; a big-endian sender is decoded by rosbags.
    raw = serialize_message(Imu())
    assert raw[:4] == b'\x00\x01\x00\x00'
    big = bytes(messages._typestore.serialize_cdr(_rosbags(raw, IMU), IMU,
                                                  little_endian=False))
    assert big[:4] == b'\x00\x00\x00\x00'
    _assert_same(_rosbags(raw, IMU), messages.decode_serialized(big, IMU))
