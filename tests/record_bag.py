"""An in-process run written as the node graph's bag, for the tests of the bag tools.

The topics, types, stamps and contents are those of a lockstep graph run recorded with
``use_sim_time`` (log time = stamp = t_k): ``/clock``, ``/wip/ground_truth``,
``/joint_states``, ``/imu/data``, ``/gps/fix``, ``/wip/reference``,
``/wip/state_estimate``, ``/wip/velocity_command``, ``/wip/yaw_torque``,
``/wip/drive_torque`` (MPC ticks), ``/wip/wheel_torques``. The sensor samples are drawn
again from the recorded true states with the scenario's sensor models and seed, in the
runner's order, so they are the ones the runner's controllers used. The scenario is stored
in ``custom_data['wip.scenario']``.
"""

from __future__ import annotations

import math

from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from wip_msgs.msg import YawTorque, GroundTruth, DriveTorque, VelocityCommand as CommandMsg
import yaml

from wip_control.core.eso import StateEstimate
from wip_control.core.references import make_reference
from wip_description.sensors import local_to_geodetic
from wip_control.core.state_observer import WipStateObserver
from wip_runtime.stamps import make_header, ns_to_stamp
from wip_control.nodes.conversions import (body_rates_from_euler, estimate_to_msg,
                                           reference_to_msg, wheel_torques_to_msg)
from wip_runtime.rotations import quaternion_from_euler
from wip_sim.core.scenario import Scenario, scenario_to_mapping
from wip_sim.core.sensor_models import Sensors
from wip_bag.bag_writer import Rosbag2McapWriter
from wip_tools.bag_scenario import SCENARIO_KEY
from wip_tools.rerun_inputs import LEFT_JOINT, MAP_FRAME, RELIABLE_QOS, RIGHT_JOINT, TOPICS

STATE_KEYS = ('x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot')
WRITTEN = ('clock', 'truth', 'joint_states', 'imu', 'gps', 'reference', 'estimate',
           'command', 'arc', 'mpc', 'wheel_torques')


def write_record_as_bag(result, scenario: Scenario, directory, clock=True,
                        compression='zstd', **writer_options):
    """Write an in-process run (``wip_sim.core.runner.run_scenario``) as the graph's bag.

    Returns
    -------
    dict
        Messages written per topic.
    """
    record = result.record
    truth = record['truth']
    n_ticks = len(record['estimate']['t'])
    messages = _TickMessages(record, scenario)
    custom = {SCENARIO_KEY: yaml.safe_dump(scenario_to_mapping(scenario), sort_keys=False)}
    with Rosbag2McapWriter(directory, compression=compression, custom_data=custom,
                           **writer_options) as bag:
        for key in WRITTEN:
            if key == 'clock' and not clock:
                continue
            bag.add_topic(TOPICS[key][0], TOPICS[key][1], qos_profiles=RELIABLE_QOS)
        for k in range(len(truth['t'])):
            t = float(truth['t'][k])
            s = int(round(t * 1e9))
            last = k >= n_ticks
            if clock and not last:
                msg = Clock()
                msg.clock = ns_to_stamp(s)
                bag.write(TOPICS['clock'][0], serialize_message(msg), s)
            bag.write(TOPICS['truth'][0], serialize_message(_ground_truth(truth, k, s)), s)
            if last:
                break
            for key, msg in messages.at(k, t, s):
                bag.write(TOPICS[key][0], serialize_message(msg), s)
        return bag.message_counts()


class _TickMessages:
    """The sensor and controller messages of one control tick of a run's record."""

    def __init__(self, record, scenario: Scenario):
        self.record, self.scenario = record, scenario
        truth = record['truth']
        self.sensors = Sensors(scenario.plant.parameters, scenario.sensors,
                               initial_yaw=float(truth['phi'][0]), seed=scenario.seed)
        c = self.config = scenario.sensors
        self.datum = (c.gps_datum_latitude, c.gps_datum_longitude, c.gps_datum_altitude)
        self.gps_every = max(1, int(round(scenario.rates.control_rate / c.gps_rate)))
        self.reference = make_reference(scenario.reference)
        self.observer = WipStateObserver(scenario.controller_model.parameters, scenario.eso)
        self.mpc_rows = {round(t * scenario.rates.control_rate): i
                         for i, t in enumerate(record['mpc']['t'])}

    def at(self, k, t, s):
        """(topic key, message) of tick ``k`` at ``t`` [s] = ``s`` [ns], in the graph's order."""
        truth = self.record['truth']
        yield from self._sensor_messages(k, s, [float(truth[name][k]) for name in STATE_KEYS])
        yield from self._controller_messages(k, t, s)

    def _sensor_messages(self, k, s, true_state):
        # Sensors in the runner's order (separate random streams per sensor).
        sensors, truth = self.sensors, self.record['truth']
        state, gps_state = sensors.delayed(true_state)
        left, right = sensors.encoders(state)
        pitch, yaw = sensors.imu(state)
        rates = sensors.imu_rates(state)
        joints = JointState(name=[LEFT_JOINT, RIGHT_JOINT], position=[left, right],
                            velocity=list(sensors.wheel_rates(state)),
                            effort=[float(truth['tau_left'][k]), float(truth['tau_right'][k])])
        joints.header = make_header(s)
        yield 'joint_states', joints
        yield 'imu', _imu(pitch, yaw, s, rates, self.config)
        if k % self.gps_every == 0:
            if sensors.gps_fix_available():
                yield 'gps', _fix(*sensors.gps(gps_state), self.datum, s, self.config)
            else:  # a dropout, as the plant node publishes it
                fix = _fix(0.0, 0.0, self.datum, s, self.config)
                fix.status.status = NavSatStatus.STATUS_NO_FIX
                fix.latitude = fix.longitude = fix.altitude = math.nan
                yield 'gps', fix

    def _controller_messages(self, k, t, s):
        record, observer = self.record, self.observer
        est = record['estimate']
        yield 'reference', reference_to_msg(self.reference.sample(t), s, MAP_FRAME)
        estimate = StateEstimate(*(float(est[name][k]) for name in (
            'phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3')),
            observer.epsilon_at(t))
        yield 'estimate', estimate_to_msg(estimate, float(est['x'][k]), float(est['y'][k]),
                                          not observer.in_ramp(t), s, MAP_FRAME)
        cmd = record['command']
        yield 'command', CommandMsg(header=make_header(s), **{f: float(cmd[f][k]) for f in (
            'v_d', 'omega_d', 'omega_d_dot', 'x_e', 'y_e', 'phi_e')})
        arc = record['arc']
        yield 'arc', YawTorque(header=make_header(s), **{f: float(arc[f][k]) for f in (
            'tau_omega', 'alpha_hat', 'e_omega')})
        row = self.mpc_rows.get(k)
        if row is not None:
            yield 'mpc', _mpc_output(record['mpc'], row, s, self.scenario)
        wheels = record['wheels']
        yield 'wheel_torques', wheel_torques_to_msg(float(wheels['tau_left'][k]),
                                                    float(wheels['tau_right'][k]), s)


def _ground_truth(truth, k, stamp):
    fields = ('x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot')
    msg = GroundTruth(header=make_header(stamp), **{f: float(truth[f][k]) for f in fields})
    msg.header.frame_id = MAP_FRAME
    msg.tau_d1, msg.tau_d2, msg.tau_d3 = (float(truth[d][k]) for d in ('d1', 'd2', 'd3'))
    msg.tau_left, msg.tau_right = float(truth['tau_left'][k]), float(truth['tau_right'][k])
    return msg


def _imu(pitch, yaw, stamp, rates, config):
    msg = Imu(header=make_header(stamp))
    msg.header.frame_id = 'imu_link'
    q = msg.orientation
    q.x, q.y, q.z, q.w = quaternion_from_euler(0.0, pitch, yaw)
    msg.orientation_covariance = [0.0, 0.0, 0.0, 0.0, config.imu_pitch_noise_std ** 2, 0.0,
                                  0.0, 0.0, config.imu_yaw_noise_std ** 2]
    # As the plant node: the gyro's body angular velocity at the published pitch.
    (msg.angular_velocity.x, msg.angular_velocity.y,
     msg.angular_velocity.z) = body_rates_from_euler(pitch, *rates)
    msg.angular_velocity_covariance = [0.0, 0.0, 0.0, 0.0, config.gyro_noise_std ** 2, 0.0,
                                       0.0, 0.0, config.gyro_noise_std ** 2]
    msg.linear_acceleration_covariance[0] = -1.0
    return msg


def _fix(x, y, datum, stamp, config):
    msg = NavSatFix(header=make_header(stamp))
    msg.header.frame_id = 'gps_link'
    msg.status.status = NavSatStatus.STATUS_FIX
    msg.status.service = NavSatStatus.SERVICE_GPS
    msg.latitude, msg.longitude, msg.altitude = local_to_geodetic(x, y, *datum)
    variance = config.gps_noise_std ** 2
    msg.position_covariance = [variance, 0.0, 0.0, 0.0, variance, 0.0, 0.0, 0.0, 0.0]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    return msg


def _mpc_output(mpc, row, stamp, scenario):
    used_fallback = bool(mpc['used_fallback'][row] > 0.5)
    slack_v, slack_theta = float(mpc['slack_v'][row]), float(mpc['slack_theta'][row])
    return DriveTorque(
        header=make_header(stamp), tau_v=float(mpc['tau_v'][row]),
        delta_tau=float(mpc['delta_tau'][row]),
        status=DriveTorque.FALLBACK_SHIFTED_PLAN if used_fallback else DriveTorque.SOLVED,
        status_text='', iterations=int(mpc['iterations'][row]),
        solve_time=float(mpc['solve_time'][row]),
        slack_v=slack_v if math.isfinite(slack_v) else 0.0,
        slack_theta=slack_theta if math.isfinite(slack_theta) else 0.0,
        sampling_period=scenario.mpc.sampling_period, used_fallback=used_fallback)
