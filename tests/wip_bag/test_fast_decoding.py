"""The bag reader's own decoding and ordering against mcap's, message for message.

Oracle: mcap's ``SeekingReader.iter_decoded_messages(log_time_order=True)`` with
mcap_ros2's decoder, what ``read_bag`` used before (docs/recording.md, "Reading a bag").
Messages serialized by rclpy (Fast CDR, as a robot's bag holds them) with values that stress
the decoding: every frame_id length 0-9 (each alignment of what follows), NaN, infinities,
-0.0, extreme integers, empty and long sequences, non-ASCII names.
"""

import math

import numpy as np
import pytest

pytest.importorskip('mcap')
serialization = pytest.importorskip('rclpy.serialization')

from mcap.reader import make_reader  # noqa: E402
from mcap.records import Chunk  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from wip_bag.bag_integrity import chunk_records  # noqa: E402
from wip_bag.bag_reader import mcap_files, read_bag  # noqa: E402
from wip_bag.bag_writer import Rosbag2McapWriter  # noqa: E402
from wip_bag.cdr_fast import CheckedDecoder, Layout, layout_of, Part  # noqa: E402

FLOATS = (0.0, -0.0, 1.5, -2.25e-300, 1e308, math.nan, math.inf, -math.inf, 5e-324)


def _messages(rng, k):
    """One message of each type of the project's 200 Hz topics and a few others."""
    from builtin_interfaces.msg import Time
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Imu, JointState, NavSatFix
    from std_msgs.msg import Float64MultiArray, String
    from wip_msgs.msg import DriveTorque, StateEstimate, WheelTorques

    def value():
        return float(FLOATS[k % len(FLOATS)] if rng.random() < 0.3 else rng.normal())
    frame = 'é' * (k % 3) + 'f' * (k % 10)       # 0-9 characters, some of two bytes
    stamp = Time(sec=int(rng.integers(-2**31, 2**31)), nanosec=int(rng.integers(0, 10**9)))
    imu = Imu()
    imu.orientation.x, imu.orientation.w = value(), value()
    imu.angular_velocity.z = value()
    imu.orientation_covariance = [value() for _ in range(9)]
    joint = JointState(name=['wheel_l_joint', 'rüad'][:k % 3], position=[value()] * (k % 3),
                       velocity=[value() for _ in range(k % 2)], effort=[])
    estimate = StateEstimate(phi=value(), theta=value(), x=value())
    wheels = WheelTorques(left=value(), right=value(), zeroed=bool(k % 2),
                          reason='stale' * (k % 4))
    drive = DriveTorque(tau_v=value(), status=k % 5, status_text='SOLVED' * (k % 2),
                        iterations=int(rng.integers(0, 2**32)))
    odometry = Odometry(child_frame_id='base_link'[:k % 10])
    odometry.pose.pose.position.x = value()
    odometry.twist.covariance = [value() for _ in range(36)]
    fix = NavSatFix(latitude=value(), position_covariance_type=k % 4)
    fix.status.status = k % 3 - 1
    found = {'/imu': imu, '/joints': joint, '/estimate': estimate, '/wheels': wheels,
             '/drive': drive, '/odom': odometry, '/fix': fix,
             '/clock': Clock(clock=stamp), '/text': String(data=frame * 3),
             '/array': Float64MultiArray(data=[value(), value()])}
    for message in found.values():
        if hasattr(message, 'header'):
            message.header.stamp, message.header.frame_id = stamp, frame
    return found


def _write(directory, rng, count, chunk_size=4096, shuffle=False):
    """Write ``count`` rounds of every message (``shuffle``: log times out of order)."""
    first = _messages(rng, 0)
    with Rosbag2McapWriter(directory, chunk_size=chunk_size) as bag:
        for topic, message in first.items():
            bag.add_topic(topic, type(message).__module__.split('.')[0] + '/msg/'
                          + type(message).__name__)
        for k in range(count):
            for i, (topic, message) in enumerate(_messages(rng, k).items()):
                log_time = 10**9 + k * 5_000_000 + i
                if shuffle:          # late and early by up to 30 ms, ties included
                    log_time = 10**9 + k * 5_000_000 + int(rng.integers(-6, 7)) * 5_000_000
                bag.write(topic, serialization.serialize_message(message), log_time)
    return directory


def _mcap_read(bag):
    out = []
    for path in mcap_files(bag):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages(
                    log_time_order=True):
                out.append((channel.topic, schema.name, message.log_time, decoded))
    return out


def _assert_same(bag):
    ours, theirs = list(read_bag(bag)), _mcap_read(bag)
    assert len(ours) == len(theirs) > 0
    for mine, (topic, type_name, log_time, decoded) in zip(ours, theirs):
        assert (mine.topic, mine.type_name, mine.log_time_ns) == (topic, type_name, log_time)
        # Every value (a float's repr is exact; NaN reads as NaN), of the same class name.
        assert type(mine.message).__name__ == type(decoded).__name__
        assert repr(mine.message) == repr(decoded), topic
    return ours


@pytest.mark.parametrize('seed', [0, 1])
def test_every_message_reads_as_mcap_ros2_reads_it(tmp_path, seed, monkeypatch):
    slow_calls = []
    made = CheckedDecoder.__init__

    def counting(self, layout, slow):
        made(self, layout, lambda data: slow_calls.append(1) or slow(data))
    monkeypatch.setattr(CheckedDecoder, '__init__', counting)
    ours = _assert_same(_write(tmp_path / 'bag', np.random.default_rng(seed), 80))
    # mcap_ros2 decoded the multi-arrays (80) and, per other topic, the first message of
    # each alignment of its fixed parts (at most 8 each): the fast path all the others.
    assert len(ours) == 80 * 10 and len(slow_calls) <= 80 + 9 * 8


def test_chunks_that_overlap_in_time_read_in_mcaps_order(tmp_path):
    # Small chunks, log times jumping back and forth by up to 30 ms with ties: the order is
    # mcap's (log time, then the chunk's place, then the place in the chunk).
    bag = _write(tmp_path / 'bag', np.random.default_rng(3), 60, chunk_size=700,
                 shuffle=True)
    ours = _assert_same(bag)
    times = [m.log_time_ns for m in ours]
    assert times == sorted(times) and len(set(times)) < len(times)


def test_the_fast_path_is_taken_for_the_topics_it_can_read():
    from sensor_msgs.msg import JointState  # noqa: F401  (the definitions come with rclpy)
    from wip_bag.message_definitions import message_definition
    for type_name, kinds in (('wip_msgs/msg/StateEstimate', ['fixed']),
                             ('sensor_msgs/msg/Imu', ['fixed']),
                             ('sensor_msgs/msg/JointState',
                              ['strings', 'sequence', 'sequence', 'sequence']),
                             ('wip_msgs/msg/WheelTorques', ['fixed', 'string']),
                             ('rosgraph_msgs/msg/Clock', ['fixed']),
                             # Its status's constants are written 'int8 NAME = -1'.
                             ('sensor_msgs/msg/NavSatFix', ['fixed'])):
        layout = layout_of(type_name, message_definition(type_name).text)
        assert [part.kind for part in layout.parts] == kinds, type_name
    # A sequence of messages (the layout of a multi-array), a byte array, a bounded
    # string: mcap_ros2's decoder.
    for type_name in ('std_msgs/msg/Float64MultiArray', 'tf2_msgs/msg/TFMessage'):
        assert layout_of(type_name, message_definition(type_name).text) is None, type_name
    assert layout_of('p/msg/T', 'uint8[4] bytes_') is None
    assert layout_of('p/msg/T', 'string<=8 name') is None
    assert layout_of('p/msg/T', 'int32 A=1\nint32 a') == Layout(False, [Part(
        'fixed', [('i', 4)], layout_of('p/msg/T', 'int32 a').parts[0].fields)])


def test_a_layout_that_differs_from_mcap_ros2_is_dropped_at_its_first_message():
    # A wrong layout (int32 read as float32): the first message is checked against
    # mcap_ros2's decoding and differs, so mcap_ros2 decodes it and every later one.
    from std_msgs.msg import Int32
    from wip_bag.message_definitions import message_definition
    from mcap.records import Schema
    text = message_definition('std_msgs/msg/Int32').text
    slow = DecoderFactory().decoder_for('cdr', Schema(id=1, name='std_msgs/msg/Int32',
                                                      encoding='ros2msg', data=text.encode()))
    calls = []

    def counted(data):
        calls.append(data)
        return slow(data)
    decoder = CheckedDecoder(layout_of('std_msgs/msg/Int32', 'float32 data'), counted)
    for value in (7, -3):
        assert decoder(serialization.serialize_message(Int32(data=value))).data == value
    assert decoder.layout is None and len(calls) == 2
    # The right layout: checked once, then the fast path alone.
    calls.clear()
    decoder = CheckedDecoder(layout_of('std_msgs/msg/Int32', text), counted)
    for value in (7, -3, 2**31 - 1):
        assert decoder(serialization.serialize_message(Int32(data=value))).data == value
    assert decoder.layout is not None and len(calls) == 1


def test_a_chunk_whose_record_runs_past_its_end_is_damaged():
    # Uncompressed, no CRC: a message record whose length says 100 bytes more than the chunk
    # holds is not cut short (mcap's reader returns what is there), the chunk is damaged.
    record = bytes([5]) + (22 + 4).to_bytes(8, 'little') + bytes(22) + b'abcd'
    good = Chunk(message_start_time=0, message_end_time=0, uncompressed_size=len(record),
                 uncompressed_crc=0, compression='', data=record)
    (message,) = chunk_records(good)
    assert message.data == b'abcd' and message.log_time == 0
    bad = bytes([5]) + (22 + 104).to_bytes(8, 'little') + bytes(22) + b'abcd'
    assert chunk_records(Chunk(message_start_time=0, message_end_time=0,
                               uncompressed_size=len(bad), uncompressed_crc=0,
                               compression='', data=bad)) is None
