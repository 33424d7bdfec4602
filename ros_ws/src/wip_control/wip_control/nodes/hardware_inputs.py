r"""Input adapters for a real base: wheel signs, IMU mounting, position from odometry.

Pure functions (no node state) between a base's standard messages and the values the
ESO node feeds the core. With the default parameters every adapter returns exactly what
the plain conversions of :mod:`.conversions` return (no arithmetic is done), so the
simulated graph, whose plant follows the project's conventions, is unchanged bit for bit.

Wheel signs (parameters ``left_wheel_sign``, ``right_wheel_sign``, each +1 or −1)
    The project's wheel angle φ is positive when the wheel rolls the robot FORWARD (REP
    103: +x). A base whose joint axis points the other way (typically one of two mirrored
    motors: its URDF joint axis is −y for one wheel and +y for the other, or the same axis
    with the motor mounted backwards) reports the opposite angle: its sign is −1. The
    sign multiplies the joint position read from sensor_msgs/JointState, and the same sign
    multiplies the effort sent to that joint (``torque_mixer``), because a positive effort
    turns the joint in its own positive direction.

IMU mounting (parameter ``imu_mounting_rpy`` [rad], 3 values)
    The rotation from ``base_link`` to the IMU's frame, as roll, pitch, yaw about the
    fixed axes x, y, z of base_link (the ``rpy`` of a URDF joint from base_link to the
    IMU's link): R_mount = Rz(yaw) Ry(pitch) Rx(roll). The IMU reports the orientation of
    its own frame in the world (REP 145, ENU): R_world_imu = R_world_base R_mount, so the
    body's orientation is

    .. math:: q_{body} = q_{imu} \otimes q_{mount}^{-1}

    and pitch θ and yaw ϕ are read from q_body (ZYX decomposition, roll ignored).

    Example: an IMU mounted **upside down**, turned half a turn about the robot's forward
    axis (its z axis points down, its y axis to the right): ``imu_mounting_rpy: [3.14159,
    0.0, 0.0]``. Standing upright and facing east, the IMU reports roll π; q_body is the
    identity (θ = 0, ϕ = 0). Leaning forward by 0.1 rad, the IMU reports a rotation of
    +0.1 rad about the body's y axis composed with its mounting, and θ = +0.1 rad comes
    out. An IMU turned a quarter turn counter-clockwise (its x axis pointing to the
    robot's left): ``[0.0, 0.0, 1.5708]``; without the parameter the robot's pitch would
    appear as the IMU's roll and be ignored.

Position source (parameter ``position_source``: 'gps' | 'odometry')
    'gps': sensor_msgs/NavSatFix about the datum (:func:`.conversions.gps_local_position`);
    'odometry': nav_msgs/Odometry (topic ``/odom``): ``pose.pose.position`` x, y [m] in the
    odometry's frame (e.g. ``odom`` of a diff_drive_controller or a localisation filter),
    which then is the frame of the reference path too.
"""

from __future__ import annotations

import math
from math import isfinite
from typing import Sequence

from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState
from wip_runtime.messages import (check_finite_values as _check_finite, InvalidMessage,
                                  is_decoded, pitch_yaw_from_quaternion,
                                  QUATERNION_NORM_TOLERANCE)
from wip_runtime.rotations import (Quaternion, quaternion_conjugate, quaternion_from_euler,
                                   quaternion_multiply, quaternion_norm, rotate_vector_into)

from .conversions import euler_rates_from_body, imu_has_rates, imu_pitch_yaw, wheel_angles
from .settings import POSITION_SOURCES  # noqa: F401 (values of position_source)

#: The identity rotation (x, y, z, w).
IDENTITY = (0.0, 0.0, 0.0, 1.0)


# --------------------------------------------------------------------- parameters

def check_wheel_sign(name: str, value) -> float:
    """``value`` as +1.0 or −1.0; ValueError naming the parameter otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value not in (1, -1):
        raise ValueError(f'{name}: must be 1 or -1, got {value!r}')
    return float(value)


def check_mounting_rpy(name: str, value) -> tuple[float, float, float]:
    """``value`` as 3 finite angles [rad]; ValueError naming the parameter otherwise."""
    try:
        angles = tuple(float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise ValueError(f'{name}: must be 3 angles [rad], got {value!r}') from err
    if len(angles) != 3 or not all(math.isfinite(a) for a in angles):
        raise ValueError(f'{name}: must be 3 finite angles [rad] (roll, pitch, yaw), got '
                         f'{value!r}')
    return angles


def check_position_source(name: str, value) -> str:
    if value not in POSITION_SOURCES:
        raise ValueError(f'{name}: {value!r} is not one of {list(POSITION_SOURCES)}')
    return value


# --------------------------------------------------------------------- the IMU mounting

def mounting_inverse(rpy: Sequence[float]) -> Quaternion | None:
    """q_mount⁻¹ of ``imu_mounting_rpy`` [rad]; None for the identity (no rotation done)."""
    roll, pitch, yaw = check_mounting_rpy('imu_mounting_rpy', rpy)
    if roll == 0.0 and pitch == 0.0 and yaw == 0.0:
        return None
    return quaternion_conjugate(quaternion_from_euler(roll, pitch, yaw))


def imu_orientation_of_body(body: Sequence[float], rpy: Sequence[float]) -> Quaternion:
    """Return what an IMU mounted with ``rpy`` reports for the body orientation ``body``.

    It computes q_imu = q_body ⊗ q_mount, the inverse of :func:`body_pitch_yaw`; simulators
    and tests use it.
    """
    roll, pitch, yaw = check_mounting_rpy('imu_mounting_rpy', rpy)
    return quaternion_multiply(body, quaternion_from_euler(roll, pitch, yaw))


# --------------------------------------------------------------------- messages

def signed_wheel_angles(msg: JointState, left_joint: str, right_joint: str,
                        left_sign: float = 1.0,
                        right_sign: float = 1.0) -> tuple[float, float]:
    """(φl, φr) [rad], positive rolling forward: the joint positions times their signs."""
    left, right = wheel_angles(msg, left_joint, right_joint)
    if left_sign != 1.0:
        left = -left
    if right_sign != 1.0:
        right = -right
    return left, right


def body_pitch_yaw(msg: Imu, inverse_mount: Sequence[float] | None = None) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] of the body from an IMU mounted with q_mount.

    ``inverse_mount`` is :func:`mounting_inverse` of the mounting (None: the IMU frame is
    base_link, and this is exactly :func:`.conversions.imu_pitch_yaw`).
    """
    if inverse_mount is None:
        return imu_pitch_yaw(msg)
    if msg.orientation_covariance[0] == -1.0:
        raise InvalidMessage('imu: no orientation (orientation_covariance[0] == -1)')
    q = msg.orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    if not (isfinite(x) and isfinite(y) and isfinite(z) and isfinite(w)):
        _check_finite('orientation', x=x, y=y, z=z, w=w)
    norm = quaternion_norm(x, y, z, w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InvalidMessage(f'orientation: quaternion norm {norm!r} is not 1')
    return pitch_yaw_from_quaternion(*quaternion_multiply((x, y, z, w), inverse_mount))


def body_pitch_yaw_rates(msg: Imu, inverse_mount: Sequence[float] | None,
                         pitch: float) -> tuple[float, float]:
    """(θ̇, ϕ̇) [rad/s] of the body from the IMU's angular velocity (gyro).

    The gyro's axes are the IMU frame: ω_body = R_mount ω_imu, then the Euler rates at the body
    pitch θ [rad] (:func:`.conversions.euler_rates_from_body`).
    """
    if not imu_has_rates(msg):
        raise InvalidMessage('imu: no angular velocity (angular_velocity_covariance[0] == '
                             '-1), needed by the gyro estimator')
    w = msg.angular_velocity
    w_imu = (float(w.x), float(w.y), float(w.z))
    if not (isfinite(w_imu[0]) and isfinite(w_imu[1]) and isfinite(w_imu[2])):
        _check_finite('angular_velocity', x=w_imu[0], y=w_imu[1], z=w_imu[2])
    # R(q)ᵀ v with q = q_mount⁻¹ is R_mount v: the IMU-frame vector in base_link.
    w_body = w_imu if inverse_mount is None else rotate_vector_into(inverse_mount, w_imu)
    return euler_rates_from_body(pitch, w_body)


class _LastAttitude:
    """The attitude of the last decoded IMU message, for the next node that reads it.

    In a composed process the ESO and the mixer's wiring checks read the same decoded IMU
    object (composition.share_raw_subscriptions) with the same mounting: the second gets
    the first one's angles and rates instead of computing them again. ``kernel``: the
    compiled reading (:func:`use_compiled_attitude`), None until then.
    """

    __slots__ = ('msg', 'inverse_mount', 'pitch_yaw', 'rates', 'kernel')

    def __init__(self) -> None:
        self.msg = self.inverse_mount = self.pitch_yaw = self.rates = self.kernel = None


_last_attitude = _LastAttitude()


def body_attitude(msg: Imu, inverse_mount: Sequence[float] | None,
                  with_rates: bool) -> tuple[float, float, tuple[float, float] | None]:
    """(θ, ϕ, (θ̇, ϕ̇) or None): :func:`body_pitch_yaw`, and :func:`body_pitch_yaw_rates`.

    The rates only ``with_rates``. A message :func:`~wip_runtime.messages.decode_serialized`
    made is converted once for every reader with the same mounting; an invalid one raises
    InvalidMessage for each reader, as the two functions do.
    """
    last = _last_attitude
    if msg is not last.msg or inverse_mount != last.inverse_mount:
        read = (None if last.kernel is None
                else _compiled_attitude(last.kernel, msg, inverse_mount, with_rates))
        if read is not None:
            if is_decoded(msg):
                last.msg, last.inverse_mount, last.pitch_yaw, last.rates = (
                    msg, inverse_mount, read[:2], read[2])
            return read
        pitch_yaw = body_pitch_yaw(msg, inverse_mount)
        if not is_decoded(msg):
            rates = body_pitch_yaw_rates(msg, inverse_mount, pitch_yaw[0]) if with_rates else None
            return pitch_yaw[0], pitch_yaw[1], rates
        last.msg, last.inverse_mount, last.pitch_yaw, last.rates = (msg, inverse_mount,
                                                                    pitch_yaw, None)
    pitch, yaw = last.pitch_yaw
    if not with_rates:
        return pitch, yaw, None
    if last.rates is None:
        last.rates = body_pitch_yaw_rates(msg, inverse_mount, pitch)
    return pitch, yaw, last.rates


def _compiled_attitude(kernel, msg: Imu, inverse_mount: Sequence[float] | None,
                       with_rates: bool) -> tuple[float, float, tuple[float, float] | None] | None:
    """:func:`body_attitude` of ``msg`` by the compiled kernel; None where it leaves it."""
    q, w = msg.orientation, msg.angular_velocity
    mount = IDENTITY if inverse_mount is None else inverse_mount
    try:
        taken, pitch, yaw, pitch_rate, yaw_rate = kernel(
            q.x, q.y, q.z, q.w, w.x, w.y, w.z, mount[0], mount[1], mount[2], mount[3],
            inverse_mount is not None, with_rates, msg.orientation_covariance[0],
            msg.angular_velocity_covariance[0], QUATERNION_NORM_TOLERANCE)
    except (TypeError, ValueError, IndexError):
        return None     # fields of another type or size: the interpreter says what is wrong
    if taken:
        return None
    return pitch, yaw, (pitch_rate, yaw_rate) if with_rates else None


def use_compiled_attitude() -> str:
    """Read the body's attitude compiled in this process (``core/attitude_kernel.py``).

    The kernel is compared with the interpreter first (:func:`attitude_difference`). Return
    '' when it is used, else why not. The angles and rates are the same floats either way.
    """
    if _last_attitude.kernel is not None:
        return ''
    from ..core.compiled import ATTITUDE_KERNEL, load_checked
    module, difference = load_checked(ATTITUDE_KERNEL, attitude_difference)
    if difference:
        return f'the compiled attitude differs from the interpreted one {difference}'
    _last_attitude.kernel = module.attitude
    return ''


def attitude_difference(module) -> str:
    """Where ``module.attitude`` differs from the interpreter on made-up samples ('' nowhere).

    Four mountings, attitudes all round (the yaw across ±π, the pitch near ±π/2), rates up
    to overflowing, and the samples the checks refuse: no orientation or rates, values not
    finite, quaternion norms just inside and outside the tolerance.
    """
    for index, (msg, inverse_mount, with_rates) in enumerate(_attitude_samples()):
        try:
            pitch, yaw = body_pitch_yaw(msg, inverse_mount)
            expected = (pitch, yaw, body_pitch_yaw_rates(msg, inverse_mount, pitch)
                        if with_rates else None)
        except InvalidMessage:
            expected = None
        got = _compiled_attitude(module.attitude, msg, inverse_mount, with_rates)
        if repr(got) != repr(expected):
            return f'at sample {index}: {got} against {expected}'
    return ''


def _attitude_samples():
    """Yield (Imu message, q_mount⁻¹ or None, with rates) for :func:`attitude_difference`."""
    mounts = [None] + [mounting_inverse(rpy) for rpy in
                       ((math.pi, 0.0, 0.0), (0.1, -0.2, 1.5), (0.0, 0.0, -0.5 * math.pi))]
    for k in range(240):
        pitch, yaw = 1.5 * math.sin(0.37 * k), math.remainder(0.71 * k, 2.0 * math.pi)
        q = quaternion_from_euler(0.02 * math.cos(k), pitch, yaw)
        scale = (1.0, 1.0 + 0.9e-3, 1.0 - 1.1e-3, math.nan, math.inf)[k % 5] if k % 3 else 1.0
        msg = Imu()
        o, w = msg.orientation, msg.angular_velocity
        o.x, o.y, o.z, o.w = (scale * v for v in q)
        w.x, w.y, w.z = 3.0 * math.cos(k), -2.0 * math.sin(k), (1e308 if k % 31 == 7 else 0.5)
        if k % 23 == 11:
            msg.orientation_covariance[0] = -1.0
        if k % 19 == 3:
            msg.angular_velocity_covariance[0] = -1.0
        yield msg, mounts[k % len(mounts)], k % 7 != 0


def odometry_position(msg: Odometry) -> tuple[float, float]:
    """(x, y) [m] of ``pose.pose.position`` in the odometry's frame (header.frame_id)."""
    p = msg.pose.pose.position
    x, y = float(p.x), float(p.y)
    _check_finite('odometry', x=x, y=y)
    return x, y


def signed_efforts(tau_left: float, tau_right: float, left_sign: float = 1.0,
                   right_sign: float = 1.0) -> tuple[float, float]:
    """Joint efforts [N m] of the wheel torques (REP 103, positive driving forward)."""
    return (tau_left if left_sign == 1.0 else -tau_left,
            tau_right if right_sign == 1.0 else -tau_right)
