"""The recorder node, run as its own process, records what is published, losslessly.

Each test starts ``python -m wip_bag.recorder_node`` in a DDS domain of its own (random id,
localhost discovery only), talks to it from a node of the test process in a private rclpy
context, and stops it with a signal, as a user would. Waits poll the graph or the
recorder's /diagnostics with timeouts; no fixed sleeps (discovery takes 0.1 s to 3 s).
"""

import os
import signal
import time

import pytest
from rclpy.qos import QoSProfile
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header, String

from bagtools_helpers import DISCOVERY_TIMEOUT, start_recorder
from ros_harness import communicate
from wip_bag.bag_reader import read_bag

pytestmark = pytest.mark.ros

N_MESSAGES = 200
PUBLISH_PERIOD = 0.002  # [s]: 500 Hz, above every rate of the project's graph

try:
    from wip_msgs.msg import StateEstimate
except ImportError:  # Workspace not built or not sourced (scripts/test does both).
    StateEstimate = None


def _publish_all(recorder, publisher, messages, clock_publisher=None, clock_start_ns=0):
    """Publish after the recorder's subscription matched, at a known period."""
    recorder.spin_until(lambda: publisher.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        f'the recorder to subscribe to {publisher.topic_name}')
    next_time = time.monotonic()
    for k, msg in enumerate(messages):
        if clock_publisher is not None:
            clock_publisher.publish(Clock(clock=_time_msg(clock_start_ns + k * 5_000_000)))
        publisher.publish(msg)
        next_time += PUBLISH_PERIOD
        time.sleep(max(0.0, next_time - time.monotonic()))


def _time_msg(ns):
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def test_records_every_message_in_order_and_closes_on_sigint(test_node, tools, tmp_path):
    bag = tmp_path / 'run'
    topic = f'/test_{os.getpid()}/chatter'
    topics = [topic]
    if StateEstimate is not None:
        topics.append(f'/test_{os.getpid()}/state_estimate')
    recorder = start_recorder(test_node, bag, topics)
    tools.append(recorder)
    reliable = QoSProfile(depth=N_MESSAGES)
    chatter = test_node.create_publisher(String, topic, reliable)
    _publish_all(recorder, chatter, [String(data=f'message {k}') for k in range(N_MESSAGES)])
    if StateEstimate is not None:
        estimates = test_node.create_publisher(StateEstimate, topics[1], reliable)
        _publish_all(recorder, estimates, [
            StateEstimate(header=Header(frame_id='map'), theta=0.001 * k, x=float(k),
                          settled=k % 2 == 0) for k in range(20)])
    expected = {topic: N_MESSAGES}
    if StateEstimate is not None:
        expected[topics[1]] = 20
    # The recorder tells on /diagnostics when it has received everything.
    recorder.spin_until(lambda: recorder.counts == expected, 10.0,
                        f'the recorder to report {expected} (last {recorder.counts})')
    output = recorder.stop(signal.SIGINT)
    assert 'closed' in output

    messages = list(read_bag(bag, topics=[topic]))
    assert [m.message.data for m in messages] == [f'message {k}' for k in range(N_MESSAGES)]
    times = [m.log_time_ns for m in messages]
    assert times == sorted(times)
    # Receive times on the system clock, spread like the publication (>= (N-1) periods).
    assert abs(times[0] * 1e-9 - time.time()) < 60.0
    assert (times[-1] - times[0]) * 1e-9 >= (N_MESSAGES - 1) * PUBLISH_PERIOD * 0.9

    # An independent rosbag2 reader opens the directory and decodes both types from the
    # embedded definitions (checking their RIHS01 hashes against the recorded ones).
    with Reader(bag) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == expected
    with AnyReader([bag]) as reader:
        decoded = {}
        for connection, _, data in reader.messages():
            decoded.setdefault(connection.topic, []).append(
                reader.deserialize(data, connection.msgtype))
    assert [m.data for m in decoded[topic]] == [f'message {k}' for k in range(N_MESSAGES)]
    if StateEstimate is not None:
        assert [(m.x, m.settled) for m in decoded[topics[1]]] == [
            (float(k), k % 2 == 0) for k in range(20)]


def test_records_topics_appearing_later_in_sim_time_and_closes_on_sigterm(
        test_node, tools, tmp_path):
    bag = tmp_path / 'all'
    prefix = f'/test_{os.getpid()}'
    recorder = start_recorder(test_node, bag, None, 'use_sim_time:=true',
                              f'exclude:=[{prefix}/excluded]', 'compression:=lz4')
    tools.append(recorder)
    # The recorder is up (its diagnostics arrive) before the topics exist.
    recorder.spin_until(lambda: recorder.reports > 0, DISCOVERY_TIMEOUT,
                        'the recorder diagnostics')
    clock = test_node.create_publisher(Clock, '/clock', 10)
    recorder.spin_until(lambda: clock.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        'the recorder to subscribe to /clock')
    start_ns = 1000 * 10**9  # simulation time [ns]
    clock.publish(Clock(clock=_time_msg(start_ns)))
    late = test_node.create_publisher(String, f'{prefix}/late', QoSProfile(depth=100))
    excluded = test_node.create_publisher(String, f'{prefix}/excluded', 10)
    _publish_all(recorder, late, [String(data=str(k)) for k in range(50)],
                 clock_publisher=clock, clock_start_ns=start_ns)
    excluded.publish(String(data='never recorded'))
    recorder.spin_until(lambda: recorder.counts.get(f'{prefix}/late') == 50, 10.0,
                        'the recorder to receive the 50 messages')
    recorder.stop(signal.SIGTERM)

    messages = list(read_bag(bag))
    topics = {m.topic for m in messages}
    assert f'{prefix}/late' in topics
    assert f'{prefix}/excluded' not in topics
    late_messages = [m for m in messages if m.topic == f'{prefix}/late']
    assert [m.message.data for m in late_messages] == [str(k) for k in range(50)]
    # Stamped with simulation time: within the published clock range (the clock message
    # of step k precedes message k; allow the message to be received a few steps late).
    for m in late_messages:
        assert start_ns <= m.log_time_ns <= start_ns + 50 * 5_000_000
    with Reader(bag) as reader:
        assert f'{prefix}/late' in {c.topic for c in reader.connections}


def test_refuses_to_overwrite_an_existing_bag(test_node, tools, tmp_path):
    bag = tmp_path / 'existing'
    bag.mkdir()
    (bag / 'metadata.yaml').write_text('precious')
    recorder = start_recorder(test_node, bag)
    tools.append(recorder)
    output, _ = communicate(recorder.process, 30.0)
    assert recorder.process.returncode == 2     # an output error: the table's 2
    assert 'refusing to overwrite' in output
    assert (bag / 'metadata.yaml').read_text() == 'precious'
