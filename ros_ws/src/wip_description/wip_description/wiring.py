"""How a base is wired: wheel joints and signs, IMU mounting, effort command, GPS datum.

Declared with :func:`wip_runtime.config.param` like every node parameter; the controllers,
the stand-in base, the viewer and the bring-up read the same declarations. No rclpy import.
"""

from __future__ import annotations

import dataclasses

from wip_runtime.config import ParamError, like, param, TEXT

from .sensors import SensorParams


@dataclasses.dataclass(frozen=True)
class WheelJoints:
    """Names of the wheel joints in /joint_states and in the effort command."""

    left_joint: str = param('left_wheel_joint', TEXT, 'name of the left wheel joint')
    right_joint: str = param('right_wheel_joint', TEXT, 'name of the right wheel joint')


@dataclasses.dataclass(frozen=True)
class WheelSigns:
    """Direction conventions of the wheel joints of a real base."""

    left_wheel_sign: int = param(1, '1', '+1: the left joint angle (and a positive effort) '
                                 'turns the wheel so that the robot rolls forward; -1: the '
                                 'joint turns the other way', choices=(1, -1))
    right_wheel_sign: int = param(1, '1', 'as left_wheel_sign, for the right wheel',
                                  choices=(1, -1))


@dataclasses.dataclass(frozen=True)
class ImuMounting:
    """How the IMU is mounted on base_link."""

    imu_mounting_rpy: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'rad', 'rotation from base_link to the IMU frame: roll, pitch, yaw '
        'about the fixed x, y, z axes of base_link (a URDF joint rpy)', minimum=-10.0,
        maximum=10.0)


@dataclasses.dataclass(frozen=True)
class EffortCommand:
    """Joint order of the ros2_control effort command."""

    joints: tuple[str, ...] = param(
        ('left_wheel_joint', 'right_wheel_joint'), TEXT, 'joints of the effort command (and '
        'of /joint_states for the stand-in base), in the order of its data; must list '
        'left_joint and right_joint once each', max_length=2)


def check_effort_joints(left_joint: str, right_joint: str, joints: tuple[str, ...]) -> None:
    """ParamError unless ``joints`` lists ``left_joint`` and ``right_joint`` once each.

    The check of the nodes that command efforts, and of a params file before a run.
    """
    if sorted(joints) != sorted([left_joint, right_joint]):
        raise ParamError(f'joints: must list left_joint {left_joint!r} and right_joint '
                          f'{right_joint!r} once each, got {list(joints)}')


@dataclasses.dataclass(frozen=True)
class DatumParams:
    """Map origin of the NavSatFix messages (``datum.*``)."""

    latitude: float = like(SensorParams, 'gps_datum_latitude',
                           description='latitude of the map origin')
    longitude: float = like(SensorParams, 'gps_datum_longitude')
    altitude: float = like(SensorParams, 'gps_datum_altitude')

    @classmethod
    def of(cls, sensors: SensorParams) -> 'DatumParams':
        """Return the datum of a scenario's sensors section."""
        return cls(sensors.gps_datum_latitude, sensors.gps_datum_longitude,
                   sensors.gps_datum_altitude)
