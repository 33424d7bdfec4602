"""Input adapters of a real base and the node parameters that use them.

Input adapters of a real base (wheel signs, IMU mounting, odometry) and the node
parameters that use them: eso, torque_mixer, reference (``realtime_start``), mpc (applied
torque in real time).

The node tests build each node in a private rclpy context and call its callbacks
directly, capturing what it publishes: no DDS traffic, no timing.
"""

import math
import time

from hypothesis import given, settings, strategies as st
import pytest

rclpy = pytest.importorskip('rclpy')

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402
from wip_msgs.msg import YawTorque, DriveTorque, StateEstimate, VelocityCommand  # noqa: E402
from wip_msgs.msg import WheelTorques  # noqa: E402

from wip_runtime.config import ParamError  # noqa: E402
from wip_control.core.references import make_reference, ReferenceParams  # noqa: E402
from wip_control.core.safety import SafetyDecision  # noqa: E402
from wip_runtime.stamps import make_header  # noqa: E402
from wip_control.nodes.conversions import (arc_from_msg, command_from_msg,  # noqa: E402
                                           estimate_from_msg, imu_pitch_yaw, wheel_angles)
from wip_runtime.messages import InvalidMessage, pitch_yaw_from_quaternion  # noqa: E402
from wip_runtime.rotations import (quaternion_from_euler, quaternion_multiply,  # noqa: E402
                                   rotate_vector_into)
from wip_control.nodes.eso_node import EsoNode  # noqa: E402
from wip_control.nodes.hardware_inputs import (body_pitch_yaw,  # noqa: E402
                                               check_mounting_rpy, check_position_source,
                                               check_wheel_sign, imu_orientation_of_body,
                                               mounting_inverse, odometry_position,
                                               signed_efforts, signed_wheel_angles)
from wip_control.nodes.mpc_node import MpcNode  # noqa: E402
from wip_control.nodes.reference_node import ReferenceNode  # noqa: E402
from wip_control.nodes.torque_mixer_node import TorqueMixerNode  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = pytest.mark.ros

UPSIDE_DOWN = (math.pi, 0.0, 0.0)
QUARTER_TURN = (0.0, 0.0, math.pi / 2)
#: The stand-in base test's mounting: upside down and turned a quarter turn.
ODD_MOUNTING = (math.pi, 0.0, math.pi / 2)
#: Quaternion products and the ZYX decomposition round to a few ulps of 1 [rad].
ANGLE_TOLERANCE = 1e-12


def joint_states(left, right, names=('left_wheel_joint', 'right_wheel_joint')):
    values = {'left_wheel_joint': left, 'right_wheel_joint': right}
    msg = JointState(name=list(names))
    msg.position = [values.get(n, 0.0) for n in names]
    return msg


def imu_with(q):
    msg = Imu()
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = q
    return msg


def roll_pitch_yaw(q):
    """ZYX Euler angles (roll, pitch, yaw) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch, yaw = pitch_yaw_from_quaternion(x, y, z, w)
    return roll, pitch, yaw


# ----------------------------------------------------------------------------- pure functions

def test_default_adapters_return_the_plain_conversions_bit_for_bit():
    # Defaults must not change the simulated graph (lockstep = runner to the bit).
    msg = joint_states(0.123456789, -2.5)
    assert signed_wheel_angles(msg, 'left_wheel_joint', 'right_wheel_joint') == wheel_angles(
        msg, 'left_wheel_joint', 'right_wheel_joint')
    imu = imu_with(quaternion_from_euler(0.0, 0.0731, -2.9))
    assert mounting_inverse((0.0, 0.0, 0.0)) is None
    assert body_pitch_yaw(imu, None) == imu_pitch_yaw(imu)
    assert signed_efforts(1.5, -2.0) == (1.5, -2.0)


def test_wheel_signs_negate_the_joint_angle_and_the_effort():
    msg = joint_states(3.0, 4.0, names=('right_wheel_joint', 'left_wheel_joint'))
    assert signed_wheel_angles(msg, 'left_wheel_joint', 'right_wheel_joint', -1.0,
                               1.0) == (-3.0, 4.0)
    assert signed_wheel_angles(msg, 'left_wheel_joint', 'right_wheel_joint', 1.0,
                               -1.0) == (3.0, -4.0)
    assert signed_efforts(1.5, -2.0, -1.0, 1.0) == (-1.5, -2.0)
    assert signed_efforts(1.5, -2.0, 1.0, -1.0) == (1.5, 2.0)


@pytest.mark.parametrize('value', [0, 2, -2, 0.5, True, 'left', None, float('nan')])
def test_a_wheel_sign_other_than_plus_or_minus_one_is_rejected_with_its_name(value):
    with pytest.raises(ValueError, match='left_wheel_sign: must be 1 or -1'):
        check_wheel_sign('left_wheel_sign', value)


def test_valid_wheel_signs_mounting_and_position_source_are_accepted():
    assert check_wheel_sign('s', 1) == 1.0 and check_wheel_sign('s', -1) == -1.0
    assert check_wheel_sign('s', -1.0) == -1.0
    assert check_mounting_rpy('m', [1, 2, 3]) == (1.0, 2.0, 3.0)
    assert check_position_source('p', 'odometry') == 'odometry'


@pytest.mark.parametrize('value', [[0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, float('inf'), 0.0],
                                   'abc', None])
def test_a_bad_mounting_is_rejected_with_its_name(value):
    with pytest.raises(ValueError, match='imu_mounting_rpy'):
        check_mounting_rpy('imu_mounting_rpy', value)


def test_an_unknown_position_source_is_rejected():
    with pytest.raises(ValueError, match="position_source: 'gnss' is not one of"):
        check_position_source('position_source', 'gnss')


def test_upside_down_imu_reports_roll_pi_and_the_body_pitch_comes_out():
    # The docstring's example: upright, facing east, the IMU says roll pi ...
    q_upright = imu_orientation_of_body(quaternion_from_euler(0.0, 0.0, 0.0), UPSIDE_DOWN)
    roll, _, _ = roll_pitch_yaw(q_upright)
    assert abs(roll) == pytest.approx(math.pi, abs=ANGLE_TOLERANCE)
    inverse = mounting_inverse(UPSIDE_DOWN)
    assert body_pitch_yaw(imu_with(q_upright), inverse) == pytest.approx(
        (0.0, 0.0), abs=ANGLE_TOLERANCE)
    # ... and leaning forward by 0.1 rad gives theta = +0.1 rad.
    q_lean = imu_orientation_of_body(quaternion_from_euler(0.0, 0.1, 0.0), UPSIDE_DOWN)
    assert body_pitch_yaw(imu_with(q_lean), inverse) == pytest.approx((0.1, 0.0),
                                                                      abs=ANGLE_TOLERANCE)
    # Gravity (specific force, +z up in the world) points along the IMU's -z.
    assert rotate_vector_into(q_upright, (0.0, 0.0, 9.81)) == pytest.approx(
        (0.0, 0.0, -9.81), abs=1e-12)


def test_a_quarter_turned_imu_needs_the_mounting_or_the_pitch_is_lost():
    q = imu_orientation_of_body(quaternion_from_euler(0.0, 0.1, 0.3), QUARTER_TURN)
    naive_pitch, _ = imu_pitch_yaw(imu_with(q))
    # Without the parameter the lean appears as a roll of the IMU, not as its pitch.
    assert abs(naive_pitch) < 1e-12
    assert body_pitch_yaw(imu_with(q), mounting_inverse(QUARTER_TURN)) == pytest.approx(
        (0.1, 0.3), abs=ANGLE_TOLERANCE)


@settings(max_examples=200, deadline=None)
@given(mount=st.tuples(*[st.floats(-math.pi, math.pi)] * 3),
       pitch=st.floats(-1.4, 1.4), yaw=st.floats(-3.1, 3.1))
def test_any_mounting_is_undone_exactly(mount, pitch, yaw):
    q_imu = imu_orientation_of_body(quaternion_from_euler(0.0, pitch, yaw), mount)
    inverse = mounting_inverse(mount)
    got = body_pitch_yaw(imu_with(q_imu), inverse)
    # asin near |pitch| = pi/2 loses digits: 1e-9 rad below 1.4 rad.
    assert got[0] == pytest.approx(pitch, abs=1e-9)
    assert math.remainder(got[1] - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_quaternion_product_composes_rotations_like_the_euler_formula():
    # Rz(yaw) Ry(pitch) = q(yaw about z) * q(pitch about y).
    q = quaternion_multiply(quaternion_from_euler(0.0, 0.0, 0.7),
                            quaternion_from_euler(0.0, -0.2, 0.0))
    assert q == pytest.approx(quaternion_from_euler(0.0, -0.2, 0.7), abs=1e-15)


def test_mounted_imu_rejects_malformed_orientations_like_the_plain_conversion():
    inverse = mounting_inverse(UPSIDE_DOWN)
    for q in [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, float('nan')), (0.0, 0.0, 0.0, 2.0)]:
        with pytest.raises(InvalidMessage):
            body_pitch_yaw(imu_with(q), inverse)
    no_orientation = imu_with((0.0, 0.0, 0.0, 1.0))
    no_orientation.orientation_covariance[0] = -1.0
    with pytest.raises(InvalidMessage, match='no orientation'):
        body_pitch_yaw(no_orientation, inverse)


def test_odometry_position_is_the_pose_position_and_rejects_non_finite():
    msg = Odometry()
    msg.pose.pose.position.x, msg.pose.pose.position.y = 1.25, -3.5
    assert odometry_position(msg) == (1.25, -3.5)
    msg.pose.pose.position.y = float('nan')
    with pytest.raises(InvalidMessage, match='odometry'):
        odometry_position(msg)


# ----------------------------------------------------------------------------- nodes

@pytest.fixture(scope='module')
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=take_private_domain(), args=[])
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def nodes():
    made = []
    yield made
    for node in made:
        node.destroy_node()


def make(nodes, context, cls, **params):
    values = {'clock_mode': 'realtime', 'diagnostics_period': 0.0, **params}
    node = cls(context=context, parameter_overrides=[Parameter(k, value=v)
                                                     for k, v in values.items()])
    nodes.append(node)
    return node


def capture(publisher):
    sent = []
    publisher.publish = sent.append
    return sent


def feed_eso(node, encode, n=40):
    """Feed ``n`` samples of a robot rolling forward and turning.

    ``encode(pitch, yaw, left, right)`` makes the base's (JointState, Imu).
    """
    out = capture(node.publisher)
    for k in range(n):
        stamp = 1_000_000_000 + k * 5_000_000
        pitch, yaw = 0.05 - 0.001 * k, 0.3 + 0.01 * k
        left, right = 0.02 * k, 0.03 * k
        joint, imu = encode(pitch, yaw, left, right)
        joint.header = make_header(stamp)
        imu.header = make_header(stamp)
        node._on_joint_states(joint)
        node._on_imu(imu)
    return out


def test_eso_with_signs_and_mounting_estimates_what_the_default_does_on_plain_input(
        context, nodes):
    names = ('wheel_r', 'wheel_l')   # another order and other names

    def plain(pitch, yaw, left, right):
        return (joint_states(left, right),
                imu_with(quaternion_from_euler(0.0, pitch, yaw)))

    def base(pitch, yaw, left, right):
        joint = JointState(name=list(names), position=[right, -left])  # left sign -1
        q = imu_orientation_of_body(quaternion_from_euler(0.0, pitch, yaw), ODD_MOUNTING)
        return joint, imu_with(q)

    reference = feed_eso(make(nodes, context, EsoNode), plain)
    configured = feed_eso(make(nodes, context, EsoNode, left_joint='wheel_l',
                               right_joint='wheel_r', left_wheel_sign=-1,
                               imu_mounting_rpy=list(ODD_MOUNTING)), base)
    assert len(reference) == len(configured) == 40
    for a, b in zip(reference, configured):
        for field in ('phi', 'omega', 'x_v', 'v', 'theta', 'theta_dot', 'f1', 'f2', 'f3'):
            # The mounting's quaternion algebra rounds the angles to ~1e-16 rad; the
            # observer's gains (up to 6/eps^3 = 6e6) scale that to < 1e-8.
            assert getattr(b, field) == pytest.approx(getattr(a, field), rel=1e-9, abs=1e-8)
    assert reference[-1].x_v > 0.0 and reference[-1].theta < 0.05


def test_eso_fed_serialized_sensors_estimates_bit_for_bit_what_message_objects_give(
        context, nodes):
    """The ESO fed serialized sensors estimates bit for bit what message objects give.

    The ESO takes /joint_states and /imu/data serialized (raw=True, decoded by
    messages.decode_serialized): the same estimates as from rclpy's message objects.
    """
    from rclpy.serialization import serialize_message

    def plain(pitch, yaw, left, right):
        imu = imu_with(quaternion_from_euler(0.0, pitch, yaw))
        imu.angular_velocity.y, imu.angular_velocity.z = 0.1 * pitch, -0.2 * yaw
        return joint_states(left, right), imu

    class Serialized:
        """feed_eso sets the header, then the node gets the bytes."""

        def __init__(self, node):
            self.node, self._on_joint_states, self._on_imu = node, self.joint, self.imu
            self.publisher = node.publisher

        def joint(self, msg):
            self.node._on_joint_states(serialize_message(msg))

        def imu(self, msg):
            self.node._on_imu(serialize_message(msg))

    objects = feed_eso(make(nodes, context, EsoNode), plain)
    serialized = feed_eso(Serialized(make(nodes, context, EsoNode)), plain)
    assert len(objects) == len(serialized) == 40
    fields = ('phi', 'omega', 'x_v', 'v', 'theta', 'theta_dot', 'f1', 'f2', 'f3')
    for a, b in zip(objects, serialized):
        assert [getattr(b, f) for f in fields] == [getattr(a, f) for f in fields]
        assert (b.header.stamp.sec, b.header.stamp.nanosec) == (a.header.stamp.sec,
                                                                a.header.stamp.nanosec)
    assert objects[-1].theta_dot != 0.0   # the gyro rates went through too


def test_undecodable_serialized_sensor_messages_are_dropped_with_one_line(context, nodes):
    from rclpy.serialization import serialize_message
    node = make(nodes, context, EsoNode)
    good = serialize_message(imu_with(quaternion_from_euler(0.0, 0.1, 0.2)))
    for raw in (b'', good[:30], b'\x00\x01\x00\x00' + b'\xff' * 7):
        with pytest.raises(InvalidMessage, match='undecodable CDR') as err:
            node._on_imu(raw)
        assert '\n' not in str(err.value)
        with pytest.raises(InvalidMessage, match='undecodable CDR'):
            node._on_joint_states(raw)


def test_eso_takes_its_position_from_odometry_when_asked(context, nodes):
    node = make(nodes, context, EsoNode, position_source='odometry')
    out = capture(node.publisher)
    odom = Odometry()
    odom.pose.pose.position.x, odom.pose.pose.position.y = 4.0, -2.0
    odom.header = make_header(1_000_000_000)
    node._on_odometry(odom)
    joint, imu = joint_states(0.0, 0.0), imu_with(quaternion_from_euler(0.0, 0.0, 0.0))
    joint.header = imu.header = make_header(1_000_000_000)
    node._on_joint_states(joint)
    node._on_imu(imu)
    assert (out[-1].x, out[-1].y) == (4.0, -2.0)
    assert node.diagnostics.received['odom'] == 1


def test_eso_refuses_odometry_in_lockstep_and_bad_hardware_parameters(context, nodes):
    with pytest.raises(ParamError, match="position_source: 'odometry' needs clock_mode"):
        make(nodes, context, EsoNode, clock_mode='lockstep', use_sim_time=True,
             position_source='odometry')
    with pytest.raises(ParamError, match='left_wheel_sign: must be 1 or -1'):
        make(nodes, context, EsoNode, left_wheel_sign=2)
    with pytest.raises(ParamError, match='imu_mounting_rpy'):
        make(nodes, context, EsoNode, imu_mounting_rpy=[0.0, 1.0])
    with pytest.raises(ParamError, match='right_wheel_sign'):
        make(nodes, context, TorqueMixerNode, right_wheel_sign=0)


def test_eso_in_real_time_advances_its_observer_by_whole_sample_periods(context, nodes):
    node = make(nodes, context, EsoNode)
    base = 1_000_000_000
    # Jitter of +-0.3 ms rounds to one period; a 10.4 ms gap (one sample lost) to two.
    stamps = [base, base + 5_300_000, base + 9_800_000, base + 20_200_000]
    times = [node._observer_time(stamps[0])]
    node.estimator.observer = object()   # as after the first update
    times += [node._observer_time(s) for s in stamps[1:]]
    node.estimator.observer = None
    assert times == pytest.approx([0.0, 0.005, 0.010, 0.020], abs=1e-15)


def test_mixer_sends_each_effort_with_its_joint_sign(context, nodes):
    node = make(nodes, context, TorqueMixerNode, left_joint='wheel_l',
                right_joint='wheel_r', joints=['wheel_r', 'wheel_l'], left_wheel_sign=-1)
    efforts = capture(node.effort_publisher)
    torques = capture(node.torques_publisher)
    node._publish(5, SafetyDecision(2.0, 3.0, False, (), 'ACTIVE'))
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import Float64MultiArray
    sent = deserialize_message(efforts[-1], Float64MultiArray)   # sent serialized
    assert list(sent.data) == [3.0, -2.0]              # joint order, left negated
    assert (torques[-1].left, torques[-1].right) == (2.0, 3.0)   # REP 103, unchanged


def test_reference_engaged_holds_the_start_until_the_first_torque_not_zeroed(context, nodes):
    config = ReferenceParams(kind='line')
    node = make(nodes, context, ReferenceNode, realtime_start='engaged',
                **{'reference.kind': 'line'})
    out = capture(node.publisher)
    start = make_reference(config).sample(0.0)
    node.publish_at(1_000_000_000)
    node.publish_at(3_000_000_000)
    on_torques, = [cb for _, topic, cb, _, _ in node.intra_subscriptions
                   if topic == '/wip/wheel_torques']     # the message callback
    on_torques(WheelTorques(header=make_header(3_500_000_000), zeroed=True))
    node.publish_at(4_000_000_000)
    assert [(m.x, m.y) for m in out] == [(start.x, start.y)] * 3
    on_torques(WheelTorques(header=make_header(5_000_000_000), left=1.0))
    node.publish_at(7_000_000_000)     # 2 s after the engagement
    expected = make_reference(config).sample(2.0)
    assert (out[-1].x, out[-1].y) == pytest.approx((expected.x, expected.y), abs=1e-12)
    with pytest.raises(ParamError, match='realtime_start'):
        make(nodes, context, ReferenceNode, realtime_start='later')


@pytest.mark.wallclock   # inputs late past 0.05 s
def test_mpc_in_real_time_plans_from_the_torque_the_mixer_applied(context, nodes):
    node = make(nodes, context, MpcNode)
    out = capture(node.publisher)
    stamp = node.now_ns()
    estimate = StateEstimate(header=make_header(stamp), theta=0.05, settled=True)
    command = VelocityCommand(header=make_header(stamp), v_d=0.5)
    arc = YawTorque(header=make_header(stamp))
    node._on_input('state_estimate', estimate, estimate_from_msg(estimate))
    node._on_input('velocity_command', command, command_from_msg(command))
    node._on_input('yaw_torque', arc, arc_from_msg(arc))
    solve_tick(node, out)
    first = out[-1]
    assert first.status == DriveTorque.SOLVED and first.tau_v != 0.0
    # The mixer held the torque at zero (start-up): the next solve starts from 0, not from
    # the MPC's own unapplied output.
    node._on_applied(WheelTorques(header=make_header(stamp), zeroed=True))
    second = solve_tick(node, out)
    assert second.tau_v - second.delta_tau == pytest.approx(0.0, abs=1e-12)
    node._on_applied(WheelTorques(header=make_header(stamp), left=1.25, right=2.0))
    third = solve_tick(node, out)
    assert third.tau_v - third.delta_tau == pytest.approx(3.25, abs=1e-12)


def test_composed_mpc_ticks_at_the_chains_end_and_on_a_late_deadline_without_one(
        context, nodes, monkeypatch):
    # Composed (its watchdog adopted by the spin loop), the real-time tick runs when the
    # mixer's wheel torques end a chain at least a tick period less half a control period
    # after the last tick, so a second command of the same period (the mixer's watchdog)
    # is no tick; without a chain the deadline, half a control period late, runs it. The
    # counter of control ticks advances by one tick period per tick either way, as the
    # timer's did.
    clock = [100.0]
    monkeypatch.setattr(time, 'monotonic', lambda: clock[0])
    node = make(nodes, context, MpcNode)
    capture(node.publisher)
    period, half = node.tick_period, 0.5 * node.control_period
    node.watchdog.adopt()
    applied = WheelTorques(header=make_header(node.now_ns()))
    node._on_applied(applied)
    assert node.realtime_k == node.every                  # the first chain: a tick
    clock[0] += period - half - 1e-6
    node._on_applied(applied)
    assert node.realtime_k == node.every                  # too soon after the last tick
    clock[0] += 2e-6
    node._on_applied(applied)
    assert node.realtime_k == 2 * node.every and node.watchdog.due == pytest.approx(
        clock[0] + period + half)
    clock[0] = node.watchdog.due - 1e-6                   # no chain comes
    node.watchdog.fire_if_due(clock[0])
    assert node.realtime_k == 2 * node.every
    clock[0] += 2e-6
    node.watchdog.fire_if_due(clock[0])
    assert node.realtime_k == 3 * node.every
    alone = make(nodes, context, MpcNode)                 # not adopted: its timer ticks
    alone._on_applied(applied)
    assert alone.realtime_k == 0 and not alone.watchdog.timer.is_canceled()


def solve_tick(node, out):
    """Run the MPC's real-time timer until it publishes; return the message.

    With ``mpc.push_trigger`` the timer runs every control period and publishes only at the
    ticks where the stage solves.
    """
    published = len(out)
    for _ in range(node.stage.decimation):
        node._realtime_tick()
        if len(out) > published:
            return out[-1]
    raise AssertionError(f'no drive torque in {node.stage.decimation} timer ticks')


def test_subscribers_of_one_message_object_share_one_checked_conversion():
    # Composed, the subscribers of a topic get the same message object: it is converted
    # once. A fresh object is converted anew; an unchecked conversion is not taken as a
    # checked one (a non-finite estimate still raises for a subscriber that checks).
    msg = StateEstimate(header=make_header(5), v=0.5, theta=0.01, x=1.0, y=2.0)
    first = estimate_from_msg(msg)
    assert estimate_from_msg(msg) is first and estimate_from_msg(msg, check=False) is first
    copy = StateEstimate(header=make_header(5), v=0.5, theta=0.01, x=1.0, y=2.0)
    assert estimate_from_msg(copy) is not first and estimate_from_msg(copy) == first
    bad = StateEstimate(header=make_header(10), v=math.nan)
    assert math.isnan(estimate_from_msg(bad, check=False).estimate.v)
    with pytest.raises(InvalidMessage, match='state_estimate'):
        estimate_from_msg(bad)
    command = VelocityCommand(header=make_header(5), v_d=0.3, omega_d=0.1)
    assert command_from_msg(command) is command_from_msg(command)
    bad_command = VelocityCommand(header=make_header(10), omega_d=math.inf)
    command_from_msg(bad_command, check=False)
    with pytest.raises(InvalidMessage, match='velocity_command'):
        command_from_msg(bad_command)


@settings(max_examples=60, deadline=None)
@given(left=st.floats(allow_nan=False, allow_infinity=True, width=64),
       right=st.floats(allow_nan=False, allow_infinity=True, width=64),
       joints=st.permutations(['wheel_l', 'wheel_r']).map(tuple))
def test_the_serialized_effort_command_is_the_message_rclpy_would_send(left, right, joints):
    # The real-time mixer publishes the effort command as CDR bytes it builds itself: the
    # base must receive exactly the message (values, order of the joints, empty layout).
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import Float64MultiArray
    from wip_control.nodes.conversions import effort_command, effort_command_cdr
    by_hand = effort_command_cdr(left, right, joints, 'wheel_l', 'wheel_r')
    expected = effort_command(left, right, joints, 'wheel_l', 'wheel_r')
    got = deserialize_message(by_hand, Float64MultiArray)
    assert list(got.data) == list(expected.data)
    assert list(got.layout.dim) == [] and got.layout.data_offset == 0
    assert len(by_hand) == len(serialize_message(expected))
