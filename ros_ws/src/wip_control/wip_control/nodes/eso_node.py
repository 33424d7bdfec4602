"""ESO node: the three extended state observers and the planar position.

The observers are those of eqs. (4), (8) in [1]_. The node computes them and the position
from standard sensor topics.

Topics
------
Subscribes ``/joint_states`` (sensor_msgs/JointState: wheel joint angles, by name, times
their signs), ``/imu/data`` (sensor_msgs/Imu: orientation, corrected for the IMU's
mounting -> pitch θ, yaw ϕ; with ``eso.estimator: gyro`` also angular_velocity, the gyro,
rotated into base_link -> θ̇, ϕ̇), ``/gps/fix`` (sensor_msgs/NavSatFix -> map-frame (x, y)
about the datum) or, with ``position_source: odometry``, ``/odom`` (nav_msgs/Odometry ->
(x, y) of its pose), ``/wip/wheel_torques`` (wip_msgs/WheelTorques: the torques applied,
the ESO's input).
Publishes ``/wip/state_estimate`` (wip_msgs/StateEstimate) stamped with the sensor sample
time, and ``/diagnostics``.

What it does per sample
-----------------------
It drives ``core.state_estimation.StateEstimator`` (the in-process runner and
``scripts/rerun`` drive the same object): yaw unwrapping, wheel odometry, the observer
(``core.eso.WipStateObserver``) with the torques τυ = τl + τr, τω = τr − τl applied over
the previous period (zero before any arrived), and the planar position, which dead-reckons
and takes the sample's GPS fix. The observer starts at the first complete measurement set
from the measured positions; the position at the first fix, dead-reckoning from (0, 0)
until then, which /diagnostics says (docs/control-loop.md).

Synchronisation
---------------
lockstep: the set for t_k is joint_states(t_k) + imu(t_k) [+ gps(t_k) at GPS ticks,
every round(gps_period / eso.sample_period)-th sample from t = 0]; in addition the wheel
torques stamped t_{k−1} (the previous sample processed) must have arrived, so the
result never depends on which of the plant's and the mixer's messages DDS delivers
first. A GPS fix off the GPS ticks is dropped (its use would depend on arrival order); a
NavSatFix without a fix (status NO_FIX) at a GPS tick completes the set without a fix
(a dropout).
realtime: update when both an IMU and an encoder message newer than at the last update
have arrived; the latest torques and the latest unused GPS fix are used. The base's
sensor topics are subscribed best effort (sensor-data QoS, ``common.SENSOR_QOS``), which
matches reliable and best-effort publishers; lockstep uses reliable. The observer's
time advances by whole sample periods: the time between two samples (their stamps) is
rounded to a multiple n >= 1 of ``eso.sample_period`` (a missed sample counts as two
periods). Decision: the exact discretisation of the observer (``core/eso.py``) is
precomputed for the nominal period, and any other period costs a matrix exponential per
channel (measured: about 1.5 ms per update on the project's machine, which saturated one
core at 200 Hz); the stamps' jitter, typically tens of microseconds of the base's timer,
is not worth it.

Position checks (``core/position.py``): each fix is gated against the odometry's
prediction, and a run of rejections longer than ``position.max_rejection_time`` is a
position fault; a first GPS fix farther than ``max_datum_distance`` from the datum is
refused for good (a datum copied from elsewhere). Either sets the estimate's
``position_status`` to FAULT, which the safety layer turns into zero torque, and the
cause goes to /diagnostics as an ERROR that names what to fix.

Odometry out: nav_msgs/Odometry of the estimate on ``/odom`` (frame ``odometry_frame_id``
'odom', child ``odometry_child_frame_id`` 'base_link', REP 105: pose x̂, ŷ, ϕ̂; twist in
base_link: linear.x = υ̂, angular.z = ω̂; diagonal covariance from ``odometry_*_std``,
1e6 on the axes a planar estimate does not observe), every ``odometry_decimation``-th
estimate once the position is valid (status TRACKING or DEAD_RECKONING: no /odom from
a dead-reckoned start before the first fix), with ``odometry_output`` 'realtime' (the
default: real time and hardware mode, not lockstep), 'always' or 'off'; never with
``position_source`` 'odometry', where ``/odom`` is the input (docs/driving.md). With it,
``odometry_tf``: the same pose as odom -> base_link on ``/tf``; ``map_to_odom_tf``: the
identity map -> odom on ``/tf_static``.

Bad input: a malformed or non-finite message (missing joint, wrong sizes, NaN, no fix,
no orientation, non-unit quaternion) is dropped, counted and reported on /diagnostics;
callbacks never raise. Finite but huge input that overflows the observer (e.g. a wheel
angle of 1e300 rad) gives no estimate: it is dropped and the estimator restarts from the
next measurement set, so one bad sample cannot poison it for good.

Real base (see ``hardware_inputs.py`` for the conventions)
-----------------------------------------------------------
``left_wheel_sign``, ``right_wheel_sign`` (1 or −1, integers): −1 for a joint whose
positive direction rolls the robot backwards; ``imu_mounting_rpy`` [rad]: the rotation
from base_link to the IMU frame (roll, pitch, yaw about base_link's fixed axes, as a URDF
joint's rpy); ``position_source``: 'gps' (NavSatFix about ``datum.*``), 'odometry'
(nav_msgs/Odometry on ``/odom``, real time only: its (x, y) is used like a fix, every
message once) or 'wheels' (no position input: dead reckoning from (0, 0)); wheel radius
and track width: ``model.wheel_radius``, ``model.track_width``.
The defaults (1, 1, [0, 0, 0], 'gps') are the simulator's conventions and change nothing
(no arithmetic is done on the inputs with them).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import sys
import time

from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix
from tf2_msgs.msg import TFMessage
from wip_msgs.msg import StateEstimate as StateEstimateMsg, WheelTorques

from wip_runtime.config import ParamError
from ..core.eso import EsoParams
from wip_description.params import ModelParams
from ..core.position import PositionParams
from ..core.safety import SafetyDecision
from ..core.state_estimation import EstimatorOverflow, PoseEstimate, StateEstimator
from .common import ControllerNode
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS, SENSOR_QOS, TF_QOS, TF_STATIC_QOS
from wip_runtime.stamps import stamp_to_ns
from .conversions import (applied_torques, gps_has_fix, gps_local_position,
                          identity_transform, odometry_to_msg, pose_to_msg,
                          transform_from_odometry, wheel_torques_from_msg)
from wip_runtime.messages import decode_serialized, prepare_decoder
from ..core.position import DEAD_RECKONING, TRACKING
from wip_runtime.diagnostics import ERROR, OK, WARN
from .hardware_inputs import (body_attitude, mounting_inverse, odometry_position,
                              signed_wheel_angles, use_compiled_attitude)
from wip_runtime.parameters import RosParams
from .settings import EsoNodeParams, WheelTorqueLimit
from wip_description.wiring import DatumParams, ImuMounting, WheelJoints, WheelSigns
from wip_runtime.sync import decimation, ExactTimeSync, is_decimated_tick, LatestSync

_SENSORS = ('joint_states', 'imu', 'gps')
#: Torque messages kept by stamp in lockstep (only the previous period's is needed).
_MAX_TORQUE_STAMPS = 64
#: How /diagnostics names each position source.
_SOURCE_NAMES = {'gps': 'GPS', 'odometry': 'odometry', 'wheels': 'wheels'}


#: Variance [m², rad², ...] of the axes a planar estimate does not observe (z, roll,
#: pitch; lateral and vertical speed, roll and pitch rates): very large, as REP 105 asks
#: of an unknown axis that a consumer (robot_localization) must not fuse.
_UNOBSERVED = 1e6


def _diagonal(values) -> list[float]:
    """Row-major 6x6 matrix with ``values`` on the diagonal."""
    matrix = [0.0] * 36
    for i, value in enumerate(values):
        matrix[7 * i] = float(value)
    return matrix


class EsoNode(ControllerNode):
    """See the module docstring. Parameters: ``NODES['eso']`` of nodes/settings.py."""

    def __init__(self, **kwargs) -> None:
        super().__init__('eso', 'extended state observer', (*_SENSORS, 'wheel_torques'),
                         **kwargs)
        settings = self._read_parameters()
        self.estimator = StateEstimator(self.model, self.eso_config, self.position_config,
                                        encoders_relative_to_body=self.relative_to_body,
                                        dead_reckoning=self.position_source == 'wheels',
                                        max_drive_torque=2.0 * self.max_wheel_torque)
        self._use_compiled_kernels()
        self.reported_fault = ''
        self.last_update_ns: int | None = None
        # Real time: the observer's sample clock (see _observer_time).
        self.sample_index: int | None = None
        self.sample_origin = self.last_sample_time = 0.0
        self.last_gps_ns: int | None = None
        self.torques_by_stamp: dict[int, tuple[float, float]] = {}
        self.latest_torques = (0.0, 0.0)
        if self.lockstep:
            self.sync = ExactTimeSync(self.sensors, self._update, required=self._required,
                                      gate=self._torques_ready)
        else:
            # Encoder and IMU samples of one set at most one sample period apart (see
            # LatestSync.max_skew_ns: a burst after a stall must not pair old with new).
            self.sync = LatestSync(self.sensors, self._update, triggers=('joint_states', 'imu'),
                                   required=('joint_states', 'imu'),
                                   max_skew_ns=round(self.sample_period * 1e9))
        self._init_topics()
        self._init_odometry(settings)
        self.diagnostics.reporters.append(self._report_values)
        self.diagnostics.state(OK, 'waiting for the first measurement set')

    def _read_parameters(self) -> EsoNodeParams:
        """Declare and read the parameters: observer, position, model, wiring, datum."""
        self.eso_config = RosParams(self, 'eso', EsoParams).config
        self.position_config = RosParams(self, 'position', PositionParams).config
        self.model = RosParams(self, 'model', ModelParams).config
        # The obstacle monitor's h_max and holding lean are those of the mixer's limit.
        self.max_wheel_torque = RosParams(self, 'mixer',
                                          WheelTorqueLimit).config.max_wheel_torque
        settings = RosParams(self, '', EsoNodeParams).config
        joints = RosParams(self, '', WheelJoints).config
        signs = RosParams(self, '', WheelSigns).config
        mounting = RosParams(self, '', ImuMounting).config
        self.relative_to_body = settings.encoders_relative_to_body
        gps_period = settings.gps_period
        self.left_joint, self.right_joint = joints.left_joint, joints.right_joint
        self.left_sign = float(signs.left_wheel_sign)
        self.right_sign = float(signs.right_wheel_sign)
        self.imu_inverse_mount = mounting_inverse(mounting.imu_mounting_rpy)
        self.position_source = settings.position_source
        if self.position_source == 'odometry' and self.lockstep:
            raise ParamError("position_source: 'odometry' needs clock_mode realtime (the "
                              'lockstep sets wait for GPS fixes)')
        datum = RosParams(self, 'datum', DatumParams).config
        self.datum = (datum.latitude, datum.longitude, datum.altitude)
        self.max_datum_distance = settings.max_datum_distance
        self.frame_id = settings.frame_id
        self.sample_period = self.eso_config.sample_period
        self.gps_every = decimation(gps_period, self.sample_period)
        # 'wheels': no position input at all (the sets are encoders and IMU).
        self.sensors = _SENSORS if self.position_source != 'wheels' else _SENSORS[:2]
        return settings

    def _init_topics(self) -> None:
        """Create the estimate's publisher and the sensor and torque subscriptions."""
        # The estimator's PoseEstimate goes as it is to this process's controllers.
        self.publisher = self.create_publisher(StateEstimateMsg, 'wip/state_estimate',
                                               RELIABLE_QOS, direct_type=PoseEstimate)
        # The base's sensors: reliable in lockstep (every sample counts), sensor-data QoS
        # in real time (see common.SENSOR_QOS).
        sensor_qos = RELIABLE_QOS if self.lockstep else SENSOR_QOS
        # Taken serialized and decoded here: half the cost of receiving them as messages.
        prepare_decoder('sensor_msgs/msg/JointState', 'sensor_msgs/msg/Imu')
        self.subscribe(JointState, 'joint_states', 'joint_states', self._on_joint_states,
                       sensor_qos, raw=True)
        self.subscribe(Imu, 'imu/data', 'imu', self._on_imu, sensor_qos, raw=True)
        if self.position_source == 'odometry':
            # The position input keeps its slot name 'gps' in the sync; diagnostics say odom.
            self.diagnostics.inputs = ('joint_states', 'imu', 'odom', 'wheel_torques')
            self.diagnostics.last_stamp = {n: None for n in self.diagnostics.inputs}
            self.subscribe(Odometry, 'odom', 'odom', self._on_odometry, sensor_qos)
        elif self.position_source == 'wheels':
            self.diagnostics.inputs = ('joint_states', 'imu', 'wheel_torques')
            self.diagnostics.last_stamp = {n: None for n in self.diagnostics.inputs}
        else:
            self.subscribe(NavSatFix, 'gps/fix', 'gps', self._on_gps, sensor_qos)
        # The mixer's SafetyDecision as it is, from a mixer of the same process.
        self.subscribe_input(WheelTorques, 'wip/wheel_torques', 'wheel_torques',
                             wheel_torques_from_msg, check=applied_torques,
                             value_type=SafetyDecision, on_value=self._on_torques)

    def _init_odometry(self, settings: EsoNodeParams) -> None:
        """Set up the /odom output (nav_msgs/Odometry of the estimate, REP 105)."""
        wanted = (settings.odometry_output == 'always'
                  or (settings.odometry_output == 'realtime' and not self.lockstep))
        self.odometry_publisher = None
        self.odometry_count = 0
        if wanted and self.position_source == 'odometry':
            # /odom is this node's position input then; publishing it would feed it back.
            self.get_logger().warning("odometry_output: no /odom output with "
                                      "position_source 'odometry' (it is the input)")
            wanted = False
        self.diagnostics.values['/odom output'] = (
            f'every {settings.odometry_decimation} estimate(s)' if wanted else 'off')
        if not wanted:
            return
        self.odometry_settings = settings
        self.odometry_every = settings.odometry_decimation
        pos, yaw = settings.odometry_position_std ** 2, settings.odometry_heading_std ** 2
        # x, y, yaw as stated; z, roll, pitch are not estimated (a planar base): very large.
        self.odometry_pose_covariance = _diagonal((pos, pos, _UNOBSERVED, _UNOBSERVED,
                                                   _UNOBSERVED, yaw))
        self.odometry_twist_covariance = _diagonal((
            settings.odometry_speed_std ** 2, _UNOBSERVED, _UNOBSERVED, _UNOBSERVED,
            _UNOBSERVED, settings.odometry_yaw_rate_std ** 2))
        self.odometry_publisher = self.create_publisher(Odometry, 'odom', RELIABLE_QOS)
        # /tf and /tf_static are global (frames carry the robot's prefix): REP 105's
        # map -> odom -> base_link, as diff_drive_controller and a localisation node give it.
        self.odometry_tf_publisher = (self.create_publisher(TFMessage, '/tf', TF_QOS)
                                      if settings.odometry_tf else None)
        if settings.map_to_odom_tf:
            self.map_to_odom_publisher = self.create_publisher(TFMessage, '/tf_static',
                                                               TF_STATIC_QOS)
            self.map_to_odom_publisher.publish(TFMessage(transforms=[identity_transform(
                self.get_clock().now().nanoseconds, settings.frame_id,
                settings.odometry_frame_id)]))

    def _publish_odometry(self, stamp: int, pose) -> None:
        self.odometry_count += 1
        if (self.odometry_count - 1) % self.odometry_every:
            return
        tf = self.odometry_tf_publisher
        if not (self.odometry_publisher.reaches_anyone()
                or (tf is not None and tf.reaches_anyone())):
            return   # composed, and no one listens: no message to build
        settings, est = self.odometry_settings, pose.estimate
        msg = odometry_to_msg(
            stamp, settings.odometry_frame_id, settings.odometry_child_frame_id, pose.x,
            pose.y, est.phi, est.v, est.omega, self.odometry_pose_covariance,
            self.odometry_twist_covariance)
        self.odometry_publisher.publish(msg)
        if tf is not None:
            tf.publish(TFMessage(transforms=[transform_from_odometry(msg)]))

    # -- lockstep set definition ------------------------------------------------------------
    def _is_gps_tick(self, stamp_ns: int) -> bool:
        return is_decimated_tick(stamp_ns, self.sample_period, self.gps_every)

    def _required(self, stamp_ns: int) -> tuple[str, ...]:
        return self.sensors if self._is_gps_tick(stamp_ns) else ('joint_states', 'imu')

    def _torques_ready(self, _stamp_ns: int) -> bool:
        return self.last_update_ns is None or self.last_update_ns in self.torques_by_stamp

    # -- subscriptions -----------------------------------------------------------------------
    def _on_joint_states(self, msg: JointState | bytes) -> None:
        msg = decode_serialized(msg, 'sensor_msgs/msg/JointState')
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('joint_states', stamp)
        angles = signed_wheel_angles(msg, self.left_joint, self.right_joint, self.left_sign,
                                     self.right_sign)
        self.feed('joint_states', stamp, angles)

    def _use_compiled_kernels(self) -> None:
        """Read the IMU's attitude, take the gyro estimator's steady samples: compiled."""
        warning = use_compiled_attitude()
        if warning:
            self.get_logger().warning(f'attitude interpreted: {warning}')
        if self.eso_config.estimator != 'gyro':
            return
        warning = self.estimator.use_compiled()
        if warning:
            self.get_logger().warning(f'estimator interpreted: {warning}')
        else:
            self.get_logger().info("the estimator's steady sample: compiled")

    def _on_imu(self, msg: Imu | bytes) -> None:
        msg = decode_serialized(msg, 'sensor_msgs/msg/Imu')
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('imu', stamp)
        # The gyro estimator needs the angular velocity (a message without it is dropped).
        pitch, yaw, rates = body_attitude(msg, self.imu_inverse_mount,
                                          self.eso_config.estimator == 'gyro')
        self.feed('imu', stamp, (pitch, yaw, rates))

    def _on_gps(self, msg: NavSatFix) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('gps', stamp)
        if self.lockstep and not gps_has_fix(msg) and self._is_gps_tick(stamp):
            # A dropout at a GPS tick: the set for this sample completes without a fix
            # (the runner skips the fix there too).
            self.feed('gps', stamp, None)
            return
        position = gps_local_position(msg, *self.datum)
        if not self.estimator.has_fix and not self._near_datum(msg, position):
            if self.lockstep and self._is_gps_tick(stamp):
                self.feed('gps', stamp, None)   # the set completes without the fix
            return
        if self.lockstep and not self._is_gps_tick(stamp):
            self.diagnostics.drop('gps', 'off the GPS ticks',
                                  f'stamp {stamp} ns is not a multiple of gps_period')
            return
        self.feed('gps', stamp, position)

    def _near_datum(self, msg: NavSatFix, position: tuple[float, float]) -> bool:
        """Whether a fix is within ``max_datum_distance`` of the datum; else refuse the source.

        Only the fixes before the first accepted one are checked: after it, each fix is
        gated against the odometry (core/position.py).
        """
        distance = (position[0] ** 2 + position[1] ** 2) ** 0.5
        if distance <= self.max_datum_distance:
            return True
        if not self.estimator.refused:
            self.estimator.refused = (
                f'GPS fix at latitude {msg.latitude:.7f}, longitude {msg.longitude:.7f} is '
                f'{distance / 1e3:.4g} km from the datum ({self.datum[0]:.7f}, '
                f'{self.datum[1]:.7f}) > max_datum_distance {self.max_datum_distance:g} m: '
                'set datum.latitude/datum.longitude to your site (this fix is one) and restart')
        self.diagnostics.drop('gps', 'far from the datum', f'{distance:.4g} m')
        return False

    def _on_odometry(self, msg: Odometry) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('odom', stamp)
        self.feed('gps', stamp, odometry_position(msg))

    def _on_torques(self, stamp: int, torques: tuple[float, float]) -> None:
        if self.lockstep:
            if len(self.torques_by_stamp) >= _MAX_TORQUE_STAMPS:
                del self.torques_by_stamp[min(self.torques_by_stamp)]
            self.torques_by_stamp[stamp] = torques
            self.sync.drain()
        else:
            self.latest_torques = torques

    # -- the update ---------------------------------------------------------------------------
    def _update(self, stamp: int, values) -> None:
        start = time.perf_counter()
        left, right = values['joint_states']
        pitch, yaw, rates = values['imu']
        gps = values.get('gps')
        if self.lockstep:
            torques = (self.torques_by_stamp.get(self.last_update_ns, (0.0, 0.0))
                       if self.last_update_ns is not None else (0.0, 0.0))
            for old in [s for s in self.torques_by_stamp
                        if self.last_update_ns is not None and s < self.last_update_ns]:
                del self.torques_by_stamp[old]
        else:
            torques = self.latest_torques
            gps_stamp = self.sync.stamps.get('gps')
            if gps is not None and gps_stamp == self.last_gps_ns:
                gps = None  # Each fix is used once.
            self.last_gps_ns = gps_stamp
        t = self._observer_time(stamp)
        tau_left, tau_right = torques
        # Steps 1-3 of the loop (core/state_estimation.py); on an overflow it raises and
        # restarts from the next measurement set (the callback reports the drop), the
        # sample counting as processed.
        try:
            pose = self.estimator.update(t, left, right, pitch, yaw, tau_left, tau_right,
                                         rates, gps)
        except EstimatorOverflow:
            self.last_update_ns = stamp
            raise
        self.last_update_ns = stamp
        self.publisher.publish_value(stamp, pose, self._pose_to_msg)
        if self.odometry_publisher is not None and pose.position_status in (
                TRACKING, DEAD_RECKONING):
            self._publish_odometry(stamp, pose)
        self.diagnostics.output(stamp, time.perf_counter() - start)
        self._report(pose.settled)

    def _pose_to_msg(self, pose: PoseEstimate, stamp: int) -> StateEstimateMsg:
        return pose_to_msg(pose, stamp, self.frame_id)

    def _observer_time(self, stamp: int) -> float:
        """Time [s] of the sample for the observer.

        The stamp's in lockstep; in real time the previous sample's plus a whole number of periods
        (see the module docstring).
        """
        t = self.time_base.seconds(stamp)
        if self.lockstep:
            return t
        if not self.estimator.started or self.sample_index is None:
            self.sample_index, self.sample_origin = 0, t
        else:
            periods = round((t - self.last_sample_time) / self.sample_period)
            self.sample_index += max(1, periods)
        self.last_sample_time = t
        return self.sample_origin + self.sample_index * self.sample_period

    def _report(self, settled: bool) -> None:
        diag = self.diagnostics
        source = _SOURCE_NAMES[self.position_source]
        fault = self.estimator.position_fault
        if fault:
            diag.state(ERROR, f'position source refused: {fault}')
            if fault != self.reported_fault:
                self.reported_fault = fault
                self.get_logger().error(f'position source refused: {fault}')
        elif self.position_source == 'wheels':
            diag.state(OK if settled else WARN, 'dead reckoning (position_source wheels): '
                       'x, y are wheel odometry along the IMU yaw from (0, 0)'
                       + ('' if settled else '; epsilon ramp still running'))
        elif not self.estimator.has_fix:
            diag.state(WARN, f'no {source} position yet: waiting for the first fix (no '
                       'torque until then; indoors without GPS use position_source: wheels)')
        elif not settled:
            diag.state(OK, 'estimating; epsilon ramp still running (not settled)')
        else:
            diag.state(OK, 'estimating')
        obstacle = self.estimator.obstacle_state
        if obstacle is not None and obstacle.blocked and not fault:
            diag.state(WARN, f'stopped by an obstacle: {obstacle.reason}; the trajectory '
                       'generator backs off and holds: clear the obstacle or plan around it')

    def _report_values(self) -> None:
        """Report the position source's and the synchronisation's counters, once per status."""
        values = self.diagnostics.values
        self._report_ground(values)
        position = self.estimator.position
        if self.position_source != 'wheels':
            source = _SOURCE_NAMES[self.position_source]
            values[f'{source} fixes accepted'] = str(position.accepted_fixes)
            values[f'{source} fixes rejected'] = str(position.rejected_fixes)
            values['last fix innovation [m]'] = f'{position.last_innovation:.3f}'
        if self.lockstep:
            values['pending sets'] = str(self.sync.pending)
            values['sets superseded/evicted'] = (
                f'{self.sync.dropped["superseded"]}/{self.sync.dropped["evicted"]}')

    def _report_ground(self, values: dict) -> None:
        """Wheel slip and an obstacle that blocks the wheels (core/slip.py, core/obstacle.py)."""
        estimator = self.estimator
        slip = estimator.slip
        if slip is not None:
            wheels = [side for side, on in zip(('left', 'right'), slip.slipping_wheels) if on]
            values['wheel slip'] = (f"{' and '.join(wheels) or 'none'}; {slip.events} slips, "
                                    f'{slip.offset:.3f} m spun away (left out of x_v)')
        obstacle = estimator.obstacle_state
        if obstacle is not None:
            values['obstacle'] = obstacle.reason or 'none'


def main(args=None) -> int:
    """Entry point ``eso`` (``ros2 run wip_control eso --ros-args ...``)."""
    return run_node(EsoNode, 'eso', args)


if __name__ == '__main__':
    sys.exit(main())
