"""The replayer plays bags back as recorded: same bytes, same order, recorded timing.

The replayer and the recorders run as their own processes (see bagtools_helpers); the test
process publishes, subscribes and, for /clock, runs a node with ``use_sim_time``.
"""

import os
import signal
import statistics
import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, QoSReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import Imu
from std_msgs.msg import String
from std_srvs.srv import SetBool

from bagtools_helpers import DISCOVERY_TIMEOUT, spin_until, start_recorder, Tool
from wip_bag.bag_reader import iter_raw_messages
from wip_bag.bag_writer import Rosbag2McapWriter

pytestmark = pytest.mark.ros

SPACING = 0.02  # [s] between recorded messages (50 Hz)
CHATTER = f'/rb_{os.getpid()}/chatter'
IMU = f'/rb_{os.getpid()}/imu'
RENAMED = f'/rb_{os.getpid()}/renamed'
DATA = f'/clocked_{os.getpid()}/data'


def _replayer(node, bag, *options):
    return Tool(node, 'replayer_node', [str(bag), *options], '/replayer')


@pytest.mark.wallclock   # judges the replay's pace on the wall clock
def test_record_replay_record_gives_identical_bytes_in_order_with_recorded_timing(
        test_node, tools, tmp_path):
    prefix = f'/rrr_{os.getpid()}'
    chatter, imu_topic = f'{prefix}/chatter', f'{prefix}/imu'
    topics = [chatter, imu_topic]
    # 1. Record what the test publishes: two topics of two types, alternating, 50 Hz each.
    first = tmp_path / 'first'
    n = 60
    _record_published(test_node, tools, first, chatter, imu_topic, n)

    # 2. Replay it into a second recorder. The replayer waits until its publishers have
    # matched the recorder's subscriptions, but DDS matches each side on its own: seen once
    # in a fresh-clone run, the recorder's side matched later and the first ~16 messages
    # (0.33 s) arrived late in a bunch (presumably dropped by the not yet matched reader and
    # sent again by the reliable protocol). --delay, as
    # rosbag2's `ros2 bag play --delay`, leaves discovery time to finish before the timing
    # that is tested here starts.
    second = tmp_path / 'second'
    recorder2 = start_recorder(test_node, second, topics)
    tools.append(recorder2)
    replayer = _replayer(test_node, first, '--wait-for-subscribers', '1',
                         '--wait-timeout', '20', '--delay', '1.0')
    tools.append(replayer)
    replayer.wait(40.0)
    recorder2.spin_until(lambda: recorder2.counts == {chatter: n, imu_topic: n}, 10.0,
                         'the second recording')
    recorder2.stop()

    original = list(iter_raw_messages(first, topics=topics))
    replayed = list(iter_raw_messages(second, topics=topics))
    # Byte-identical messages on each topic, in the same order (raw bytes republished).
    for topic in topics:
        assert [m.data for m in replayed if m.topic == topic] == [
            m.data for m in original if m.topic == topic]
    _assert_recorded_timing(original, replayed, chatter)


def _record_published(test_node, tools, path, chatter, imu_topic, n):
    """Record ``n`` String and Imu messages the test publishes, alternating, 50 Hz each."""
    recorder = start_recorder(test_node, path, [chatter, imu_topic])
    tools.append(recorder)
    reliable = QoSProfile(depth=100)
    chatter_pub = test_node.create_publisher(String, chatter, reliable)
    imu_pub = test_node.create_publisher(Imu, imu_topic, reliable)
    recorder.spin_until(lambda: chatter_pub.get_subscription_count() >= 1
                        and imu_pub.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        'the first recorder to subscribe')
    next_time = time.monotonic()
    for k in range(n):
        chatter_pub.publish(String(data=f'message {k} ' + 'é' * (k % 7)))
        imu = Imu()
        imu.header.stamp.sec, imu.header.frame_id = k, 'imu_link'
        imu.angular_velocity.y = 0.01 * k
        imu.orientation.w = 1.0
        imu_pub.publish(imu)
        next_time += SPACING
        test_node.executor_for_test.spin_once(
            timeout_sec=max(0.0, next_time - time.monotonic()))
    recorder.spin_until(lambda: recorder.counts == {chatter: n, imu_topic: n}, 10.0,
                        'the first recording')
    recorder.stop()


def _assert_recorded_timing(original, replayed, topic):
    """Assert that the replayed receive times of ``topic`` follow the recorded ones."""
    # Timing: the replayed receive times against the recorded ones, up to a constant shift
    # (the start of the replay), as a fraction of the recorded spacing: error_i =
    # ((t2_i - t1_i) - median(t2 - t1)) / spacing. The median, not the first message, is the
    # reference, because the first message of a new publisher is ~3 ms slower (0.16
    # spacing, measured). The errors are the sums of scheduling and DDS latencies of the
    # two recordings and the replay (0.1..1 ms each on this host) against 20 ms: measured
    # median 0.003, 90th percentile < 0.02 spacing. Bounds: the median within 0.05 and the
    # 90th percentile within 0.25 spacing (a replayer off its schedule, at the wrong rate
    # or bunching, moves most messages out of their slots and fails both). Not the
    # maximum: on this shared 2-core host a process of the replay path is now and then
    # descheduled (seen: 330 ms, one message late; in a fresh-clone run ~80 ms, four
    # consecutive messages late by 0.3 to 1.3 spacings), which no replayer can prevent;
    # the percentile tolerates 6 of 60 such hits.
    #
    # On a machine 3x slower, or with other processes taking the cores, the two recorders
    # and the replayer are descheduled for tens of ms at a time (measured with 4 other
    # jobs on 2 cores: median error 0.23 spacing, growing along the run), so the check is
    # robust statistics of the time map t1 -> t2: its rate (Theil-Sen slope: the median
    # of the pairwise slopes, unaffected by up to 29 % of late messages) must be 1 within
    # 20 % (a replay at twice the rate gives 0.5, one that bunches gives about 0), and the
    # median error about the median shift within half a spacing (a replayer off its
    # schedule moves most messages out of their slots). The quiet-machine figures are
    # printed (measured: median 0.003, 90th percentile < 0.02 spacing).
    t1 = [m.log_time_ns for m in original if m.topic == topic]
    t2 = [m.log_time_ns for m in replayed if m.topic == topic]
    slope = statistics.median(
        (t2[j] - t2[i]) / (t1[j] - t1[i]) for i in range(len(t1))
        for j in range(i + 1, len(t1)) if t1[j] - t1[i] >= 5 * SPACING * 1e9)
    shift = statistics.median(b - a for a, b in zip(t1, t2))
    errors = sorted(abs(b - a - shift) / 1e9 / SPACING for a, b in zip(t1, t2))
    p90 = errors[int(0.90 * (len(errors) - 1))]
    print(f'replay timing: rate {slope:.4f}; error / spacing: median '
          f'{statistics.median(errors):.4f}, 90th percentile {p90:.4f}, max {errors[-1]:.4f}')
    assert 0.8 < slope < 1.2, slope
    assert statistics.median(errors) < 0.5, errors[-8:]


def _clock_bag(path, start_ns, n, period_ns):
    with Rosbag2McapWriter(path) as bag:
        bag.add_topic(DATA, 'std_msgs/msg/String', qos_profiles=[QoSProfile(depth=10)])
        for k in range(n):
            bag.write(DATA, serialize_message(String(data=str(k))), start_ns + k * period_ns)


def _assert_timer_fired_at_recorded_times(test_node, fired, start_ns, period_ns,
                                          timer_period):
    """Assert that a sim-time timer fired at each period of the bag played at rate 1."""
    # Timers on simulation time fire at the recorded times: at each multiple of
    # 0.1 s in (1000, 1001], seen by now() within 2 recorded spacings (the clock
    # advances in steps of one spacing, the message times; one more clock message
    # may be handled before the timer's callback runs). The timer also fires once
    # when the clock jumps from 0 to 1000 s (its missed periods collapse into one
    # call at about 1000.00 s): that call is not one of the periods of the bag.
    def times():
        return [t.nanoseconds for t in fired if t.nanoseconds > start_ns + 5 * period_ns]

    expected = [start_ns + round(j * timer_period * 1e9) for j in range(1, 11)]
    # The last call (at 1001 s, the last message's time) may still be pending.
    spin_until(test_node, lambda: len(times()) >= len(expected), 5.0,
               'the timer call at the end of the bag')
    times = times()
    assert len(times) == len(expected), [(t - start_ns) / 1e9 for t in times]
    for got, want in zip(times, expected):
        assert 0 <= got - want <= 2 * period_ns, (got, want)


@pytest.mark.wallclock   # judges the replay's pace on the wall clock
def test_clock_drives_sim_time_timers_and_rate_two_halves_the_wall_time(
        test_node, tools, tmp_path):
    bag = tmp_path / 'timed'
    start_ns, n, period_ns = 1000 * 10**9, 101, 10_000_000  # 1000 s .. 1001 s at 100 Hz
    _clock_bag(bag, start_ns, n, period_ns)
    arrivals = []   # (the replayer's send time [s], data)
    test_node.create_subscription(
        String, DATA, lambda m, info: arrivals.append((info['source_timestamp'] * 1e-9, m.data)),
        QoSProfile(depth=200))
    # A node on simulation time with a timer of 0.1 s.
    sim_node = rclpy.create_node('sim_time_node', context=test_node.context,
                                 parameter_overrides=[Parameter('use_sim_time', value=True)])
    test_node.executor_for_test.add_node(sim_node)
    timer_period = 0.1
    fired = []
    sim_node.create_timer(timer_period, lambda: fired.append(sim_node.get_clock().now()))

    spans = {}
    for rate in (1.0, 2.0):
        arrivals.clear()
        fired.clear()
        # --delay: the replayer's wait sees only its writers' matches; the readers' side
        # may match later and get the first messages late in a bunch (see the test above).
        replayer = _replayer(test_node, bag, '--clock', '--clock-rate', '100', '--rate',
                             str(rate), '--wait-for-subscribers', '1', '--wait-topics',
                             DATA, '/clock', '--delay', '1.0')
        tools.append(replayer)
        spin_until(test_node, lambda: len(arrivals) == n, 20.0,
                   f'the messages at rate {rate}', replayer.process)
        replayer.wait(10.0)
        assert [d for _, d in arrivals] == [str(k) for k in range(n)]
        # The playback's pace: the median of the pairwise slopes of send time against
        # message index (Theil-Sen; a few descheduled sends do not move it) times the span.
        sent = [t for t, _ in arrivals]
        spans[rate] = (n - 1) * statistics.median(
            (sent[j] - sent[i]) / (j - i) for i in range(n) for j in range(i + 10, n, 7))
        if rate == 1.0:
            _assert_timer_fired_at_recorded_times(test_node, fired, start_ns, period_ns,
                                                  timer_period)
    # Rate 2 halves the wall time of the playback. The spans (1 s and 0.5 s) are taken
    # from the replayer's send stamps, robustly: measured at this subscriber they moved
    # by the test process's own scheduling (a ratio of 0.553 with a busy core); 5 % of
    # the ratio is still far from what a wrong rate gives (1.0 or 0.25).
    ratio = spans[2.0] / spans[1.0]
    print(f'wall time ratio rate 2 / rate 1: {ratio:.4f}')
    assert ratio == pytest.approx(0.5, abs=0.025)
    sim_node.destroy_node()


def _rosbags_bag(path):
    """Return a bag written by rosbags (independent writer): MCAP storage, zstd chunks."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    string_type = typestore.types['std_msgs/msg/String']
    imu_type = typestore.types['sensor_msgs/msg/Imu']
    header_type = typestore.types['std_msgs/msg/Header']
    time_type = typestore.types['builtin_interfaces/msg/Time']
    quaternion = typestore.types['geometry_msgs/msg/Quaternion']
    vector = typestore.types['geometry_msgs/msg/Vector3']
    zero = QosTime(0, 0)
    best_effort = Qos(QosHistory.KEEP_LAST, 5, QosReliability.BEST_EFFORT,
                      QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)
    reliable = best_effort._replace(reliability=QosReliability.RELIABLE)
    written = []
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        chatter = writer.add_connection(CHATTER, 'std_msgs/msg/String', typestore=typestore,
                                        offered_qos_profiles=[reliable])
        imu = writer.add_connection(IMU, 'sensor_msgs/msg/Imu', typestore=typestore,
                                    offered_qos_profiles=[best_effort])
        for k in range(30):
            t = 5 * 10**9 + k * 20_000_000
            data = typestore.serialize_cdr(string_type(data=f'rosbags {k}'),
                                           'std_msgs/msg/String')
            writer.write(chatter, t, data)
            written.append((CHATTER, bytes(data)))
            msg = imu_type(
                header=header_type(stamp=time_type(sec=k, nanosec=7), frame_id='imu'),
                orientation=quaternion(x=0.0, y=0.1, z=0.0, w=0.995),
                orientation_covariance=np.zeros(9),
                angular_velocity=vector(x=0.0, y=float(k), z=0.0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vector(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9))
            data = typestore.serialize_cdr(msg, 'sensor_msgs/msg/Imu')
            writer.write(imu, t + 10_000_000, data)
            written.append((IMU, bytes(data)))
    return written


def _padded_to_words(data):
    """Return ``data`` with zero bytes appended up to a whole number of 4-byte words."""
    return data + b'\x00' * (-len(data) % 4)


def test_replays_a_bag_written_by_rosbags_with_pause_remap_and_recorded_qos(
        test_node, tools, tmp_path):
    bag = tmp_path / 'from_rosbags'
    written = _rosbags_bag(bag)
    received = []
    # (source timestamp, topic, bytes): the publication order is checked with the
    # replayer's own send times, not the order in which this (possibly descheduled)
    # process happens to take two messages that are both waiting.
    test_node.create_subscription(String, RENAMED, lambda d, info: received.append(
        (info['source_timestamp'], CHATTER, bytes(d))), QoSProfile(depth=100), raw=True)
    test_node.create_subscription(Imu, IMU, lambda d, info: received.append(
        (info['source_timestamp'], IMU, bytes(d))),
        QoSProfile(depth=100, reliability=QoSReliabilityPolicy.BEST_EFFORT), raw=True)
    # The single .mcap file (rosbags names it <name>.mcap), started paused.
    replayer = _replayer(test_node, bag / 'from_rosbags.mcap', '--start-paused',
                         '--remap', f'{CHATTER}:={RENAMED}', '--stay')
    tools.append(replayer)
    spin_until(test_node, lambda: len(test_node.get_publishers_info_by_topic(IMU)) == 1
               and len(test_node.get_publishers_info_by_topic(RENAMED)) == 1,
               DISCOVERY_TIMEOUT, 'the replayer publishers', replayer.process)
    # The recorded QoS: the IMU was recorded best effort, the chatter reliable.
    (imu_info,) = test_node.get_publishers_info_by_topic(IMU)
    (chatter_info,) = test_node.get_publishers_info_by_topic(RENAMED)
    assert imu_info.qos_profile.reliability == QoSReliabilityPolicy.BEST_EFFORT
    assert chatter_info.qos_profile.reliability == QoSReliabilityPolicy.RELIABLE
    assert test_node.get_publishers_info_by_topic(CHATTER) == []
    # Paused: nothing comes until ~/pause is called with false.
    client = test_node.create_client(SetBool, '/replayer/pause')
    spin_until(test_node, client.service_is_ready, DISCOVERY_TIMEOUT, 'the pause service',
               replayer.process)
    deadline = time.monotonic() + 0.5
    while time.monotonic() < deadline:
        test_node.executor_for_test.spin_once(timeout_sec=0.01)
    assert received == []
    future = client.call_async(SetBool.Request(data=False))
    spin_until(test_node, future.done, 10.0, 'the pause service answer', replayer.process)
    assert future.result().success and 'playing' in future.result().message
    spin_until(test_node, lambda: len(received) == len(written), 10.0, 'every message',
               replayer.process)
    # The bytes rosbags wrote, sent in the recorded order (per topic; across topics too
    # since they are 10 ms apart: ordered by the replayer's send stamps). Fast DDS sends a
    # serialized payload as a whole number of 4-byte words: a message whose CDR is not
    # (rosbags does not pad, rclpy does) arrives with up to 3 zero bytes appended, which CDR
    # readers ignore.
    for topic in (CHATTER, IMU):        # per topic: the order of arrival itself
        assert [d for _, t, d in received if t == topic] == [
            _padded_to_words(d) for t, d in written if t == topic]
    received.sort(key=lambda item: item[0])
    assert [t for _, t, _ in received] == [t for t, _ in written]
    assert [d for _, _, d in received] == [_padded_to_words(d) for _, d in written]
    assert any(len(d) % 4 for _, d in written)  # the padding case is exercised
    msg = deserialize_message(received[1][2], Imu)
    assert (msg.header.frame_id, msg.angular_velocity.y) == ('imu', 0.0)
    # Paused again (the replayer stays up at the end: --stay), then SIGTERM: a clean exit.
    future = client.call_async(SetBool.Request(data=True))
    spin_until(test_node, future.done, 10.0, 'the pause service answer', replayer.process)
    assert 'paused' in future.result().message
    replayer.stop(signal.SIGTERM, expected_code=0, timeout=5.0)


def test_start_offset_duration_loop_and_topic_selection(test_node, tools, tmp_path):
    bag = tmp_path / 'window'
    other = f'{DATA}_other'
    with Rosbag2McapWriter(bag) as writer:
        writer.add_topic(DATA, 'std_msgs/msg/String')
        writer.add_topic(other, 'std_msgs/msg/String')
        for k in range(100):  # 10 ms apart, 2000 s + 0 .. 0.99 s
            writer.write(DATA, serialize_message(String(data=str(k))),
                         2000 * 10**9 + k * 10_000_000)
            writer.write(other, serialize_message(String(data='no')),
                         2000 * 10**9 + k * 10_000_000 + 1)
    received, unwanted = [], []
    test_node.create_subscription(String, DATA, lambda m: received.append(int(m.data)),
                                  QoSProfile(depth=100))
    test_node.create_subscription(String, other, lambda m: unwanted.append(m.data),
                                  QoSProfile(depth=100))
    # From 0.2 s for 0.3 s: the messages logged in [+0.2 s, +0.5 s], k = 20 .. 50, looped.
    replayer = _replayer(test_node, bag, '--start-offset', '0.2', '--duration', '0.3',
                         '--loop', '--topics', DATA, '--wait-for-subscribers', '1')
    tools.append(replayer)
    window = list(range(20, 51))
    spin_until(test_node, lambda: len(received) >= 2 * len(window) + 5, 20.0,
               'two loops', replayer.process)
    replayer.stop(signal.SIGINT)
    assert received[:2 * len(window)] == window * 2
    assert unwanted == []


def test_command_line_and_qos_rules():
    from rclpy.qos import QoSDurabilityPolicy
    from wip_bag.playback import playback_qos
    from wip_bag.replayer_node import parse_command_line
    overrides, ros_args = parse_command_line([
        'bag_dir', '--rate', '2', '--clock', '--topics', '/a', '/b', '--stay',
        '--ros-args', '-r', '/a:=/c'])
    values = {p.name: p.value for p in overrides}
    assert values == {'bag': 'bag_dir', 'rate': 2.0, 'clock': True, 'topics': ['/a', '/b'],
                      'exit_when_done': False}
    assert ros_args == ['--ros-args', '-r', '/a:=/c']
    latched = {'history': 'keep_last', 'depth': 1, 'reliability': 'reliable',
               'durability': 'transient_local'}
    volatile = dict(latched, durability='volatile')
    # One recorded profile (or several equal ones): offered again, history keep-last depth.
    qos = playback_qos([latched, dict(latched, depth=5)], depth=100)
    assert (qos.durability, qos.depth) == (QoSDurabilityPolicy.TRANSIENT_LOCAL, 100)
    # Mixed offers: rosbag2's default (reliable, volatile), as adapt_offer_to_recorded_offers.
    qos = playback_qos([latched, volatile], depth=10)
    assert (qos.reliability, qos.durability) == (QoSReliabilityPolicy.RELIABLE,
                                                 QoSDurabilityPolicy.VOLATILE)
    assert playback_qos('', depth=10).reliability == QoSReliabilityPolicy.RELIABLE


def test_a_replayer_under_a_namespace_plays_the_bag_into_it(test_node, tools, tmp_path):
    # A vehicle's bag (the recorder stores it without the vehicle's namespace) played to
    # one vehicle of several: its topics under the replayer's namespace.
    bag = tmp_path / 'vehicle'
    topic = f'/nsplay_{os.getpid()}/data'
    with Rosbag2McapWriter(bag) as writer:
        writer.add_topic(topic, 'std_msgs/msg/String')
        for k in range(20):
            writer.write(topic, serialize_message(String(data=str(k))),
                         2000 * 10**9 + k * 10_000_000)
    received, unwanted = [], []
    test_node.create_subscription(String, f'/robot7{topic}',
                                  lambda m: received.append(int(m.data)), QoSProfile(depth=100))
    test_node.create_subscription(String, topic, lambda m: unwanted.append(m.data),
                                  QoSProfile(depth=100))
    replayer = Tool(test_node, 'replayer_node',
                    [str(bag), '--wait-for-subscribers', '1', '--ros-args', '-r',
                     '__ns:=/robot7'], '/robot7/replayer')
    tools.append(replayer)
    spin_until(test_node, lambda: len(received) >= 20, 20.0, 'the played messages',
               None)
    assert received == list(range(20)) and unwanted == []
