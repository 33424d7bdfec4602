"""Messages <-> core values: no control math, only unpacking, packing and validation.

Sign conventions (REP 103): x forward, y left, z up; yaw ϕ about z, counter-clockwise
positive; pitch θ about y, positive leaning forward (a positive rotation about the
left-pointing y axis tips the body's z axis toward +x). Orientation quaternions are
the ZYX (yaw, pitch, roll) Euler composition R = Rz(ϕ) Ry(θ) Rx(roll), as tf2 and
the plant node use ("orientation from roll 0, pitch θ, yaw ϕ").

Every ``*_from_msg`` that reads an external message raises ``InvalidMessage``
(a ValueError) with the reason on malformed or non-finite content; the nodes drop or
neutralise such input and report it on /diagnostics.
"""

from __future__ import annotations

import array
import math
from math import isfinite
import struct
from typing import Sequence

from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from std_msgs.msg import Float64MultiArray
from wip_description.sensors import geodetic_to_local
from wip_msgs.msg import (YawTorque, DriveTorque, ReferenceState as ReferenceStateMsg,
                          StateEstimate as StateEstimateMsg,
                          VelocityCommand as VelocityCommandMsg, WheelTorques)
from wip_runtime import cdr
from wip_runtime.messages import (check_finite_record, check_finite_values, InvalidMessage,
                                  pitch_yaw_from_quaternion, stamped, StampedBuilder)
from wip_runtime.rotations import euler_rates, quaternion_from_euler

from ..core.arc import ArcOutput
from ..core.eso import StateEstimate
from ..core.mpc_plan import HELD_STATUS_TEXT, MpcResult
from ..core.qp import MpcStatus
from ..core.reference_state import ReferenceState
from ..core.safety import SafetyDecision
from ..core.state_estimation import PoseEstimate
from ..core.trajectory_generator import VelocityCommand

_build_reference = StampedBuilder(ReferenceStateMsg, ('x', 'y', 'phi', 'v', 'omega',
                                                      'omega_dot')).build
_build_estimate = StampedBuilder(StateEstimateMsg, (
    'phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3', 'epsilon', 'x', 'y',
    'settled', 'position_status', 'obstacle_blocked')).build
_build_command = StampedBuilder(VelocityCommandMsg, ('v_d', 'omega_d', 'omega_d_dot', 'x_e',
                                                     'y_e', 'phi_e')).build
_build_arc = StampedBuilder(YawTorque, ('tau_omega', 'alpha_hat', 'e_omega')).build
_build_wheel_torques = StampedBuilder(WheelTorques, ('left', 'right', 'tau_v', 'tau_omega',
                                                     'zeroed', 'reason')).build


# --------------------------------------------------------------------- sensors

def wheel_angles(msg: JointState, left_joint: str, right_joint: str) -> tuple[float, float]:
    """(φl, φr) [rad]: the positions of the two wheel joints, found by name."""
    names = list(msg.name)
    positions = msg.position
    try:
        i_left, i_right = names.index(left_joint), names.index(right_joint)
    except ValueError:
        raise InvalidMessage(f'joint_states: needs joints {left_joint!r} and '
                             f'{right_joint!r}, got {names}') from None
    if len(positions) != len(names):
        raise InvalidMessage(f'joint_states: {len(names)} names but {len(positions)} '
                             'positions')
    left, right = float(positions[i_left]), float(positions[i_right])
    if not (isfinite(left) and isfinite(right)):   # the common case without a kwargs call
        check_finite_values('joint_states', left=left, right=right)
    return left, right


def imu_pitch_yaw(msg: Imu) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] from the IMU orientation (REP 145: ENU world frame)."""
    if msg.orientation_covariance[0] == -1.0:
        raise InvalidMessage('imu: no orientation (orientation_covariance[0] == -1)')
    q = msg.orientation
    return pitch_yaw_from_quaternion(q.x, q.y, q.z, q.w)


def euler_rates_from_body(pitch: float, w_body: Sequence[float]) -> tuple[float, float]:
    """(θ̇, ϕ̇) [rad/s] from a message's body angular velocity (base_link axes) at pitch θ.

    :func:`~wip_runtime.rotations.euler_rates` of the three rates, after the reader's
    check: InvalidMessage if one is not finite.
    """
    wx, wy, wz = (float(v) for v in w_body)
    if not (isfinite(wx) and isfinite(wy) and isfinite(wz)):
        check_finite_values('angular_velocity', x=wx, y=wy, z=wz)
    return euler_rates(pitch, wx, wy, wz)


def body_rates_from_euler(pitch: float, pitch_rate: float,
                          yaw_rate: float) -> tuple[float, float, float]:
    """Inverse of :func:`euler_rates_from_body`: (−ϕ̇ sin θ, θ̇, ϕ̇ cos θ) [rad/s]."""
    return (-yaw_rate * math.sin(pitch), pitch_rate, yaw_rate * math.cos(pitch))


def imu_has_rates(msg: Imu) -> bool:
    """Whether the message carries an angular velocity (REP 145: covariance[0] ≠ −1)."""
    return msg.angular_velocity_covariance[0] != -1.0


def gps_has_fix(msg: NavSatFix) -> bool:
    """Whether the NavSatFix holds a fix (status ≥ STATUS_FIX)."""
    return msg.status.status >= NavSatStatus.STATUS_FIX


def gps_local_position(msg: NavSatFix, datum_latitude: float, datum_longitude: float,
                       datum_altitude: float) -> tuple[float, float]:
    """(x east, y north) [m] of a fix in the map frame whose origin is the datum."""
    if msg.status.status < NavSatStatus.STATUS_FIX:
        raise InvalidMessage(f'gps: no fix (status {msg.status.status})')
    lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
    check_finite_values('gps', latitude=lat, longitude=lon, altitude=alt)
    if not -90.0 <= lat <= 90.0:
        raise InvalidMessage(f'gps: latitude {lat!r} outside [-90, 90] deg')
    east, north, _ = geodetic_to_local(lat, lon, alt, datum_latitude, datum_longitude,
                                       datum_altitude)
    return east, north


def wheel_torques_from_msg(msg: WheelTorques) -> tuple[float, float]:
    """(τl, τr) [N m] of an applied command."""
    return checked_torques(msg.left, msg.right)


def applied_torques(decision: SafetyDecision) -> tuple[float, float]:
    """(τl, τr) [N m] of a safety decision handed along the composed chain.

    The same values and the same rule as :func:`wheel_torques_from_msg` of its message
    (:func:`decision_to_msg`).
    """
    return checked_torques(decision.tau_left, decision.tau_right)


def checked_torques(left: float, right: float) -> tuple[float, float]:
    """(τl, τr) as floats if both are finite (InvalidMessage otherwise)."""
    left, right = float(left), float(right)
    if not (isfinite(left) and isfinite(right)):
        check_finite_values('wheel_torques', left=left, right=right)
    return left, right


# --------------------------------------------------------------------- project messages

def odometry_to_msg(stamp_ns: int, frame_id: str, child_frame_id: str, x: float, y: float,
                    phi: float, v: float, omega: float,
                    pose_covariance: Sequence[float] = (0.0,) * 36,
                    twist_covariance: Sequence[float] = (0.0,) * 36) -> Odometry:
    """nav_msgs/Odometry of a planar pose and its twist.

    The pose (x, y [m], heading phi [rad]) is in ``frame_id`` and the twist in
    ``child_frame_id`` (REP 105: υ along x, ω about z). The covariances are row-major 6x6
    (all zero: unknown, the ROS convention). The ESO's /odom and the viewer's Odometry
    topics are built here.
    """
    msg = stamped(Odometry(), stamp_ns, frame_id)
    msg.child_frame_id = child_frame_id
    position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
    position.x, position.y = float(x), float(y)
    _, _, orientation.z, orientation.w = quaternion_from_euler(0.0, 0.0, float(phi))
    msg.pose.covariance = [float(c) for c in pose_covariance]
    msg.twist.twist.linear.x = float(v)
    msg.twist.twist.angular.z = float(omega)
    msg.twist.covariance = [float(c) for c in twist_covariance]
    return msg


def transform_from_odometry(msg: Odometry) -> TransformStamped:
    """Return the pose of an Odometry as the transform header.frame_id -> child_frame_id.

    The same stamp, translation and rotation, copied (what diff_drive_controller's
    ``enable_odom_tf`` publishes beside its odometry).
    """
    transform = TransformStamped(header=msg.header, child_frame_id=msg.child_frame_id)
    position = msg.pose.pose.position
    translation = transform.transform.translation
    translation.x, translation.y, translation.z = position.x, position.y, position.z
    transform.transform.rotation = msg.pose.pose.orientation
    return transform


def identity_transform(stamp_ns: int, parent: str, child: str) -> TransformStamped:
    """Return the transform parent -> child that places child on parent (identity)."""
    return stamped(TransformStamped(child_frame_id=child), stamp_ns, parent)


def reference_to_msg(ref: ReferenceState, stamp_ns: int, frame_id: str) -> ReferenceStateMsg:
    return _build_reference(stamp_ns, frame_id, ref.x, ref.y, ref.phi, ref.v, ref.omega,
                            ref.omega_dot)


def reference_from_msg(msg: ReferenceStateMsg) -> ReferenceState:
    return checked_reference(ReferenceState(msg.x, msg.y, msg.phi, msg.v, msg.omega,
                                            msg.omega_dot))


def checked_reference(ref: ReferenceState) -> ReferenceState:
    """``ref`` if every field is finite (InvalidMessage otherwise), from a message or not."""
    check_finite_record('reference', ref)
    return ref


def estimate_to_msg(est: StateEstimate, x: float, y: float, settled: bool, stamp_ns: int,
                    frame_id: str, position_status: int = 0,
                    obstacle_blocked: bool = False) -> StateEstimateMsg:
    return _build_estimate(stamp_ns, frame_id, est.phi, est.omega, est.f1, est.x_v, est.v,
                           est.f2, est.theta, est.theta_dot, est.f3, est.epsilon, x, y,
                           settled, position_status, obstacle_blocked)


def pose_to_msg(pose: PoseEstimate, stamp_ns: int, frame_id: str) -> StateEstimateMsg:
    """:func:`estimate_to_msg` of the estimator's output."""
    est = pose.estimate
    return _build_estimate(stamp_ns, frame_id, est.phi, est.omega, est.f1, est.x_v, est.v,
                           est.f2, est.theta, est.theta_dot, est.f3, est.epsilon, pose.x,
                           pose.y, pose.settled, pose.position_status, pose.obstacle_blocked)


class _LastConversion:
    """The result of converting the last message object, for the next subscriber of it.

    In a composed process every local subscriber of a topic receives the same message
    object (intra_process.py), and no node modifies a message it receives: the four
    subscribers of a state estimate then convert it once (about 13 us each, at 200 Hz).
    Holding the message keeps its identity from being reused.
    """

    __slots__ = ('msg', 'value', 'checked')

    def __init__(self) -> None:
        self.msg, self.value, self.checked = None, None, False

    def get(self, msg, check: bool):
        """Return the cached conversion of ``msg`` if it is the last and was checked as asked."""
        if msg is self.msg and (self.checked or not check):
            return self.value
        return None

    def keep(self, msg, value, checked: bool):
        self.msg, self.value, self.checked = msg, value, checked
        return value


_last_estimate = _LastConversion()
_last_command = _LastConversion()


def estimate_from_msg(msg: StateEstimateMsg, check: bool = True) -> PoseEstimate:
    cached = _last_estimate.get(msg, check)
    if cached is not None:
        return cached
    est = StateEstimate(msg.phi, msg.omega, msg.f1, msg.x_v, msg.v, msg.f2, msg.theta,
                        msg.theta_dot, msg.f3, msg.epsilon)
    out = PoseEstimate(est, msg.x, msg.y, bool(msg.settled), int(msg.position_status),
                       bool(msg.obstacle_blocked))
    return _last_estimate.keep(msg, checked_estimate(out) if check else out, check)


def checked_estimate(pose: PoseEstimate) -> PoseEstimate:
    """``pose`` if what the controllers read of it is finite (InvalidMessage otherwise).

    The rule for an estimate from a message and for one handed along the composed chain.
    """
    est = pose.estimate
    # ε (the last field) is inf at the very start of the paper's ramp: not an input of any
    # controller. The names of the bad fields are only built when there is one.
    if not (all(map(math.isfinite, est[:-1])) and math.isfinite(pose.x)
            and math.isfinite(pose.y)):
        values = est._asdict()
        del values['epsilon']
        check_finite_values('state_estimate', x=pose.x, y=pose.y, **values)
    return pose


def unchecked_estimate_from_msg(msg: StateEstimateMsg) -> PoseEstimate:
    """:func:`estimate_from_msg` for a node that checks what it uses itself (mixer, reference)."""
    return estimate_from_msg(msg, check=False)


def command_to_msg(cmd: VelocityCommand, stamp_ns: int) -> VelocityCommandMsg:
    return _build_command(stamp_ns, '', cmd.v_d, cmd.omega_d, cmd.omega_d_dot, cmd.x_e,
                          cmd.y_e, cmd.phi_e)


def command_from_msg(msg: VelocityCommandMsg, check: bool = True) -> VelocityCommand:
    cached = _last_command.get(msg, check)
    if cached is not None:
        return cached
    cmd = VelocityCommand(msg.v_d, msg.omega_d, msg.omega_d_dot, msg.x_e, msg.y_e, msg.phi_e)
    return _last_command.keep(msg, checked_command(cmd) if check else cmd, check)


def checked_command(cmd: VelocityCommand) -> VelocityCommand:
    """``cmd`` if every field is finite (InvalidMessage otherwise), from a message or not."""
    check_finite_record('velocity_command', cmd)
    return cmd


def arc_to_msg(out: ArcOutput, stamp_ns: int) -> YawTorque:
    return _build_arc(stamp_ns, '', out.tau_omega, out.alpha_hat, out.e_omega)


def arc_from_msg(msg: YawTorque, check: bool = True) -> ArcOutput:
    out = ArcOutput(msg.tau_omega, msg.alpha_hat, msg.e_omega)
    if check:
        check_finite_record('yaw_torque', out)
    return out


# --------------------------------------------------------------------- MPC

def mpc_status(status: MpcStatus) -> int:
    """DriveTorque status constant of a core status.

    SOLVED -> SOLVED; INPUT_INVALID -> INPUT_INVALID; every solver failure -> the core's
    documented fallback, the previous plan shifted (which holds τ(k−1) when there is no
    plan yet): FALLBACK_SHIFTED_PLAN. ``status_text`` carries the core status name.
    """
    if status == MpcStatus.SOLVED:
        return DriveTorque.SOLVED
    if status == MpcStatus.INPUT_INVALID:
        return DriveTorque.INPUT_INVALID
    return DriveTorque.FALLBACK_SHIFTED_PLAN


def _column(values: Sequence[float]) -> array.array:
    return array.array('d', values)


def mpc_to_msg(result: MpcResult, stamp_ns: int, sampling_period: float) -> DriveTorque:
    """DriveTorque of a core tick.

    Unknown quantities are not sent as NaN: slacks are 0 and the predictions empty when the QP was
    not solved (``status`` says so).
    """
    predicted = result.predicted
    have_prediction = bool(predicted.size) and bool(math.isfinite(float(predicted.sum())))
    slack_v = result.slack_v if math.isfinite(result.slack_v) else 0.0
    slack_theta = result.slack_theta if math.isfinite(result.slack_theta) else 0.0
    return stamped(DriveTorque(
        tau_v=float(result.tau_v),
        delta_tau=float(result.delta_tau), status=mpc_status(result.status),
        status_text=result.status.name, iterations=int(result.iterations),
        solve_time=float(result.solve_time_s + result.build_time_s),
        slack_v=float(slack_v), slack_theta=float(slack_theta),
        sampling_period=float(sampling_period),
        predicted_v=_column(predicted[:, 0].tolist() if have_prediction else ()),
        predicted_theta=_column(predicted[:, 1].tolist() if have_prediction else ()),
        predicted_theta_dot=_column(predicted[:, 2].tolist() if have_prediction else ()),
        planned_tau_v=_column(planned_drive_torque(result)),
        used_fallback=bool(result.used_fallback)), stamp_ns)


def planned_drive_torque(result: MpcResult) -> list[float]:
    """τυ(k), τυ(k+1), … of the plan (eq. (23) applied to each planned increment).

    Empty when the plan is not finite.
    """
    plan = [float(v) for v in result.plan]
    if not (plan and all(math.isfinite(v) for v in plan) and math.isfinite(result.tau_v)):
        return []
    planned = [float(result.tau_v)]
    for increment in plan[1:]:
        planned.append(planned[-1] + increment)
    return planned


def mpc_hold_msg(stamp_ns: int, tau_v: float, sampling_period: float) -> DriveTorque:
    """DriveTorque of a tick of the re-solve grid at which the MPC did not solve.

    The re-solve grid is that of ``mpc.fast_resolve_period`` in lockstep (every control tick
    with ``mpc.push_trigger``). The message has
    the held τυ, status SOLVED (of the last solve), ``status_text`` HELD, Δτ 0, and no plan
    or prediction.
    """
    return stamped(DriveTorque(tau_v=float(tau_v), delta_tau=0.0, status=DriveTorque.SOLVED,
                             status_text=HELD_STATUS_TEXT, sampling_period=float(sampling_period),
                             used_fallback=False), stamp_ns)


def mpc_idle_msg(stamp_ns: int, status: int, text: str, sampling_period: float) -> DriveTorque:
    """DriveTorque with τυ = 0 when the MPC did not run (NOT_READY, INPUT_INVALID)."""
    return stamped(DriveTorque(tau_v=0.0, delta_tau=0.0, status=status, status_text=text,
                             sampling_period=float(sampling_period), used_fallback=True),
                   stamp_ns)


# --------------------------------------------------------------------- wheel torques

def wheel_torques_to_msg(left: float, right: float, stamp_ns: int, zeroed: bool = False,
                         reason: str = '') -> WheelTorques:
    return _build_wheel_torques(stamp_ns, '', left, right, left + right, right - left, zeroed,
                                reason)


def decision_to_msg(decision: SafetyDecision, stamp_ns: int) -> WheelTorques:
    """/wip/wheel_torques of one safety decision: its torques, ``zeroed`` and reasons."""
    return wheel_torques_to_msg(decision.tau_left, decision.tau_right, stamp_ns,
                                decision.zeroed, decision.reason)


def effort_command(left: float, right: float, joints: Sequence[str], left_joint: str,
                   right_joint: str) -> Float64MultiArray:
    """ros2_control JointGroupEffortController command: one effort per joint of ``joints``."""
    return Float64MultiArray(data=_column(_in_joint_order(left, right, joints, left_joint,
                                                          right_joint)))


def _in_joint_order(left: float, right: float, joints: Sequence[str], left_joint: str,
                    right_joint: str) -> list[float]:
    """Return the efforts in the order of ``joints`` (the base's command layout)."""
    by_name = {left_joint: left, right_joint: right}
    return [by_name[j] for j in joints]


def effort_command_cdr(left: float, right: float, joints: Sequence[str], left_joint: str,
                       right_joint: str) -> bytes:
    """:func:`effort_command` already serialized (CDR, little endian).

    For ``Publisher.publish(bytes)``: the real-time mixer sends one per tick, and building the
    message object for rclpy to convert and serialize cost about 30 µs of the ~140 µs of the
    publication here (docs/realtime.md). The layout is empty (no dimensions, offset 0), as
    :func:`effort_command` leaves it; the bytes differ from rclpy's only in the alignment padding,
    which Fast CDR leaves uninitialised.
    """
    return cdr.float64_multi_array(
        [float(v) for v in _in_joint_order(left, right, joints, left_joint, right_joint)])


class EffortCommandCdr:
    """:func:`effort_command_cdr` of one joint layout: ``(left, right)`` -> the same bytes.

    The mixer sends one command per tick in a layout that never changes: the joint order,
    the data's count and the CDR prefix are worked out here, not per command.
    """

    __slots__ = ('prefix', 'doubles', 'left_at')

    def __init__(self, joints: Sequence[str], left_joint: str, right_joint: str) -> None:
        unknown = [j for j in joints if j not in (left_joint, right_joint)]
        if unknown:
            raise KeyError(f'joints {unknown} are neither {left_joint!r} nor {right_joint!r}')
        self.left_at = tuple(j == left_joint for j in joints)
        self.prefix = cdr.float64_multi_array([0.0] * len(joints))[:-8 * len(joints) or None]
        self.doubles = struct.Struct(f'<{len(joints)}d')

    def __call__(self, left: float, right: float) -> bytes:
        return self.prefix + self.doubles.pack(*[left if is_left else right
                                                 for is_left in self.left_at])
