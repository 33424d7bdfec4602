"""A bag's recorded inputs and controller outputs, as the open-loop re-run reads them.

The message conversions are those of the controller nodes (``wip_control.nodes.conversions``),
so the re-run reads a bag exactly as the nodes read the live topics.
"""

from __future__ import annotations

import dataclasses

from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState, NavSatFix
from wip_msgs.msg import (YawTorque, GroundTruth, DriveTorque, ReferenceState as ReferenceMsg,
                          StateEstimate as StateEstimateMsg, VelocityCommand as CommandMsg,
                          WheelTorques)

from wip_runtime.stamps import stamp_to_ns
from wip_control.nodes.conversions import (euler_rates_from_body, imu_has_rates, imu_pitch_yaw,
                                           reference_from_msg, wheel_angles,
                                           wheel_torques_from_msg)
from wip_runtime.messages import InvalidMessage

from wip_bag.bag_reader import iter_raw_messages, read_topics

DEFAULT_PREFIX = '/rerun'
LEFT_JOINT, RIGHT_JOINT = 'left_wheel_joint', 'right_wheel_joint'
MAP_FRAME = 'map'
RELIABLE_QOS = [{'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
                 'durability': 'volatile'}]

TOPICS = {
    'joint_states': ('/joint_states', 'sensor_msgs/msg/JointState'),
    'imu': ('/imu/data', 'sensor_msgs/msg/Imu'),
    'gps': ('/gps/fix', 'sensor_msgs/msg/NavSatFix'),
    'reference': ('/wip/reference', 'wip_msgs/msg/ReferenceState'),
    'wheel_torques': ('/wip/wheel_torques', 'wip_msgs/msg/WheelTorques'),
    'estimate': ('/wip/state_estimate', 'wip_msgs/msg/StateEstimate'),
    'command': ('/wip/velocity_command', 'wip_msgs/msg/VelocityCommand'),
    'arc': ('/wip/yaw_torque', 'wip_msgs/msg/YawTorque'),
    'mpc': ('/wip/drive_torque', 'wip_msgs/msg/DriveTorque'),
    'truth': ('/wip/ground_truth', 'wip_msgs/msg/GroundTruth'),
    'clock': ('/clock', 'rosgraph_msgs/msg/Clock'),
}
_CLASSES = {'joint_states': JointState, 'imu': Imu, 'gps': NavSatFix,
            'reference': ReferenceMsg, 'wheel_torques': WheelTorques,
            'estimate': StateEstimateMsg, 'command': CommandMsg, 'arc': YawTorque,
            'mpc': DriveTorque, 'truth': GroundTruth}
#: Recomputed outputs: (key, record group, fields compared with the recorded message).
COMPARED = (
    ('estimate', ('phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3', 'x',
                  'y')),
    ('command', ('v_d', 'omega_d', 'omega_d_dot', 'x_e', 'y_e', 'phi_e')),
    ('arc', ('tau_omega', 'alpha_hat', 'e_omega')),
    ('mpc', ('tau_v', 'delta_tau')),
    ('wheel_torques', ('left', 'right')),
)


class RerunError(Exception):
    """The bag cannot be re-run (missing topics, unreadable bag, bad scenario)."""


@dataclasses.dataclass
class RecordedRun:
    """The inputs and recorded outputs of a bag, keyed by header stamp [ns]."""

    joint_states: dict  # stamp -> (left, right) [rad]
    imu: dict  # stamp -> (pitch, yaw) [rad]
    gps: dict  # stamp -> NavSatFix (converted with the scenario's datum later)
    reference: dict  # stamp -> core ReferenceState
    wheel_torques: dict  # stamp -> (left, right) [N m]
    outputs: dict  # key of COMPARED -> {stamp: message}
    log_times: dict  # stamp of a /joint_states message -> its log time [ns]
    truth: dict  # stamp -> GroundTruth
    invalid: dict  # topic key -> number of malformed messages skipped
    receive_times: dict = dataclasses.field(default_factory=dict)  # key -> {stamp: log time}
    has_clock: bool = False  # the bag holds /clock: recorded in lockstep simulation time
    imu_rates: dict = dataclasses.field(default_factory=dict)  # stamp -> (θ̇, ϕ̇) [rad/s]


def read_recorded_run(bag, left_joint=LEFT_JOINT, right_joint=RIGHT_JOINT,
                      allow_partial=False) -> RecordedRun:
    """Deserialize the re-run's input topics and the recorded controller outputs.

    A damaged bag raises :class:`~wip_bag.bag_reader.BagIntegrityError` unless
    ``allow_partial`` (then the intact chunks are used).
    """
    wanted = {TOPICS[key][0]: key for key in _CLASSES}
    run = RecordedRun({}, {}, {}, {}, {}, {key: {} for key, _ in COMPARED}, {}, {}, {})
    run.receive_times = {key: {} for key in ('joint_states', 'imu', 'gps', 'wheel_torques',
                                             'mpc')}
    run.has_clock = read_topics(bag, allow_partial).get(TOPICS['clock'][0]) is not None
    for raw in iter_raw_messages(bag, topics=list(wanted), allow_partial=allow_partial):
        key = wanted[raw.topic]
        msg = deserialize_message(raw.data, _CLASSES[key])
        stamp = stamp_to_ns(msg.header.stamp)
        if key in run.receive_times:
            run.receive_times[key].setdefault(stamp, raw.log_time_ns)
        try:
            if key == 'joint_states':
                run.joint_states[stamp] = wheel_angles(msg, left_joint, right_joint)
                run.log_times.setdefault(stamp, raw.log_time_ns)
            elif key == 'imu':
                run.imu[stamp] = imu_pitch_yaw(msg)
                if imu_has_rates(msg):  # the gyro, for the gyro estimator
                    w = msg.angular_velocity
                    run.imu_rates[stamp] = euler_rates_from_body(run.imu[stamp][0],
                                                                 (w.x, w.y, w.z))
            elif key == 'gps':
                run.gps[stamp] = msg
            elif key == 'reference':
                run.reference[stamp] = reference_from_msg(msg)
            elif key == 'wheel_torques':
                run.wheel_torques[stamp] = wheel_torques_from_msg(msg)
                run.outputs[key][stamp] = msg
            elif key == 'truth':
                run.truth[stamp] = msg
            else:
                run.outputs[key][stamp] = msg
        except InvalidMessage:
            run.invalid[key] = run.invalid.get(key, 0) + 1
    return run
