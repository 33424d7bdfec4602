"""What the per-tick savings of the composed controllers keep: the same messages, every input.

Message builders (wip_runtime.messages.StampedBuilder) against the generated constructors, and
one DDS subscription per outside sensor topic in a composed process
(wip_runtime.composition.share_raw_subscriptions).
"""

import time

import pytest

rclpy = pytest.importorskip('rclpy')
wip_msgs = pytest.importorskip('wip_msgs.msg')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from wip_control.core.arc import ArcOutput  # noqa: E402
from wip_control.core.eso import StateEstimate  # noqa: E402
from wip_control.core.reference_state import ReferenceState  # noqa: E402
from wip_control.core.trajectory_generator import VelocityCommand  # noqa: E402
from wip_control.nodes import conversions  # noqa: E402
from wip_runtime import messages  # noqa: E402
from wip_control.nodes.common import ControllerNode  # noqa: E402
from wip_runtime.composition import connect_intra_process  # noqa: E402
from wip_runtime.qos import SENSOR_QOS  # noqa: E402
from wip_runtime.stamps import make_header, stamp_to_ns  # noqa: E402

STAMP = 1_700_000_123_456_789_012   # [ns] a wall-clock stamp, nanoseconds not zero
DEADLINE = 60.0   # [s] discovery and matching on a slow, shared machine


def _same(built, expected):
    assert built == expected
    # On the wire: the same length, and each decodes to the other. Not the same bytes: the
    # serializer leaves alignment padding (after a bool, before a string) as the buffer held
    # it, so two serializations of one message may differ there (wip_runtime/cdr.py).
    wire, expected_wire = serialize_message(built), serialize_message(expected)
    assert len(wire) == len(expected_wire)
    assert deserialize_message(wire, type(expected)) == expected
    assert deserialize_message(expected_wire, type(built)) == built


def test_the_builders_give_the_constructors_messages_field_for_field_and_on_the_wire():
    est = StateEstimate(*(0.1 * i - 0.3 for i in range(10)))
    _same(conversions.estimate_to_msg(est, 1.5, -2.5, True, STAMP, 'map', 2),
          wip_msgs.StateEstimate(
              header=make_header(STAMP, 'map'), phi=est.phi, omega=est.omega, f1=est.f1,
              x_v=est.x_v, v=est.v, f2=est.f2, theta=est.theta, theta_dot=est.theta_dot,
              f3=est.f3, epsilon=est.epsilon, x=1.5, y=-2.5, settled=True, position_status=2))
    ref = ReferenceState(1.0, 2.0, 0.5, 0.4, -0.1, 0.01)
    _same(conversions.reference_to_msg(ref, STAMP, 'map'),
          wip_msgs.ReferenceState(header=make_header(STAMP, 'map'), **ref._asdict()))
    cmd = VelocityCommand(0.3, 0.2, -0.05, 0.1, -0.02, 0.003)
    _same(conversions.command_to_msg(cmd, STAMP),
          wip_msgs.VelocityCommand(header=make_header(STAMP), **cmd._asdict()))
    out = ArcOutput(0.7, 0.02, -0.001)
    _same(conversions.arc_to_msg(out, STAMP),
          wip_msgs.YawTorque(header=make_header(STAMP), **out._asdict()))
    _same(conversions.wheel_torques_to_msg(1.25, -0.5, STAMP, True, 'FAULT: tilt'),
          wip_msgs.WheelTorques(header=make_header(STAMP), left=1.25, right=-0.5, tau_v=0.75,
                                tau_omega=-1.75, zeroed=True, reason='FAULT: tilt'))
    # Messages built one after the other share nothing (a receiver may keep one).
    first, second = (conversions.arc_to_msg(out, s) for s in (1, 2))
    assert first.header is not second.header and stamp_to_ns(first.header.stamp) == 1


def test_a_builder_refuses_a_message_type_whose_fields_it_does_not_list():
    with pytest.raises(TypeError, match='tau_omega'):
        messages.StampedBuilder(wip_msgs.YawTorque, ('alpha_hat', 'e_omega'))
    with pytest.raises(TypeError, match='header'):
        messages.StampedBuilder(Float64MultiArray, ('layout', 'data'))


class RawSensor(ControllerNode):
    """Takes /joint_states serialized, as the ESO does."""

    def __init__(self, **kwargs):
        super().__init__('tick_raw', 'test raw', ('joint_states',), **kwargs)
        self.received = []
        self.subscribe(JointState, '/joint_states', 'joint_states', self._on, SENSOR_QOS,
                       raw=True)

    def _on(self, msg):
        msg = messages.decode_serialized(msg, 'sensor_msgs/msg/JointState')
        self.received.append(list(msg.position))


class PlainSensor(ControllerNode):
    """Takes /joint_states as messages, as the mixer's wiring checks do."""

    def __init__(self, **kwargs):
        super().__init__('tick_plain', 'test plain', (), **kwargs)
        self.received = []
        subscription = self.create_subscription(JointState, '/joint_states', self._on,
                                                SENSOR_QOS)
        self.add_intra_subscription(JointState, subscription, self._on)

    def _on(self, msg):
        self.received.append((list(msg.name), list(msg.position)))


def _params():
    return [Parameter('clock_mode', value='realtime'),
            Parameter('diagnostics_period', value=0.0)]


@pytest.mark.ros
def test_a_composed_process_takes_an_outside_sensor_topic_once_and_serves_both_nodes(context):
    raw = RawSensor(context=context, parameter_overrides=_params())
    plain = PlainSensor(context=context, parameter_overrides=_params())
    base = rclpy.create_node('tick_base', context=context)
    publisher = base.create_publisher(JointState, '/joint_states', 10)
    executor = SingleThreadedExecutor(context=context)
    for node in (raw, plain, base):
        executor.add_node(node)
    try:
        assert len(list(plain.subscriptions)) == 1
        bus = connect_intra_process([raw, plain])
        assert bus is not None
        # The plain node's own subscription is gone: DDS matches one reader of this process.
        assert list(plain.subscriptions) == [] and len(list(raw.subscriptions)) == 1
        end = time.monotonic() + DEADLINE
        while publisher.get_subscription_count() < 1:
            assert time.monotonic() < end, 'the raw subscription never matched'
            executor.spin_once(timeout_sec=0.05)
        assert publisher.get_subscription_count() == 1
        sent = JointState(header=make_header(STAMP), name=['left', 'right'],
                          position=[0.25, -1.5])
        for _ in range(3):
            publisher.publish(sent)
        end = time.monotonic() + DEADLINE
        while len(plain.received) < 3 or len(raw.received) < 3:
            assert time.monotonic() < end, f'{raw.received}, {plain.received}'
            executor.spin_once(timeout_sec=0.05)
            bus.drain()
        # Each message once to each node, decoded: the same names and positions as sent.
        assert raw.received == [[0.25, -1.5]] * 3
        assert plain.received == [(['left', 'right'], [0.25, -1.5])] * 3
        assert raw.diagnostics.dropped == {}
    finally:
        for node in (raw, plain, base):
            node.destroy_node()


@pytest.mark.ros
def test_a_topic_published_within_the_process_keeps_every_subscription(context):
    raw = RawSensor(context=context, parameter_overrides=_params())
    plain = PlainSensor(context=context, parameter_overrides=_params())
    plant = ControllerNode('tick_plant', 'test plant', (), context=context,
                           parameter_overrides=_params())
    plant.create_publisher(JointState, '/joint_states', SENSOR_QOS)
    try:
        assert connect_intra_process([raw, plain, plant]) is not None
        # The bus hands the plant's messages to both; DDS subscriptions stay as they were.
        assert len(list(plain.subscriptions)) == 1 and len(list(raw.subscriptions)) == 1
    finally:
        for node in (raw, plain, plant):
            node.destroy_node()
