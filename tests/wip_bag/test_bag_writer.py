"""The bag writer makes rosbag2 (MCAP, metadata v9) bags that independent readers accept.

Two readers that share no code with the writer check every bag: ``rosbags`` (a rosbag2
implementation that also recomputes each type's RIHS01 hash from the embedded definition and
compares it with the recorded one) and ``mcap`` + ``mcap-ros2-support``. Messages are
serialized by rclpy (the ROS middleware's own CDR), so "equal" means the bytes and the field
values survive the round trip exactly (no tolerance: nothing is recomputed).
"""

import array
import math

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.reader import make_reader
import numpy as np
import pytest
from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, Header, String
import yaml

from wip_bag.bag_reader import bag_summary, read_bag
from wip_bag.bag_repair import repair_bag
from wip_bag.bag_writer import BagExistsError, Rosbag2McapWriter
from wip_bag.message_definitions import message_definition, type_description_hash
from wip_bag.qos_yaml import dump_offered_qos, qos_profile_to_dict

START_NS = 1_700_000_000_000_000_000  # an epoch time [ns]
PERIOD_NS = 5_000_000  # 200 Hz


def _stamp(k):
    ns = START_NS + k * PERIOD_NS
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def _imu(k):
    msg = Imu(header=Header(stamp=_stamp(k), frame_id='imu_link'))
    msg.orientation.x, msg.orientation.w = 0.01 * k, math.sqrt(1.0 - (0.01 * k) ** 2)
    msg.angular_velocity.y = -0.25 * k
    msg.linear_acceleration.z = 9.81
    msg.orientation_covariance[0] = 1e-4 * (k + 1)
    return msg


def _joints(k):
    return JointState(header=Header(stamp=_stamp(k)),
                      name=['left_wheel_joint', 'right_wheel_joint'],
                      position=[0.1 * k, -0.1 * k], velocity=[1.5, -1.5 + k],
                      effort=[0.25, -0.25])


def _diagnostics(k):
    return DiagnosticArray(header=Header(stamp=_stamp(k)), status=[
        DiagnosticStatus(level=DiagnosticStatus.WARN, name='recorder', message=f'tick {k}',
                         hardware_id='', values=[KeyValue(key='count', value=str(k)),
                                                 KeyValue(key='rate', value='200.0')])])


# (topic, type name, message factory); two topics share a type to exercise schema reuse.
TOPICS = (
    ('/imu/data', 'sensor_msgs/msg/Imu', _imu),
    ('/joint_states', 'sensor_msgs/msg/JointState', _joints),
    ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', _diagnostics),
    ('/chatter', 'std_msgs/msg/String', lambda k: String(data=f'hello {k} é')),
    ('/chatter_copy', 'std_msgs/msg/String', lambda k: String(data='x' * k)),
    ('/array', 'std_msgs/msg/Float64MultiArray',
     lambda k: Float64MultiArray(data=[float(k), -0.5, 1e-300, math.pi])),
)
COUNTS = {'/imu/data': 40, '/joint_states': 40, '/diagnostics': 5, '/chatter': 7,
          '/chatter_copy': 3, '/array': 11}
RELIABLE = QoSProfile(depth=10)
LATCHED = QoSProfile(depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)


def _messages():
    """All messages in receive order: (topic, type, log time [ns], rclpy message, CDR bytes).

    Serialized once: rclpy's CDR leaves alignment padding uninitialised, so serializing the
    same message twice can give different bytes.
    """
    out = []
    for topic, type_name, factory in TOPICS:
        for k in range(COUNTS[topic]):
            # Interleave topics: each topic's k-th message is received at slot k, offset per
            # topic by 1 us so that receive times are all distinct.
            out.append((START_NS + k * PERIOD_NS + 1000 * len(out) % 7000, topic, type_name,
                        factory(k)))
    out.sort(key=lambda item: item[0])
    return [(topic, type_name, t, msg, bytes(serialize_message(msg)))
            for t, topic, type_name, msg in out]


def _write_bag(directory, compression, chunk_size=4096):
    messages = _messages()
    with Rosbag2McapWriter(directory, compression=compression, chunk_size=chunk_size) as bag:
        for topic, type_name, _ in TOPICS:
            qos = [LATCHED] if topic == '/diagnostics' else [RELIABLE]
            bag.add_topic(topic, type_name, qos_profiles=qos)
        for topic, _, log_time, _, data in messages:
            bag.write(topic, data, log_time, publish_time_ns=log_time - 1)
    return messages


def _assert_same(expected, decoded, path='msg'):
    """Compare an rclpy message with a decoded one field by field, exactly."""
    if hasattr(expected, 'get_fields_and_field_types'):
        for field in expected.get_fields_and_field_types():
            _assert_same(getattr(expected, field), getattr(decoded, field), f'{path}.{field}')
    elif isinstance(expected, (list, tuple, array.array, np.ndarray)):
        expected, decoded = list(expected), list(decoded)
        assert len(expected) == len(decoded), path
        for i, (a, b) in enumerate(zip(expected, decoded)):
            _assert_same(a, b, f'{path}[{i}]')
    else:
        if isinstance(expected, bytes) and len(expected) == 1:
            expected = expected[0]  # rclpy gives a 'byte' field as bytes, decoders as int.
        assert expected == decoded, f'{path}: {expected!r} != {decoded!r}'


@pytest.fixture(params=['none', 'zstd', 'lz4'])
def bag(request, tmp_path):
    directory = tmp_path / f'run_{request.param}'
    return directory, _write_bag(directory, request.param)


def test_layout_and_metadata_follow_rosbag2_v9(bag):
    directory, messages = bag
    assert sorted(p.name for p in directory.iterdir()) == [
        'metadata.yaml', f'{directory.name}_0.mcap']
    info = yaml.safe_load((directory / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert info['version'] == 9
    assert info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == [f'{directory.name}_0.mcap']
    # Chunk compression belongs to the MCAP storage; rosbag2's own compression is unused.
    assert (info['compression_format'], info['compression_mode']) == ('', '')
    assert info['message_count'] == len(messages) == sum(COUNTS.values())
    times = [t for _, _, t, _, _ in messages]
    assert info['starting_time']['nanoseconds_since_epoch'] == min(times)
    assert info['duration']['nanoseconds'] == max(times) - min(times)
    assert info['files'] == [{
        'path': f'{directory.name}_0.mcap',
        'starting_time': {'nanoseconds_since_epoch': min(times)},
        'duration': {'nanoseconds': max(times) - min(times)},
        'message_count': len(messages)}]
    by_topic = {t['topic_metadata']['name']: t for t in info['topics_with_message_count']}
    assert {name: t['message_count'] for name, t in by_topic.items()} == COUNTS
    for topic, type_name, _ in TOPICS:
        meta = by_topic[topic]['topic_metadata']
        assert meta['type'] == type_name
        assert meta['serialization_format'] == 'cdr'
        assert meta['type_description_hash'].startswith('RIHS01_')
        # v9: a sequence of mappings with the policies by name.
        (qos,) = meta['offered_qos_profiles']
        assert qos['reliability'] == 'reliable'
        assert qos['durability'] == ('transient_local' if topic == '/diagnostics'
                                     else 'volatile')
        assert qos['history'] == 'keep_last'


def test_mcap_records_carry_the_rosbag2_profile_schemas_and_channel_metadata(bag):
    directory, _ = bag
    with open(directory / f'{directory.name}_0.mcap', 'rb') as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        schemas = {s.name: s for s in summary.schemas.values()}
        # One schema per type, shared by the two String topics.
        assert sorted(schemas) == sorted({type_name for _, type_name, _ in TOPICS})
        for type_name, schema in schemas.items():
            assert schema.encoding == 'ros2msg'
            assert schema.data.decode() == message_definition(type_name).text
        for channel in summary.channels.values():
            type_name = summary.schemas[channel.schema_id].name
            assert channel.message_encoding == 'cdr'
            assert channel.metadata['topic_type_hash'] == type_description_hash(type_name)
            assert yaml.safe_load(channel.metadata['offered_qos_profiles'])[0][
                'reliability'] == 'reliable'
        (record,) = [m for m in reader.iter_metadata() if m.name == 'rosbag2']
        serialized = yaml.safe_load(record.metadata['serialized_metadata'])
        assert serialized['message_count'] == sum(COUNTS.values())


def test_rosbags_reads_every_message_back_exactly(bag):
    directory, messages = bag
    with Reader(directory) as reader:
        assert reader.message_count == len(messages)
        assert {c.topic: c.msgcount for c in reader.connections} == COUNTS
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in reader.connections}
        assert qos['/imu/data'].reliability == QosReliability.RELIABLE
        assert qos['/diagnostics'].durability == QosDurability.TRANSIENT_LOCAL
        raw = [(c.topic, t, bytes(data)) for c, t, data in reader.messages()]
    # Same bytes, same receive times, same order.
    assert raw == [(topic, t, data) for topic, _, t, _, data in messages]

    # AnyReader builds its types from the embedded definitions only (empty default store) and
    # checks each recorded RIHS01 hash against the hash of those definitions.
    with AnyReader([directory]) as reader:
        decoded = [(c.topic, reader.deserialize(data, c.msgtype))
                   for c, _, data in reader.messages()]
    for (topic, msg), (_, _, _, original, _) in zip(decoded, messages):
        _assert_same(original, msg, topic)
    assert len(decoded) == len(messages)


def test_mcap_ros2_reader_decodes_every_message_back_exactly(bag):
    directory, messages = bag
    read = list(read_bag(directory))
    assert [(m.topic, m.type_name, m.log_time_ns) for m in read] == [
        (topic, type_name, t) for topic, type_name, t, _, _ in messages]
    for item, (_, _, _, original, _) in zip(read, messages):
        _assert_same(original, item.message, item.topic)
    # Same through the single .mcap file, and with a topic filter.
    only = list(read_bag(directory / f'{directory.name}_0.mcap', topics=['/array']))
    assert len(only) == COUNTS['/array']
    assert [m.message.data[0] for m in only] == [float(k) for k in range(COUNTS['/array'])]

    summary = bag_summary(directory)
    assert summary['finished']
    assert summary['message_count'] == len(messages)
    assert {t: v['message_count'] for t, v in summary['topics'].items()} == COUNTS
    assert summary['topics']['/imu/data']['type'] == 'sensor_msgs/msg/Imu'
    assert summary['duration_ns'] == summary['end_ns'] - summary['start_ns'] > 0


def test_reader_decodes_fast_cdr_padding_of_an_empty_trailing_sequence(tmp_path):
    # rclpy (Fast CDR) aligns an empty float64[] to 8 bytes, leaving 4 padding bytes at the
    # end of a JointState without efforts; rosbags 0.11 rejects such messages ("CDR message
    # size mismatch", it allows 3), the mcap-ros2 reader used by the reports must not.
    msg = JointState(name=['left_wheel_joint'], position=[1.0], velocity=[2.0], effort=[])
    with Rosbag2McapWriter(tmp_path / 'js') as bag:
        bag.add_topic('/joint_states', 'sensor_msgs/msg/JointState')
        bag.write('/joint_states', serialize_message(msg), START_NS)
    (item,) = read_bag(tmp_path / 'js')
    _assert_same(msg, item.message)


def test_message_definition_is_rosbag2s_full_text():
    text = message_definition('sensor_msgs/msg/Imu').text
    blocks = text.split('\n' + '=' * 80 + '\n')
    # The type's own .msg file first, verbatim, then each dependency once, depth first with
    # the dependencies of a type in sorted order (std::set in rosbag2).
    from wip_bag.message_definitions import interface_file
    assert blocks[0] == interface_file('sensor_msgs/msg/Imu', '.msg').read_text()
    assert [b.split('\n', 1)[0] for b in blocks[1:]] == [
        'MSG: geometry_msgs/Quaternion', 'MSG: geometry_msgs/Vector3', 'MSG: std_msgs/Header',
        'MSG: builtin_interfaces/Time']


@pytest.mark.parametrize('type_name', [
    'sensor_msgs/msg/Imu', 'diagnostic_msgs/msg/DiagnosticArray', 'std_msgs/msg/String',
    'rosgraph_msgs/msg/Clock', 'sensor_msgs/msg/NavSatFix'])
def test_type_hash_is_the_rihs01_of_the_definition(type_name):
    # rosbags computes REP 2011 hashes from the parsed definition: an independent check of
    # both the definition text and the hash read from the installed .json file.
    typestore = get_typestore(Stores.EMPTY)
    typestore.register(get_types_from_msg(message_definition(type_name).text, type_name))
    assert type_description_hash(type_name) == typestore.hash_rihs01(type_name)


def test_wip_msgs_definitions_decode_when_built(tmp_path):
    # The project's own types (built by colcon) go through the same path.
    try:
        definition = message_definition('wip_msgs/msg/StateEstimate')
    except LookupError:
        pytest.skip('wip_msgs is not built (scripts/setup builds it)')
    typestore = get_typestore(Stores.EMPTY)
    typestore.register(get_types_from_msg(definition.text, 'wip_msgs/msg/StateEstimate'))
    assert typestore.hash_rihs01('wip_msgs/msg/StateEstimate') == type_description_hash(
        'wip_msgs/msg/StateEstimate')


def test_refuses_to_overwrite_a_non_empty_directory(tmp_path):
    (tmp_path / 'old').mkdir()
    (tmp_path / 'old' / 'notes.txt').write_text('keep me')
    with pytest.raises(BagExistsError, match='refusing to overwrite'):
        Rosbag2McapWriter(tmp_path / 'old')
    assert (tmp_path / 'old' / 'notes.txt').read_text() == 'keep me'
    # An existing empty directory is fine.
    (tmp_path / 'empty').mkdir()
    Rosbag2McapWriter(tmp_path / 'empty', compression='none').close()


def test_bad_arguments_fail_clearly(tmp_path):
    with pytest.raises(ValueError, match='compression'):
        Rosbag2McapWriter(tmp_path / 'a', compression='bz2')
    with Rosbag2McapWriter(tmp_path / 'b') as bag:
        with pytest.raises(ValueError, match='absolute'):
            bag.add_topic('imu', 'sensor_msgs/msg/Imu')
        with pytest.raises(LookupError, match='no_such_pkg'):
            bag.add_topic('/x', 'no_such_pkg/msg/Thing')
        with pytest.raises(Exception, match='unknown topic'):
            bag.write('/y', b'', 0)


def test_empty_bag_is_valid(tmp_path):
    with Rosbag2McapWriter(tmp_path / 'empty_bag') as bag:
        bag.add_topic('/chatter', 'std_msgs/msg/String')
    with Reader(tmp_path / 'empty_bag') as reader:
        assert reader.message_count == 0
        assert [c.topic for c in reader.connections] == ['/chatter']
    assert bag_summary(tmp_path / 'empty_bag')['message_count'] == 0


def test_repair_bag_keeps_everything_flushed_before_a_crash(tmp_path):
    directory = tmp_path / 'crashed'
    bag = Rosbag2McapWriter(directory, compression='zstd', chunk_size=1 << 20)
    bag.add_topic('/chatter', 'std_msgs/msg/String', qos_profiles=[RELIABLE])
    # Strings need no alignment padding, so their serialization is deterministic.
    for k in range(50):
        bag.write('/chatter', serialize_message(String(data=str(k))), START_NS + k)
    bag.flush()
    for k in range(50, 60):  # Never flushed: lost in the crash.
        bag.write('/chatter', serialize_message(String(data=str(k))), START_NS + k)
    bag._stream.close()  # The process dies: no finish(), no metadata.yaml.
    assert not (directory / 'metadata.yaml').exists()
    assert not bag_summary(directory)['finished']
    assert [m.message.data for m in read_bag(directory, allow_partial=True)] == [
        str(k) for k in range(50)]

    information = repair_bag(directory).metadata
    assert information['message_count'] == 50
    with Reader(directory.with_name('crashed_repaired')) as reader:
        assert [bytes(d) for _, _, d in reader.messages()] == [
            bytes(serialize_message(String(data=str(k)))) for k in range(50)]
        assert reader.connections[0].ext.offered_qos_profiles[0].reliability == (
            QosReliability.RELIABLE)


def test_qos_profiles_are_written_by_name_with_infinite_durations():
    from rclpy.duration import Infinite
    profile = QoSProfile(depth=7, reliability=QoSReliabilityPolicy.BEST_EFFORT,
                         deadline=Infinite)
    entry = qos_profile_to_dict(profile)
    assert entry == {
        'history': 'keep_last', 'depth': 7, 'reliability': 'best_effort',
        'durability': 'volatile',
        'deadline': {'sec': 9223372036, 'nsec': 854775807},  # RMW_DURATION_INFINITE
        'lifespan': {'sec': 0, 'nsec': 0}, 'liveliness': 'system_default',
        'liveliness_lease_duration': {'sec': 0, 'nsec': 0},
        'avoid_ros_namespace_conventions': False}
    assert yaml.safe_load(dump_offered_qos([profile])) == [entry]
    assert dump_offered_qos([]) == '[]'
    with pytest.raises(ValueError, match='unknown QoS keys'):
        qos_profile_to_dict({'relyability': 'reliable'})
