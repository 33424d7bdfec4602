"""The sensor messages of a simulated base, built once and rewritten each tick.

The plant node and the stand-in base publish the same sensor_msgs: an Imu whose
covariances state the scenario's noise, a NavSatFix with a diagonal known covariance, and
on GPS ticks either a fix or a dropout (REP 145: no fix, NaN position). The messages are
preallocated and their fields overwritten per tick (a new message per tick would cost an
allocation of every nested field).
"""

from __future__ import annotations

import math

from sensor_msgs.msg import Imu, NavSatFix, NavSatStatus

from wip_description.sensors import local_to_geodetic, SensorParams

# Variance reported when a quantity is exact (noise-free simulation): REP 145 reserves
# -1 for "not provided", 0 is a legitimate "known exactly".
EXACT = 0.0
NOT_PROVIDED = -1.0


def imu_message(config: SensorParams, frame_id: str, acceleration: bool) -> Imu:
    """Make an Imu in ``frame_id`` with the covariances of ``config``'s noise.

    Pitch, yaw and the gyro's noise; roll exact. ``acceleration``: whether
    linear_acceleration is filled (else its covariance says "not provided").
    """
    msg = Imu()
    msg.header.frame_id = frame_id
    msg.orientation_covariance = [EXACT, 0.0, 0.0,
                                  0.0, config.imu_pitch_noise_std ** 2, 0.0,
                                  0.0, 0.0, config.imu_yaw_noise_std ** 2]
    gyro_variance = config.gyro_noise_std ** 2
    msg.angular_velocity_covariance = [EXACT, 0.0, 0.0, 0.0, gyro_variance, 0.0, 0.0, 0.0,
                                       gyro_variance]
    if not acceleration:
        msg.linear_acceleration_covariance[0] = NOT_PROVIDED
    return msg


def gps_message(config: SensorParams, frame_id: str) -> NavSatFix:
    """Make a NavSatFix in ``frame_id``: GPS service, ``config``'s horizontal noise.

    The horizontal variance is that of ``config``'s noise; the altitude is exact.
    """
    msg = NavSatFix()
    msg.header.frame_id = frame_id
    msg.status.status = NavSatStatus.STATUS_FIX
    msg.status.service = NavSatStatus.SERVICE_GPS
    variance = config.gps_noise_std ** 2
    msg.position_covariance = [variance, 0.0, 0.0, 0.0, variance, 0.0, 0.0, 0.0, EXACT]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    return msg


def write_fix(msg: NavSatFix, position: tuple[float, float] | None,
              datum: tuple[float, float, float]) -> None:
    """Write a GPS tick's report into ``msg``.

    ``position`` (x, y) [m] in the map frame becomes latitude, longitude [deg] and
    altitude [m] about ``datum``; None is a dropout (the receiver reports no fix, NaN
    position; the eso node skips it).
    """
    if position is not None:
        msg.status.status = NavSatStatus.STATUS_FIX
        msg.latitude, msg.longitude, msg.altitude = local_to_geodetic(*position, *datum)
    else:
        msg.status.status = NavSatStatus.STATUS_NO_FIX
        msg.latitude = msg.longitude = msg.altitude = math.nan


def set_stamp(stamp, nanoseconds: int) -> None:
    """Write integer nanoseconds into a builtin_interfaces/Time in place.

    The messages are preallocated; ``common.ns_to_stamp`` would allocate a new Time per
    message.
    """
    stamp.sec, stamp.nanosec = divmod(nanoseconds, 1_000_000_000)
