"""The six controller nodes, each in isolation: messages in, core calls, messages out.

Each node runs in this process, in a private rclpy context (DDS domain of its own),
with a harness node that publishes its inputs and collects its outputs; the test drives
a SingleThreadedExecutor itself, so callbacks run here, exceptions from a callback
would fail the test, and nothing depends on sleeps. What a node publishes is compared
with the core computed directly on the same inputs: the nodes are thin wrappers, so
the comparison is exact (==), not approximate. Two tests start a node as its own
process (``python -m``) to cover ``main()``: the EventsExecutor loop, SIGINT, and the
refusal to start on a bad parameter.
"""

import dataclasses
import math
import pathlib
import random
import signal
import sys
import time

import pytest

rclpy = pytest.importorskip('rclpy')
wip_msgs = pytest.importorskip('wip_msgs.msg')

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from ros_harness import (communicate, node_process, NodeHarness,  # noqa: E402
                         PROCESS_START_TIMEOUT)
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
import yaml  # noqa: E402

from wip_control.core.arc import AdaptiveRobustYawController, ArcParams  # noqa: E402
from wip_runtime.config import ParamError  # noqa: E402
from wip_sim.core.disturbances import Disturbances  # noqa: E402
from wip_control.core.eso import EsoParams  # noqa: E402
from wip_control.core.mixer import drive_torque_limit, mix  # noqa: E402
from wip_control.core.model import PHI  # noqa: E402
from wip_control.core.lqr import LongitudinalLqr  # noqa: E402
from wip_control.core.mpc import LongitudinalMpc  # noqa: E402
from wip_control.core.mpc_config import MpcParams  # noqa: E402
from wip_description.params import ModelParams  # noqa: E402
from wip_sim.core.plant import Plant, simulate_hold  # noqa: E402
from wip_control.core.reference_state import ReferenceState  # noqa: E402
from wip_control.core.references import make_reference  # noqa: E402
from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.simulation import initial_state  # noqa: E402
from wip_sim.core.scenario import Scenario  # noqa: E402
from wip_description.sensors import (geodetic_to_local, local_to_geodetic,  # noqa: E402
                                     SensorParams)
from wip_sim.core.sensor_models import Sensors  # noqa: E402
from wip_control.core.state_estimation import StateEstimator  # noqa: E402
from wip_control.core.trajectory_generator import (TrajectoryGenerator,  # noqa: E402
                                                   TrajectoryGeneratorParams)
from wip_control.core.control_step import (initial_alpha,  # noqa: E402
                                           TrajectoryGeneratorStage)
from wip_control.core.mpc_plan import HELD_STATUS_TEXT  # noqa: E402
from wip_control.nodes.arc_node import ArcNode  # noqa: E402
from wip_runtime.composition import connect_intra_process, share_sim_clock  # noqa: E402
from wip_runtime.diagnostics import WARN  # noqa: E402
from wip_runtime.qos import CLOCK_QOS  # noqa: E402
from wip_runtime.stamps import make_header, ns_to_stamp, stamp_to_ns  # noqa: E402
from wip_control.nodes.conversions import (body_rates_from_euler,  # noqa: E402
                                           euler_rates_from_body, mpc_status)
from wip_runtime.messages import pitch_yaw_from_quaternion  # noqa: E402
from wip_runtime.rotations import quaternion_from_euler  # noqa: E402
from wip_control.nodes.eso_node import EsoNode  # noqa: E402
from wip_control.nodes.mpc_node import MpcNode  # noqa: E402
from wip_control.nodes.reference_node import ReferenceNode  # noqa: E402
from wip_control.nodes.torque_mixer_node import TorqueMixerNode  # noqa: E402
from wip_control.nodes.trajectory_generator_node import TrajectoryGeneratorNode  # noqa: E402

pytestmark = pytest.mark.ros

YawTorque = wip_msgs.YawTorque
DriveTorque = wip_msgs.DriveTorque
ReferenceStateMsg = wip_msgs.ReferenceState
StateEstimateMsg = wip_msgs.StateEstimate
VelocityCommandMsg = wip_msgs.VelocityCommand
WheelTorques = wip_msgs.WheelTorques

H_NS = 5_000_000          # control period 1/200 Hz [ns] (the default rates)
TIMEOUT = 10.0            # [s] for any single wait; normally milliseconds
SENSORS = SensorParams()
DATUM = (SENSORS.gps_datum_latitude, SENSORS.gps_datum_longitude, SENSORS.gps_datum_altitude)


# ----------------------------------------------------------------------------- fixtures

@pytest.fixture(scope='module')
def domain_id(module_domain):
    """Return the module's DDS domain (conftest), set before any rclpy.init of this module."""
    return module_domain


def _new_context(domain, args=None):
    context = rclpy.Context()
    rclpy.init(args=args, context=context, domain_id=domain)
    return context


@pytest.fixture(scope='module')
def context(domain_id):
    ctx = _new_context(domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def params_context(domain_id, tmp_path):
    """Return a factory of contexts whose nodes read a params file.

    The file is given as ``--ros-args --params-file``.
    """
    made = []

    def factory(node_name, parameters):
        path = tmp_path / f'params_{len(made)}.yaml'
        path.write_text(yaml.safe_dump({node_name: {'ros__parameters': parameters}}))
        ctx = _new_context(domain_id, ['--ros-args', '--params-file', str(path)])
        made.append(ctx)
        return ctx
    yield factory
    for ctx in made:
        rclpy.try_shutdown(context=ctx)


def overrides(mode='lockstep', **params):
    """parameter_overrides: clock mode, sim time in lockstep, no diagnostics timer."""
    values = {'clock_mode': mode, 'use_sim_time': mode == 'lockstep',
              'diagnostics_period': 0.0, **params}
    return [Parameter(name, value=value) for name, value in values.items()]


#: Message type of every topic a controller node reads or writes.
TOPIC_TYPES = {'/clock': Clock, '/joint_states': JointState, '/imu/data': Imu,
               '/gps/fix': NavSatFix, '/wip/wheel_torques': WheelTorques,
               '/wip/reference': ReferenceStateMsg, '/wip/state_estimate': StateEstimateMsg,
               '/wip/velocity_command': VelocityCommandMsg, '/wip/yaw_torque': YawTorque,
               '/wip/drive_torque': DriveTorque,
               '/effort_controller/commands': Float64MultiArray}


def wire(harness, inputs=(), outputs=()):
    """Wire publishers of ``inputs`` and listeners of ``outputs`` on the harness node.

    Publishers of the topics ``inputs`` and listeners of ``outputs`` on the harness node
    (types from :data:`TOPIC_TYPES`), matched with the node under test.
    """
    for topic in inputs:
        harness.publisher(TOPIC_TYPES[topic], topic, CLOCK_QOS if topic == '/clock' else 100)
    for topic in outputs:
        harness.listen(TOPIC_TYPES[topic], topic)
    harness.wait_matched()
    return harness


def harness_of(harnesses, node):
    """``node`` under test in a harness (closed at the end of the test)."""
    harness = NodeHarness(node.context, node, timeout=TIMEOUT)
    harnesses.append(harness)
    return harness


def start(harnesses, context, node_cls, mode='lockstep', inputs=(), outputs=(), **params):
    """Start a node of ``node_cls`` with the test's parameter overrides, in a harness.

    Wire it to ``inputs`` and ``outputs`` (see :func:`wire`) if given.
    """
    harness = harness_of(harnesses, node_cls(context=context, parameter_overrides=overrides(
        mode, **params)))
    if inputs or outputs:
        wire(harness, inputs, outputs)
    return harness


def publish_shuffled(harness, msgs, rng):
    """Publish the (topic, message) pairs in a random order (the nodes must not care)."""
    rng.shuffle(msgs)
    for topic, msg in msgs:
        harness.publish(topic, msg)


def assert_finite(msg):
    """Every float field (and float array) of ``msg`` is finite."""
    for name, kind in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        if kind in ('double', 'float'):
            assert math.isfinite(value), f'{type(msg).__name__}.{name} = {value}'
        elif kind.startswith('sequence<double'):
            assert all(math.isfinite(v) for v in value), f'{type(msg).__name__}.{name}'


# ----------------------------------------------------------------------------- messages

def joint_states(stamp_ns, left, right, names=('left_wheel_joint', 'right_wheel_joint')):
    return JointState(header=make_header(stamp_ns), name=list(names),
                      position=[left, right], velocity=[0.0, 0.0], effort=[0.0, 0.0])


def imu(stamp_ns, pitch, yaw, rates=(0.0, 0.0)):
    """Orientation and gyro (the body angular velocity of the Euler rates (θ̇, ϕ̇))."""
    msg = Imu(header=make_header(stamp_ns))
    q = quaternion_from_euler(0.0, pitch, yaw)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = q
    (msg.angular_velocity.x, msg.angular_velocity.y,
     msg.angular_velocity.z) = body_rates_from_euler(pitch, *rates)
    return msg


def decoded_rates(s):
    """(θ̇, ϕ̇) as the eso node decodes them from :func:`imu`'s message."""
    msg = imu(0, s['pitch'], s['yaw'], s['rates'])
    w = msg.angular_velocity
    pitch, _ = pitch_yaw_from_quaternion(msg.orientation.x, msg.orientation.y,
                                         msg.orientation.z, msg.orientation.w)
    return euler_rates_from_body(pitch, (w.x, w.y, w.z))


def gps_fix(stamp_ns, x, y):
    lat, lon, alt = local_to_geodetic(x, y, *DATUM)
    return NavSatFix(header=make_header(stamp_ns), latitude=lat, longitude=lon, altitude=alt,
                     status=NavSatStatus(status=NavSatStatus.STATUS_FIX))


def torques(stamp_ns, left, right):
    return WheelTorques(header=make_header(stamp_ns), left=left, right=right)


def estimate_msg(stamp_ns, **values):
    fields = dict(phi=0.0, omega=0.0, f1=0.0, x_v=0.0, v=0.0, f2=0.0, theta=0.0,
                  theta_dot=0.0, f3=0.0, epsilon=0.01, x=0.0, y=0.0)
    fields.update(values)
    return StateEstimateMsg(header=make_header(stamp_ns, 'map'), **fields)


def clock(stamp_ns):
    return Clock(clock=ns_to_stamp(stamp_ns))


# ----------------------------------------------------------------------------- conversions

def test_imu_quaternion_round_trip_and_rep103_pitch_sign():
    for pitch, yaw in [(0.05, 1.47), (-0.3, -3.1), (0.0, math.pi), (0.4, -0.2)]:
        x, y, z, w = quaternion_from_euler(0.0, pitch, yaw)
        got_pitch, got_yaw = pitch_yaw_from_quaternion(x, y, z, w)
        # 1e-15 rad: a few ulp of asin/atan2 on a unit quaternion.
        assert got_pitch == pytest.approx(pitch, abs=1e-15)
        assert math.remainder(got_yaw - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-15)
    # Positive pitch = leaning forward: the body z axis tips toward +x (REP 103).
    x, y, z, w = quaternion_from_euler(0.0, 0.1, 0.0)
    body_z_x = 2.0 * (x * z + w * y)        # x component of R e_z
    assert body_z_x == pytest.approx(math.sin(0.1), abs=1e-15)


def test_mpc_status_mapping_covers_every_core_status():
    from wip_control.core.mpc import MpcStatus
    assert mpc_status(MpcStatus.SOLVED) == DriveTorque.SOLVED
    assert mpc_status(MpcStatus.INPUT_INVALID) == DriveTorque.INPUT_INVALID
    for status in MpcStatus:
        if status not in (MpcStatus.SOLVED, MpcStatus.INPUT_INVALID):
            assert mpc_status(status) == DriveTorque.FALLBACK_SHIFTED_PLAN


# ----------------------------------------------------------------------------- ESO

def eso_measurements(n=60):
    """Synthetic noise-free sensor samples: yaw crosses +pi (wrap), GPS every 20 samples."""
    p = ModelParams()
    samples = []
    yaw0 = 3.0
    for k in range(n):
        t = k * H_NS / 1e9
        yaw = yaw0 + 2.0 * t                 # crosses pi at t = 0.07 s (k = 14)
        pitch = 0.05 * math.cos(3.0 * t)
        x_v = 0.1 + 0.5 * t + 0.3 * t * t
        half_turn = 0.5 * p.track_width * (yaw - yaw0)
        left = (x_v - half_turn) / p.wheel_radius - pitch
        right = (x_v + half_turn) / p.wheel_radius - pitch
        gps = (1.0 + 0.5 * t, -2.0 + 0.1 * t) if k % 20 == 0 else None
        applied = (2.0 * math.sin(10.0 * t), 1.5 * math.cos(7.0 * t))  # over [t_k, t_k+1)
        rates = (-0.15 * math.sin(3.0 * t), 2.0)                         # (θ̇, ϕ̇)
        samples.append(dict(stamp=k * H_NS, left=left, right=right, pitch=pitch,
                            yaw=math.remainder(yaw, 2 * math.pi), gps=gps, applied=applied,
                            rates=rates))
    return samples


def eso_expected(samples, config=EsoParams(), applied_before=None, use_gps=True,
                 origin_ns=0):
    """Return the runner's steps 1-3 on the values the node decodes from the messages.

    ``applied_before(k)``: the torques the ESO input uses at sample k (lockstep: those of
    sample k - 1, zero at k = 0). Without GPS the position starts at (0, 0). ``origin_ns``:
    the stamp of t = 0 (real time: the first stamp).
    """
    if applied_before is None:
        def applied_before(k):
            return samples[k - 1]['applied'] if k else (0.0, 0.0)
    estimator = StateEstimator(ModelParams(), config, encoders_relative_to_body=True)
    out = []
    for k, s in enumerate(samples):
        t = (s['stamp'] - origin_ns) / 1e9
        pitch, yaw = pitch_yaw_from_quaternion(*quaternion_from_euler(0.0, s['pitch'],
                                                                      s['yaw']))
        gps = None
        if use_gps and s['gps'] is not None:
            lat, lon, alt = local_to_geodetic(*s['gps'], *DATUM)
            gps = geodetic_to_local(lat, lon, alt, *DATUM)[:2]
        pose = estimator.update(t, s['left'], s['right'], pitch, yaw, *applied_before(k),
                                decoded_rates(s), gps)
        out.append((pose.estimate, pose.x, pose.y))
    return out


def run_eso_lockstep(harness, samples, seed=0):
    """Publish each sample's messages in a random order; wait for its estimate."""
    rng = random.Random(seed)
    out = harness.outputs['/wip/state_estimate']
    for k, s in enumerate(samples):
        msgs = [('/joint_states', joint_states(s['stamp'], s['left'], s['right'])),
                ('/imu/data', imu(s['stamp'], s['pitch'], s['yaw'], s['rates']))]
        if s['gps'] is not None:
            msgs.append(('/gps/fix', gps_fix(s['stamp'], *s['gps'])))
        elif s.get('dropout'):  # a GPS tick without a fix (status NO_FIX)
            fix = gps_fix(s['stamp'], 0.0, 0.0)
            fix.status.status = NavSatStatus.STATUS_NO_FIX
            msgs.append(('/gps/fix', fix))
        if k:  # The torques applied since the previous sample, stamped with it.
            msgs.append(('/wip/wheel_torques', torques(samples[k - 1]['stamp'],
                                                       *samples[k - 1]['applied'])))
        publish_shuffled(harness, msgs, rng)
        harness.spin_until(lambda: len(out) == k + 1, f'estimate {k}')
    return out


ESO_INPUTS = ('/joint_states', '/imu/data', '/gps/fix', '/wip/wheel_torques')


def eso_harness(harnesses, context, mode='lockstep', **params):
    return start(harnesses, context, EsoNode, mode, ESO_INPUTS, ['/wip/state_estimate'],
                 **params)


def assert_estimate_equal(msg, expected, stamp):
    est, x, y = expected
    assert msg.header.stamp == ns_to_stamp(stamp) and msg.header.frame_id == 'map'
    got = (msg.phi, msg.omega, msg.f1, msg.x_v, msg.v, msg.f2, msg.theta, msg.theta_dot,
           msg.f3, msg.epsilon, msg.x, msg.y)
    assert got == (*est, x, y)  # exact: the node calls the same core functions


def test_eso_lockstep_equals_the_core_whatever_the_arrival_order(context, harnesses):
    samples = eso_measurements()
    harness = eso_harness(harnesses, context)
    out = run_eso_lockstep(harness, samples, seed=1)
    expected = eso_expected(samples)
    for msg, exp, s in zip(out, expected, samples):
        assert_estimate_equal(msg, exp, s['stamp'])
    assert out[-1].phi > math.pi          # unwrapped through the +pi crossing
    # Starts at the first fix (1e-6 m: the geodetic round trip is exact to ~1e-9 m).
    assert (out[0].x, out[0].y) == pytest.approx(samples[0]['gps'], abs=1e-6)
    assert all(m.settled for m in out)    # constant epsilon: settled from the start
    assert harness.node.diagnostics.compute_count == len(samples)


def test_eso_lockstep_completes_a_gps_tick_without_a_fix(context, harnesses):
    # A dropout: the simulator publishes a NavSatFix with status NO_FIX at the GPS tick;
    # the set completes without a fix, as the runner skips it.
    samples = eso_measurements(45)
    samples[20] = dict(samples[20], gps=None, dropout=True)
    harness = eso_harness(harnesses, context)
    out = run_eso_lockstep(harness, samples)
    for msg, exp, s in zip(out, eso_expected(samples), samples):
        assert_estimate_equal(msg, exp, s['stamp'])


@pytest.mark.parametrize('section', [{'epsilon': 0.02, 'estimator': 'paper'},
                                     {'longitudinal_bandwidth': 30.0}])
def test_eso_epsilon_from_a_params_file_changes_the_estimate_as_the_core_predicts(
        params_context, harnesses, section):
    # The paper's ESOs (ε) and the default gyro estimator (its x_v ESO's bandwidth,
    # reported as ε = 1/ω_l).
    ctx = params_context('eso', {'eso': section})
    samples = eso_measurements(30)
    harness = eso_harness(harnesses, ctx)
    config = EsoParams(**section)
    assert harness.node.get_parameter('eso.epsilon').value == config.epsilon
    out = run_eso_lockstep(harness, samples)
    expected = eso_expected(samples, config)
    default = eso_expected(samples)
    for msg, exp, s in zip(out, expected, samples):
        assert_estimate_equal(msg, exp, s['stamp'])
    assert out[-1].epsilon == (0.02 if 'epsilon' in section else 1.0 / 30.0)
    assert out[-1].f2 != default[-1][0].f2  # the change is visible in the output


def test_eso_drops_malformed_and_non_finite_input_and_goes_on(context, harnesses):
    harness = eso_harness(harnesses, context, 'realtime')
    out = harness.outputs['/wip/state_estimate']
    stamp = 1_000_000_000
    bad_imu = imu(stamp, 0.0, 0.0)
    bad_imu.orientation.w = float('nan')
    zero_q = imu(stamp, 0.0, 0.0)
    zero_q.orientation.w = 0.0
    no_orientation = imu(stamp, 0.0, 0.0)
    no_orientation.orientation_covariance[0] = -1.0
    bad = [('/joint_states', JointState(header=make_header(stamp))),                 # empty
           ('/joint_states', joint_states(stamp, 0.0, 0.0, names=('a', 'b'))),     # names
           ('/joint_states', JointState(header=make_header(stamp),                 # sizes
                                        name=['left_wheel_joint', 'right_wheel_joint'],
                                        position=[0.0])),
           ('/joint_states', joint_states(stamp, float('nan'), 0.0)),
           ('/joint_states', joint_states(stamp, 0.0, float('inf'))),
           ('/imu/data', bad_imu), ('/imu/data', zero_q), ('/imu/data', no_orientation),
           ('/gps/fix', NavSatFix(header=make_header(stamp), latitude=float('nan'))),
           ('/gps/fix', NavSatFix(header=make_header(stamp), latitude=10.0,
                                  status=NavSatStatus(status=NavSatStatus.STATUS_NO_FIX))),
           ('/wip/wheel_torques', torques(stamp, float('nan'), 0.0))]
    for topic, msg in bad:
        harness.publish(topic, msg)
    received = harness.node.diagnostics.received
    harness.spin_until(lambda: sum(received.values()) == len(bad), 'the bad messages')
    assert out == []                      # nothing usable arrived
    assert sum(harness.node.diagnostics.dropped.values()) == len(bad)
    harness.publish('/joint_states', joint_states(stamp, 1.0, 1.0))
    harness.publish('/imu/data', imu(stamp, 0.01, 0.5))
    harness.spin_until(lambda: len(out) == 1, 'an estimate from valid input')
    assert_finite(out[0])
    assert out[0].theta == pytest.approx(0.01, abs=1e-15) and out[0].phi == pytest.approx(
        0.5, abs=1e-15)


def test_eso_realtime_updates_once_per_imu_and_encoder_pair_with_the_latest_torques(
        context, harnesses):
    harness = eso_harness(harnesses, context, 'realtime')
    out = harness.outputs['/wip/state_estimate']
    received = harness.node.diagnostics.received
    wall = 1_700_000_000_000_000_000         # wall-clock stamps: t is relative to the first
    samples = [dict(s, stamp=wall + s['stamp']) for s in eso_measurements(30)]
    for k, s in enumerate(samples):
        harness.publish('/wip/wheel_torques', torques(s['stamp'] - 1, *s['applied']))
        harness.spin_until(lambda: received['wheel_torques'] == k + 1, f'torques {k}')
        first, second = (('/imu/data', imu(s['stamp'], s['pitch'], s['yaw'], s['rates'])),
                         ('/joint_states', joint_states(s['stamp'], s['left'], s['right'])))
        if k % 2:
            first, second = second, first
        harness.publish(*first)
        harness.spin_until(lambda: received['imu'] + received['joint_states'] == 2 * k + 1,
                           'the first sensor of the pair')
        assert len(out) == k                 # one of the two is not enough
        harness.publish(*second)
        harness.spin_until(lambda: len(out) == k + 1, f'estimate {k}')
    # The latest torques at each update are the ones published just before it.
    expected = eso_expected(samples, applied_before=lambda k: samples[k]['applied'],
                            use_gps=False, origin_ns=wall)
    for msg, exp, s in zip(out, expected, samples):
        assert_estimate_equal(msg, exp, s['stamp'])
    assert not harness.node.estimator.has_fix          # no fix: dead reckoning from (0, 0)
    assert (out[0].x, out[0].y) == (0.0, 0.0) and out[-1].x != 0.0


def test_eso_lockstep_waits_for_the_fix_at_gps_ticks_and_drops_fixes_off_them(
        context, harnesses):
    harness = eso_harness(harnesses, context)
    out = harness.outputs['/wip/state_estimate']
    dropped = harness.node.diagnostics.dropped
    s = eso_measurements(1)[0]
    harness.publish('/joint_states', joint_states(0, s['left'], s['right']))
    harness.publish('/imu/data', imu(0, s['pitch'], s['yaw'], s['rates']))
    harness.spin_for(0.03)
    assert out == []                       # t = 0 is a GPS tick: the set needs the fix
    harness.publish('/gps/fix', gps_fix(0, 1.0, 2.0))
    harness.spin_until(lambda: len(out) == 1, 'the estimate at t = 0')
    harness.publish('/gps/fix', gps_fix(H_NS, 5.0, 5.0))   # k = 1: not a GPS tick
    harness.publish('/wip/wheel_torques', torques(0, 0.0, 0.0))
    harness.publish('/joint_states', joint_states(H_NS, s['left'], s['right']))
    harness.publish('/imu/data', imu(H_NS, s['pitch'], s['yaw'], s['rates']))
    harness.spin_until(lambda: len(out) == 2, 'the estimate at t = h')
    assert dropped[('gps', 'off the GPS ticks')] == 1
    assert (out[1].x, out[1].y) == (out[0].x, out[0].y)   # the off-tick fix was not used


def test_eso_refuses_to_start_on_out_of_range_or_non_hurwitz_parameters(params_context):
    ctx = params_context('eso', {'eso': {'epsilon': -0.01}})
    with pytest.raises(ParamError, match=r'eso\.epsilon: must be > 0'):
        EsoNode(context=ctx)
    ctx = params_context('eso', {'eso': {'yaw_gains': [1.0, 1.0, 5.0]}})
    with pytest.raises(ParamError, match=r'eso\.yaw_gains: .*not Hurwitz'):
        EsoNode(context=ctx)


def test_eso_reports_drops_on_diagnostics(context, harnesses):
    harness = eso_harness(harnesses, context, 'realtime', diagnostics_period=0.05)
    statuses = []
    harness.io.create_subscription(DiagnosticArray, '/diagnostics',
                                   lambda m: statuses.extend(m.status), 10)
    msg = imu(0, 0.0, 0.0)
    msg.orientation.x = float('inf')
    harness.publish('/imu/data', msg)
    harness.spin_until(lambda: any(s.level == DiagnosticStatus.WARN and 'dropped imu' in
                                   s.message for s in statuses), 'a WARN naming the drop')
    status = next(s for s in statuses if s.level == DiagnosticStatus.WARN)
    assert status.name == '/eso: extended state observer'
    keys = {v.key: v.value for v in status.values}
    assert keys['dropped imu (invalid)'] == '1' and keys['age joint_states [s]'] == \
        'never received'


def test_eso_says_why_when_an_obstacle_blocks_the_wheels(context, harnesses):
    # Wheels held still, the body leaning 0.1 rad forward, 8 N m per wheel (16 N m of
    # drive torque, above the 10 N m stall torque): after the 0.3 s stall time the node's
    # state is a WARN that names the obstacle and the 2.0 cm edge 2 x 15 N m can climb.
    n = 100   # 0.5 s at the 200 Hz of H_NS
    samples = [dict(stamp=k * H_NS, left=-0.1, right=-0.1, pitch=0.1, yaw=0.0,
                    gps=(0.0, 0.0) if k % 20 == 0 else None, applied=(8.0, 8.0),
                    rates=(0.0, 0.0)) for k in range(n)]
    harness = eso_harness(harnesses, context)
    run_eso_lockstep(harness, samples)
    status = harness.node.diagnostics.status()
    assert status.level == DiagnosticStatus.WARN
    assert 'stopped by an obstacle' in status.message
    values = {v.key: v.value for v in status.values}
    assert '2.0 cm' in values['obstacle'] and values['wheel slip'].startswith('none;')
    assert 'plan around it' in status.message
    # The verdict goes out with the estimate, for the trajectory generator to refuse.
    estimates = harness.outputs['/wip/state_estimate']
    assert estimates[-1].obstacle_blocked and not estimates[0].obstacle_blocked


def test_eso_derives_the_climbable_edge_from_the_mixers_torque_limit(context, harnesses):
    # mixer.max_wheel_torque 20 N m: 2 x 20 N m climb h_max = r - sqrt(r^2 - (tau/(M g))^2)
    # (docs/mujoco-plant.md), 3.7 cm with the default model, not the 2.0 cm of 2 x 15 N m.
    from wip_control.core.obstacle import climbable_edge_height
    model = ModelParams()
    total = model.body_mass + model.chassis_mass + 2.0 * model.wheel_mass
    h_max = climbable_edge_height(model.wheel_radius, 40.0, total, model.gravity)
    samples = [dict(stamp=k * H_NS, left=-0.1, right=-0.1, pitch=0.1, yaw=0.0,
                    gps=(0.0, 0.0) if k % 20 == 0 else None, applied=(8.0, 8.0),
                    rates=(0.0, 0.0)) for k in range(100)]
    harness = eso_harness(harnesses, context, **{'mixer.max_wheel_torque': 20.0})
    run_eso_lockstep(harness, samples)
    reason = harness.node.estimator.obstacle_state.reason
    assert f'{100.0 * h_max:.1f} cm' in reason and '40 N m climbs' in reason
    assert f'{100.0 * h_max:.1f}' != '2.0'


# ----------------------------------------------------------------------------- reference

def test_reference_lockstep_publishes_one_sample_per_clock_tick_from_zero(context, harnesses):
    harness = start(harnesses, context, ReferenceNode, inputs=['/clock'],
                    outputs=['/wip/reference'])
    out = harness.outputs['/wip/reference']
    reference = make_reference()
    stamps = [0, H_NS, 2 * H_NS, 2 * H_NS + H_NS // 2, 3 * H_NS, 3 * H_NS, 4 * H_NS]
    expected = [0, H_NS, 2 * H_NS, 3 * H_NS, 4 * H_NS]   # off-grid and repeated: skipped
    for stamp in stamps:
        harness.publish('/clock', clock(stamp))
        if stamp in expected:
            harness.spin_until(lambda: out and out[-1].header.stamp == ns_to_stamp(stamp),
                               f'the reference at {stamp} ns')
    harness.spin_for(0.05)
    assert [m.header.stamp for m in out] == [ns_to_stamp(s) for s in expected]
    # One /clock subscription, which also drives the node's sim-time clock.
    assert [s.topic_name for s in harness.node.subscriptions].count('/clock') == 1
    assert harness.node.get_clock().now().nanoseconds == 4 * H_NS
    for msg, stamp in zip(out, expected):
        ref = reference.sample(stamp / 1e9)
        assert (msg.x, msg.y, msg.phi, msg.v, msg.omega, msg.omega_dot) == tuple(ref)
        assert msg.header.frame_id == 'map'


@pytest.mark.wallclock   # judges the timer rate on the wall clock
def test_reference_realtime_runs_on_a_timer_from_its_first_tick(context, harnesses):
    harness = start(harnesses, context, ReferenceNode, 'realtime',
                    outputs=['/wip/reference'], realtime_trigger='timer',
                    **{'rates.control_rate': 100.0, 'rates.plant_rate': 1000.0})
    out = harness.outputs['/wip/reference']
    harness.spin_until(lambda: len(out) >= 5, 'five references')
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in out]
    reference = make_reference()
    assert (out[0].x, out[0].y) == reference.sample(0.0)[:2]    # the path starts at t = 0
    for msg, stamp in zip(out, stamps):
        assert msg.phi == reference.sample((stamp - stamps[0]) / 1e9).phi
    # Wall-clock timer at 100 Hz: 10 ms apart on average (loose: a shared 2-core machine).
    assert 5e6 < (stamps[-1] - stamps[0]) / (len(stamps) - 1) < 30e6


def test_reference_realtime_publishes_one_sample_per_state_estimate_at_its_stamp(
        context, harnesses):
    # The default real-time trigger: no timer of its own; the reference of the estimate's
    # time (from the first estimate), nothing without estimates, a stale estimate dropped.
    harness = start(harnesses, context, ReferenceNode, 'realtime',
                    inputs=['/wip/state_estimate'], outputs=['/wip/reference'])
    assert not [t for t in harness.node.timers if t.timer_period_ns < 10**9]
    out = harness.outputs['/wip/reference']
    harness.spin_for(0.2)
    assert out == []
    t0 = time.time_ns()
    stamps = [t0, t0 + 5_000_000, t0 + 12_000_000, t0 + 5_000_000, t0 + 20_000_000]
    for stamp in stamps:
        harness.publish('/wip/state_estimate', StateEstimateMsg(header=make_header(stamp)))
    harness.spin_until(lambda: len(out) >= 4, 'four references')
    harness.spin_for(0.2)
    reference = make_reference()
    assert [stamp_to_ns(m.header.stamp) for m in out] == [stamps[i] for i in (0, 1, 2, 4)]
    for msg in out:
        expected = reference.sample((stamp_to_ns(msg.header.stamp) - t0) / 1e9)
        assert (msg.x, msg.y, msg.phi, msg.v) == (expected.x, expected.y, expected.phi,
                                                  expected.v)
    assert harness.node.diagnostics.dropped[('tick', 'stale')] == 1


def test_reference_kind_from_parameters(context, harnesses):
    harness = start(harnesses, context, ReferenceNode, inputs=['/clock'],
                    outputs=['/wip/reference'],
                    **{'reference.kind': 'circle', 'reference.circle_radius': 3.0})
    out = harness.outputs['/wip/reference']
    harness.publish('/clock', clock(0))
    harness.spin_until(lambda: out, 'a reference')
    assert out[0].x == 3.0 and out[0].omega == pytest.approx(0.5 / 3.0, rel=1e-15)


# ----------------------------------------------------------------------------- generator

def pose_stream(n):
    for k in range(n):
        t = k * H_NS / 1e9
        yield k * H_NS, dict(phi=1.4 + 0.2 * t, x=-0.3 + 0.1 * t, y=2.5 - 0.05 * t)


def test_trajectory_generator_lockstep_equals_the_core(context, harnesses):
    harness = start(harnesses, context, TrajectoryGeneratorNode,
                    inputs=['/wip/reference', '/wip/state_estimate'],
                    outputs=['/wip/velocity_command'],
                    **{'trajectory_generator.max_yaw_rate': 0.2})
    out = harness.outputs['/wip/velocity_command']
    reference = make_reference()
    generator = TrajectoryGenerator(TrajectoryGeneratorParams(max_yaw_rate=0.2))
    rng = random.Random(2)
    for k, (stamp, pose) in enumerate(pose_stream(40)):
        ref = reference.sample(stamp / 1e9)
        msgs = [('/wip/reference', ReferenceStateMsg(header=make_header(stamp), **ref._asdict())),
                ('/wip/state_estimate', estimate_msg(stamp, **pose))]
        publish_shuffled(harness, msgs, rng)
        harness.spin_until(lambda: len(out) == k + 1, f'command {k}')
        expected = generator.step(stamp / 1e9, ref, pose['x'], pose['y'], pose['phi'])
        msg = out[-1]
        assert msg.header.stamp == ns_to_stamp(stamp)
        assert (msg.v_d, msg.omega_d, msg.omega_d_dot, msg.x_e, msg.y_e, msg.phi_e) == \
            tuple(expected)
    assert any(abs(m.omega_d) == 0.2 for m in out)  # the overridden limit was active


def test_trajectory_generator_refuses_a_blocked_estimate_and_says_why(context, harnesses):
    # From obstacle_refuse_delay after the estimate says obstacle_blocked, the commands
    # are eq. (9) on a point at rest 0.2 m (obstacle_back_off) behind the blocked pose:
    # the core stage on the same inputs, exactly, and υd = λ3 tanh(-0.2) < 0 while the
    # vehicle is still there; /diagnostics is a WARN that says where, why and what
    # resumes. A reference behind the line across the stopped axle (a new path that turns
    # back) resumes.
    harness = start(harnesses, context, TrajectoryGeneratorNode,
                    inputs=['/wip/reference', '/wip/state_estimate'],
                    outputs=['/wip/velocity_command'],
                    **{'trajectory_generator.obstacle_refuse_delay': 0.02})
    out = harness.outputs['/wip/velocity_command']
    stage = TrajectoryGeneratorStage(TrajectoryGeneratorParams(obstacle_refuse_delay=0.02))
    line = ReferenceState(0.0, 0.0, 0.5, 0.3, 0.0, 0.0)
    pose = dict(x=1.0, y=0.5, phi=0.5)
    rng = random.Random(4)
    for k in range(30):
        stamp, blocked = k * H_NS, 10 <= k < 20
        d = 0.3 * k * H_NS / 1e9
        ref = line._replace(x=1.2 + d * math.cos(0.5), y=0.6 + d * math.sin(0.5))
        if k >= 25:   # turned back: behind the line across the stopped axle
            ref = line._replace(x=0.5, y=0.3, phi=0.5 + math.pi, v=0.1)
        msgs = [('/wip/reference', ReferenceStateMsg(header=make_header(stamp),
                                                     **ref._asdict())),
                ('/wip/state_estimate', estimate_msg(stamp, obstacle_blocked=blocked,
                                                     **pose))]
        publish_shuffled(harness, msgs, rng)
        harness.spin_until(lambda: len(out) == k + 1, f'command {k}')
        expected = stage.step(stamp / 1e9, ref, pose['x'], pose['y'], pose['phi'], blocked)
        msg = out[-1]
        assert (msg.v_d, msg.omega_d, msg.omega_d_dot, msg.x_e, msg.y_e, msg.phi_e) == \
            tuple(expected)
        status = harness.node.diagnostics.status()
        if 14 <= k < 25:   # blocked from k = 10, refused 0.02 s (4 samples) later
            # eq. (9) with υr = 0 toward the point 0.2 m back: λ3 tanh(−0.2)
            assert msg.v_d == pytest.approx(
                TrajectoryGeneratorParams().lambda3 * math.tanh(-0.2), abs=1e-12)
            assert status.level == DiagnosticStatus.WARN
            assert 'refused' in status.message and 'plan around it' in status.message
            assert '(1.00, 0.50) m' in status.message
        else:   # pushing on before it; following the turned-back reference after it
            assert status.level == DiagnosticStatus.OK
            assert (msg.v_d > 0.0) == (k < 14)
    values = {v.key: v.value for v in harness.node.diagnostics.status().values}
    assert values['obstacle refusals'] == '1'


def test_trajectory_generator_status_says_what_its_last_tick_did(context, harnesses):
    # The status is made when it is sent, from what the last tick left: new refusal
    # settings between two ticks apply from the next one, so the status still says where
    # the last tick held (0.2 m back, the default) until a tick with the new settings.
    harness = start(harnesses, context, TrajectoryGeneratorNode,
                    inputs=['/wip/reference', '/wip/state_estimate'],
                    outputs=['/wip/velocity_command'],
                    **{'trajectory_generator.obstacle_refuse_delay': 0.0})
    node, out = harness.node, harness.outputs['/wip/velocity_command']
    status = node.diagnostics.status()
    assert status.message == 'waiting for inputs'
    assert 'obstacle refusals' not in {v.key for v in status.values}
    ref = ReferenceState(1.5, 0.7, 0.5, 0.3, 0.0, 0.0)   # ahead of the pose: leads past it

    def tick(k: int, blocked: bool) -> DiagnosticStatus:
        harness.publish('/wip/reference', ReferenceStateMsg(header=make_header(k * H_NS),
                                                            **ref._asdict()))
        harness.publish('/wip/state_estimate', estimate_msg(
            k * H_NS, obstacle_blocked=blocked, x=1.0, y=0.5, phi=0.5))
        harness.spin_until(lambda: len(out) == k + 1, f'command {k}')
        return node.diagnostics.status()

    def refusals(status: DiagnosticStatus) -> str:
        return {v.key: v.value for v in status.values}['obstacle refusals']

    assert tick(0, False).level == DiagnosticStatus.OK
    status = tick(1, True)   # refused at once (obstacle_refuse_delay 0)
    assert status.level == DiagnosticStatus.WARN and 'holding 0.20 m back' in status.message
    assert node.set_parameters([Parameter('trajectory_generator.obstacle_back_off',
                                          value=0.3)])[0].successful
    status = node.diagnostics.status()
    assert status.level == DiagnosticStatus.WARN and 'holding 0.20 m back' in status.message
    assert refusals(status) == '1'
    status = tick(2, False)  # the new refusal has seen no blocking: eq. (9) on the reference
    assert status.level == DiagnosticStatus.OK and refusals(status) == '0'
    assert out[-1].v_d > 0.0


def test_reference_cmd_vel_restarts_at_rest_behind_a_blocked_estimate(context, harnesses):
    # A commanded reference that ran on ahead restarts at rest obstacle_back_off behind
    # the pose of the estimate at which the generator refuses (obstacle_refuse_delay after
    # the first that says obstacle_blocked), so that the generator's refusal ends and a
    # new command resumes from there (core/obstacle_refusal.py).
    from geometry_msgs.msg import TwistStamped
    harness = start(harnesses, context, ReferenceNode,
                    inputs=['/clock', '/wip/state_estimate'], outputs=['/wip/reference'],
                    **{'reference.kind': 'cmd_vel',
                       'trajectory_generator.obstacle_refuse_delay': 0.0})
    harness.publisher(TwistStamped, '/cmd_vel')
    harness.wait_matched()
    out, node = harness.outputs['/wip/reference'], harness.node
    harness.publish('/clock', clock(0))
    harness.spin_until(lambda: out, 'the first reference')
    msg = TwistStamped(header=make_header(0))
    msg.twist.linear.x = 0.3
    harness.publish('/cmd_vel', msg)
    harness.spin_until(lambda: node.diagnostics.received['cmd_vel'] == 1, 'the command')
    tick_every(harness, out, 10 * H_NS, 0.3)
    assert out[-1].v > 0.0
    received = node.diagnostics.received
    harness.publish('/wip/state_estimate', estimate_msg(
        6 * 10 * H_NS, x=0.05, y=0.0, phi=0.0, obstacle_blocked=True))
    harness.spin_until(lambda: received['state_estimate'] == 1, 'the estimate')
    harness.publish('/clock', clock(40 * H_NS * 10))
    harness.spin_until(lambda: out[-1].header.stamp == ns_to_stamp(400 * H_NS),
                       'the reference after it')
    assert (out[-1].x, out[-1].y, out[-1].v, out[-1].omega) == pytest.approx(
        (0.05 - 0.2, 0.0, 0.0, 0.0), abs=1e-12)
    assert 'restarted at rest at (-0.15, 0.00) m' in node.diagnostics.values['obstacle']


# ----------------------------------------------------------------------------- ARC

def arc_inputs(n):
    for k in range(n):
        t = k * H_NS / 1e9
        yield (k * H_NS, dict(omega=0.1 * math.sin(5 * t), f1=0.3 * math.cos(2 * t)),
               dict(v_d=0.5, omega_d=0.2, omega_d_dot=0.4 * math.cos(3 * t)))


def run_arc(harness, n, seed=3):
    out = harness.outputs['/wip/yaw_torque']
    rng = random.Random(seed)
    for k, (stamp, est, cmd) in enumerate(arc_inputs(n)):
        msgs = [('/wip/state_estimate', estimate_msg(stamp, **est)),
                ('/wip/velocity_command', VelocityCommandMsg(header=make_header(stamp), **cmd))]
        publish_shuffled(harness, msgs, rng)
        harness.spin_until(lambda: len(out) == k + 1, f'yaw torque {k}')
    return out


ARC_INPUTS = ('/wip/state_estimate', '/wip/velocity_command')


def arc_harness(harnesses, context, mode='lockstep', **params):
    return start(harnesses, context, ArcNode, mode, ARC_INPUTS, ['/wip/yaw_torque'],
                 **params)


def arc_expected(config, n, alpha_initial=None):
    if alpha_initial is None:
        alpha_initial = initial_alpha(ModelParams(), EsoParams().yaw_input_gain_scale)
    arc = AdaptiveRobustYawController(config, alpha_initial)
    return [arc.step(1.0 / 200.0, est['omega'], est['f1'], cmd['omega_d'], cmd['omega_d_dot'])
            for _, est, cmd in arc_inputs(n)]


def test_arc_yaw_rate_gain_from_a_params_file_equals_the_core(params_context, harnesses):
    ctx = params_context('arc', {'arc': {'yaw_rate_gain': 5.0}, 'clock_mode': 'lockstep'})
    harness = wire(harness_of(harnesses, ArcNode(context=ctx)), ARC_INPUTS,
                   ['/wip/yaw_torque'])
    assert harness.node.lockstep
    out = run_arc(harness, 30)
    expected = arc_expected(ArcParams(yaw_rate_gain=5.0), 30)
    default = arc_expected(ArcParams(), 30)
    for msg, exp in zip(out, expected):
        assert (msg.tau_omega, msg.alpha_hat, msg.e_omega) == tuple(exp)
    assert out[-1].tau_omega != default[-1].tau_omega


def test_arc_computes_its_initial_alpha_from_the_model_and_the_eso_gain_scale_it_is_given(
        params_context, harnesses):
    # α̂(0) = 1/ĝ1 is derived in the node from model.* and eso.yaw_input_gain_scale (one
    # source each, as the runner's ControlStep), not passed in as a number of its own.
    model = ModelParams(body_mass=30.0, yaw_inertia=1.5)
    ctx = params_context('arc', {'clock_mode': 'lockstep', 'eso': {'yaw_input_gain_scale': 1.5},
                                 'model': {'body_mass': 30.0, 'yaw_inertia': 1.5}})
    harness = wire(harness_of(harnesses, ArcNode(context=ctx)), ARC_INPUTS,
                   ['/wip/yaw_torque'])
    alpha0 = initial_alpha(model, 1.5)
    default_alpha = initial_alpha(ModelParams(), EsoParams().yaw_input_gain_scale)
    assert alpha0 != pytest.approx(default_alpha)
    assert harness.node.controller.alpha_hat == alpha0
    out = run_arc(harness, 20)
    expected = arc_expected(ArcParams(), 20, alpha0)
    assert [(m.tau_omega, m.alpha_hat) for m in out] == \
        [(e.tau_omega, e.alpha_hat) for e in expected]


def test_arc_rejects_a_bad_run_time_parameter_with_the_reason_and_applies_a_good_one(
        context, harnesses):
    harness = arc_harness(harnesses, context)
    node = harness.node
    result = node.set_parameters([Parameter('arc.yaw_rate_gain', value=-1.0)])[0]
    assert not result.successful and result.reason.startswith('arc.yaw_rate_gain: must be > 0')
    result = node.set_parameters([Parameter('arc.alpha_max', value=0.01)])[0]
    assert not result.successful and 'alpha_max: must exceed alpha_min' in result.reason
    result = node.set_parameters([Parameter('rates.control_rate', value=100.0)])[0]
    assert not result.successful                     # read-only at run time
    assert node.set_parameters([Parameter('arc.yaw_rate_gain', value=7.0)])[0].successful
    out = run_arc(harness, 10)
    expected = arc_expected(ArcParams(yaw_rate_gain=7.0), 10)
    assert [m.tau_omega for m in out] == [e.tau_omega for e in expected]


# ----------------------------------------------------------------------------- MPC

def mpc_inputs(n):
    for k in range(n):
        t = k * H_NS / 1e9
        yield (k * H_NS, dict(v=0.1 * t, theta=0.05 - 0.1 * t, theta_dot=-0.1, f2=0.2 * t,
                              f3=1.0 - t), 0.4 + t, 0.3 * math.sin(20 * t))


def mpc_harness(harnesses, context, mode='lockstep', **params):
    return start(harnesses, context, MpcNode, mode,
                 ('/wip/state_estimate', '/wip/velocity_command', '/wip/yaw_torque'),
                 ['/wip/drive_torque'], **params)


# DAQP is bit-reproducible: exact equality. ProxSuite's result depends in the last bits on
# the memory alignment of the QP arrays (Eigen peels its vectorised sums to alignment): two
# LongitudinalMpc instances on the same inputs, in one process, differ by 7e-15 N m at the
# first tick and 2.2e-12 N m at the third (measured over 40 instances), so 1e-9 N m.
@pytest.mark.parametrize('backend, tolerance', [('daqp', 0.0), ('proxsuite', 1e-9)])
def test_mpc_lockstep_solves_at_each_tick_from_t0_and_equals_the_core(
        context, harnesses, backend, tolerance):
    # Without the push trigger: its inputs (f̂3 falls by 1 rad/s² per second) would show a
    # push between the MPC's ticks, which the bare core below does not look for.
    harness = mpc_harness(harnesses, context, **{'mpc.backend': backend,
                                                 'mpc.push_trigger': False})
    out = harness.outputs['/wip/drive_torque']
    mpc = LongitudinalMpc(ModelParams(), MpcParams(backend=backend))
    rng = random.Random(4)
    ticks = 0
    for stamp, est, v_d, tau_omega in mpc_inputs(45):
        msgs = [('/wip/state_estimate', estimate_msg(stamp, **est)),
                ('/wip/velocity_command', VelocityCommandMsg(header=make_header(stamp),
                                                             v_d=v_d)),
                ('/wip/yaw_torque', YawTorque(header=make_header(stamp), tau_omega=tau_omega))]
        publish_shuffled(harness, msgs, rng)
        if stamp % (20 * H_NS) != 0:
            continue  # not a tick: no output (checked below: outputs only at ticks)
        ticks += 1
        harness.spin_until(lambda: len(out) == ticks, f'MPC tick at {stamp}')
        expected = mpc.step(est['v'], est['theta'], est['theta_dot'], est['f2'], est['f3'],
                            v_d, drive_torque_limit(tau_omega, 15.0))
        msg = out[-1]
        assert msg.header.stamp == ns_to_stamp(stamp)
        got = (msg.tau_v, msg.delta_tau, msg.slack_v, msg.slack_theta)
        assert got == pytest.approx((expected.tau_v, expected.delta_tau, expected.slack_v,
                                     expected.slack_theta), rel=0.0, abs=tolerance)
        assert (msg.status, msg.status_text, msg.used_fallback) == (
            DriveTorque.SOLVED, 'SOLVED', False)
        if tolerance == 0.0:
            assert msg.iterations == expected.iterations
        for i, name in enumerate(('predicted_v', 'predicted_theta', 'predicted_theta_dot')):
            assert list(getattr(msg, name)) == pytest.approx(
                expected.predicted[:, i].tolist(), rel=0.0, abs=tolerance)
        assert msg.sampling_period == 0.1 and msg.solve_time > 0.0
    harness.spin_for(0.05)
    assert [m.header.stamp for m in out] == [ns_to_stamp(k * H_NS) for k in (0, 20, 40)]
    assert len({round(m.tau_v, 6) for m in out}) == 3  # three different torques


def test_mpc_lockstep_holds_on_the_estimate_alone_and_solves_on_a_push(context, harnesses):
    """With the push trigger the node answers every control tick.

    Where the stage does not solve, HELD as soon as the tick's estimate has come (whether
    it solves depends on the estimate only; the command and yaw torque of that tick are
    then not needed); where the estimate shows a push (f̂2 10 m/s², beyond the 1 m/s² dead
    zone), it waits for the tick's inputs and solves, at that tick, off the 50 ms grid.
    """
    harness = mpc_harness(harnesses, context, **{'mpc.backend': 'daqp',
                                                 'mpc.disturbance_startup_time': 0.0})
    out = harness.outputs['/wip/drive_torque']

    def command_and_yaw(stamp):
        harness.publish('/wip/velocity_command',
                        VelocityCommandMsg(header=make_header(stamp), v_d=0.3))
        harness.publish('/wip/yaw_torque', YawTorque(header=make_header(stamp)))
    harness.publish('/wip/state_estimate', estimate_msg(0))
    command_and_yaw(0)
    harness.spin_until(lambda: len(out) == 1, 'the MPC tick at t = 0')
    assert out[0].status_text == 'SOLVED'
    harness.publish('/wip/state_estimate', estimate_msg(H_NS))
    harness.spin_until(lambda: len(out) == 2, 'the HELD answer on the estimate alone')
    assert out[1].header.stamp == ns_to_stamp(H_NS)
    assert (out[1].status_text, out[1].tau_v) == (HELD_STATUS_TEXT, out[0].tau_v)
    command_and_yaw(H_NS)                                   # not needed: no answer
    stamp = 3 * H_NS
    harness.publish('/wip/state_estimate', estimate_msg(2 * H_NS))
    harness.spin_until(lambda: len(out) == 3, 'the HELD answer at tick 2')
    harness.publish('/wip/state_estimate', estimate_msg(stamp, f2=10.0))
    harness.spin_for(0.05)
    assert len(out) == 3, 'a push: the node must wait for the command and the yaw torque'
    command_and_yaw(2 * H_NS)
    command_and_yaw(stamp)
    harness.spin_until(lambda: len(out) == 4, 'the solve on the push')
    assert out[3].header.stamp == ns_to_stamp(stamp) and out[3].status_text == 'SOLVED'
    assert out[3].delta_tau != 0.0


def test_mpc_node_runs_the_lqr_baseline_when_selected(context, harnesses):
    # mpc.controller: lqr -> the node publishes core.lqr.LongitudinalLqr's torque (no QP,
    # deterministic: exact equality).
    harness = mpc_harness(harnesses, context, **{'mpc.controller': 'lqr',
                                                 'mpc.push_trigger': False})
    out = harness.outputs['/wip/drive_torque']
    lqr = LongitudinalLqr(ModelParams(), MpcParams(controller='lqr'))
    ticks = 0
    for stamp, est, v_d, tau_omega in mpc_inputs(45):
        harness.publish('/wip/state_estimate', estimate_msg(stamp, **est))
        harness.publish('/wip/velocity_command',
                        VelocityCommandMsg(header=make_header(stamp), v_d=v_d))
        harness.publish('/wip/yaw_torque',
                        YawTorque(header=make_header(stamp), tau_omega=tau_omega))
        if stamp % (20 * H_NS) != 0:
            continue
        ticks += 1
        harness.spin_until(lambda: len(out) == ticks, f'LQR tick at {stamp}')
        expected = lqr.step(est['v'], est['theta'], est['theta_dot'], est['f2'], est['f3'],
                            v_d, drive_torque_limit(tau_omega, 15.0))
        assert (out[-1].tau_v, out[-1].delta_tau) == (expected.tau_v, expected.delta_tau)
        assert out[-1].status == DriveTorque.SOLVED and out[-1].iterations == 0
    assert ticks == 3


def test_mpc_non_finite_input_answers_input_invalid_with_a_finite_torque(context, harnesses):
    harness = mpc_harness(harnesses, context)
    out = harness.outputs['/wip/drive_torque']
    harness.publish('/wip/state_estimate', estimate_msg(0, theta=float('nan')))
    harness.publish('/wip/velocity_command', VelocityCommandMsg(header=make_header(0)))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(0)))
    harness.spin_until(lambda: out, 'the tick at t = 0')
    stamp = 20 * H_NS
    harness.publish('/wip/state_estimate', estimate_msg(stamp))
    harness.publish('/wip/velocity_command', VelocityCommandMsg(header=make_header(stamp)))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(stamp),
                                                tau_omega=float('inf')))
    harness.spin_until(lambda: len(out) == 2, 'the tick at t = 0.1')
    for msg in out:
        assert msg.status == DriveTorque.INPUT_INVALID and msg.used_fallback
        assert_finite(msg)
        assert len(msg.predicted_v) == 0 and msg.tau_v == 0.0


@pytest.mark.wallclock   # late at 0.05 s, stale at 0.15 s
def test_mpc_realtime_not_ready_then_solved_then_late_then_stale(context, harnesses):
    """Inputs that stop are first late (held, WARN), then stale (INPUT_INVALID, τυ = 0).

    The limits are the safety layer's: late past ``safety.max_estimate_age``, which the
    mixer bridges, so the MPC holds its tick rather than make it a fault; stale past the
    bridge too (``safety.bridge_time``), where the mixer faults anyway.
    """
    harness = mpc_harness(harnesses, context, 'realtime', **{
        'mpc.sampling_period': 0.02, 'safety.max_estimate_age': 0.05,
        'safety.bridge_time': 0.1})
    out = harness.outputs['/wip/drive_torque']
    harness.spin_until(lambda: out, 'a timer tick')
    assert out[0].status == DriveTorque.NOT_READY and out[0].tau_v == 0.0
    assert 'NOT_READY' in out[0].status_text
    now = harness.node.now_ns()
    harness.publish('/wip/state_estimate', estimate_msg(now, theta=0.02))
    harness.publish('/wip/velocity_command', VelocityCommandMsg(header=make_header(now),
                                                                v_d=0.3))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(now)))
    harness.spin_until(lambda: out[-1].status == DriveTorque.SOLVED, 'a solved tick')
    assert out[-1].header.stamp == ns_to_stamp(now)  # stamped with the estimate's time
    diagnostics = harness.node.diagnostics
    harness.spin_until(lambda: 'late' in diagnostics.message, 'late inputs held')
    assert diagnostics.level == WARN
    assert DriveTorque.INPUT_INVALID not in [m.status for m in out]
    harness.spin_until(lambda: out[-1].status == DriveTorque.INPUT_INVALID, 'stale inputs')
    assert out[-1].tau_v == 0.0 and 'stale' in out[-1].status_text
    # Received no earlier than stamped: stale only past the whole ride-through.
    assert stamp_to_ns(out[-1].header.stamp) - now >= 0.15e9
    assert harness.node.mpc.tau_previous == 0.0       # the core knows 0 is applied


def test_mpc_refuses_to_start_on_a_value_outside_its_declared_range(params_context):
    ctx = params_context('mpc', {'mpc': {'eps_abs': 0.5}})
    with pytest.raises(rclpy.exceptions.InvalidParameterValueException, match='mpc.eps_abs'):
        MpcNode(context=ctx)


# ----------------------------------------------------------------------------- mixer

def mixer_harness(harnesses, context, mode='lockstep', **params):
    return start(harnesses, context, TorqueMixerNode, mode,
                 ('/wip/yaw_torque', '/wip/drive_torque'),
                 ['/wip/wheel_torques', '/effort_controller/commands'], **params)


@pytest.mark.parametrize('trigger', [False, True])
def test_mixer_lockstep_waits_for_the_drive_torque_at_ticks_and_holds_it_between(
        context, harnesses, trigger):
    harness = mixer_harness(harnesses, context, **{'mpc.push_trigger': trigger},
                            joints=['right_wheel_joint', 'left_wheel_joint'])
    wheels = harness.outputs['/wip/wheel_torques']
    efforts = harness.outputs['/effort_controller/commands']
    # A drive torque every 10 ticks: the grid of mpc.fast_resolve_period (50 ms), where
    # the MPC node answers every tick (at 10 its HELD answer, the same torque); with the
    # push trigger at every control tick.
    drives = ({k: 12.0 if k < 20 else -29.0 for k in range(25)} if trigger
              else {0: 12.0, 10: 12.0, 20: -29.0})    # -29: the limit 30 - |tau_w| acts
    for k in range(25):
        stamp, tau_omega = k * H_NS, 1.5 * math.sin(k)
        harness.publish('/wip/yaw_torque', YawTorque(header=make_header(stamp),
                                                    tau_omega=tau_omega))
        if k in drives:
            harness.spin_for(0.03)
            assert len(wheels) == k, 'the mixer must wait for the drive torque of a tick'
            harness.publish('/wip/drive_torque', DriveTorque(header=make_header(stamp),
                                                           tau_v=drives[k]))
        harness.spin_until(lambda: len(wheels) == k + 1 and len(efforts) == k + 1,
                           f'wheel torques {k}')
        held = drives[0] if k < 20 else drives[20]
        left, right = mix(held, tau_omega, 15.0)
        msg = wheels[-1]
        assert msg.header.stamp == ns_to_stamp(stamp)
        assert (msg.left, msg.right, msg.zeroed, msg.reason) == (left, right, False, '')
        assert (msg.tau_v, msg.tau_omega) == (left + right, right - left)
        assert list(efforts[-1].data) == [right, left]  # order of the joints parameter
    assert max(max(abs(m.left), abs(m.right)) for m in wheels) <= 15.0


def test_mixer_zeroes_both_wheels_on_non_finite_input_and_says_why(context, harnesses):
    # On the 50 ms grid of the drive torque (no push trigger): ticks 1-19 need none.
    harness = mixer_harness(harnesses, context, **{'mpc.push_trigger': False})
    wheels = harness.outputs['/wip/wheel_torques']
    harness.publish('/wip/drive_torque', DriveTorque(header=make_header(0), tau_v=5.0))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(0), tau_omega=math.nan))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(H_NS), tau_omega=0.1))
    harness.spin_until(lambda: len(wheels) == 2, 'two wheel torques')
    assert (wheels[0].left, wheels[0].right, wheels[0].zeroed) == (0.0, 0.0, True)
    assert 'non-finite yaw torque' in wheels[0].reason
    assert (wheels[1].left, wheels[1].right) == mix(5.0, 0.1, 15.0)
    harness.publish('/wip/drive_torque', DriveTorque(header=make_header(20 * H_NS),
                                                   tau_v=math.inf))
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(20 * H_NS)))
    harness.spin_until(lambda: len(wheels) == 3, 'the tick with an infinite drive torque')
    assert wheels[2].zeroed and 'non-finite drive torque' in wheels[2].reason
    for msg in wheels + harness.outputs['/effort_controller/commands']:
        assert_finite(msg)


def test_mixer_run_time_limit_change_and_bad_joints(context, params_context, harnesses):
    # Real time: the safety layer (tests/wip_control/nodes/test_safety_node.py) sends torque only
    # once a settled estimate has arrived too; no settle time here. Each input is sent
    # once, so the age limits are long: a loaded machine may pause this process for more
    # than the default 50 ms between two of them (ages are tested in test_safety_node.py).
    harness = start(harnesses, context, TorqueMixerNode, 'realtime',
                    **{'safety.settle_time': 0.0, 'safety.max_estimate_age': 30.0,
                       'safety.max_yaw_torque_age': 30.0,
                       'safety.max_drive_torque_age': 30.0},
                    inputs=['/wip/yaw_torque', '/wip/drive_torque', '/wip/state_estimate'],
                    outputs=['/wip/wheel_torques'])
    wheels = harness.outputs['/wip/wheel_torques']
    node = harness.node
    assert not node.set_parameters([Parameter('mixer.max_wheel_torque', value=-2.0)])[0] \
        .successful
    assert node.set_parameters([Parameter('mixer.max_wheel_torque', value=2.0)])[0].successful
    harness.publish('/wip/state_estimate', estimate_msg(4, settled=True))
    harness.publish('/wip/drive_torque', DriveTorque(header=make_header(5), tau_v=10.0))
    harness.spin_for(0.02)
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(6), tau_omega=0.5))
    # The safety layer's rate limit is per second of the clock: the tick the yaw torque
    # triggers may come a fraction of a millisecond after a watchdog tick and take only a
    # step toward the mix; the ticks after it reach the mix, never beyond the limit.
    limited = mix(10.0, 0.5, 2.0)
    harness.spin_until(lambda: any((m.left, m.right) == limited for m in wheels if not m.zeroed),
                       'wheel torques mixed within the 2 N m limit')
    assert all(abs(m.left) <= 2.0 and abs(m.right) <= 2.0 for m in wheels)
    # The status is made when it is sent, from the last tick: a new limit applies from
    # the next tick, and the status still says the one the last tick was mixed with.
    clipped = 'ACTIVE: wheel torque at the 2 N m limit'
    assert node.diagnostics.status().message == clipped
    assert node.set_parameters([Parameter('mixer.max_wheel_torque', value=20.0)])[0].successful
    assert node.diagnostics.status().message == clipped
    ctx = params_context('torque_mixer', {'joints': ['left_wheel_joint', 'caster']})
    with pytest.raises(ParamError, match=r'joints: must list'):
        TorqueMixerNode(context=ctx)


def test_topics_are_remappable(context, harnesses):
    node = TorqueMixerNode(context=context, parameter_overrides=overrides('realtime'),
                           cli_args=['--ros-args', '-r', '/wip/wheel_torques:=/robot/torques'])
    harness = harness_of(harnesses, node)
    harness.publisher(YawTorque, '/wip/yaw_torque')
    out = harness.listen(WheelTorques, '/robot/torques')
    harness.wait_matched()
    harness.publish('/wip/yaw_torque', YawTorque(header=make_header(1), tau_omega=0.2))
    harness.spin_until(lambda: out, 'wheel torques on the remapped topic')


# ----------------------------------------------------------------------------- all six

@pytest.mark.parametrize('composed', [False, True], ids=['dds', 'composed'])
def test_six_nodes_in_lockstep_reproduce_the_in_process_runner(context, harnesses, composed):
    """Six nodes in lockstep reproduce the in-process runner.

    A minimal plant (the runner's plant, sensors and disturbances) drives the six nodes
    in lockstep: the wheel torques equal the runner's from t = 0 on. ``composed``: as in
    ``ros2 run wip_control controllers``, one /clock subscription for all six and the
    messages between them delivered in-process (wip_runtime.composition.connect_intra_process).

    Not bit-exact: GPS goes through a geodetic round trip (1e-9 m), the IMU through a
    quaternion (1e-16 rad), t = ns/1e9 instead of k h, and ProxSuite's last bits depend
    on memory alignment; measured max difference 6e-10 N m over 2 s, 4e-9 N m over 10 s.
    """
    scenario = dataclasses.replace(Scenario(), duration=1.0)
    wheels = run_scenario(scenario).record.groups['wheels']
    nodes = [cls(context=context, parameter_overrides=overrides()) for cls in
             (ReferenceNode, EsoNode, TrajectoryGeneratorNode, ArcNode, MpcNode)]
    harness = start(harnesses, context, TorqueMixerNode)
    harness.add(*nodes)
    if composed:
        assert share_sim_clock([*nodes, harness.node]) is nodes[0]
        harness.bus = connect_intra_process([*nodes, harness.node])
        harness.after_spin = harness.bus.drain   # the in-process delivery
        assert sum(1 for node in (*nodes, harness.node) for sub in node.subscriptions
                   if sub.topic_name == '/clock') == 1
    wire(harness, ('/clock', '/joint_states', '/imu/data', '/gps/fix'),
         ['/wip/wheel_torques'])
    out = harness.outputs['/wip/wheel_torques']
    plant = Plant(scenario.plant.parameters, scenario.plant.model.model)
    disturbances = Disturbances(scenario.disturbances, seed=scenario.seed)
    state = initial_state(scenario, make_reference(scenario.reference).sample(0.0))
    sensors = Sensors(scenario.plant.parameters, scenario.sensors,
                      initial_yaw=float(state[PHI]), seed=scenario.seed)
    n = int(round(scenario.duration * 200))
    for k in range(n):
        stamp = k * H_NS
        harness.publish('/clock', clock(stamp))
        harness.publish('/joint_states', joint_states(stamp, *sensors.encoders(state)))
        pitch, yaw = sensors.imu(state)
        harness.publish('/imu/data', imu(stamp, pitch, yaw, sensors.imu_rates(state)))
        if k % 20 == 0:
            harness.publish('/gps/fix', gps_fix(stamp, *sensors.gps(state)))
        harness.spin_until(lambda: len(out) == k + 1, f'wheel torques at step {k}')
        assert out[-1].header.stamp == ns_to_stamp(stamp)
        state = simulate_hold(plant, state, out[-1].left, out[-1].right, disturbances.sample,
                              k * 0.005, 0.001, 5)
    graph = [v for m in out for v in (m.left, m.right)]
    runner = [float(v) for pair in zip(wheels['tau_left'][:n], wheels['tau_right'][:n])
              for v in pair]
    # 1e-7 N m: 100x the measured difference (see the docstring), 1e-8 of the torques.
    assert graph == pytest.approx(runner, rel=0.0, abs=1e-7)
    assert max(abs(v) for v in graph) > 0.1     # the loop really acts
    if composed:
        # Estimate, command, yaw torque, reference and drive torque went in-process (the
        # harness subscribes none of them); the wheel torques, which the harness (the
        # plant) subscribes, went to DDS for everyone, the eso node included; every
        # node's clock followed /clock.
        assert harness.bus.delivered >= 4 * n and harness.bus.published_dds == n
        assert all(node.get_clock().now().nanoseconds == (n - 1) * H_NS
                   for node in (*nodes, harness.node))


# ----------------------------------------------------------------------------- bad input

def _publish_bad_inputs(harness, bad):
    """Publish each bad message with valid other inputs of its stamp: (topics, count)."""
    topics = {t: m for t, m, _ in bad}
    published = 0
    for k, (topic, msg_type, fields) in enumerate(bad):
        stamp = k * 20 * H_NS              # MPC ticks, so the MPC answers them
        harness.publish(topic, msg_type(header=make_header(stamp), **fields))
        # The other inputs of the same stamp, valid, so that lockstep sets complete.
        for other, other_type in topics.items():
            if other != topic:
                harness.publish(other, other_type(header=make_header(stamp)))
        published += len(topics)
    return topics, published


def test_bad_input_into_every_subscription_never_raises_or_outputs_non_finite(
        context, harnesses):
    nan, inf = float('nan'), float('inf')
    cases = {
        TrajectoryGeneratorNode: [
            ('/wip/reference', ReferenceStateMsg, dict(x=nan)),
            ('/wip/reference', ReferenceStateMsg, dict(v=inf)),
            ('/wip/state_estimate', StateEstimateMsg, dict(phi=nan)),
            ('/wip/state_estimate', StateEstimateMsg, dict(x=-inf))],
        ArcNode: [
            ('/wip/velocity_command', VelocityCommandMsg, dict(omega_d=nan)),
            ('/wip/velocity_command', VelocityCommandMsg, dict(omega_d_dot=inf)),
            ('/wip/state_estimate', StateEstimateMsg, dict(f1=nan)),
            ('/wip/state_estimate', StateEstimateMsg, dict(omega=inf))],
        MpcNode: [
            ('/wip/state_estimate', StateEstimateMsg, dict(v=nan)),
            ('/wip/velocity_command', VelocityCommandMsg, dict(v_d=inf)),
            ('/wip/yaw_torque', YawTorque, dict(tau_omega=nan))],
        TorqueMixerNode: [
            ('/wip/drive_torque', DriveTorque, dict(tau_v=nan, predicted_v=[nan, 1.0])),
            ('/wip/yaw_torque', YawTorque, dict(tau_omega=-inf))],
    }
    outputs = {TrajectoryGeneratorNode: (VelocityCommandMsg, '/wip/velocity_command'),
               ArcNode: (YawTorque, '/wip/yaw_torque'),
               MpcNode: (DriveTorque, '/wip/drive_torque'),
               TorqueMixerNode: (WheelTorques, '/wip/wheel_torques')}
    for node_cls, bad in cases.items():
        for mode in ('lockstep', 'realtime'):
            extra = {'mpc.sampling_period': 0.01} if node_cls is MpcNode else {}
            harness = start(harnesses, context, node_cls, mode, **extra)
            for topic, msg_type, _ in bad:
                if topic not in harness.publishers:
                    harness.publisher(msg_type, topic)
            out = harness.listen(*outputs[node_cls])
            harness.wait_matched()
            topics, published = _publish_bad_inputs(harness, bad)
            received = harness.node.diagnostics.received
            harness.spin_until(lambda: sum(received.values()) == published,
                               'every message')
            harness.spin_for(0.05)
            for msg in out:
                assert_finite(msg)
            dropped = harness.node.diagnostics.dropped
            if node_cls in (TrajectoryGeneratorNode, ArcNode):
                # Dropped, counted, and in lockstep no set of those stamps completes.
                assert dropped == {(t.split('/')[-1], 'invalid'): 2 for t in topics}
                assert mode == 'realtime' or out == []
            elif mode == 'lockstep':
                # Passed on and neutralised: one answer per stamp, never NaN.
                assert len(out) == len(bad) and not dropped
                if node_cls is MpcNode:
                    assert {m.status for m in out} == {DriveTorque.INPUT_INVALID}
                else:
                    assert all(m.zeroed and (m.left, m.right) == (0.0, 0.0) for m in out)
            harness.close()
            harnesses.remove(harness)


# ----------------------------------------------------------------------------- processes

def _node_process(module, *ros_args):
    """``python -m wip_control.nodes.<module> --ros-args ...``, killed at the block's end."""
    return node_process([sys.executable, '-m', f'wip_control.nodes.{module}', '--ros-args',
                         *ros_args])


def test_node_process_refuses_to_start_on_a_bad_params_file(domain_id, tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump({'arc': {'ros__parameters': {
        'arc': {'yaw_rate_gain': -3.0}}}}))
    with _node_process('arc_node', '--params-file', str(path)) as process:
        _, stderr = communicate(process, PROCESS_START_TIMEOUT)
    assert process.returncode == 2     # the table's usage or input error
    assert 'arc: error: arc.yaw_rate_gain: must be > 0.0, got -3.0' in stderr


def test_reference_node_process_runs_lockstep_on_the_events_executor_and_stops_on_sigint(
        context, harnesses):
    with _node_process('reference_node', '-p', 'clock_mode:=lockstep',
                       '-p', 'use_sim_time:=true') as process:
        harness = NodeHarness(context)   # no node under test here: it is the process
        harnesses.append(harness)
        io, executor = harness.io, harness.executor
        out = []
        io.create_subscription(ReferenceStateMsg, '/wip/reference', out.append, 10)
        pub = io.create_publisher(Clock, '/clock', CLOCK_QOS)
        deadline = time.monotonic() + PROCESS_START_TIMEOUT
        # One /clock subscription: the node's ticker also drives its clock (ClockTicker).
        while pub.get_subscription_count() < 1 or io.count_publishers('/wip/reference') < 1:
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, 'reference node not discovered'
            executor.spin_once(timeout_sec=0.05)
        # Discovery is not symmetric: our reader may know the node's writer before that
        # writer knows our reader: a /clock published before the match is lost either way
        # (volatile). So the first ticks may be lost; the node ignores a
        # repeated clock value, so advance the clock until the first reference arrives.
        first = 0
        while not out:
            assert time.monotonic() < deadline, 'no reference for any tick'
            first += 1
            pub.publish(clock(first * H_NS))
            for _ in range(10):
                executor.spin_once(timeout_sec=0.01)
        # Several clocks may have been sent before the first answer, and one among them
        # lost: take every answer still in flight (none for 1 s), then go
        # on after the newest tick the node answered (it ignores older clocks).
        quiet_since, seen = time.monotonic(), len(out)
        while time.monotonic() - quiet_since < 1.0:
            assert time.monotonic() < deadline, 'answers still arriving'
            executor.spin_once(timeout_sec=0.01)
            if len(out) != seen:
                quiet_since, seen = time.monotonic(), len(out)
        first = max(stamp_to_ns(m.header.stamp) for m in out) // H_NS
        del out[:]
        # Matched both ways now: every tick is answered exactly once, in lockstep.
        deadline = time.monotonic() + 30.0
        ticks = range(first + 1, first + 6)
        for k in ticks:
            sent = -math.inf
            while len(out) < k - first:
                assert time.monotonic() < deadline, f'no reference for tick {k}'
                if time.monotonic() - sent > 1.0:   # best effort: resend; a repeat is ignored
                    pub.publish(clock(k * H_NS))
                    sent = time.monotonic()
                executor.spin_once(timeout_sec=0.01)
        assert [m.header.stamp for m in out] == [ns_to_stamp(k * H_NS) for k in ticks]
        assert out[0].x == make_reference().sample((first + 1) * H_NS * 1e-9).x
        process.send_signal(signal.SIGINT)
        _, stderr = communicate(process, 20, 'stop on SIGINT')
        assert process.returncode == 0, stderr


def test_reference_message_and_core_tuple_have_the_same_fields():
    # The ReferenceState NamedTuple and the message carry the same six fields, in order.
    fields = ReferenceStateMsg.get_fields_and_field_types()
    assert list(ReferenceState._fields) == [f for f in fields if f != 'header']


def test_an_executor_error_after_shutdown_is_a_stop_and_before_it_an_error():
    from rclpy.executors import ExternalShutdownException
    from wip_runtime.executors import spin_once_or_stop

    class Failing:
        def spin_once(self, timeout_sec):
            raise RuntimeError("Unable to convert call argument '0' to Python object")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=0)
    with pytest.raises(RuntimeError, match='Unable to convert'):
        spin_once_or_stop(Failing(), 0.0, context=ctx)
    rclpy.shutdown(context=ctx)
    with pytest.raises(ExternalShutdownException, match='Unable to convert'):
        spin_once_or_stop(Failing(), 0.0, context=ctx)


def test_realtime_input_stamped_far_ahead_is_refused_and_does_not_block_the_stream(
        context, harnesses):
    """A real-time input stamped far ahead is refused and does not block the stream.

    Real time takes inputs newest stamp first: one message from a sender whose clock
    jumped a day ahead must be refused (with the reason), not kept as the newest, which
    would drop every correct message after it.
    """
    harness = arc_harness(harnesses, context, 'realtime')
    out = harness.outputs['/wip/yaw_torque']
    dropped = harness.node.diagnostics.dropped
    now = harness.node.now_ns()
    est = dict(omega=0.1, f1=0.0)
    cmd = dict(v_d=0.5, omega_d=0.2, omega_d_dot=0.0)
    harness.publish('/wip/velocity_command', VelocityCommandMsg(header=make_header(now),
                                                                **cmd))
    harness.publish('/wip/state_estimate', estimate_msg(now + 86_400 * 10**9, **est))
    harness.spin_until(lambda: dropped[('state_estimate', 'invalid')] == 1, 'the refusal')
    assert out == []
    reason = harness.node.diagnostics.last_drop      # what /diagnostics reports
    assert 'ahead of this node' in reason and 'max_stamp_lead' in reason, reason
    for k in range(1, 4):      # correct stamps right after it are used
        stamp = now + k * H_NS
        harness.publish('/wip/state_estimate', estimate_msg(stamp, **est))
        harness.spin_until(lambda: len(out) == k, f'yaw torque {k}')
        assert out[-1].header.stamp == ns_to_stamp(stamp)
    # A small lead (clocks of two computers a few ms apart) is accepted.
    stamp = harness.node.now_ns() + 10**8
    harness.publish('/wip/state_estimate', estimate_msg(stamp, **est))
    harness.spin_until(lambda: len(out) == 4, 'the input 0.1 s ahead')


def test_diagnostics_report_the_dds_match_counts_of_both_sides(context, harnesses):
    """The diagnostics report the DDS match counts of both sides.

    The graph runner starts a lockstep run only when both sides of every pair count
    each other: the node must report them (and not ROS infrastructure topics).
    """
    harness = arc_harness(harnesses, context)
    values = {kv.key: kv.value for kv in harness.node.diagnostics.status().values}
    assert values['matched publishers /wip/state_estimate'] == '1'
    assert values['matched publishers /wip/velocity_command'] == '1'
    assert values['matched subscriptions /wip/yaw_torque'] == '1'   # the harness
    assert not any(k.endswith(('/rosout', '/parameter_events', '/diagnostics'))
                   for k in values)


def test_the_readme_params_file_of_a_real_base_is_taken_by_the_eso_and_the_mixer(
        domain_id, tmp_path):
    """The README's "Running on a real base" example must stay loadable as written."""
    readme = (pathlib.Path(__file__).resolve().parents[3] / 'README.md').read_text()
    start = readme.index('```yaml\n/**:') + len('```yaml\n')
    path = tmp_path / 'my_base.yaml'
    path.write_text(readme[start:readme.index('```', start)])
    example = yaml.safe_load(path.read_text())['/**']['ros__parameters']
    ctx = _new_context(domain_id, ['--ros-args', '--params-file', str(path)])
    try:
        realtime = [Parameter('clock_mode', value='realtime')]
        eso = EsoNode(context=ctx, parameter_overrides=realtime)
        mixer = TorqueMixerNode(context=ctx, parameter_overrides=realtime)
        assert (eso.left_joint, eso.right_joint) == (example['left_joint'],
                                                     example['right_joint'])
        signs = (example['left_wheel_sign'], example['right_wheel_sign'])
        assert (eso.left_sign, eso.right_sign) == signs == (mixer.left_sign, mixer.right_sign)
        assert eso.model.wheel_radius == example['model.wheel_radius']
        assert eso.model.track_width == example['model.track_width']
        assert eso.datum[0] == example['datum.latitude']
        assert mixer.joints == example['joints']
        eso.destroy_node()
        mixer.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


# ----------------------------------------------------------- commanded references, /odom

def tick_every(harness, out, step_ns, duration):
    """Publish /clock every step_ns up to duration [s], waiting for the reference each time.

    Publish /clock every step_ns up to duration [s], each time waiting for the
    reference (a burst of clock messages would overrun the clock's queue).
    """
    for k in range(1, round(duration * 1e9 / step_ns) + 1):
        count = len(out)
        harness.publish('/clock', clock(k * step_ns))
        harness.spin_until(lambda: len(out) == count + 1, f'the reference at tick {k}')


def test_reference_cmd_vel_follows_stamped_commands_and_refuses_bad_ones(context, harnesses):
    from geometry_msgs.msg import TwistStamped
    harness = start(harnesses, context, ReferenceNode, inputs=['/clock'],
                    outputs=['/wip/reference'], **{'reference.kind': 'cmd_vel'})
    harness.publisher(TwistStamped, '/cmd_vel')
    harness.wait_matched()
    out, node = harness.outputs['/wip/reference'], harness.node
    harness.publish('/clock', clock(0))
    harness.spin_until(lambda: out, 'the first reference')

    def command(stamp_ns, v, w):
        msg = TwistStamped(header=make_header(stamp_ns))
        msg.twist.linear.x, msg.twist.angular.z = v, w
        count = node.diagnostics.received['cmd_vel']
        harness.publish('/cmd_vel', msg)
        harness.spin_until(lambda: node.diagnostics.received['cmd_vel'] == count + 1,
                           'the command')
    command(0, math.nan, 0.0)
    command(10 * 10**9, 0.3, 0.0)                     # 10 s in the future
    command(0, 9.0, 0.1)                              # clipped to 0.5 m/s, 0.25 rad/s
    dropped = node.diagnostics.dropped
    assert dropped[('cmd_vel', 'invalid')] == 1 and dropped[('cmd_vel', 'future')] == 1
    tick_every(harness, out, 10 * H_NS, 1.0)
    speeds = [m.v for m in out]
    # Accelerates at 0.3 m/s^2 until the command times out at 0.5 s, then brakes.
    assert max(speeds) == pytest.approx(0.15, abs=1e-9)
    assert speeds[10] == pytest.approx(0.15) and speeds[-1] < speeds[10]
    assert all(abs(m.omega) <= 0.25 for m in out) and out[-1].phi > 0.0
    assert node.diagnostics.values['command'] == 'no command in force: braking'


def test_reference_path_in_another_frame_is_refused_and_a_map_path_followed(
        context, harnesses):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    harness = start(harnesses, context, ReferenceNode, inputs=['/clock'],
                    outputs=['/wip/reference'], **{'reference.kind': 'path'})
    harness.publisher(Path, '/plan')
    harness.wait_matched()
    node = harness.node

    def path(frame_id, points):
        msg = Path(header=make_header(0, frame_id))
        for x, y in points:
            pose = PoseStamped()
            pose.pose.position.x, pose.pose.position.y = x, y
            msg.poses.append(pose)
        count = node.diagnostics.received['plan']
        harness.publish('/plan', msg)
        harness.spin_until(lambda: node.diagnostics.received['plan'] == count + 1,
                           'the path')
    path('odom', [(1.0, 0.0)])
    path('map', [(1.0, math.inf)])
    assert node.diagnostics.dropped[('plan', 'frame')] == 1
    assert node.diagnostics.dropped[('plan', 'invalid')] == 1
    assert node.reference.done
    path('map', [(1.0, 0.0), (1.0, 1.0)])
    assert node.reference.points == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    out = harness.outputs['/wip/reference']
    tick_every(harness, out, 10 * H_NS, 4.0)
    assert out[-1].x > 0.5 and 0.0 < out[-1].v <= 0.3
    assert node.diagnostics.values['command'] == 'following the path'
    # The same path again (a route publisher repeating it) changes nothing.
    before = (list(node.reference.points), node.reference.progress)
    path('map', [(1.0, 0.0), (1.0, 1.0)])
    assert node.reference.joined == 'same'
    assert (node.reference.points, node.reference.progress) == before


def test_eso_publishes_odometry_of_the_estimate_in_real_time(context, harnesses):
    from nav_msgs.msg import Odometry
    harness = start(harnesses, context, EsoNode, 'realtime', ESO_INPUTS,
                    ['/wip/state_estimate'], odometry_decimation=2)
    odom = harness.listen(Odometry, '/odom')
    harness.wait_matched()
    estimates = harness.outputs['/wip/state_estimate']
    wall = time.time_ns()
    for k, s in enumerate(eso_measurements(12)):
        if k == 2:   # the first fix: no /odom before a valid position
            harness.publish('/gps/fix', gps_fix(wall + s['stamp'], 0.0, 0.0))
        harness.publish('/imu/data', imu(wall + s['stamp'], s['pitch'], s['yaw'], s['rates']))
        harness.publish('/joint_states', joint_states(wall + s['stamp'], s['left'], s['right']))
        harness.spin_until(lambda: len(estimates) == k + 1, f'estimate {k}')
    harness.spin_until(lambda: len(odom) == 5, 'every second estimate on /odom')
    statuses = [e.position_status for e in estimates]
    # The fix is used by the first update after it arrived (sample 2, or 3 if the sample's
    # encoder and IMU messages came first).
    tracking = statuses.index(StateEstimateMsg.POSITION_TRACKING)
    assert tracking in (2, 3), statuses
    assert set(statuses[:tracking]) == {StateEstimateMsg.POSITION_NO_FIX}
    assert set(statuses[tracking:]) == {StateEstimateMsg.POSITION_TRACKING}
    # The decimation counts the estimates /odom carries: those from the first fix on.
    for msg, est in zip(odom, estimates[tracking::2]):
        assert msg.header.stamp == est.header.stamp
        assert (msg.header.frame_id, msg.child_frame_id) == ('odom', 'base_link')
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (est.x, est.y)
        q = msg.pose.pose.orientation
        assert 2.0 * math.atan2(q.z, q.w) == pytest.approx(math.remainder(est.phi, 2 * math.pi))
        assert (msg.twist.twist.linear.x, msg.twist.twist.angular.z) == (est.v, est.omega)
        assert msg.pose.covariance[0] == msg.pose.covariance[7] == 0.25
        assert msg.pose.covariance[35] == pytest.approx(0.05 ** 2)
        assert msg.twist.covariance[0] == pytest.approx(0.05 ** 2)
    # Off in lockstep by default (the viewer's /wip/odom/estimate serves the simulation).
    lockstep = start(harnesses, context, EsoNode, 'lockstep')
    assert lockstep.node.odometry_publisher is None


def test_eso_odometry_transforms_compose_to_the_odometry_pose(context, harnesses):
    # A tf consumer (tests/tf_reader.py) reads /tf_static (map -> odom) and /tf
    # (odom -> base_link), composes map -> base_link at each /odom stamp and must find
    # /odom's pose: the same numbers, not merely close.
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSDurabilityPolicy, QoSProfile
    from tf2_msgs.msg import TFMessage
    from tf_reader import TfBuffer, yaw

    # Dead reckoning: the position is valid from the first sample (no fix to wait for).
    inputs = [topic for topic in ESO_INPUTS if topic != '/gps/fix']
    harness = start(harnesses, context, EsoNode, 'realtime', inputs,
                    ['/wip/state_estimate'], odometry_decimation=2, position_source='wheels',
                    odometry_frame_id='robot1/odom', odometry_child_frame_id='robot1/base_link')
    odom = harness.listen(Odometry, '/odom')
    tf = harness.listen(TFMessage, '/tf')
    tf_static = harness.listen(TFMessage, '/tf_static', QoSProfile(
        depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL))
    harness.wait_matched()
    wall = time.time_ns()
    estimates = harness.outputs['/wip/state_estimate']
    for k, s in enumerate(eso_measurements(10)):
        harness.publish('/imu/data', imu(wall + s['stamp'], s['pitch'], s['yaw'] + 0.7,
                                         s['rates']))
        harness.publish('/joint_states', joint_states(wall + s['stamp'], s['left'], s['right']))
        harness.spin_until(lambda: len(estimates) == k + 1, f'estimate {k}')
    harness.spin_until(lambda: len(odom) == 5 and len(tf) == 5 and tf_static, '/odom, /tf')
    assert [len(m.transforms) for m in tf_static] == [1]
    static = tf_static[0].transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ('map', 'robot1/odom')
    buffer = TfBuffer()
    buffer.add(tf_static[0].transforms, static=True)
    for message in tf:
        buffer.add(message.transforms)
    for msg in odom:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        translation, rotation = buffer.lookup('map', 'robot1/base_link', stamp)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        assert tuple(translation) == (p.x, p.y, p.z)
        assert rotation == (q.x, q.y, q.z, q.w)
        assert yaw(rotation) == pytest.approx(2.0 * math.atan2(q.z, q.w))
    assert abs(yaw(rotation)) > 0.5          # a heading that a swapped axis would show
    # Both switch off; /odom stays.
    quiet = start(harnesses, context, EsoNode, 'realtime', odometry_tf=False,
                  map_to_odom_tf=False)
    assert quiet.node.odometry_tf_publisher is None
    assert not hasattr(quiet.node, 'map_to_odom_publisher')
    assert quiet.node.odometry_publisher is not None


def test_reference_cmd_vel_in_real_time_starts_at_the_estimated_pose(context, harnesses):
    from geometry_msgs.msg import TwistStamped
    harness = start(harnesses, context, ReferenceNode, 'realtime',
                    inputs=['/wip/state_estimate'], outputs=['/wip/reference'],
                    **{'reference.kind': 'cmd_vel'})
    harness.publisher(TwistStamped, '/cmd_vel')
    harness.wait_matched()
    out, node = harness.outputs['/wip/reference'], harness.node
    t0 = time.time_ns()
    harness.publish('/wip/state_estimate',
                    StateEstimateMsg(header=make_header(t0), x=2.0, y=-3.0, phi=1.0))
    harness.spin_until(lambda: out, 'the first reference')
    assert (out[0].x, out[0].y, out[0].phi, out[0].v) == (2.0, -3.0, 1.0, 0.0)
    command = TwistStamped(header=make_header(time.time_ns()))
    command.twist.linear.x = 0.3
    harness.publish('/cmd_vel', command)
    harness.spin_until(lambda: node.diagnostics.received['cmd_vel'] == 1, 'the command')
    assert not node.diagnostics.dropped and node.reference.v_command == 0.3
    # Later estimates (elsewhere) do not move the start again; the command drives it.
    harness.publish('/wip/state_estimate', StateEstimateMsg(
        header=make_header(t0 + 400_000_000), x=9.0, y=9.0, phi=0.0))
    harness.spin_until(lambda: len(out) == 2, 'the second reference')
    assert out[1].v > 0.0 and out[1].phi == 1.0
    assert out[1].x > 2.0 and out[1].y < -3.0 + 0.2 and out[1].y > -3.0
    assert node.diagnostics.values['command'] == 'following the command'


def test_reference_path_in_real_time_restarts_at_rest_when_refused(context, harnesses):
    # The estimate-triggered reference (real time) restarts a path reference at rest
    # obstacle_back_off behind the pose of the estimate at which the refusal begins
    # (obstacle_refuse_delay after the first blocked one), dropping the path, and publishes
    # that for the same stamp: the generator's refusal then ends on a reference not ahead
    # of the obstacle, and a new path starts from there.
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    harness = start(harnesses, context, ReferenceNode, 'realtime',
                    inputs=['/wip/state_estimate'], outputs=['/wip/reference'],
                    **{'reference.kind': 'path',
                       'trajectory_generator.obstacle_refuse_delay': 0.1})
    harness.publisher(Path, '/plan')
    harness.wait_matched()
    out, node = harness.outputs['/wip/reference'], harness.node
    t0 = time.time_ns()

    def estimate(dt, blocked=False):
        count = len(out)
        harness.publish('/wip/state_estimate', StateEstimateMsg(
            header=make_header(t0 + int(dt * 1e9)), x=1.0, y=0.0, phi=0.0,
            obstacle_blocked=blocked))
        harness.spin_until(lambda: len(out) == count + 1, f'the reference at {dt} s')
        return out[-1]
    estimate(0.0)
    msg = Path(header=make_header(time.time_ns(), 'map'))
    for x in (1.0, 5.0):
        pose = PoseStamped()
        pose.pose.position.x = x
        msg.poses.append(pose)
    harness.publish('/plan', msg)
    harness.spin_until(lambda: node.diagnostics.received['plan'] == 1, 'the path')
    assert estimate(1.0).x > 1.0 and not node.reference.done
    ahead = estimate(1.5, blocked=True)           # blocked: not refused before 0.1 s
    assert ahead.x > 1.0 and ahead.v > 0.0
    held = estimate(1.6, blocked=True)
    assert (held.x, held.y, held.phi, held.v, held.omega) == pytest.approx(
        (1.0 - 0.2, 0.0, 0.0, 0.0, 0.0), abs=1e-12)
    assert node.reference.done and not node.reference.points
    assert 'restarted at rest at (0.80, 0.00) m' in node.diagnostics.values['obstacle']
    assert estimate(2.0, blocked=True).x == held.x   # one refusal per blocking: at rest
