"""The viewer's hand-written CDR is rclpy's serialization of the same message.

Each encoder of :mod:`wip_runtime.cdr` is checked against ``rclpy.serialization``: the bytes
decode to a message equal to one built as objects, and have the same length as rclpy's
serialization of it (the same layout: rclpy's padding bytes are not zeroed, so the bytes
themselves are compared only through decoding). Frame names of every length mod 8 move the
alignment of what follows them.
"""

from __future__ import annotations

import random

import pytest

pytest.importorskip('rclpy')

pytestmark = pytest.mark.ros

FRAMES = ('', 'm', 'ma', 'map', 'odom', 'world', 'base_l', 'base_li', 'base_link')


@pytest.fixture(scope='module')
def ros():
    from geometry_msgs.msg import Point, PoseStamped
    from nav_msgs.msg import Path
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray

    from wip_runtime.stamps import make_header
    from wip_control.nodes.conversions import odometry_to_msg
    from wip_runtime.rotations import quaternion_from_euler
    return dict(Point=Point, PoseStamped=PoseStamped, Path=Path, ColorRGBA=ColorRGBA,
                Marker=Marker, MarkerArray=MarkerArray, make_header=make_header,
                odometry_to_msg=odometry_to_msg, quaternion_from_euler=quaternion_from_euler,
                deserialize=deserialize_message, serialize=serialize_message)


def assert_same_message(ros, data: bytes, expected) -> None:
    assert data[:4] == b'\x00\x01\x00\x00'                # CDR little endian
    assert len(data) == len(ros['serialize'](expected))
    assert ros['deserialize'](data, type(expected)) == expected


@pytest.mark.parametrize('frame_id', FRAMES)
@pytest.mark.parametrize('child_frame_id', ('', 'b', 'base_link'))
def test_odometry_is_what_odometry_to_msg_builds(ros, frame_id, child_frame_id):
    from wip_runtime import cdr
    rng = random.Random(f'{frame_id}/{child_frame_id}')
    stamp_ns = rng.randrange(0, 10 ** 12)
    x, y, phi, v, omega = (rng.uniform(-3.0, 3.0) for _ in range(5))
    pose_cov = [rng.random() for _ in range(36)]
    twist_cov = [rng.random() for _ in range(36)]
    _, _, qz, qw = ros['quaternion_from_euler'](0.0, 0.0, phi)
    data = cdr.odometry(stamp_ns, frame_id, child_frame_id, (x, y, 0.0), (0.0, 0.0, qz, qw),
                        pose_cov, (v, 0.0, 0.0), (0.0, 0.0, omega), twist_cov)
    assert_same_message(ros, data, ros['odometry_to_msg'](
        stamp_ns, frame_id, child_frame_id, x, y, phi, v, omega, pose_cov, twist_cov))


@pytest.mark.parametrize('frame_id', FRAMES)
@pytest.mark.parametrize('count', [0, 1, 3])
def test_marker_array_with_and_without_points(ros, frame_id, count):
    from wip_runtime import cdr
    rng = random.Random(f'{frame_id}/{count}')
    writer = cdr.CdrWriter()
    writer.u32(count)
    markers = []
    for index in range(count):
        ns = rng.choice(['', 'vehicle', 'prediction'])
        kind = rng.randrange(12)
        position = tuple(rng.uniform(-5, 5) for _ in range(3))
        orientation = tuple(rng.uniform(-1, 1) for _ in range(4))
        scale = tuple(rng.random() for _ in range(3))
        color = tuple(rng.randrange(256) / 256.0 for _ in range(4))  # exact in float32
        points = [tuple(rng.uniform(-5, 5) for _ in range(3))
                  for _ in range(rng.choice([0, 1, 2, 21]))]
        marker = ros['Marker'](header=ros['make_header'](stamp_ns := rng.randrange(10 ** 12),
                                                         frame_id),
                               ns=ns, id=index, type=kind, action=ros['Marker'].ADD)
        (marker.pose.position.x, marker.pose.position.y,
         marker.pose.position.z) = position
        (marker.pose.orientation.x, marker.pose.orientation.y, marker.pose.orientation.z,
         marker.pose.orientation.w) = orientation
        marker.scale.x, marker.scale.y, marker.scale.z = scale
        marker.color = ros['ColorRGBA'](r=color[0], g=color[1], b=color[2], a=color[3])
        marker.points = [ros['Point'](x=p[0], y=p[1], z=p[2]) for p in points]
        markers.append(marker)
        cdr.marker(writer, stamp_ns, frame_id, ns, index, kind, ros['Marker'].ADD, position,
                   orientation, scale, color, [c for p in points for c in p])
    assert_same_message(ros, writer.message(), ros['MarkerArray'](markers=markers))


@pytest.mark.parametrize('frame_id', FRAMES)
@pytest.mark.parametrize('count', [0, 1, 2, 5])
def test_path_from_poses_encoded_once(ros, frame_id, count):
    """The first pose's padding follows the header; every later pose starts 8-aligned."""
    from wip_runtime import cdr
    rng = random.Random(f'{frame_id}/{count}')
    stamp_ns = rng.randrange(10 ** 12)
    expected = ros['Path'](header=ros['make_header'](stamp_ns, frame_id))
    poses = []
    for _ in range(count):
        pose = (rng.randrange(10 ** 12), frame_id,
                (rng.uniform(-9, 9), rng.uniform(-9, 9), 0.0),
                tuple(rng.uniform(-1, 1) for _ in range(4)))
        poses.append(pose)
        stamped = ros['PoseStamped'](header=ros['make_header'](pose[0], frame_id))
        p, q = stamped.pose.position, stamped.pose.orientation
        p.x, p.y, p.z = pose[2]
        q.x, q.y, q.z, q.w = pose[3]
        expected.poses.append(stamped)
    data = cdr.path(stamp_ns, frame_id, poses[0] if poses else None,
                    [cdr.pose_stamped(*pose) for pose in poses[1:]])
    assert_same_message(ros, data, expected)


@pytest.mark.parametrize('count', [0, 1, 3])
def test_tf_message_of_transforms(ros, count):
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from wip_runtime import cdr
    rng = random.Random(count)
    transforms, expected = [], TFMessage()
    for k in range(count):
        stamp_ns = rng.randrange(0, 10 ** 12)
        frame_id, child = FRAMES[(3 * k + count) % len(FRAMES)], FRAMES[(5 * k + 1) % 9]
        translation = tuple(rng.uniform(-5.0, 5.0) for _ in range(3))
        rotation = tuple(rng.uniform(-1.0, 1.0) for _ in range(4))
        transforms.append((stamp_ns, frame_id, child, translation, rotation))
        msg = TransformStamped(header=ros['make_header'](stamp_ns, frame_id),
                               child_frame_id=child)
        t, q = msg.transform.translation, msg.transform.rotation
        t.x, t.y, t.z = translation
        q.x, q.y, q.z, q.w = rotation
        expected.transforms.append(msg)
    assert_same_message(ros, cdr.tf_message(transforms), expected)


def test_bad_arguments_are_refused():
    from wip_runtime import cdr
    with pytest.raises(ValueError, match='triples'):
        cdr.marker(cdr.CdrWriter(), 0, 'map', '', 0, 0, 0, (0, 0, 0), (0, 0, 0, 1),
                   (1, 1, 1), (1, 1, 1, 1), [0.0, 1.0])
    with pytest.raises(ValueError, match='first pose'):
        cdr.path(0, 'map', None, [cdr.pose_stamped(0, 'map', (0, 0, 0), (0, 0, 0, 1))])


def test_the_process_own_subscribers_get_message_objects(ros, context):
    """A publisher with subscribers in the process (the bus hands them objects) gets one."""
    from nav_msgs.msg import Odometry

    from wip_viewer.viewer_node import ViewerNode

    class Recording:
        def __init__(self, local: int) -> None:
            self.msg_type, self.local_subscriptions, self.sent = Odometry, local, []

        def publish(self, msg) -> None:
            self.sent.append(msg)

    node = ViewerNode(context=context)
    try:
        for local in (0, 1):
            recording = Recording(local)
            node.publishers_['/wip/odom/truth'] = recording
            node._publish_odometry('/wip/odom/truth', 123, 1.0, 2.0, 0.5, 0.3, 0.1,
                                   node.truth_covariance)
            (sent,) = recording.sent
            expected = ros['odometry_to_msg'](123, 'map', 'base_link', 1.0, 2.0, 0.5, 0.3, 0.1)
            if local:
                assert sent == expected
            else:
                assert_same_message(ros, sent, expected)
    finally:
        node.destroy_node()


def test_wheel_transforms_from_joint_states_and_bad_ones_dropped(ros, context):
    # The viewer as robot_state_publisher: each wheel joint's position in /joint_states
    # (any order, other joints ignored) becomes its joint's rotation about ±y, in prefixed
    # frames; a message without a wheel joint or with a non-finite angle is dropped and
    # counted, never a traceback.
    import math

    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage

    from wip_viewer.viewer_node import ViewerNode

    class Recording:
        msg_type, local_subscriptions = TFMessage, 0

        def __init__(self) -> None:
            self.sent = []

        def publish(self, msg) -> None:
            self.sent.append(ros['deserialize'](msg, TFMessage))

    node = ViewerNode(context=context, parameter_overrides=[
        Parameter('viewer.frame_prefix', value='robot1/'),
        Parameter('right_wheel_sign', value=-1),
        Parameter('encoders_relative_to_body', value=False)])
    try:
        recording = node.publishers_['/tf'] = Recording()
        node._on_joint_states(JointState(name=['caster', 'right_wheel_joint',
                                               'left_wheel_joint'],
                                         position=[9.0, 0.4, -1.2]), 5)
        (message,) = recording.sent
        by_child = {t.child_frame_id: t for t in message.transforms}
        assert set(by_child) == {'robot1/left_wheel', 'robot1/right_wheel'}
        for child, angle, sign in (('robot1/left_wheel', -1.2, 1.0),
                                   ('robot1/right_wheel', 0.4, -1.0)):
            t = by_child[child]
            assert t.header.frame_id == 'robot1/chassis'      # encoders not on the body
            assert t.header.stamp.nanosec == 5
            q = t.transform.rotation
            assert (q.x, q.y, q.z, q.w) == pytest.approx(
                (0.0, sign * math.sin(angle / 2), 0.0, math.cos(angle / 2)), abs=1e-15)
        for bad in (JointState(name=['left_wheel_joint'], position=[0.1]),
                    JointState(name=['left_wheel_joint', 'right_wheel_joint'],
                               position=[0.1, math.nan])):
            node._on_joint_states(bad, 6)
        assert len(recording.sent) == 1
        assert node.diagnostics.dropped[('joint_states', 'invalid')] == 2
    finally:
        node.destroy_node()
    plain = ViewerNode(context=context, parameter_overrides=[
        Parameter('viewer.robot_model', value=False)])
    try:
        assert plain.robot is None and '/tf' not in plain.publishers_
    finally:
        plain.destroy_node()


def test_a_simulations_viewer_keeps_what_its_recorder_has_not_acknowledged(ros, context):
    # Composed with a simulation (a recorded run) the viewer's reliable writers keep the
    # lockstep history, so a recorder descheduled for a while loses no pose (with 10 one
    # was lost under load); alone, beside a robot, they keep the graph design's 10 (/tf:
    # tf2's 100) and a stalled viewer client holds no backlog of minutes.
    from wip_runtime.qos import LOCKSTEP_WRITER_DEPTH
    from wip_viewer.viewer_node import ViewerNode

    for keep, depth, tf_depth in ((True, LOCKSTEP_WRITER_DEPTH, LOCKSTEP_WRITER_DEPTH),
                                  (False, 10, 100)):
        node = ViewerNode(context=context, keep_unacknowledged=keep)
        try:
            depths = {topic: publisher.qos_profile.depth
                      for topic, publisher in node.publishers_.items()}
            assert depths.pop('/tf') == tf_depth
            assert set(depths.values()) == {depth}, depths
            assert all(publisher.qos_profile.reliability.name == 'RELIABLE'
                       for publisher in node.publishers_.values())
        finally:
            node.destroy_node()
