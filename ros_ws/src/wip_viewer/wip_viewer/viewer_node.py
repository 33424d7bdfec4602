"""Viewer node: standard messages that a 3-D viewer (Foxglove, RViz) draws, from the graph.

The graph's own messages (StateEstimate, GroundTruth, ReferenceState, DriveTorque) are custom
types that no viewer can place in 3-D. This node turns them into standard ones, off the
control loop: it only subscribes to the controllers' topics (best effort, keep-last 5:
a slow viewer loses its own samples and never makes a publisher wait), and nothing in the
graph subscribes to what it publishes. Its inputs at the control rate are subscribed raw:
the stamp is read from the CDR bytes and a message is deserialized only when the node
publishes from it (:func:`~wip_viewer.viewer_core.cdr_stamp_ns`), which keeps its CPU per
control tick small. Composed with the simulation (``ros2 run wip_sim simulation
--with-viewer``, what run_graph starts for a recorded run in the single layout) it is an
intra-process node like the controllers: its inputs arrive from the process's own nodes as
message objects, every one of them (the bus ignores the best-effort depth), and nothing is
decoded. Its own messages are published already serialized, written by :mod:`wip_runtime.cdr` (the
same messages; rclpy's conversion of message objects was most of the node's cost), and a
Path's poses are encoded once each.

Published (frame ``viewer.frame_id``, default ``map``; child ``base_link``)
--------------------------------------------------------------------------
=========================== ============================== ==============================
topic                       type                           from / rate
=========================== ============================== ==============================
/wip/odom/estimate          nav_msgs/Odometry              /wip/state_estimate, pose_rate
/wip/odom/truth             nav_msgs/Odometry              /wip/ground_truth, pose_rate
/wip/markers/vehicle        visualization_msgs/MarkerArray body tilted by θ, two wheels
                                                           (truth if any, else estimate)
/wip/markers/prediction     visualization_msgs/MarkerArray the MPC's predicted υ, θ over
                                                           its horizon (/wip/drive_torque)
/wip/path/reference         nav_msgs/Path                  /wip/reference, path_rate
/wip/path/travelled         nav_msgs/Path                  /wip/ground_truth, path_rate
/wip/path/estimated         nav_msgs/Path                  /wip/state_estimate, path_rate
=========================== ============================== ==============================

Robot model (``viewer.robot_model``, default on): ``robot_description`` (std_msgs/String,
transient local; relative, so under the vehicle's namespace) holds the URDF of the
``model.*`` parameters (``wip_description.robot_model``); the viewer is its
robot_state_publisher: ``/tf_static`` the fixed joint (base_link -> chassis), ``/tf`` the
wheel joints from ``/joint_states`` and the body's tilt (chassis -> body) from the estimate
at pose_rate, and in simulation ``map -> truth/base_link`` from the ground truth. Every
frame carries ``viewer.frame_prefix``. odom -> base_link and map -> odom are the ESO
node's (with /odom). The markers and paths are drawn directly in ``map``.

Rates are of message stamps (simulated time in lockstep): a message goes out when an input
arrives at least 1/rate after the previous one (the paths sample their source at the
pose rate) (:class:`~wip_viewer.viewer_core.RateGate`), so
a lockstep bag holds the same viewer messages on every run and a replay needs no timer.
Odometry twist: υ along base_link x, ω about z (the child frame). Covariance: the truth's
is zero (exact); the estimate's holds ``viewer.position_std``² on x and y when set (the GPS
noise, written by ``scripts/run_graph``), very large on z, roll, pitch; else all zero
(unknown, the ROS convention).

Parameters: ``viewer.*`` (:class:`~wip_viewer.viewer_core.ViewerParams`), read-only.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry, Path
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from wip_description.robot_model import RobotModel, urdf
from wip_runtime.composition import IntraProcessNode
from wip_runtime.node_main import run_node
from wip_runtime.qos import lockstep_writer_qos, RELIABLE_QOS, TF_QOS, TF_STATIC_QOS
from wip_runtime.stamps import stamp_to_ns
from wip_runtime.rotations import quaternion_from_euler
from wip_runtime.diagnostics import NodeDiagnostics
from wip_runtime.parameters import RosParams
from wip_msgs.msg import GroundTruth, DriveTorque, ReferenceState, StateEstimate

from wip_runtime import cdr
from .settings import ROBOT_MODEL_GROUPS
from .viewer_core import (cdr_stamp_ns, PathBuffer, planar_pose_covariance, predicted_track,
                          quaternion_yaw_pitch, RateGate, vehicle_geometry, VIEWER_TOPICS,
                          ViewerParams)

#: Topics it reads.
VIEWER_INPUTS = ('/wip/state_estimate', '/wip/ground_truth', '/wip/reference',
                 '/wip/drive_torque')

_INPUT_QOS = QoSProfile(depth=5, history=QoSHistoryPolicy.KEEP_LAST,
                        reliability=QoSReliabilityPolicy.BEST_EFFORT)


_ZERO_COVARIANCE = (0.0,) * 36
_VEHICLE_COLOR = {'truth': (0.2, 0.45, 0.8, 0.9), 'estimate': (0.85, 0.35, 0.2, 0.9)}
_WHEEL_COLOR = (0.15, 0.15, 0.15, 1.0)
_TRACK_COLOR, _STICKS_COLOR = (0.1, 0.7, 0.3, 0.9), (0.1, 0.7, 0.3, 0.5)
_NO_ROTATION = (0.0, 0.0, 0.0, 1.0)
_ORIGIN = (0.0, 0.0, 0.0)


class ViewerNode(IntraProcessNode):
    """See the module docstring."""

    def __init__(self, keep_unacknowledged: bool = False, **kwargs) -> None:
        super().__init__('viewer', **kwargs)
        # Composed with the simulation (``ros2 run wip_sim simulation --with-viewer``), its
        # inputs come from the intra-process bus as message objects; alone, raw from DDS.
        self.init_intra_process(True)
        # Composed with a simulation (keep_unacknowledged), a recorded run: its writers keep
        # what the recorder has not acknowledged, as the lockstep nodes' do. With a history
        # of 10 a recorder descheduled for some 30 ms of wall time lost a pose (49 of 50).
        self._output_qos = (lockstep_writer_qos(RELIABLE_QOS) if keep_unacknowledged
                            else RELIABLE_QOS)
        self._tf_qos = lockstep_writer_qos(TF_QOS) if keep_unacknowledged else TF_QOS
        self.config: ViewerParams = RosParams(self, 'viewer', ViewerParams).config
        c = self.config
        # No input ages: the node runs on the wall clock also in lockstep (no /clock
        # subscription, one callback less per tick); received counts are reported instead.
        self.diagnostics = NodeDiagnostics(self, 'viewer topics', ())
        self.create_timer(1.0, self._report_counts)
        self.publishers_ = {topic: self.create_publisher(
            {'nav_msgs/msg/Odometry': Odometry,
             'visualization_msgs/msg/MarkerArray': MarkerArray,
             'nav_msgs/msg/Path': Path}[kind], topic.lstrip('/'), self._output_qos)
            for topic, kind in VIEWER_TOPICS.items()}  # relative: under the vehicle's namespace
        self.estimate_gate, self.truth_gate = RateGate(c.pose_rate), RateGate(c.pose_rate)
        self.reference_gate = RateGate(c.pose_rate)
        self.path_gate, self.prediction_gate = RateGate(c.path_rate), RateGate(c.pose_rate)
        self.paths = {name: PathBuffer(c.path_resolution, c.max_path_points)
                      for name in ('reference', 'travelled', 'estimated')}
        # Each point's serialized PoseStamped, encoded once: a Path message holds the whole
        # path, and serializing every pose again at each message grew with the run.
        self.path_poses: dict[str, list[bytes]] = {name: [] for name in self.paths}
        self.path_poses_dropped = dict.fromkeys(self.paths, 0)
        self.estimate_covariance = planar_pose_covariance(c.position_std)
        self.truth_covariance = _ZERO_COVARIANCE
        self.last_estimate: StateEstimate | None = None
        self.have_truth = False
        for msg_type, topic, name, gate, handler in (
                (StateEstimate, 'wip/state_estimate', 'state_estimate', self.estimate_gate,
                 self._on_estimate),
                (GroundTruth, 'wip/ground_truth', 'ground_truth', self.truth_gate,
                 self._on_truth),
                (ReferenceState, 'wip/reference', 'reference', self.reference_gate,
                 self._on_reference)):
            subscription = self.create_subscription(
                msg_type, topic, self._gated(msg_type, name, gate, handler), _INPUT_QOS,
                raw=True)
            self.add_intra_subscription(msg_type, subscription,
                                        self._gated_local(name, gate, handler))
        subscription = self.create_subscription(DriveTorque, 'wip/drive_torque', self._on_mpc,
                                                 _INPUT_QOS)
        self.add_intra_subscription(DriveTorque, subscription, self._on_mpc)
        self.robot: RobotModel | None = None
        if c.robot_model:
            self._init_robot_model()
        self.diagnostics.state(DiagnosticStatus.OK, 'waiting for inputs')

    def _init_robot_model(self) -> None:
        """robot_description, the fixed joints on /tf_static, the joints' inputs."""
        model, joints, signs, mounting = (RosParams(self, prefix, cls).config
                                          for prefix, cls in ROBOT_MODEL_GROUPS)
        self.robot = RobotModel(model, joints.left_joint, joints.right_joint,
                                signs.left_wheel_sign, signs.right_wheel_sign,
                                mounting.encoders_relative_to_body)
        self.publishers_['/tf'] = self.create_publisher(TFMessage, '/tf', self._tf_qos)
        static = self.create_publisher(TFMessage, '/tf_static', TF_STATIC_QOS)
        description = self.create_publisher(String, 'robot_description', TF_STATIC_QOS)
        description.publish(String(data=urdf(self.robot)))
        stamp_ns = self.get_clock().now().nanoseconds
        static.publish(cdr.tf_message([self._joint_transform(stamp_ns, joint)
                                       for joint in self.robot.joints if joint.kind == 'fixed']))
        self.wheel_joints = (self.robot.joint(joints.left_joint),
                             self.robot.joint(joints.right_joint))
        self.body_joint = self.robot.joint('body_pitch_joint')
        self.truth_frame = self.config.frame_prefix + 'truth/base_link'
        gate = RateGate(self.config.pose_rate)
        subscription = self.create_subscription(
            JointState, 'joint_states',
            self._gated(JointState, 'joint_states', gate, self._on_joint_states),
            _INPUT_QOS, raw=True)
        self.add_intra_subscription(JointState, subscription, self._gated_local(
            'joint_states', gate, self._on_joint_states))

    def _joint_transform(self, stamp_ns: int, joint, position: float = 0.0) -> tuple:
        prefix = self.config.frame_prefix
        return (stamp_ns, prefix + joint.parent, prefix + joint.child,
                *joint.transform(position))

    # -- helpers ------------------------------------------------------------------------------
    def _report_counts(self) -> None:
        for name, count in self.diagnostics.received.items():
            self.diagnostics.values[f'received {name}'] = str(count)
        self.diagnostics.values['path points'] = ', '.join(
            f'{name} {len(buffer.points)}' for name, buffer in self.paths.items())

    def _send(self, topic: str, data: bytes) -> None:
        """Publish a message serialized by :mod:`.cdr`.

        The process's own subscribers (the bus hands them objects) get it decoded.
        """
        publisher = self.publishers_[topic]
        if getattr(publisher, 'local_subscriptions', 0):
            data = deserialize_message(data, publisher.msg_type)
        publisher.publish(data)

    def _publish_odometry(self, topic: str, stamp_ns: int, x: float, y: float, phi: float,
                          v: float, omega: float, covariance) -> None:
        # As conversions.odometry_to_msg: pose in frame_id, twist in the child frame.
        _, _, qz, qw = quaternion_from_euler(0.0, 0.0, float(phi))
        c = self.config
        self._send(topic, cdr.odometry(
            stamp_ns, c.frame_id, c.child_frame_id, (float(x), float(y), 0.0),
            (0.0, 0.0, qz, qw), covariance, (float(v), 0.0, 0.0), (0.0, 0.0, float(omega)),
            _ZERO_COVARIANCE))

    def _publish_paths(self, stamp_ns: int) -> None:
        if not self.path_gate.ready(stamp_ns):
            return
        frame_id = self.config.frame_id
        for name, buffer in self.paths.items():
            if not buffer.changed:
                continue
            buffer.changed = False
            poses = self.path_poses[name]
            gone = buffer.dropped - self.path_poses_dropped[name]
            if gone:
                del poses[:gone]
                self.path_poses_dropped[name] = buffer.dropped
            for point_ns, x, y, yaw in buffer.points[len(poses):]:
                poses.append(cdr.pose_stamped(point_ns, frame_id, (x, y, 0.0),
                                              quaternion_yaw_pitch(yaw, 0.0)))
            first = None
            if buffer.points:
                point_ns, x, y, yaw = buffer.points[0]
                first = (point_ns, frame_id, (x, y, 0.0), quaternion_yaw_pitch(yaw, 0.0))
            self._send(f'/wip/path/{name}',
                       cdr.path(stamp_ns, frame_id, first, poses[1:]))

    def _publish_vehicle(self, stamp_ns: int, x: float, y: float, phi: float, theta: float,
                         source: str) -> None:
        g = vehicle_geometry(x, y, phi, theta, self.config)
        frame_id = self.config.frame_id
        w = cdr.CdrWriter()
        w.u32(3)
        cdr.marker(w, stamp_ns, frame_id, 'vehicle', 0, Marker.CUBE, Marker.ADD,
                   g.body_center, g.body_orientation, g.body_size, _VEHICLE_COLOR[source])
        for index, center in ((1, g.left_wheel), (2, g.right_wheel)):
            cdr.marker(w, stamp_ns, frame_id, 'vehicle', index, Marker.CYLINDER, Marker.ADD,
                       center, g.wheel_orientation, g.wheel_size, _WHEEL_COLOR)
        self._send('/wip/markers/vehicle', w.message())

    # -- callbacks ------------------------------------------------------------------------------
    def _gated(self, msg_type, name: str, gate: RateGate, handler):
        """Raw-subscription callback: count, read the stamp, decode only past the gate."""
        def callback(data: bytes) -> None:
            try:
                stamp_ns = cdr_stamp_ns(data)
            except ValueError as err:
                self.diagnostics.drop(name, 'invalid', str(err))
                return
            self._through_gate(name, gate, handler, stamp_ns,
                               lambda: deserialize_message(data, msg_type))
        return callback

    def _gated_local(self, name: str, gate: RateGate, handler):
        """Intra-process callback: the message object itself, nothing to decode."""
        def callback(msg) -> None:
            self._through_gate(name, gate, handler, stamp_to_ns(msg.header.stamp),
                               lambda: msg)
        return callback

    def _through_gate(self, name: str, gate: RateGate, handler, stamp_ns: int,
                      message) -> None:
        """Count an input; past the gate, hand ``message()`` to ``handler`` (timed)."""
        self.diagnostics.input(name, stamp_ns)
        if gate.ready(stamp_ns):
            started = time.perf_counter()
            handler(message(), stamp_ns)
            self.diagnostics.output(stamp_ns, time.perf_counter() - started)

    def _on_estimate(self, msg: StateEstimate, stamp_ns: int) -> None:
        self.last_estimate = msg
        self.paths['estimated'].add(stamp_ns, msg.x, msg.y, msg.phi)
        self._publish_odometry('/wip/odom/estimate', stamp_ns, msg.x, msg.y, msg.phi, msg.v,
                               msg.omega, self.estimate_covariance)
        if not self.have_truth:
            self._publish_vehicle(stamp_ns, msg.x, msg.y, msg.phi, msg.theta, 'estimate')
        if self.robot is not None:
            self._send('/tf', cdr.tf_message([
                self._joint_transform(stamp_ns, self.body_joint, float(msg.theta))]))
        self._publish_paths(stamp_ns)

    def _on_truth(self, msg: GroundTruth, stamp_ns: int) -> None:
        self.have_truth = True
        self.paths['travelled'].add(stamp_ns, msg.x, msg.y, msg.phi)
        self._publish_odometry('/wip/odom/truth', stamp_ns, msg.x, msg.y, msg.phi, msg.v,
                               msg.omega, self.truth_covariance)
        self._publish_vehicle(stamp_ns, msg.x, msg.y, msg.phi, msg.theta, 'truth')
        if self.robot is not None:
            self._send('/tf', cdr.tf_message([(
                stamp_ns, self.config.frame_id, self.truth_frame,
                (float(msg.x), float(msg.y), 0.0), quaternion_yaw_pitch(float(msg.phi), 0.0))]))
        self._publish_paths(stamp_ns)

    def _on_joint_states(self, msg: JointState, stamp_ns: int) -> None:
        positions = dict(zip(msg.name, msg.position))
        transforms = []
        for joint in self.wheel_joints:
            position = positions.get(joint.name)
            if position is None or not math.isfinite(position):
                self.diagnostics.drop('joint_states', 'invalid',
                                      f'{joint.name!r}: no finite position')
                return
            transforms.append(self._joint_transform(stamp_ns, joint, float(position)))
        self._send('/tf', cdr.tf_message(transforms))

    def _on_reference(self, msg: ReferenceState, stamp_ns: int) -> None:
        self.paths['reference'].add(stamp_ns, msg.x, msg.y, msg.phi)
        self._publish_paths(stamp_ns)

    def _on_mpc(self, msg: DriveTorque) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('drive_torque', stamp_ns)
        if not len(msg.predicted_v):
            # No plan (a tick of the MPC's re-solve grid at which it held its torque, or an
            # idle answer): the last prediction drawn stays.
            return
        # The prediction starts at the latest decoded estimate (at most 1/pose_rate old).
        estimate = self.last_estimate
        if estimate is None or not self.prediction_gate.ready(stamp_ns):
            return
        c = self.config
        axle, top = predicted_track(estimate.x, estimate.y, estimate.phi, estimate.omega,
                                    msg.predicted_v, msg.predicted_theta,
                                    msg.sampling_period, c.com_height, c.wheel_radius)
        w = cdr.CdrWriter()
        w.u32(2)
        cdr.marker(w, stamp_ns, c.frame_id, 'prediction', 0, Marker.LINE_STRIP, Marker.ADD,
                   _ORIGIN, _NO_ROTATION, (0.02, 0.0, 0.0), _TRACK_COLOR,
                   axle.ravel().tolist())
        # LINE_LIST: one segment per pair of points, axle k then body top k.
        cdr.marker(w, stamp_ns, c.frame_id, 'prediction', 1, Marker.LINE_LIST, Marker.ADD,
                   _ORIGIN, _NO_ROTATION, (0.01, 0.0, 0.0), _STICKS_COLOR,
                   np.stack([axle, top], axis=1).ravel().tolist())
        self._send('/wip/markers/prediction', w.message())


def main(args=None) -> int:
    """Entry point ``viewer`` (``ros2 run wip_viewer viewer``)."""
    return run_node(ViewerNode, 'viewer', args)


if __name__ == '__main__':
    sys.exit(main())
