"""Core values handed along the composed chain (``IntraProcessPublisher.publish_value``).

Without ROS: who gets the value, who a message, when the message is built, and the order
of the deliveries, which must be that of the message path (the real-time LatestSyncs
pair what is delivered in order). With rclpy: a node's input rules (non-finite, stale)
refuse the same inputs, with the same reasons, whether they come as a message or as a
value.
"""

import contextlib
import math
import time

import pytest

from wip_runtime.intra_process import IntraProcessBus, IntraProcessPublisher


class FakeDdsPublisher:
    def __init__(self, topic='/wip/t', matched=0):
        self.topic_name = topic
        self.matched = matched
        self.sent = []

    def get_subscription_count(self):
        return self.matched

    def publish(self, msg):
        self.sent.append(msg)


class Msg:
    def __init__(self, value, stamp):
        self.value, self.stamp = value, stamp


class Value(tuple):
    """A core value (immutable, as the NamedTuples handed along the chain)."""


class Builder:
    """``to_msg`` counting the messages it builds."""

    def __init__(self):
        self.built = 0

    def __call__(self, value, stamp):
        self.built += 1
        return Msg(value, stamp)


def _bus(dds_ignores_local=False):
    bus = IntraProcessBus(dds_ignores_local=dds_ignores_local)
    got = []
    bus.add_subscription('/wip/t', Msg, lambda m: got.append(('a msg', m)),
                         lambda stamp, v: got.append(('a', stamp, v)), Value)
    bus.add_subscription('/wip/t', Msg, lambda m: got.append(('b msg', m)))
    bus.add_subscription('/wip/t', Msg, lambda m: got.append(('c msg', m)),
                         lambda stamp, v: got.append(('c', stamp, v)), tuple)   # other type
    return bus, got


def test_a_value_goes_as_it_is_where_declared_and_as_one_message_elsewhere_in_order():
    bus, got = _bus()
    dds = FakeDdsPublisher(matched=3)        # the three local subscriptions
    publisher = IntraProcessPublisher(dds, Msg, direct_type=Value)
    assert bus.attach(publisher) == 3
    value, to_msg = Value((1.0, 2.0)), Builder()
    publisher.publish_value(7, value, to_msg)
    assert got == [] and bus.pending == 1    # queued, as a message is
    bus.drain()
    # Registration order kept; b and c (a value type it did not declare) share one message.
    assert [entry[0] for entry in got] == ['a', 'b msg', 'c msg']
    assert got[0][1] == 7 and got[0][2] is value
    assert got[1][1] is got[2][1] and got[1][1].value is value and got[1][1].stamp == 7
    assert to_msg.built == 1 and dds.sent == []


def test_no_message_is_built_when_every_local_subscription_takes_the_value():
    bus = IntraProcessBus()
    got = []
    bus.add_subscription('/wip/t', Msg, got.append, lambda s, v: got.append((s, v)), Value)
    publisher = IntraProcessPublisher(FakeDdsPublisher(matched=1), Msg, direct_type=Value)
    bus.attach(publisher)
    to_msg = Builder()
    for stamp in (1, 2):
        publisher.publish_value(stamp, Value((stamp,)), to_msg)
    bus.drain()
    assert got == [(1, (1,)), (2, (2,))] and to_msg.built == 0


def test_someone_outside_gets_the_message_and_the_process_what_the_message_path_gives():
    # DDS matching the process's own endpoints: the message goes to DDS for everyone
    # (the local subscriptions take it from DDS), nothing on the bus, as publish() does.
    bus, got = _bus()
    dds = FakeDdsPublisher(matched=4)
    publisher = IntraProcessPublisher(dds, Msg, direct_type=Value)
    bus.attach(publisher)
    to_msg = Builder()
    publisher.publish_value(3, Value((0.5,)), to_msg)
    assert len(dds.sent) == 1 and bus.pending == 0 and to_msg.built == 1
    # DDS ignoring them (run_graph's profile): DDS for the outside, the bus for the process.
    bus, got = _bus(dds_ignores_local=True)
    dds = FakeDdsPublisher(matched=1)
    publisher = IntraProcessPublisher(dds, Msg, direct_type=Value)
    bus.attach(publisher)
    value, to_msg = Value((0.5,)), Builder()
    publisher.publish_value(3, value, to_msg)
    bus.drain()
    assert to_msg.built == 1 and got[1][1] is dds.sent[0] and got[0] == ('a', 3, value)
    assert bus.published_dds == 1


def test_an_unattached_publisher_publishes_the_message():
    dds = FakeDdsPublisher()
    publisher = IntraProcessPublisher(dds, Msg, direct_type=Value)
    publisher.publish_value(4, Value((1,)), Builder())     # a node alone: `ros2 run`
    assert [(m.value, m.stamp) for m in dds.sent] == [((1,), 4)]


# --------------------------------------------------------------------------- with rclpy

rclpy = pytest.importorskip('rclpy')
wip_msgs = pytest.importorskip('wip_msgs.msg')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from wip_control.core.trajectory_generator import VelocityCommand  # noqa: E402
from wip_control.nodes.common import ControllerNode  # noqa: E402
from wip_control.nodes.conversions import (checked_command, command_from_msg,  # noqa: E402
                                           command_to_msg)
from wip_runtime.composition import connect_intra_process  # noqa: E402
from wip_runtime.qos import RELIABLE_QOS  # noqa: E402
from wip_runtime.sync import LatestSync  # noqa: E402

DEADLINE = 60.0   # [s] discovery and matching on a slow, shared machine
TOPIC = '/wip/velocity_command'


def _realtime_params():
    return [Parameter('clock_mode', value='realtime'),
            Parameter('diagnostics_period', value=0.0)]


class Receiver(ControllerNode):
    """An input of a LatestSync, subscribed as the controllers subscribe theirs."""

    def __init__(self, name, **kwargs):
        super().__init__(name, 'test receiver', ('velocity_command',), **kwargs)
        self.computed = []
        self.sync = LatestSync(('velocity_command',), self._compute,
                               triggers=('velocity_command',))
        self.subscribe_input(wip_msgs.VelocityCommand, TOPIC, 'velocity_command',
                             command_from_msg, check=checked_command,
                             value_type=VelocityCommand)
        _, _, self.on_message, self.on_value, _ = self.intra_subscriptions[-1]

    def _compute(self, stamp, values):
        self.computed.append((stamp, values['velocity_command']))


@pytest.mark.ros
def test_the_input_rules_refuse_the_same_inputs_from_a_message_and_from_a_value(context):
    params = _realtime_params()
    by_message = Receiver('direct_by_message', context=context, parameter_overrides=params)
    by_value = Receiver('direct_by_value', context=context, parameter_overrides=params)
    now = by_value.now_ns()
    inputs = [(now - 2_000_000, VelocityCommand(0.1, 0.2, 0.0, 0.0, 0.0, 0.0)),
              (now - 1_000_000, VelocityCommand(math.nan, 0.2, 0.0, 0.0, 0.0, 0.0)),  # NaN
              (now - 3_000_000, VelocityCommand(0.3, 0.2, 0.0, 0.0, 0.0, 0.0)),  # older
              (now + 10_000_000_000, VelocityCommand(0.4, 0.2, 0.0, 0.0, 0.0, 0.0)),  # ahead
              (now, VelocityCommand(0.5, 0.2, 0.0, 0.0, 0.0, 0.0))]
    try:
        for stamp, command in inputs:
            by_message.on_message(command_to_msg(command, stamp))
            by_value.on_value(stamp, command)
        # The first and the last computed, the same values at the same stamps; the NaN,
        # the older and the one stamped ahead of the clock refused, for the same reasons.
        assert by_value.computed == by_message.computed
        assert [stamp for stamp, _ in by_value.computed] == [inputs[0][0], inputs[-1][0]]
        assert by_value.computed[-1][1] is inputs[-1][1]      # handed, not copied
        expected = {('velocity_command', 'invalid'): 2, ('velocity_command', 'stale'): 1}
        assert by_value.diagnostics.dropped == by_message.diagnostics.dropped == expected
        assert by_value.diagnostics.last_stamp == by_message.diagnostics.last_stamp
    finally:
        by_message.destroy_node()
        by_value.destroy_node()


class Sender(ControllerNode):
    """A node publishing ``value_type`` values on ``topic`` (the message ``msg_type``)."""

    def __init__(self, name='direct_sender', msg_type=None, topic=TOPIC,
                 value_type=VelocityCommand, **kwargs):
        super().__init__(name, 'test sender', (), **kwargs)
        self.publisher = self.create_publisher(msg_type or wip_msgs.VelocityCommand, topic,
                                               RELIABLE_QOS, direct_type=value_type)


@contextlib.contextmanager
def _composed_beside_outside(context, nodes, outside_name):
    """Yield (bus, executor, outside): ``nodes`` composed, one more node of the test."""
    outside = rclpy.create_node(outside_name, context=context)
    executor = SingleThreadedExecutor(context=context)
    for node in (*nodes, outside):
        executor.add_node(node)
    try:
        yield connect_intra_process(list(nodes)), executor, outside
    finally:
        for node in (*nodes, outside):
            node.destroy_node()


def _spin_until(executor, bus, condition, what):
    end = time.monotonic() + DEADLINE
    while not condition():
        assert time.monotonic() < end, f'not within {DEADLINE} s: {what}'
        executor.spin_once(timeout_sec=0.05)
        bus.drain()


@pytest.mark.ros
def test_a_value_handed_in_the_process_is_the_message_an_outside_subscriber_sees(context):
    # `ros2 topic echo` must see the topic: the value goes to the process's subscription as
    # it is and, once someone outside listens, as its message to DDS, same stamp and fields.
    sender = Sender(context=context, parameter_overrides=_realtime_params())
    receiver = Receiver('direct_receiver', context=context,
                        parameter_overrides=_realtime_params())
    with _composed_beside_outside(context, (sender, receiver),
                                  'direct_outside') as (bus, executor, outside):
        seen = []
        outside.create_subscription(wip_msgs.VelocityCommand, TOPIC, seen.append,
                                    RELIABLE_QOS)
        # The process's subscription and the outside one (DDS's match count, or the
        # outside one and the bus's where DDS ignores the process's own endpoints).
        _spin_until(executor, bus, lambda: sender.publisher.get_subscription_count() >= 2,
                    'the outside subscription matched')
        stamp = receiver.now_ns()
        command = VelocityCommand(0.25, -0.5, 0.125, 1.0, 2.0, 0.75)
        sender.publisher.publish_value(stamp, command, command_to_msg)
        _spin_until(executor, bus, lambda: seen and receiver.computed, 'both deliveries')
        assert seen[0] == command_to_msg(command, stamp)       # every field and the stamp
        assert receiver.computed[0][0] == stamp
        assert tuple(receiver.computed[0][1]) == tuple(command)


# ------------------------------------------------- the mixer's decision as wheel torques

from wip_control.core.safety import SafetyDecision  # noqa: E402
from wip_control.nodes.conversions import decision_to_msg  # noqa: E402
from wip_control.nodes.eso_node import EsoNode  # noqa: E402
from wip_control.nodes.mpc_node import MpcNode  # noqa: E402

WHEELS = '/wip/wheel_torques'


def _wheel_callbacks(node):
    """Return the message and the value callback of the node's /wip/wheel_torques input."""
    (on_message, on_value), = [(cb, direct) for _, topic, cb, direct, _ in
                               node.intra_subscriptions if topic == WHEELS]
    return on_message, on_value


def _realtime(cls, context):
    return cls(context=context, parameter_overrides=_realtime_params())


@pytest.mark.ros
def test_the_eso_and_the_mpc_take_a_decision_as_they_take_its_message(context):
    # The torques the mixer applied are the ESO's input and the MPC's previous torque: a
    # decision handed as it is must give them the same values, and a non-finite one must be
    # refused for the same reason, as the message (every field of which comes from it).
    pairs = [(_realtime(EsoNode, context), _realtime(EsoNode, context)),
             (_realtime(MpcNode, context), _realtime(MpcNode, context))]
    decisions = [SafetyDecision(1.25, -0.5, False, (), 'ACTIVE'),
                 SafetyDecision(math.nan, 0.5, False, (), 'ACTIVE'),
                 SafetyDecision(0.0, 0.0, True, ('tilt',), 'FAULT'),
                 SafetyDecision(-0.75, 2.0, False, (), 'DEGRADED')]
    try:
        for k, decision in enumerate(decisions):
            stamp = 1_000_000_000 + 5_000_000 * k
            for by_message, by_value in pairs:
                _wheel_callbacks(by_message)[0](decision_to_msg(decision, stamp))
                _wheel_callbacks(by_value)[1](stamp, decision)
            (eso_msg, eso_value), (mpc_msg, mpc_value) = pairs
            if k != 1:   # the NaN leaves the last finite torques in force
                assert eso_value.latest_torques == eso_msg.latest_torques \
                    == (decision.tau_left, decision.tau_right)
                assert mpc_value.applied_drive_torque == mpc_msg.applied_drive_torque \
                    == decision.tau_left + decision.tau_right
        (eso_msg, eso_value), (mpc_msg, mpc_value) = pairs
        assert eso_value.latest_torques == (-0.75, 2.0)
        for by_message, by_value in pairs:
            assert by_value.diagnostics.dropped == by_message.diagnostics.dropped
            assert by_value.diagnostics.last_drop == by_message.diagnostics.last_drop
        assert eso_value.diagnostics.dropped == {('wheel_torques', 'invalid'): 1}
        assert eso_value.diagnostics.received['wheel_torques'] == len(decisions)
    finally:
        for pair in pairs:
            for node in pair:
                node.destroy_node()


@pytest.mark.ros
def test_wheel_torques_reach_an_outside_subscriber_while_the_eso_takes_the_decision(context):
    # `ros2 topic echo /wip/wheel_torques` (a recorder, the plant of a lockstep run) must get
    # every message, each the one the mixer built before, while the process's ESO gets the
    # decision itself.
    mixer = Sender('direct_mixer', wip_msgs.WheelTorques, WHEELS, SafetyDecision,
                   context=context, parameter_overrides=_realtime_params())
    eso = _realtime(EsoNode, context)
    with _composed_beside_outside(context, (mixer, eso),
                                  'direct_wheels_outside') as (bus, executor, outside):
        assert mixer.publisher.local_subscriptions == 1
        seen = []
        outside.create_subscription(wip_msgs.WheelTorques, WHEELS, seen.append, RELIABLE_QOS)
        _spin_until(executor, bus, lambda: mixer.publisher.get_subscription_count() >= 2,
                    'the outside subscription matched')
        stamp = eso.now_ns()
        decisions = [SafetyDecision(0.5 * k, -0.25 * k, k == 2, ('tilt',) if k == 2 else (),
                                    'FAULT' if k == 2 else 'ACTIVE') for k in range(4)]
        for k, decision in enumerate(decisions):
            mixer.publisher.publish_value(stamp + k, decision, decision_to_msg)
        _spin_until(executor, bus, lambda: len(seen) == len(decisions)
                    and eso.diagnostics.received['wheel_torques'] == len(decisions),
                    'every message outside, every decision inside')
        assert seen == [decision_to_msg(d, stamp + k) for k, d in enumerate(decisions)]
        assert seen[2].zeroed and seen[2].reason == 'tilt'
        assert eso.latest_torques == (decisions[-1].tau_left, decisions[-1].tau_right)
