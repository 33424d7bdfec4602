"""The torque mixer's wiring-check inputs: the base's own sensors, read by the mixer itself.

A mixin of :class:`~wip_control.nodes.torque_mixer_node.TorqueMixerNode` (which sets
``lockstep``, ``control_period``, the joints and signs, ``monitor`` and ``_tick`` before
calling :meth:`WiringCheckInputs._init_wiring_check`).
"""

from __future__ import annotations

from sensor_msgs.msg import Imu, JointState

from wip_description.params import ModelParams
from wip_description.wiring import ImuMounting
from wip_runtime.messages import InvalidMessage
from wip_runtime.parameters import RosParams
from wip_runtime.qos import SENSOR_QOS
from ..core.wiring_check import WiringCheck, WiringCheckParams
from wip_runtime.rotations import rotate_vector_into
from .hardware_inputs import (body_attitude, mounting_inverse, signed_wheel_angles,
                              use_compiled_attitude)


class WiringCheckInputs:
    """/joint_states and /imu/data into ``core.wiring_check.WiringCheck``; a verdict faults."""

    def _init_wiring_check(self) -> None:
        """Real time: the wiring checks (core/wiring_check.py) on the base's own sensors.

        The mixer reads /joint_states and /imu/data itself (not the ESO's estimates): the
        check compares raw sensors with each other and with the torque this node sends,
        and its verdict must reach the safety layer in the same process without a hop.
        """
        config = RosParams(self, 'wiring_check', WiringCheckParams).config
        model = RosParams(self, 'model', ModelParams).config
        mounting = RosParams(self, '', ImuMounting).config.imu_mounting_rpy
        self.wiring_check = None
        if self.lockstep or not config.enabled:
            return
        self.inverse_mount = mounting_inverse(mounting)
        self.wiring_check = WiringCheck(config, model, self.control_period, configured={
            'left_joint': self.left_joint, 'right_joint': self.right_joint,
            'left_wheel_sign': int(self.left_sign), 'right_wheel_sign': int(self.right_sign),
            'imu_mounting_rpy': tuple(mounting)})
        warning = use_compiled_attitude()    # done already where an ESO shares the process
        if warning:
            self.get_logger().warning(f'attitude interpreted: {warning}')
        self._last_wheels: tuple[float, float, float] | None = None   # (t, φl, φr)
        # Also taken from the plant of the same process (the single layout).
        joints = self.create_subscription(JointState, 'joint_states', self._on_joint_states,
                                          SENSOR_QOS)
        self.add_intra_subscription(JointState, joints, self._on_joint_states)
        imu = self.create_subscription(Imu, 'imu/data', self._on_imu, SENSOR_QOS)
        self.add_intra_subscription(Imu, imu, self._on_imu)

    def _on_joint_states(self, msg: JointState) -> None:
        """Feed the wiring check the signed wheel rates (a bad message is the ESO's to report)."""
        t = self.monitor_time()
        try:
            left, right = signed_wheel_angles(msg, self.left_joint, self.right_joint,
                                              self.left_sign, self.right_sign)
            names = list(msg.name)
            if len(msg.velocity) == len(names):
                rates = (self.left_sign * float(msg.velocity[names.index(self.left_joint)]),
                         self.right_sign * float(msg.velocity[names.index(self.right_joint)]))
            elif self._last_wheels is not None and t > self._last_wheels[0]:
                dt = t - self._last_wheels[0]
                rates = ((left - self._last_wheels[1]) / dt, (right - self._last_wheels[2]) / dt)
            else:
                rates = None
            self._last_wheels = (t, left, right)
            if rates is not None:
                self.wiring_check.wheels(t, *rates)
        except (InvalidMessage, ValueError, TypeError):
            return

    def _on_imu(self, msg: Imu) -> None:
        t = self.monitor_time()
        try:
            pitch, _yaw, (pitch_rate, yaw_rate) = body_attitude(msg, self.inverse_mount, True)
            accel = None    # read only while the gravity check runs (before any torque)
            if (self.wiring_check.wants_gravity
                    and msg.linear_acceleration_covariance[0] != -1.0):
                a = msg.linear_acceleration
                accel = (float(a.x), float(a.y), float(a.z))
                if self.inverse_mount is not None:
                    accel = rotate_vector_into(self.inverse_mount, accel)
        except (InvalidMessage, ValueError, TypeError):
            return
        verdict = self.wiring_check.imu(t, pitch, pitch_rate, yaw_rate, accel)
        if verdict is not None and not self.monitor.wiring:
            self.monitor.wiring_fault(verdict.reason)
            self.get_logger().error(f'{verdict.reason}: zero torque (latched; fix the '
                                    'parameter, then restart or reset)')
            self._tick()    # zero torque now, not at the next yaw torque
