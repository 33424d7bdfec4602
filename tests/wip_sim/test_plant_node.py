"""The plant node in isolation: lockstep handshake, exact stepping, sensor encoding, endings.

The node runs in this process (a private rclpy context and domain) next to a test node
that plays the controllers: it reads what the plant publishes and publishes wheel
torques. The expected values come from the same core objects the in-process runner uses
(``simulate_hold``, ``Sensors`` with the same seed, ``runner.initial_state``), so
states must be equal to the last bit and sensor values to the precision of their
message encoding.
"""

import os
import subprocess
import sys
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from ros_harness import (communicate, installed_executable, node_process,  # noqa: E402
                         NodeHarness, PROCESS_START_TIMEOUT, spin_for, spin_until)
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import Imu, JointState, NavSatFix  # noqa: E402
import yaml  # noqa: E402

from wip_sim.core.disturbances import Disturbances  # noqa: E402
from wip_control.core.model import PHI  # noqa: E402
from wip_sim.core.plant import Plant, simulate_hold  # noqa: E402
from wip_control.core.references import make_reference  # noqa: E402
from wip_sim.core.simulation import initial_state  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping  # noqa: E402
from wip_description.sensors import geodetic_to_local  # noqa: E402
from wip_sim.core.sensor_models import Sensors  # noqa: E402
from wip_control.nodes.conversions import euler_rates_from_body  # noqa: E402
from wip_runtime.messages import pitch_yaw_from_quaternion  # noqa: E402
from wip_runtime.rotations import quaternion_from_euler  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = pytest.mark.ros

try:
    from wip_msgs.msg import GroundTruth, WheelTorques
except ImportError:  # Workspace not built or not sourced (scripts/test does both).
    GroundTruth = WheelTorques = None

TIMEOUT = 15.0  # [s] of wall time for anything to arrive (discovery takes up to ~3 s)
# A scenario where every sensor has noise or quantisation and the plant is the full model,
# so that equal values cannot come from a trivial path.
NOISY = {
    'duration': 1.0,
    'seed': 7,
    'plant': {'model': 'full'},
    'sensors': {'imu_pitch_noise_std': 0.01, 'imu_yaw_noise_std': 0.02, 'gps_noise_std': 0.5,
                'gyro_noise_std': 0.05, 'gyro_pitch_bias': 0.01,
                'encoder_counts_per_rev': 4096, 'gps_datum_latitude': -33.8688,
                'gps_datum_longitude': 151.2093, 'gps_datum_altitude': 58.0},
    'disturbances': {'tilt': [{'kind': 'sine', 'amplitude': 0.3, 'frequency': 2.0}]},
}
CONTROL_PERIOD_NS = 5_000_000  # 1 / 200 Hz
# Round trip of a fix through WGS84 (local_to_geodetic then geodetic_to_local): the
# core documents better than 1e-6 m; double precision of degrees at this scale is 1e-9 m.
GPS_ROUND_TRIP_M = 1e-6
# Pitch and yaw back from the quaternion: a few ulps of asin/atan2 on unit quaternions.
QUATERNION_ROUND_TRIP_RAD = 1e-12


def stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def write_scenario(tmp_path, mapping, name='scenario.yaml'):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(mapping))
    return path


class Harness(NodeHarness):
    """The plant node and a test node in one private context, spun by one executor."""

    def __init__(self, scenario_path, clock_mode='lockstep', **extra):
        from wip_sim.plant_node import PlantNode
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=take_private_domain())
        overrides = [Parameter('scenario_file', value=str(scenario_path)),
                     Parameter('clock_mode', value=clock_mode),
                     Parameter('start.expected_sensor_subscribers', value=1),
                     Parameter('start.expected_ground_truth_subscribers', value=1)]
        if clock_mode == 'lockstep':
            overrides.append(Parameter('start.expected_clock_subscribers', value=1))
        overrides += [Parameter(k, value=v) for k, v in extra.items()]
        super().__init__(context, PlantNode(context=context, parameter_overrides=overrides),
                         name='plant_test', timeout=TIMEOUT)
        self.plant = self.node
        qos = QoSProfile(depth=1000)
        self.received = {name: self.listen(msg_type, topic, qos) for name, msg_type, topic in (
            ('clock', Clock, '/clock'), ('joint', JointState, '/joint_states'),
            ('imu', Imu, '/imu/data'), ('gps', NavSatFix, '/gps/fix'),
            ('truth', GroundTruth, '/wip/ground_truth'))}
        self.torques = self.publisher(WheelTorques, '/wip/wheel_torques', qos)

    def publish_torques(self, left, right, stamp):
        msg = WheelTorques(left=left, right=right, tau_v=left + right, tau_omega=right - left)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        self.torques.publish(msg)

    def close(self):
        super().close()
        rclpy.try_shutdown(context=self.context)


def truth_state(msg):
    return (msg.x, msg.y, msg.phi, msg.x_v, msg.theta, msg.omega, msg.v, msg.theta_dot)


def check_sensors(harness, sensors, state, index, gps_expected):
    """Check that the sample ``index`` of each sensor topic decodes to the core sensor values."""
    joint = harness.received['joint'][index]
    assert list(joint.name) == ['left_wheel_joint', 'right_wheel_joint']
    left, right = sensors.encoders(state)
    assert tuple(joint.position) == (left, right)  # float64 through CDR: exact
    pitch, yaw = sensors.imu(state)
    q = harness.received['imu'][index].orientation
    decoded = pitch_yaw_from_quaternion(q.x, q.y, q.z, q.w)
    assert decoded == pytest.approx((pitch, yaw), abs=QUATERNION_ROUND_TRIP_RAD)
    # The plant's quaternion is the shared ZYX convention with roll 0.
    assert (q.x, q.y, q.z, q.w) == pytest.approx(quaternion_from_euler(0.0, pitch, yaw),
                                                 abs=1e-15)
    rates = sensors.imu_rates(state)  # drawn after the angles, as the plant node does
    imu = harness.received['imu'][index]
    # The gyro reads the body angular velocity (x = −ϕ̇ sin θ, y = θ̇, z = ϕ̇ cos θ); the
    # eso node's inverse returns the Euler rates to rounding.
    w = imu.angular_velocity
    assert euler_rates_from_body(pitch, (w.x, w.y, w.z)) == pytest.approx(rates, abs=1e-15)
    assert w.y == rates[0]
    if gps_expected:
        assert sensors.gps_fix_available()  # no dropouts configured: draws nothing
        x, y = sensors.gps(state)
        fix = harness.received['gps'][-1]
        config = sensors.config
        east, north, _ = geodetic_to_local(
            fix.latitude, fix.longitude, fix.altitude, config.gps_datum_latitude,
            config.gps_datum_longitude, config.gps_datum_altitude)
        assert (east, north) == pytest.approx((x, y), abs=GPS_ROUND_TRIP_M)
        assert stamp_ns(fix.header.stamp) == stamp_ns(joint.header.stamp)


def test_lockstep_waits_for_the_torques_of_t_k_then_steps_exactly_one_period(
        tmp_path, harnesses):
    scenario = scenario_from_mapping(NOISY)
    harness = Harness(write_scenario(tmp_path, NOISY))
    harnesses.append(harness)
    received = harness.received
    harness.spin_until(lambda: all(received[n] for n in ('clock', 'joint', 'imu', 'gps',
                                                         'truth')), 'the sample of t_0')

    # t_0: the runner's initial state and the core sensors with the same seed.
    reference = make_reference(scenario.reference)
    state0 = initial_state(scenario, reference.sample(0.0))
    sensors = Sensors(scenario.plant.parameters, scenario.sensors,
                      initial_yaw=float(state0[PHI]), seed=scenario.seed)
    truth0 = received['truth'][0]
    assert stamp_ns(truth0.header.stamp) == 0 and stamp_ns(received['clock'][0].clock) == 0
    assert truth_state(truth0) == tuple(state0)
    assert (truth0.tau_left, truth0.tau_right) == (0.0, 0.0)
    disturbances = Disturbances(scenario.disturbances, seed=scenario.seed)
    assert (truth0.tau_d1, truth0.tau_d2, truth0.tau_d3) == disturbances.sample(0.0)
    check_sensors(harness, sensors, state0, 0, gps_expected=True)

    # No torques, or torques of another stamp: the plant does not move.
    harness.spin_for(0.3)
    harness.publish_torques(1.0, 1.0, CONTROL_PERIOD_NS)  # from the future
    harness.publish_torques(1.0, 1.0, 1)  # 1 ns off
    harness.spin_until(lambda: harness.plant.stale_torques == 2, 'two ignored commands')
    assert len(received['truth']) == 1 and len(received['clock']) == 1

    # The torques of t_0: exactly one control period, as the core simulate_hold.
    tau_left, tau_right = 0.4, -0.25
    harness.publish_torques(tau_left, tau_right, 0)
    harness.spin_until(lambda: len(received['truth']) == 2 and len(received['joint']) == 2,
                       'the sample of t_1')
    harness.spin_for(0.2)
    assert len(received['truth']) == 2, 'the plant went on without torques'
    plant = Plant(scenario.plant.parameters, scenario.plant.model.model)
    dt = scenario.control_period
    state1 = simulate_hold(plant, state0, tau_left, tau_right, disturbances.sample, 0.0,
                           dt / scenario.rates.substeps, scenario.rates.substeps)
    truth1 = received['truth'][1]
    assert stamp_ns(received['clock'][1].clock) == CONTROL_PERIOD_NS
    assert stamp_ns(truth1.header.stamp) == CONTROL_PERIOD_NS
    assert truth_state(truth1) == tuple(state1.tolist())  # same code, same floats
    assert (truth1.tau_left, truth1.tau_right) == (tau_left, tau_right)
    assert tuple(received['joint'][1].effort) == (tau_left, tau_right)
    assert (truth1.tau_d1, truth1.tau_d2, truth1.tau_d3) == disturbances.sample(dt)
    # GPS every control_rate / gps_rate = 20 ticks: none at t_1.
    assert len(received['gps']) == 1
    check_sensors(harness, sensors, state1, 1, gps_expected=False)


def test_a_fall_ends_the_run_with_the_falling_sample_and_no_clock(tmp_path, harnesses):
    falling = {'duration': 5.0, 'fall_threshold': 0.3,
               'initial_state': {'theta': 0.25, 'pose': [0.0, 0.0, 0.0]}}
    harness = Harness(write_scenario(tmp_path, falling))
    harnesses.append(harness)
    received = harness.received

    def echo_zero():
        # Play a controller that commands nothing: the body falls forward.
        if len(received['joint']) > harness.answered:
            harness.publish_torques(0.0, 0.0, stamp_ns(received['joint'][-1].header.stamp))
            harness.answered += 1
        return harness.plant.exit_code is not None
    harness.answered = 0
    harness.spin_until(echo_zero, 'the fall')
    harness.spin_until(lambda: len(received['truth']) == harness.plant.k + 1, 'the last truth')
    assert harness.plant.exit_code == 1    # the table's 'the vehicle fell'
    last = received['truth'][-1]
    assert abs(last.theta) >= 0.3
    assert all(abs(m.theta) < 0.3 for m in received['truth'][:-1])
    # The falling sample has no /clock and no sensors: no control step follows it.
    assert len(received['clock']) == len(received['joint']) == len(received['truth']) - 1


@pytest.mark.wallclock   # torques older than 0.05 s
def test_realtime_steps_on_the_wall_clock_with_zero_torques_until_fresh_ones_arrive(
        tmp_path, harnesses):
    harness = Harness(write_scenario(tmp_path, {'duration': 30.0}), clock_mode='realtime',
                      max_torque_age=0.05)
    harnesses.append(harness)
    received = harness.received
    harness.spin_until(lambda: len(received['truth']) >= 20, '20 realtime samples')
    assert not received['clock'], 'realtime publishes no /clock'
    now_ns = time.time_ns()
    last = stamp_ns(received['truth'][-1].header.stamp)
    assert abs(now_ns - last) < 1e9, 'realtime stamps are wall-clock times'
    stamps = [stamp_ns(m.header.stamp) for m in received['truth']]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all((m.tau_left, m.tau_right) == (0.0, 0.0) for m in received['truth'])
    assert harness.plant.zeroed_torques == harness.plant.k

    count = len(received['truth'])
    harness.publish_torques(0.5, 0.7, time.time_ns())
    harness.spin_until(lambda: any((m.tau_left, m.tau_right) == (0.5, 0.7)
                                   for m in received['truth'][count:]), 'the fresh torques')
    # Older than max_torque_age: back to zero.
    harness.spin_for(0.2)
    assert (received['truth'][-1].tau_left, received['truth'][-1].tau_right) == (0.0, 0.0)


@pytest.mark.slow
def test_the_executable_ends_the_scenario_with_exit_code_0_and_the_documented_counts(
        tmp_path, test_node):
    """The plant as its own process (what run_graph starts): 4 ticks, then exit code 0."""
    scenario_path = write_scenario(tmp_path, {'duration': 0.02})
    node = test_node  # in the test's DDS domain, which the process inherits
    received = {'truth': [], 'joint': [], 'gps': [], 'clock': []}
    qos = QoSProfile(depth=100)
    node.create_subscription(GroundTruth, '/wip/ground_truth', received['truth'].append, qos)
    node.create_subscription(Imu, '/imu/data', lambda msg: None, qos)
    node.create_subscription(NavSatFix, '/gps/fix', received['gps'].append, qos)
    node.create_subscription(Clock, '/clock', received['clock'].append, qos)
    publisher = node.create_publisher(WheelTorques, '/wip/wheel_torques', qos)

    def echo(msg):  # a controller answering each sample at once
        out = WheelTorques(left=0.1, right=0.1)
        out.header.stamp = msg.header.stamp
        publisher.publish(out)
        received['joint'].append(msg)
    node.create_subscription(JointState, '/joint_states', echo, qos)
    with node_process([installed_executable('wip_sim', 'plant'), '--ros-args',
                       '-p', f'scenario_file:={scenario_path}',
                       '-p', 'start.expected_ground_truth_subscribers:=1',
                       '-p', f'stats_file:={tmp_path / "stats.json"}'],
                      stderr=subprocess.STDOUT) as process:
        spin_until(node.executor_for_test, lambda: process.poll() is not None,
                   'the end of the scenario', PROCESS_START_TIMEOUT)
        spin_for(node.executor_for_test, 0.2)  # what is still queued
        output, _ = communicate(process, 10.0)
    assert process.returncode == 0, output
    assert 'end of the scenario at t = 0.02 s' in output
    # N = 4 ticks: N + 1 ground truths (the last at t = 0.02 s), N sensor samples and
    # clocks, GPS at tick 0 only (every 20 ticks).
    assert len(received['truth']) == 5 and len(received['joint']) == 4
    assert len(received['clock']) == 4 and len(received['gps']) == 1
    assert stamp_ns(received['truth'][-1].header.stamp) == 4 * CONTROL_PERIOD_NS
    assert (received['truth'][-1].tau_left, received['truth'][-1].tau_right) == (0.1, 0.1)
    stats = yaml.safe_load((tmp_path / 'stats.json').read_text())
    assert stats['ticks'] == 4 and stats['exit_code'] == 0
    assert stats['wait_for_torques_s']['count'] == 4


def test_an_invalid_scenario_is_refused_with_exit_code_2(tmp_path):
    bad = write_scenario(tmp_path, {'duration': -1.0})
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()))
    result = subprocess.run(
        [sys.executable, '-m', 'wip_sim.plant_node', '--ros-args', '-p',
         f'scenario_file:={bad}'], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert 'duration' in result.stderr
