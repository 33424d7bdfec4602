"""How a ros2_control-style base reports its wheels and IMU, from the body's motion.

The stand-in base publishes with :class:`BaseConventions`; tests and tools that play a
base's motions by hand use it too. No node here.
"""

from __future__ import annotations

import math

from sensor_msgs.msg import Imu, JointState

from wip_runtime.rotations import quaternion_from_euler, rotate_vector_into
from wip_control.nodes.hardware_inputs import imu_orientation_of_body


def body_quaternion(pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Orientation of base_link (roll 0) in ENU."""
    return quaternion_from_euler(0.0, pitch, yaw)


def body_angular_velocity(pitch: float, pitch_rate: float,
                          yaw_rate: float) -> tuple[float, float, float]:
    """Return the angular velocity [rad/s] in base_link of R = Rz(ϕ) Ry(θ) (roll 0).

    It is (−ϕ̇ sin θ, θ̇, ϕ̇ cos θ).
    """
    return (-yaw_rate * math.sin(pitch), pitch_rate, yaw_rate * math.cos(pitch))


class BaseConventions:
    """How a base reports its wheels and IMU.

    Joint names and order, per-joint signs, IMU mounting. :meth:`fill` writes a
    JointState and an Imu from the body's motion in the project's conventions (REP 103
    wheel angles, body pitch and yaw); the stand-in base publishes with it, and tests that
    play a base's motions by hand use it too.
    """

    def __init__(self, joints, left_joint: str, right_joint: str, left_sign: float,
                 right_sign: float, mounting) -> None:
        self.joints = list(joints)
        self.left_joint, self.right_joint = left_joint, right_joint
        self.sign = {left_joint: float(left_sign), right_joint: float(right_sign)}
        self.mounting = tuple(float(a) for a in mounting)
        self.mount_q = quaternion_from_euler(*self.mounting)

    def fill(self, joint: JointState, imu: Imu, wheels: tuple[float, float],
             wheel_rates: tuple[float, float], torques: tuple[float, float], pitch: float,
             yaw: float, pitch_rate: float, yaw_rate: float, gravity: float) -> None:
        """Write the fields (not the headers) of ``joint`` and ``imu``.

        wheels, wheel_rates, torques : (left, right) joint angle [rad], rate [rad/s], effort
            [N m], positive rolling/driving forward; pitch, yaw [rad] and their rates
            [rad/s] of the body; gravity [m/s²].
        """
        left, right = self.left_joint, self.right_joint
        angle = {left: wheels[0], right: wheels[1]}
        rate = {left: wheel_rates[0], right: wheel_rates[1]}
        effort = {left: torques[0], right: torques[1]}
        joint.name = self.joints
        joint.position = [self.sign[j] * angle[j] for j in self.joints]
        joint.velocity = [self.sign[j] * rate[j] for j in self.joints]
        joint.effort = [self.sign[j] * effort[j] for j in self.joints]
        q_imu = imu_orientation_of_body(body_quaternion(pitch, yaw), self.mounting)
        imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = q_imu
        w_body = body_angular_velocity(pitch, pitch_rate, yaw_rate)
        (imu.angular_velocity.x, imu.angular_velocity.y,
         imu.angular_velocity.z) = rotate_vector_into(self.mount_q, w_body)
        (imu.linear_acceleration.x, imu.linear_acceleration.y,
         imu.linear_acceleration.z) = rotate_vector_into(q_imu, (0.0, 0.0, gravity))
