"""Messages <-> core values: no control math, only unpacking, packing and validation.

Sign conventions (REP 103): x forward, y left, z up; yaw ϕ about z, counter-clockwise
positive; pitch θ about y, positive leaning forward (a positive rotation about the
left-pointing y axis tips the body's z axis toward +x). Orientation quaternions are
the ZYX (yaw, pitch, roll) Euler composition R = Rz(ϕ) Ry(θ) Rx(roll), as tf2 and
the plant node use ("orientation from roll 0, pitch θ, yaw ϕ").

Every ``*_from_msg`` that reads an external message raises :class:`InvalidMessage`
(a ValueError) with the reason on malformed or non-finite content; the nodes drop or
neutralise such input and report it on /diagnostics.
"""

from __future__ import annotations

import array
import math
import os
import struct
from typing import Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from std_msgs.msg import Float64MultiArray, Header
from wip_msgs.msg import (ArcState, MpcOutput, ReferenceState as ReferenceStateMsg,
                          StateEstimate as StateEstimateMsg,
                          VelocityCommand as VelocityCommandMsg, WheelTorques)

from ..core.arc import ArcOutput
from ..core.eso import StateEstimate
from ..core.mpc_plan import HELD_STATUS_TEXT, MpcResult
from ..core.qp import MpcStatus
from ..core.reference_state import ReferenceState
from ..core.sensors import geodetic_to_local
from ..core.state_estimation import PoseEstimate
from ..core.trajectory_generator import VelocityCommand

#: Quaternions whose norm is further than this from 1 are rejected as malformed [1]
#: (a normalised float quaternion is within 1e-15; 1e-3 tolerates single-precision drivers).
QUATERNION_NORM_TOLERANCE = 1e-3


class InvalidMessage(ValueError):
    """A message is malformed (missing field, wrong size) or carries non-finite numbers."""


# --------------------------------------------------------------------- building messages

#: The generated message classes check each field's type only when this is '1' (rosidl's
#: ``ROS_PYTHON_CHECK_FIELDS``); the builders below then use their constructors, checks and all.
_CHECK_FIELDS = os.environ.get('ROS_PYTHON_CHECK_FIELDS', '') == '1'
_NS_PER_S = 1_000_000_000


def _bare(cls):
    """Return an instance of a generated message class: no field set yet, type checks off."""
    msg = cls.__new__(cls)
    msg._check_fields = False
    return msg


def fast_header(stamp_ns: int, frame_id: str = '') -> Header:
    """std_msgs/Header with the stamp [ns] and frame, equal to ``common.make_header``'s."""
    if _CHECK_FIELDS:
        return Header(stamp=Time(sec=int(stamp_ns) // _NS_PER_S,
                                 nanosec=int(stamp_ns) % _NS_PER_S), frame_id=frame_id)
    stamp = _bare(Time)
    stamp._sec, stamp._nanosec = divmod(int(stamp_ns), _NS_PER_S)
    header = _bare(Header)
    header._stamp, header._frame_id = stamp, frame_id
    return header


class StampedBuilder:
    """Builds a stamped message of one flat type: its header and every other field, in order.

    The project's messages of a control tick (an estimate, a reference, a command, ...) are
    built once per tick each. The generated constructor evaluates every default (a Header
    and a Time to drop), looks each keyword up and imports Header on every call: 4.4 us
    per message here, against 0.7 us for filling the instance's slots directly
    (docs/realtime.md). The result is the same message (``==``, the same CDR bytes).
    Refuses, at import, a type whose fields are not the header and ``fields``: a message
    definition that changed must not leave a field unset.
    """

    __slots__ = ('cls', 'fields', 'slots')

    def __init__(self, cls, fields: Sequence[str]) -> None:
        self.cls, self.fields = cls, tuple(fields)
        self.slots = tuple('_' + name for name in self.fields)
        expected = set(cls.__slots__) - {'_header', '_check_fields'}
        if '_header' not in cls.__slots__ or set(self.slots) != expected:
            raise TypeError(f'{cls.__name__}: fields {sorted(expected)} besides the header, '
                            f'the builder has {sorted(self.slots)}')

    def __call__(self, stamp_ns: int, frame_id: str, *values):
        if _CHECK_FIELDS:
            return self.cls(header=fast_header(stamp_ns, frame_id),
                            **dict(zip(self.fields, values)))
        msg = _bare(self.cls)
        msg._header = fast_header(stamp_ns, frame_id)
        for slot, value in zip(self.slots, values):
            setattr(msg, slot, value)
        return msg


_build_reference = StampedBuilder(ReferenceStateMsg, ('x', 'y', 'phi', 'v', 'omega',
                                                      'omega_dot'))
_build_estimate = StampedBuilder(StateEstimateMsg, (
    'phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3', 'epsilon', 'x', 'y',
    'settled', 'position_status'))
_build_command = StampedBuilder(VelocityCommandMsg, ('v_d', 'omega_d', 'omega_d_dot', 'x_e',
                                                     'y_e', 'phi_e'))
_build_arc = StampedBuilder(ArcState, ('tau_omega', 'alpha_hat', 'e_omega'))
_build_wheel_torques = StampedBuilder(WheelTorques, ('left', 'right', 'tau_v', 'tau_omega',
                                                     'zeroed', 'reason'))


def _check_finite_record(what: str, record, skip: str = '') -> None:
    """:func:`_check_finite` of a NamedTuple's fields but ``skip``, without building a dict.

    A dict of the fields is built only to name the bad ones.
    """
    if all(map(math.isfinite, record)):   # the common case
        return
    values = record._asdict()
    values.pop(skip, None)
    _check_finite(what, **values)


def stamped(msg, stamp_ns: int, frame_id: str = ''):
    """``msg`` with its own header set, in place, to the stamp [ns] and frame; returns it.

    On the hot path instead of ``Msg(header=make_header(...))``: the generated constructors
    evaluate their defaults eagerly, so that also builds a Header and a Time to drop
    (1.8 us of 5.5 per message measured, six messages per control tick).
    """
    header = msg.header
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if frame_id:
        header.frame_id = frame_id
    return msg


def _check_finite(what: str, **values: float) -> None:
    if all(map(math.isfinite, values.values())):  # the common case, at C speed
        return
    bad = [f'{k}={v!r}' for k, v in values.items() if not math.isfinite(v)]
    raise InvalidMessage(f'{what}: non-finite {", ".join(bad)}')


# --------------------------------------------------------------------- orientation

def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, ...]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (REP 103, as tf2)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def pitch_yaw_from_quaternion(x: float, y: float, z: float, w: float) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] of the ZYX decomposition; yaw in (−π, π].

    Inverse of :func:`quaternion_from_euler` for |pitch| < π/2 (the round trip is exact to
    about 1e-16 rad). The quaternion is normalised first; its roll is ignored (the WIP
    does not roll).
    """
    _check_finite('orientation', x=x, y=y, z=z, w=w)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InvalidMessage(f'orientation: quaternion norm {norm!r} is not 1')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    sin_pitch = 2.0 * (w * y - z * x)
    pitch = math.asin(max(-1.0, min(1.0, sin_pitch)))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return pitch, yaw


# --------------------------------------------------------------------- sensors

#: rosbags' type store of ROS 2 Jazzy's messages, built on the first raw message.
_typestore = None


def prepare_decoder(*typenames: str) -> None:
    """Build the type store and the decoders of ``typenames`` now.

    This takes about 0.16 s of CPU here, more on a slow machine, so it is done at a node's
    start rather than in the callback of its first sensor sample.
    """
    global _typestore  # noqa: PLW0603 - one store per process
    if _typestore is None:
        from rosbags.typesys import get_typestore, Stores
        _typestore = get_typestore(Stores.ROS2_JAZZY)
    for typename in typenames:
        _typestore.get_msgdef(typename)


def decode_serialized(msg, typename: str):
    """Decode a sensor message taken serialized (``create_subscription(..., raw=True)``).

    A sensor message taken serialized (``create_subscription(..., raw=True)``) as an
    object with the message's fields (rosbags' CDR decoder, pinned version); a message
    object is returned as is (the intra-process bus and tests deliver objects).

    Why: for a 200 Hz sensor stream, rclpy building the Python message in its take costs
    more than the control math (the base's two streams: 5.2 % of a core taken as
    messages, 2.7 % taken serialized and decoded here; docs/realtime.md).
    """
    if msg.__class__ is not bytes:
        return msg
    if _typestore is None:
        prepare_decoder()
    try:
        if len(msg) < 4 or msg[0] != 0 or msg[1] not in (0, 1) or msg[2:4] != b'\x00\x00':
            raise ValueError('not a plain CDR encapsulation header')
        msgdef = _typestore.get_msgdef(typename)
        decode = msgdef.deserialize_cdr_le if msg[1] else msgdef.deserialize_cdr_be
        # A truncated message fails in decode. Bytes after the last field are the
        # serializer's and ignored: Fast CDR (rclpy, rmw_fastrtps) sizes an empty trailing
        # float64[] with its 8-byte alignment, so a JointState without efforts ends 8 bytes
        # early (rosbags' public deserialize_cdr allows 3 and rejects it).
        return decode(msg[4:], 0, msgdef.cls, _typestore)[0]
    except Exception as err:  # noqa: BLE001 - any decoding failure is a malformed message
        raise InvalidMessage(f'{typename}: undecodable CDR message of {len(msg)} bytes '
                             f'({type(err).__name__}: {err})') from None


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
    _check_finite('joint_states', left=left, right=right)
    return left, right


def imu_pitch_yaw(msg: Imu) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] from the IMU orientation (REP 145: ENU world frame)."""
    if msg.orientation_covariance[0] == -1.0:
        raise InvalidMessage('imu: no orientation (orientation_covariance[0] == -1)')
    q = msg.orientation
    return pitch_yaw_from_quaternion(q.x, q.y, q.z, q.w)


def euler_rates_from_body(pitch: float, w_body: Sequence[float]) -> tuple[float, float]:
    """(θ̇, ϕ̇) [rad/s] from the body angular velocity (base_link axes, roll 0) at pitch θ.

    The body of R = Rz(ϕ) Ry(θ) turns at ω_body = (−ϕ̇ sin θ, θ̇, ϕ̇ cos θ) (a gyro's
    reading), so θ̇ = ω_y and ϕ̇ = ω_z cos θ − ω_x sin θ.
    """
    wx, wy, wz = (float(v) for v in w_body)
    _check_finite('angular_velocity', x=wx, y=wy, z=wz)
    return wy, wz * math.cos(pitch) - wx * math.sin(pitch)


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
    _check_finite('gps', latitude=lat, longitude=lon, altitude=alt)
    if not -90.0 <= lat <= 90.0:
        raise InvalidMessage(f'gps: latitude {lat!r} outside [-90, 90] deg')
    east, north, _ = geodetic_to_local(lat, lon, alt, datum_latitude, datum_longitude,
                                       datum_altitude)
    return east, north


def wheel_torques_from_msg(msg: WheelTorques) -> tuple[float, float]:
    """(τl, τr) [N m] of an applied command."""
    left, right = float(msg.left), float(msg.right)
    _check_finite('wheel_torques', left=left, right=right)
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
    ref = ReferenceState(msg.x, msg.y, msg.phi, msg.v, msg.omega, msg.omega_dot)
    _check_finite_record('reference', ref)
    return ref


def estimate_to_msg(est: StateEstimate, x: float, y: float, settled: bool, stamp_ns: int,
                    frame_id: str, position_status: int = 0) -> StateEstimateMsg:
    return _build_estimate(stamp_ns, frame_id, est.phi, est.omega, est.f1, est.x_v, est.v,
                           est.f2, est.theta, est.theta_dot, est.f3, est.epsilon, x, y,
                           settled, position_status)


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
    out = PoseEstimate(est, msg.x, msg.y, bool(msg.settled), int(msg.position_status))
    # ε (the last field) is inf at the very start of the paper's ramp: not an input of any
    # controller. The names of the bad fields are only built when there is one.
    if check and not (all(map(math.isfinite, est[:-1])) and math.isfinite(out.x)
                      and math.isfinite(out.y)):
        values = est._asdict()
        del values['epsilon']
        _check_finite('state_estimate', x=out.x, y=out.y, **values)
    return _last_estimate.keep(msg, out, check)


def command_to_msg(cmd: VelocityCommand, stamp_ns: int) -> VelocityCommandMsg:
    return _build_command(stamp_ns, '', cmd.v_d, cmd.omega_d, cmd.omega_d_dot, cmd.x_e,
                          cmd.y_e, cmd.phi_e)


def command_from_msg(msg: VelocityCommandMsg, check: bool = True) -> VelocityCommand:
    cached = _last_command.get(msg, check)
    if cached is not None:
        return cached
    cmd = VelocityCommand(msg.v_d, msg.omega_d, msg.omega_d_dot, msg.x_e, msg.y_e, msg.phi_e)
    if check:
        _check_finite_record('velocity_command', cmd)
    return _last_command.keep(msg, cmd, check)


def arc_to_msg(out: ArcOutput, stamp_ns: int) -> ArcState:
    return _build_arc(stamp_ns, '', out.tau_omega, out.alpha_hat, out.e_omega)


def arc_from_msg(msg: ArcState, check: bool = True) -> ArcOutput:
    out = ArcOutput(msg.tau_omega, msg.alpha_hat, msg.e_omega)
    if check:
        _check_finite_record('yaw_torque', out)
    return out


# --------------------------------------------------------------------- MPC

def mpc_status(status: MpcStatus) -> int:
    """MpcOutput status constant of a core status.

    SOLVED -> SOLVED; INPUT_INVALID -> INPUT_INVALID; every solver failure -> the core's
    documented fallback, the previous plan shifted (which holds τ(k−1) when there is no
    plan yet): FALLBACK_SHIFTED_PLAN. ``status_text`` carries the core status name.
    """
    if status == MpcStatus.SOLVED:
        return MpcOutput.SOLVED
    if status == MpcStatus.INPUT_INVALID:
        return MpcOutput.INPUT_INVALID
    return MpcOutput.FALLBACK_SHIFTED_PLAN


def _column(values: Sequence[float]) -> array.array:
    return array.array('d', values)


def mpc_to_msg(result: MpcResult, stamp_ns: int, sampling_period: float) -> MpcOutput:
    """MpcOutput of a core tick.

    Unknown quantities are not sent as NaN: slacks are 0 and the predictions empty when the QP was
    not solved (``status`` says so).
    """
    predicted = result.predicted
    have_prediction = bool(predicted.size) and bool(math.isfinite(float(predicted.sum())))
    slack_v = result.slack_v if math.isfinite(result.slack_v) else 0.0
    slack_theta = result.slack_theta if math.isfinite(result.slack_theta) else 0.0
    return stamped(MpcOutput(
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


def mpc_hold_msg(stamp_ns: int, tau_v: float, sampling_period: float) -> MpcOutput:
    """MpcOutput of a tick of the re-solve grid at which the MPC did not solve.

    The re-solve grid is that of ``mpc.fast_resolve_period`` in lockstep. The message has
    the held τυ, status SOLVED (of the last solve), ``status_text`` HELD, Δτ 0, and no plan
    or prediction.
    """
    return stamped(MpcOutput(tau_v=float(tau_v), delta_tau=0.0, status=MpcOutput.SOLVED,
                             status_text=HELD_STATUS_TEXT, sampling_period=float(sampling_period),
                             used_fallback=False), stamp_ns)


def mpc_idle_msg(stamp_ns: int, status: int, text: str, sampling_period: float) -> MpcOutput:
    """MpcOutput with τυ = 0 when the MPC did not run (NOT_READY, INPUT_INVALID)."""
    return stamped(MpcOutput(tau_v=0.0, delta_tau=0.0, status=status, status_text=text,
                             sampling_period=float(sampling_period), used_fallback=True),
                   stamp_ns)


# --------------------------------------------------------------------- wheel torques

def wheel_torques_to_msg(left: float, right: float, stamp_ns: int, zeroed: bool = False,
                         reason: str = '') -> WheelTorques:
    return _build_wheel_torques(stamp_ns, '', left, right, left + right, right - left, zeroed,
                                reason)


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
    values = [float(v) for v in _in_joint_order(left, right, joints, left_joint, right_joint)]
    # encapsulation CDR_LE | layout.dim length 0 | layout.data_offset 0 | data length |
    # padding to the doubles' 8-byte alignment (counted from after the encapsulation)
    return struct.pack(f'<4sIII4x{len(values)}d', b'\x00\x01\x00\x00', 0, 0, len(values),
                       *values)
