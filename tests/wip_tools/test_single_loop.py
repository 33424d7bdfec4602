"""One control loop: the runner's objects, rerun and the node callbacks compute the same.

One recorded input stream (the bag of an in-process run: encoder, IMU and GPS samples,
the reference and the wheel torques applied) goes through

(a) ``StateEstimator`` and ``ControlStep`` called as ``core.runner.run_scenario`` calls
    them (the inputs decoded from the messages, t = stamp / 1e9 as the nodes take it);
(b) ``wip_tools.rerun_loop.rerun_controllers`` (its lockstep timing);
(c) the ESO, generator, ARC, MPC and mixer nodes, in-process in lockstep, each message
    handed to the callback the node registered and each output passed on to the next
    nodes' callbacks (no DDS, so no arrival order to depend on);

and the three give bit-identical estimates, commands, yaw torques, drive torques and
wheel torques at every tick. The MPC uses the DAQP backend, whose solution depends only on
its inputs (ProxSuite's last bits vary with memory alignment).
"""

import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('wip_msgs.msg')

from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus  # noqa: E402
from wip_msgs.msg import (YawTorque, DriveTorque, ReferenceState,  # noqa: E402
                          StateEstimate as StateEstimateMsg, VelocityCommand, WheelTorques)

from wip_control.core.control_step import ControlStep  # noqa: E402
from wip_control.core.mpc_plan import HELD_STATUS_TEXT  # noqa: E402
from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping  # noqa: E402
from wip_control.core.state_estimation import StateEstimator  # noqa: E402
from wip_control.nodes.arc_node import ArcNode  # noqa: E402
from wip_runtime.stamps import stamp_to_ns  # noqa: E402
from wip_control.nodes.conversions import gps_local_position  # noqa: E402
from wip_control.nodes.eso_node import EsoNode  # noqa: E402
from wip_control.nodes.mpc_node import MpcNode  # noqa: E402
from wip_control.nodes.torque_mixer_node import TorqueMixerNode  # noqa: E402
from wip_control.nodes.trajectory_generator_node import TrajectoryGeneratorNode  # noqa: E402
from wip_bag.bag_reader import iter_raw_messages  # noqa: E402
from record_bag import write_record_as_bag  # noqa: E402
from wip_tools.rerun_inputs import read_recorded_run, TOPICS  # noqa: E402
from wip_tools.rerun_loop import rerun_controllers  # noqa: E402

pytestmark = pytest.mark.ros

# The node defaults with the DAQP backend; a yaw disturbance so that every stage acts.
SCENARIO = {'name': 'single_loop', 'duration': 1.5, 'mpc': {'backend': 'daqp'},
            'disturbances': {'yaw': [{'kind': 'sine', 'amplitude': 1.0, 'frequency': 2.0}]}}
ESTIMATE_FIELDS = ('phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3')
COMMAND_FIELDS = ('v_d', 'omega_d', 'omega_d_dot', 'x_e', 'y_e', 'phi_e')
ARC_FIELDS = ('tau_omega', 'alpha_hat', 'e_omega')


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    scenario = scenario_from_mapping(SCENARIO)
    bag = tmp_path_factory.mktemp('single_loop') / 'bag'
    write_record_as_bag(run_scenario(scenario), scenario, bag)
    return scenario, bag, read_recorded_run(bag)


def _row(estimate, x, y, command, arc, tau_v, wheels):
    """One tick's outputs as a flat tuple of floats (tau_v None between MPC ticks)."""
    return (tuple(getattr(estimate, f) for f in ESTIMATE_FIELDS) + (x, y)
            + tuple(getattr(command, f) for f in COMMAND_FIELDS)
            + tuple(getattr(arc, f) for f in ARC_FIELDS) + (tau_v, *wheels))


def runner_objects(scenario, run):
    """Compute (a): the runner's two objects on the recorded inputs, called as the runner does."""
    sensors = scenario.sensors
    datum = (sensors.gps_datum_latitude, sensors.gps_datum_longitude,
             sensors.gps_datum_altitude)
    estimator = StateEstimator.from_scenario(scenario)
    control = ControlStep.from_scenario(scenario)
    rows, applied = {}, (0.0, 0.0)
    for k, stamp in enumerate(sorted(run.joint_states)):
        t = stamp / 1e9
        fix = run.gps.get(stamp)
        fix = (gps_local_position(fix, *datum)
               if fix is not None and fix.status.status >= NavSatStatus.STATUS_FIX else None)
        pose = estimator.update(t, *run.joint_states[stamp], *run.imu[stamp], *applied,
                                run.imu_rates.get(stamp), fix)
        out = control.step(t, run.reference[stamp], pose, control.drive.is_tick(k), k=k)
        rows[stamp] = _row(pose.estimate, pose.x, pose.y, out.command, out.arc,
                           None if out.mpc is None else out.mpc.tau_v,
                           (out.tau_left, out.tau_right))
        applied = run.wheel_torques[stamp]
    return rows


def rerun_path(scenario, run):
    """(b): the re-run of the bag."""
    return {tick.stamp_ns: _row(tick.estimate, tick.x, tick.y, tick.command, tick.arc,
                                None if tick.mpc is None else tick.mpc.tau_v, tick.wheels)
            for tick in rerun_controllers(run, scenario, 'stamps')}


class _Captured:
    """What a node publishes (its publishers' publish replaced), by message type."""

    def __init__(self, node):
        self.messages = []
        for publisher in node.publishers:
            publisher.publish = self.messages.append

    def take(self, msg_type):
        found = [m for m in self.messages if isinstance(m, msg_type)]
        self.messages.clear()
        return found


def node_callbacks(context, bag):
    """(c): the five controller nodes in lockstep, fed through their callbacks."""
    params = {'clock_mode': 'lockstep', 'use_sim_time': True, 'diagnostics_period': 0.0}
    extra = {MpcNode: {'mpc.backend': 'daqp'}}
    classes = (EsoNode, TrajectoryGeneratorNode, ArcNode, MpcNode, TorqueMixerNode)
    nodes = {cls: cls(context=context, parameter_overrides=[
        Parameter(k, value=v) for k, v in {**params, **extra.get(cls, {})}.items()])
        for cls in classes}
    try:
        out = {cls: _Captured(node) for cls, node in nodes.items()}
        cb = {cls: {s.topic_name: s.callback for s in node.subscriptions}
              for cls, node in nodes.items()}
        # The recorded messages in bag order, grouped by stamp.
        types = {TOPICS[key][0]: cls for key, cls in (
            ('joint_states', JointState), ('imu', Imu), ('gps', NavSatFix),
            ('reference', ReferenceState), ('wheel_torques', WheelTorques))}
        by_stamp = {}
        for raw in iter_raw_messages(bag, topics=list(types)):
            msg = deserialize_message(raw.data, types[raw.topic])
            by_stamp.setdefault(stamp_to_ns(msg.header.stamp), []).append((raw.topic, msg))
        rows, previous_torques = {}, None
        for stamp in sorted(by_stamp):
            messages = dict(by_stamp[stamp])
            if '/joint_states' not in messages:
                continue   # the last truth sample has no tick
            eso = cb[EsoNode]
            if previous_torques is not None:   # applied over the previous period
                eso['/wip/wheel_torques'](previous_torques)
            for topic in ('/joint_states', '/imu/data', '/gps/fix'):
                if topic in messages:
                    eso[topic](messages[topic])
            (estimate,) = out[EsoNode].take(StateEstimateMsg)
            cb[TrajectoryGeneratorNode]['/wip/reference'](messages['/wip/reference'])
            for cls in (TrajectoryGeneratorNode, ArcNode, MpcNode, TorqueMixerNode):
                cb[cls]['/wip/state_estimate'](estimate)
            (command,) = out[TrajectoryGeneratorNode].take(VelocityCommand)
            cb[ArcNode]['/wip/velocity_command'](command)
            cb[MpcNode]['/wip/velocity_command'](command)
            (arc,) = out[ArcNode].take(YawTorque)
            cb[MpcNode]['/wip/yaw_torque'](arc)
            drive = out[MpcNode].take(DriveTorque)
            for msg in drive:
                cb[TorqueMixerNode]['/wip/drive_torque'](msg)
            cb[TorqueMixerNode]['/wip/yaw_torque'](arc)
            (wheels,) = out[TorqueMixerNode].take(WheelTorques)
            assert not wheels.zeroed, wheels.reason
            # (A HELD answer at a tick of the re-solve grid is not a solve: the runner
            # records none there.)
            solved = [msg for msg in drive if msg.status_text != HELD_STATUS_TEXT]
            rows[stamp] = _row(estimate, estimate.x, estimate.y, command, arc,
                               solved[0].tau_v if solved else None, (wheels.left, wheels.right))
            previous_torques = messages['/wip/wheel_torques']
        return rows
    finally:
        for node in nodes.values():
            node.destroy_node()


def test_runner_rerun_and_nodes_compute_bit_identical_outputs(recorded, context):
    scenario, bag, run = recorded
    a = runner_objects(scenario, run)
    b = rerun_path(scenario, run)
    c = node_callbacks(context, bag)
    n_ticks = int(round(scenario.duration * scenario.rates.control_rate))
    assert len(a) == len(b) == len(c) == n_ticks
    assert sum(row[-3] is not None for row in a.values()) == n_ticks // scenario.mpc_decimation
    for stamp in sorted(a):
        assert a[stamp] == b[stamp], f'runner objects vs rerun at {stamp} ns'
        assert a[stamp] == c[stamp], f'runner objects vs nodes at {stamp} ns'
    # The loop acts: the torques are far from zero and the GPS fixes were used.
    assert max(abs(row[-1]) for row in a.values()) > 0.1
    assert any(stamp in run.gps for stamp in a) and run.gps


def test_the_runner_itself_computes_what_its_objects_give_on_its_own_samples(recorded):
    """The runner itself computes what its objects give on its own samples.

    The stream is the runner's: its own run recorded the same wheel torques, to the
    rounding of the GPS fix's geodetic round trip and of t = k h vs stamp / 1e9.
    """
    scenario, _, run = recorded
    rows = runner_objects(scenario, run)
    for stamp, row in rows.items():
        left, right = run.wheel_torques[stamp]
        assert row[-2:] == pytest.approx((left, right), rel=0.0, abs=1e-7), stamp
