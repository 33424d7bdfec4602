"""Intra-process delivery of the composed controllers (wip_runtime.intra_process).

The bus is checked without ROS (fake publishers: which path a message takes, the order,
errors), then with rclpy: two controller nodes of one context connected as the composed
process connects them, and a subscriber outside the bus that appears later. Reliable
QoS throughout; every wait on DDS has a deadline of 60 s (a slow, shared machine) and
none depends on a best-effort sample.
"""

import time

import pytest

from wip_runtime import intra_process
from wip_runtime.intra_process import IntraProcessBus, IntraProcessPublisher, local_match_count


class FakeDdsPublisher:
    """What IntraProcessPublisher needs of an rclpy publisher."""

    def __init__(self, topic='/wip/t', matched=0):
        self.topic_name = topic
        self.matched = matched
        self.sent = []
        self.queries = 0

    def get_subscription_count(self):
        self.queries += 1
        return self.matched

    def match(self, wrapper, count):
        """DDS matches ``count`` subscriptions now, and the executor delivers the event."""
        self.matched = count
        wrapper.on_matched(type('Matched', (), {'current_count': count})())

    def publish(self, msg):
        self.sent.append(msg)


class Msg:
    def __init__(self, value):
        self.value = value


def test_a_message_no_one_outside_wants_goes_to_the_local_subscriptions_alone_in_order():
    bus = IntraProcessBus()
    got = []
    bus.add_subscription('/wip/t', Msg, lambda m: got.append(('a', m.value)))
    bus.add_subscription('/wip/t', Msg, lambda m: got.append(('b', m.value)))
    bus.add_subscription('/wip/t', int, lambda m: got.append(('wrong type', m)))
    bus.add_subscription('/wip/other', Msg, lambda m: got.append(('other topic', m)))
    dds = FakeDdsPublisher(matched=2)        # the two local subscriptions, matched by DDS
    publisher = IntraProcessPublisher(dds, Msg)
    assert bus.attach(publisher) == 2 and publisher.local_subscriptions == 2
    publisher.publish(Msg(1))
    publisher.publish(Msg(2))
    assert got == [] and bus.pending == 2    # queued: nothing runs inside publish()
    assert bus.drain() == 2
    assert got == [('a', 1), ('b', 1), ('a', 2), ('b', 2)]
    assert dds.sent == [] and bus.delivered == 2 and bus.published_dds == 0


def test_with_a_subscriber_outside_every_message_goes_to_dds_once_and_not_locally():
    bus = IntraProcessBus()
    got = []
    bus.add_subscription('/wip/t', Msg, got.append)
    dds = FakeDdsPublisher(matched=2)        # one local, one outside (a recorder)
    publisher = IntraProcessPublisher(dds, Msg)
    bus.attach(publisher)
    message = Msg(1)
    publisher.publish(message)
    assert dds.sent == [message] and bus.pending == 0 and bus.published_dds == 1
    dds.match(publisher, 1)                  # the outside subscriber left
    publisher.publish(Msg(2))
    assert bus.drain() == 1 and [m.value for m in got] == [2] and len(dds.sent) == 1


def test_the_match_count_comes_from_the_matched_events_and_a_query_per_second_at_most(
        monkeypatch):
    # DDS's query costs about 2 us and a tick publishes about 6 messages: the count is
    # kept from the matched events, and asked again only once it is a second old (an
    # event missed: DDS matched before the node joined an executor).
    now = [50.0]
    monkeypatch.setattr(intra_process.time, 'monotonic', lambda: now[0])
    bus = IntraProcessBus()
    bus.add_subscription('/wip/t', Msg, lambda m: None)
    dds = FakeDdsPublisher(matched=1)
    publisher = IntraProcessPublisher(dds, Msg)
    bus.attach(publisher)
    for value in range(100):
        publisher.publish(Msg(value))
        now[0] += 0.005
    assert dds.queries == 1 and bus.drain() == 100   # 0.5 s: asked at the first publication
    dds.matched = 2                                   # matched, its event not yet taken
    publisher.publish(Msg(100))
    assert dds.sent == [] and bus.pending == 1
    now[0] += intra_process.MATCH_COUNT_MAX_AGE       # the safety net asks DDS again
    publisher.publish(Msg(101))
    assert [m.value for m in dds.sent] == [101] and dds.queries == 2
    dds.match(publisher, 1)                           # the event: at once, no query
    publisher.publish(Msg(102))
    assert len(dds.sent) == 1 and bus.pending == 2 and dds.queries == 2


def test_a_message_published_by_a_local_callback_is_queued_behind_the_others():
    bus = IntraProcessBus()
    order = []
    first = IntraProcessPublisher(FakeDdsPublisher('/wip/first', matched=1), Msg)
    second = IntraProcessPublisher(FakeDdsPublisher('/wip/second', matched=1), Msg)

    def relay(msg):                          # a node that publishes on what it receives
        order.append(('relay', msg.value))
        second.publish(Msg(msg.value * 10))
    bus.add_subscription('/wip/first', Msg, relay)
    bus.add_subscription('/wip/second', Msg, lambda m: order.append(('end', m.value)))
    bus.attach(first)
    bus.attach(second)
    first.publish(Msg(1))
    first.publish(Msg(2))
    assert bus.drain() == 4
    assert order == [('relay', 1), ('relay', 2), ('end', 10), ('end', 20)]


def test_an_unattached_publisher_is_plain_and_an_attached_one_skips_what_no_one_reads():
    alone = FakeDdsPublisher(matched=0)
    plain = IntraProcessPublisher(alone, Msg)
    assert plain.reaches_anyone()           # unattached: rclpy's, whatever it matches
    plain.publish(Msg(0))                   # a node alone: plain rclpy
    assert [m.value for m in alone.sent] == [0]
    bus = IntraProcessBus()
    dds = FakeDdsPublisher(matched=0)
    volatile = IntraProcessPublisher(dds, Msg)
    assert bus.attach(volatile) == 0        # no subscription of this process on the topic
    assert not volatile.reaches_anyone()    # so a node need not build the message
    volatile.publish(Msg(1))                # no subscriber: DDS would deliver to no one
    assert dds.sent == [] and bus.pending == 0
    dds.match(volatile, 1)
    assert volatile.reaches_anyone()
    volatile.publish(Msg(2))
    assert [m.value for m in dds.sent] == [2]
    latched = FakeDdsPublisher(matched=0)
    kept = IntraProcessPublisher(latched, Msg, skip_unmatched=False)
    bus.attach(kept)
    assert kept.reaches_anyone()
    kept.publish(Msg(3))
    assert [m.value for m in latched.sent] == [3]   # transient local: kept for late joiners
    assert volatile.topic_name == '/wip/t' and volatile.get_subscription_count() == 1


def test_a_failing_local_callback_is_reported_and_the_others_still_get_the_message():
    errors = []
    bus = IntraProcessBus(lambda kind, err: errors.append((kind, str(err))))
    got = []

    def broken(msg):
        raise RuntimeError('boom')
    bus.add_subscription('/wip/t', Msg, broken)
    bus.add_subscription('/wip/t', Msg, got.append)
    publisher = IntraProcessPublisher(FakeDdsPublisher(matched=2), Msg)
    bus.attach(publisher)
    publisher.publish(Msg(7))
    assert bus.drain() == 1
    assert [m.value for m in got] == [7] and errors == [('Msg', 'boom')] and bus.errors == 1


def test_where_dds_ignores_local_endpoints_local_ones_take_the_bus_and_outsiders_dds():
    # DDS then counts and serves the subscriptions of other processes only (a recorder):
    # every message goes to them through DDS and, always, to this process through the bus.
    bus = IntraProcessBus(dds_ignores_local=True)
    got = []
    bus.add_subscription('/wip/t', Msg, got.append)
    dds = FakeDdsPublisher(matched=0)        # no one outside
    publisher = IntraProcessPublisher(dds, Msg)
    assert bus.attach(publisher) == 1
    assert publisher.get_subscription_count() == 1   # DDS's 0 and the bus's 1
    publisher.publish(Msg(1))
    assert dds.sent == [] and bus.drain() == 1
    dds.match(publisher, 1)                  # a recorder subscribes
    publisher.publish(Msg(2))
    assert [m.value for m in dds.sent] == [2] and bus.drain() == 1
    assert [m.value for m in got] == [1, 2] and bus.published_dds == 1
    assert publisher.get_subscription_count() == 2
    # Nothing local, nothing outside: a volatile message goes nowhere, a transient local one
    # to DDS for a late joiner.
    lonely = FakeDdsPublisher('/wip/lonely', matched=0)
    volatile = IntraProcessPublisher(lonely, Msg)
    bus.attach(volatile)
    assert not volatile.reaches_anyone() and publisher.reaches_anyone()
    volatile.publish(Msg(3))
    latched = IntraProcessPublisher(lonely, Msg, skip_unmatched=False)
    bus.attach(latched)
    latched.publish(Msg(4))
    assert [m.value for m in lonely.sent] == [4] and bus.pending == 0


def test_the_local_match_counts_are_read_from_the_node():
    class Node:
        local_matches = {('subscriptions', '/wip/t'): 2, ('publishers', '/clock'): 1}
    assert local_match_count(Node(), 'subscriptions', '/wip/t') == 2
    assert local_match_count(Node(), 'publishers', '/clock') == 1
    assert local_match_count(Node(), 'publishers', '/wip/t') == 0
    assert local_match_count(object(), 'subscriptions', '/wip/t') == 0   # DDS counts them


# --------------------------------------------------------------------------- with rclpy

rclpy = pytest.importorskip('rclpy')
wip_msgs = pytest.importorskip('wip_msgs.msg')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from wip_control.nodes.common import ControllerNode  # noqa: E402
from wip_runtime.composition import connect_intra_process  # noqa: E402
from wip_runtime.qos import RELIABLE_QOS  # noqa: E402
from wip_runtime.stamps import make_header, stamp_to_ns  # noqa: E402

DEADLINE = 60.0   # [s] discovery and matching on a slow, shared machine
TOPIC = '/wip/velocity_command'


class Sender(ControllerNode):
    def __init__(self, **kwargs):
        super().__init__('ipc_sender', 'test sender', (), **kwargs)
        self.publisher = self.create_publisher(wip_msgs.VelocityCommand, TOPIC, RELIABLE_QOS)

    def send(self, stamp_ns):
        self.publisher.publish(wip_msgs.VelocityCommand(header=make_header(stamp_ns)))


class Receiver(ControllerNode):
    def __init__(self, **kwargs):
        super().__init__('ipc_receiver', 'test receiver', ('velocity_command',), **kwargs)
        self.stamps = []
        self.messages = []
        self.subscribe(wip_msgs.VelocityCommand, TOPIC, 'velocity_command', self._on)

    def _on(self, msg):
        self.messages.append(msg)
        self.stamps.append(stamp_to_ns(msg.header.stamp))


def _params(intra=True):
    return [Parameter('clock_mode', value='realtime'),
            Parameter('diagnostics_period', value=0.0),
            Parameter('use_intra_process_comms', value=intra)]


def _spin_until(executor, bus, condition, what):
    end = time.monotonic() + DEADLINE
    while not condition():
        assert time.monotonic() < end, f'not within {DEADLINE} s: {what}'
        executor.spin_once(timeout_sec=0.05)
        if bus is not None:
            bus.drain()


@pytest.mark.ros
def test_composed_nodes_exchange_messages_locally_until_someone_outside_subscribes(context):
    sender = Sender(context=context, parameter_overrides=_params())
    receiver = Receiver(context=context, parameter_overrides=_params())
    outside = rclpy.create_node('ipc_outside', context=context)
    executor = SingleThreadedExecutor(context=context)
    for node in (sender, receiver, outside):
        executor.add_node(node)
    try:
        bus = connect_intra_process([sender, receiver])
        assert bus is not None and sender.publisher.local_subscriptions == 1
        _spin_until(executor, bus, lambda: sender.publisher.get_subscription_count() >= 1,
                    'the local subscription matched by DDS')
        sent = wip_msgs.VelocityCommand(header=make_header(1))
        sender.publisher.publish(sent)
        assert bus.pending == 1 and receiver.stamps == []
        bus.drain()
        assert receiver.stamps == [1] and receiver.messages[0] is sent   # shared, not copied
        assert bus.published_dds == 0

        # Someone outside the process subscribes (a recorder, `ros2 topic echo`).
        seen = []
        outside.create_subscription(wip_msgs.VelocityCommand, TOPIC,
                                    lambda m: seen.append(stamp_to_ns(m.header.stamp)),
                                    RELIABLE_QOS)
        _spin_until(executor, bus, lambda: sender.publisher.get_subscription_count() >= 2,
                    'the outside subscription matched')
        sender.send(2)
        assert bus.pending == 0 and bus.published_dds == 1   # DDS, for everyone
        _spin_until(executor, bus, lambda: seen == [2] and receiver.stamps == [1, 2],
                    'the DDS message at the outside and the local subscription')
        # The same stamp and content outside; nothing delivered twice.
        sender.send(3)
        _spin_until(executor, bus, lambda: seen == [2, 3] and receiver.stamps == [1, 2, 3],
                    'the second DDS message')
        assert bus.delivered == 1 and receiver.diagnostics.dropped == {}
    finally:
        for node in (sender, receiver, outside):
            node.destroy_node()


@pytest.mark.ros
def test_use_intra_process_comms_false_keeps_every_message_on_dds(context):
    sender = Sender(context=context, parameter_overrides=_params(intra=False))
    receiver = Receiver(context=context, parameter_overrides=_params(intra=False))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(sender)
    executor.add_node(receiver)
    try:
        assert connect_intra_process([sender, receiver]) is None
        _spin_until(executor, None, lambda: sender.publisher.get_subscription_count() >= 1,
                    'the subscription matched')
        sender.send(5)
        _spin_until(executor, None, lambda: receiver.stamps == [5], 'the DDS message')
        assert receiver.messages[0] is not None
    finally:
        sender.destroy_node()
        receiver.destroy_node()


@pytest.mark.ros
def test_now_ns_is_the_node_clock_on_system_time_and_on_sim_time(context):
    node = Receiver(context=context, parameter_overrides=_params())
    try:
        before = node.get_clock().now().nanoseconds
        now = node.now_ns()
        after = node.get_clock().now().nanoseconds
        assert before <= now <= after          # the system clock, read directly
        node.set_parameters([Parameter('use_sim_time', value=True)])
        from rosgraph_msgs.msg import Clock
        from rclpy.time import Time
        node._time_source.clock_callback(Clock(clock=Time(seconds=3).to_msg()))
        assert node.now_ns() == 3_000_000_000 == node.get_clock().now().nanoseconds
        node.set_parameters([Parameter('use_sim_time', value=False)])
        assert abs(node.now_ns() - time.time_ns()) < 60e9   # system time again
    finally:
        node.destroy_node()
