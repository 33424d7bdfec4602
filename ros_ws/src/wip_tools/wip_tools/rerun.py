"""Open-loop re-run of the controllers on a recorded bag: ``scripts/rerun BAG --out DIR``.

How a user checks a tuning change against a recorded run (or a recorded fall): the
recorded sensor and command inputs of a bag are fed into the loop's two core objects,
freshly built (``core.state_estimation.StateEstimator``, ``core.control_step.ControlStep``:
the ones the in-process runner and the controller nodes drive), in this process, and what
they compute now is written next to what was recorded.

Inputs read from the bag (sensor_msgs / wip_msgs, as the node graph publishes them):
``/joint_states`` (wheel joint angles), ``/imu/data`` (orientation -> pitch, yaw),
``/gps/fix`` (-> map-frame x, y about the scenario's datum), ``/wip/reference`` (the
recorded reference, not recomputed), ``/wip/wheel_torques`` (the recorded commands, used as
the torques applied over the following period, the ESO's input).

Per control tick k (the stamps t_k present on both /joint_states and /imu/data, in order):

1. the ESO (eqs. (4), (8)) with the measurements of t_k and the wheel torques stamped
   t_{k-1} (the last recorded command before t_k; zero before the first), built at the
   first tick from the measured positions (as the ESO node does);
2. the planar position: odometry, then the GPS fix stamped t_k if there is one (the
   estimator starts at the first fix);
3. the trajectory generator (eq. (9)) with the recorded reference stamped t_k (or the
   newest before it), then the ARC (eqs. (12), (13));
4. every ``mpc.sampling_period`` (every ``mpc_decimation``-th tick from the first) the MPC
   (eqs. (16)-(23)), its torque held in between; then the mixer (eq. (24)).

This is exact for a bag recorded in lockstep (it holds ``/clock``; ``--timing stamps``):
the graph then computes exactly this, and the re-run of unchanged controllers reproduces
its recording to rounding. For a bag recorded in real time (``--timing receive``, the
default without ``/clock``) what each node used is decided by arrival order, which a bag
records only as the recorder's receive times: the ticks are those the recorded ESO
estimated; the command applied is the newest the recorder had received before the tick's
samples; a GPS fix is used at the first tick after it was received; the MPC runs on the
estimates its recorded outputs are stamped with, and its torque is mixed from the first
recorded command received after that output. This approximates the nodes' own arrival
order (measured on a 3 s real-time graph run: estimates and positions reproduced except
around scheduling gaps, wheel torques within 0.7 N m RMS).

The message conversions are those of the controller nodes
(``wip_control.nodes.conversions``), so the re-run reads a bag exactly as the nodes read the
live topics.

**Open loop**: the applied torques come from the bag, so the recorded states (the sensors,
the ground truth) do not respond to the recomputed torques. With the controllers unchanged
the re-run reproduces the recorded estimates, commands and torques (to rounding); with a
change it shows how the controllers would have reacted to the same data at the first
instants, diverging in meaning as the recorded trajectory no longer follows them.

Outputs in ``--out DIR``:

- ``bag/``: a rosbag2 MCAP bag with every recorded topic copied (same bytes and times) and
  the recomputed ``/rerun/wip/state_estimate``, ``/rerun/wip/velocity_command``,
  ``/rerun/wip/yaw_torque``, ``/rerun/wip/drive_torque``, ``/rerun/wip/wheel_torques``
  (prefix ``--prefix``), stamped like the recorded ones;
- ``comparison.json``: per compared field, the max and RMS difference recomputed - recorded
  on the common stamps, and the largest recorded magnitude for scale;
- the report of :func:`wip_tools.simulate.write_run_outputs` on the recomputed
  run: ``metrics.json`` (with the comparison under ``rerun``), ``timeseries.npz``,
  ``scenario.yaml``, ``figures/`` (unless ``--no-figures``; plus
  ``figures/rerun_comparison.png``).

The scenario (controller parameters, rates, datum) is the bag's own, with ``--scenario
FILE`` applied over it (a partial file changes only its keys): the lookup rule of
:mod:`wip_tools.bag_scenario`, shared with ``scripts/report``.
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import heapq
import json
import math
import pathlib
import shutil
import sys
import tempfile
from typing import Any, NamedTuple

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from wip_msgs.msg import (ArcState, GroundTruth, MpcOutput, ReferenceState as ReferenceMsg,
                          StateEstimate as StateEstimateMsg, VelocityCommand as CommandMsg,
                          WheelTorques)
import yaml

from wip_control.core.config import ConfigError
from wip_control.core.control_step import ControlStep
from wip_control.core.eso import StateEstimate
from wip_control.core.state_observer import WipStateObserver
from wip_tools.analysis.metrics import compute_metrics
from wip_sim.core.record import GROUPS, RunRecord
from wip_control.core.references import make_reference
from wip_sim.core.scenario import Scenario, scenario_to_mapping
from wip_control.core.sensors import local_to_geodetic
from wip_sim.core.sensor_models import Sensors
from wip_control.core.state_estimation import StateEstimator
from wip_control.nodes.common import make_header, ns_to_stamp, stamp_to_ns
from wip_control.nodes.conversions import (arc_to_msg, body_rates_from_euler,
                                           command_to_msg, estimate_to_msg,
                                           euler_rates_from_body, gps_local_position,
                                           imu_has_rates, imu_pitch_yaw, InvalidMessage,
                                           mpc_to_msg, quaternion_from_euler,
                                           reference_from_msg, reference_to_msg, wheel_angles,
                                           wheel_torques_from_msg, wheel_torques_to_msg)

from wip_control.tools.cli import check_output_directory, EXIT_USAGE, exit_with, write_atomic

from wip_bag.bag_reader import bag_summary, BagReadError, iter_raw_messages, read_topics
from wip_tools.bag_scenario import SCENARIO_KEY, scenario_for_bag
from wip_bag.bag_writer import BagWriterError, Rosbag2McapWriter
from wip_control.tools.cli import add_exit_codes

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
    'arc': ('/wip/yaw_torque', 'wip_msgs/msg/ArcState'),
    'mpc': ('/wip/drive_torque', 'wip_msgs/msg/MpcOutput'),
    'truth': ('/wip/ground_truth', 'wip_msgs/msg/GroundTruth'),
    'clock': ('/clock', 'rosgraph_msgs/msg/Clock'),
}
_CLASSES = {'joint_states': JointState, 'imu': Imu, 'gps': NavSatFix,
            'reference': ReferenceMsg, 'wheel_torques': WheelTorques,
            'estimate': StateEstimateMsg, 'command': CommandMsg, 'arc': ArcState,
            'mpc': MpcOutput, 'truth': GroundTruth}
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


# ============================================================== reading the recorded inputs

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


# ============================================================== the re-run

class TickOutputs(NamedTuple):
    """What the controllers computed at one tick (core values)."""

    stamp_ns: int
    t: float
    estimate: Any  # core StateEstimate
    x: float
    y: float
    settled: bool
    reference: Any  # core ReferenceState
    command: Any  # core VelocityCommand
    arc: Any  # core ArcOutput
    mpc: Any  # core MpcResult, or None between MPC ticks
    wheels: tuple  # (left, right) [N m]


TIMINGS = ('auto', 'stamps', 'receive')


def resolve_timing(run: RecordedRun, timing: str = 'auto') -> str:
    """Return the timing of a bag: 'stamps' or 'receive'.

    'stamps' for a bag recorded in lockstep simulation time (it holds /clock), else
    'receive'; an explicit 'stamps' or 'receive' is returned as is.
    """
    if timing not in TIMINGS:
        raise ValueError(f'timing {timing!r} is not one of {TIMINGS}')
    if timing == 'auto':
        return 'stamps' if run.has_clock else 'receive'
    return timing


def rerun_controllers(run: RecordedRun, scenario: Scenario,
                      timing: str = 'auto') -> list[TickOutputs]:
    """Feed the recorded inputs to fresh core controllers; see the module docstring.

    ``timing`` chooses which recorded command was applied at a tick and when the MPC ran:
    'stamps' (lockstep: the command stamped t_{k-1}; the MPC every ``mpc_decimation``-th
    tick, exactly as the graph and the runner do), 'receive' (real time: the newest
    command the recorder had received before the tick's sensor samples, the MPC at the
    ticks after which the recorder received an MPC output; the controller nodes' own
    receive times are not recorded, so this approximates them by the recorder's), or
    'auto' (:func:`resolve_timing`).

    Raises
    ------
    RerunError
        If the bag has no control tick (no stamp with both joint states and IMU) or no
        reference.
    """
    timing = resolve_timing(run, timing)
    ticks = sorted(set(run.joint_states) & set(run.imu))
    if timing == 'receive' and run.outputs['estimate']:
        # The samples the recorded ESO used (in real time it skips a sample whose IMU and
        # encoder messages did not both arrive before the next ones).
        used = set(ticks) & set(run.outputs['estimate'])
        ticks = sorted(used) if used else ticks
    if not ticks:
        raise RerunError('no control tick: the bag has no /joint_states and /imu/data '
                         'messages with equal stamps')
    if not run.reference:
        raise RerunError('the bag has no /wip/reference message')
    sensors = scenario.sensors
    datum = (sensors.gps_datum_latitude, sensors.gps_datum_longitude,
             sensors.gps_datum_altitude)
    # The loop's two core objects, as the runner and the nodes drive them.
    estimator = StateEstimator.from_scenario(scenario)
    control = ControlStep.from_scenario(scenario)
    drive = control.drive

    torque_stamps = sorted(run.wheel_torques)
    reference_stamps = sorted(run.reference)
    receive = run.receive_times
    by_receive = sorted((t, s) for s, t in receive.get('wheel_torques', {}).items())
    torque_receive_times = [t for t, _ in by_receive]
    # Real time: the MPC ran on the estimates its recorded outputs are stamped with, and the
    # mixer used an output from the first command it sent after the output arrived.
    tick_set = set(ticks)
    mpc_runs = {s: t for s, t in receive.get('mpc', {}).items() if s in tick_set}
    pending = []  # (receive time of the recorded output, tau_v) not yet used by the mixer
    gps_order = [s for _, s in sorted((t, s) for s, t in receive.get('gps', {}).items())]
    gps_by_receive = [receive['gps'][s] for s in gps_order]
    last_fix = None
    origin = ticks[0]
    previous = None
    outputs = []
    for k, stamp in enumerate(ticks):
        t = (stamp - origin) / 1e9  # as the nodes' TimeBase: 0 at the first sample
        left, right = run.joint_states[stamp]
        pitch, yaw = run.imu[stamp]
        # 1: the torques applied over [t_{k-1}, t_k): the command stamped t_{k-1}, i.e. the
        # newest recorded before t_k (zero before the first).
        tau_left = tau_right = 0.0
        tick_receive = max(receive['joint_states'].get(stamp, 0), receive['imu'].get(stamp, 0))
        if timing == 'receive':
            index = _newest_at_or_before(torque_receive_times, tick_receive - 1)
            if index is not None:
                tau_left, tau_right = run.wheel_torques[by_receive[index][1]]
        elif previous is not None:
            index = _newest_at_or_before(torque_stamps, stamp - 1)
            if index is not None:
                tau_left, tau_right = run.wheel_torques[torque_stamps[index]]
        # 2: position, as the ESO node: start at the first fix. Lockstep: the fix of t_k;
        # real time: the newest fix received before the tick's samples and not used yet
        # (the ESO updates when the IMU and encoder samples are in; a fix published with
        # them usually arrives just after and is used at the next update).
        if timing == 'receive':
            index = _newest_at_or_before(gps_by_receive, tick_receive - 1)
            fix = None
            if index is not None and gps_order[index] != last_fix:
                last_fix = gps_order[index]
                fix = run.gps[last_fix]
        else:
            fix = run.gps.get(stamp)
        gps = None
        if fix is not None and fix.status.status >= NavSatStatus.STATUS_FIX:
            try:
                gps = gps_local_position(fix, *datum)
            except InvalidMessage:
                run.invalid['gps'] = run.invalid.get('gps', 0) + 1
        pose = estimator.update(t, left, right, pitch, yaw, tau_left, tau_right,
                                run.imu_rates.get(stamp), gps)
        # 3-4: generator with the recorded reference, ARC, MPC (held), mixer. Real time:
        # the MPC ran at the ticks of its recorded outputs, and its output was mixed from
        # the first command recorded after it arrived, so it is held then.
        receive_mode = timing == 'receive' and bool(mpc_runs)
        mpc_tick = stamp in mpc_runs if receive_mode else drive.is_tick(k)
        index = _newest_at_or_before(reference_stamps, stamp)
        if index is None:
            previous = stamp
            continue  # No reference yet: the graph's generator would wait too.
        reference = run.reference[reference_stamps[index]]
        out = control.step(t, reference, pose, mpc_tick, hold=not receive_mode, k=k,
                           decide=not receive_mode)
        command, arc_out, result = out.command, out.arc, out.mpc
        wheels = (out.tau_left, out.tau_right)
        if receive_mode:
            if result is not None:
                pending.append((mpc_runs[stamp], result.tau_v))
            mixed_at = receive['wheel_torques'].get(stamp, tick_receive)
            while pending and pending[0][0] <= mixed_at:
                drive.tau_v = pending.pop(0)[1]
            wheels = control.mix(arc_out.tau_omega)
        outputs.append(TickOutputs(stamp, t, pose.estimate, pose.x, pose.y, pose.settled,
                                   reference, command, arc_out, result, wheels))
        previous = stamp
    return outputs


def _newest_at_or_before(stamps, stamp):
    """Index of the largest element of the sorted ``stamps`` that is <= ``stamp``."""
    index = bisect.bisect_right(stamps, stamp) - 1
    return index if index >= 0 else None


# ============================================================== comparison and report

def _recomputed_values(tick: TickOutputs, key: str):
    if key == 'estimate':
        return dict(tick.estimate._asdict(), x=tick.x, y=tick.y)
    if key == 'command':
        return tick.command._asdict()
    if key == 'arc':
        return tick.arc._asdict()
    if key == 'mpc':
        return None if tick.mpc is None else {'tau_v': tick.mpc.tau_v,
                                              'delta_tau': tick.mpc.delta_tau}
    return {'left': tick.wheels[0], 'right': tick.wheels[1]}


def compare(run: RecordedRun, outputs: list[TickOutputs]) -> dict:
    """Recomputed minus recorded on the common stamps, per output and field.

    Returns
    -------
    dict
        ``{key: {'topic', 'compared', 'fields': {field: {'max_abs_difference',
        'rms_difference', 'max_abs_recorded'}}}}``; a key whose topic was not recorded has
        ``compared: 0`` and no fields.
    """
    result = {}
    for key, fields in COMPARED:
        recorded = run.outputs[key]
        pairs = [(_recomputed_values(tick, key), recorded[tick.stamp_ns]) for tick in outputs
                 if tick.stamp_ns in recorded]
        pairs = [(new, old) for new, old in pairs if new is not None]
        entry = {'topic': TOPICS[key][0], 'compared': len(pairs), 'fields': {}}
        for field in fields:
            if not pairs:
                break
            new = np.array([p[0][field] for p in pairs], dtype=float)
            old = np.array([getattr(p[1], field) for p in pairs], dtype=float)
            diff = new - old
            entry['fields'][field] = {
                'max_abs_difference': float(np.max(np.abs(diff))),
                'rms_difference': float(np.sqrt(np.mean(diff ** 2))),
                'max_abs_recorded': float(np.max(np.abs(old))),
            }
        result[key] = entry
    return result


def run_record(run: RecordedRun, outputs: list[TickOutputs], scenario: Scenario) -> RunRecord:
    """Return a RunRecord of the recomputed run (truth: the recorded ground truth, if any)."""
    rows = {group: [] for group in GROUPS}
    for tick in outputs:
        e, c, a = tick.estimate, tick.command, tick.arc
        rows['reference'].append((tick.t, tick.reference.x, tick.reference.y,
                                  tick.reference.phi, tick.reference.v, tick.reference.omega))
        rows['estimate'].append((tick.t, e.phi, e.omega, e.f1, e.x_v, e.v, e.f2, e.theta,
                                 e.theta_dot, e.f3, tick.x, tick.y))
        rows['command'].append((tick.t, c.v_d, c.omega_d, c.omega_d_dot, c.x_e, c.y_e,
                                c.phi_e))
        rows['arc'].append((tick.t, a.tau_omega, a.alpha_hat, a.e_omega))
        rows['wheels'].append((tick.t, tick.wheels[0], tick.wheels[1]))
        if tick.mpc is not None:
            m = tick.mpc
            rows['mpc'].append((tick.t, m.tau_v, m.delta_tau, int(m.status), m.iterations,
                                m.solve_time_s, float(m.used_fallback), m.slack_v,
                                m.slack_theta))
    if outputs and run.truth:
        origin = outputs[0].stamp_ns - int(round(outputs[0].t * 1e9))
        for stamp in sorted(run.truth):
            g = run.truth[stamp]
            rows['truth'].append(((stamp - origin) / 1e9, g.x, g.y, g.phi, g.x_v, g.theta,
                                  g.omega, g.v, g.theta_dot, g.tau_d1, g.tau_d2, g.tau_d3,
                                  g.tau_left, g.tau_right))
    groups = {}
    for group, columns in GROUPS.items():
        data = np.array(rows[group], dtype=float).reshape(-1, len(columns))
        groups[group] = {name: data[:, i].copy() for i, name in enumerate(columns)}
    return RunRecord(groups, attributes={'scenario': scenario.name, 'source': 'rerun'})


def _output_messages(outputs, run, scenario, prefix):
    """(log time, topic, serialized) of the recomputed outputs, in log time order."""
    period = scenario.mpc.sampling_period
    items = []
    for tick in outputs:
        log_time = run.log_times.get(tick.stamp_ns, tick.stamp_ns)
        s = tick.stamp_ns
        items.append((log_time, 0, f'{prefix}/wip/state_estimate', serialize_message(
            estimate_to_msg(tick.estimate, tick.x, tick.y, tick.settled, s, MAP_FRAME))))
        items.append((log_time, 1, f'{prefix}/wip/velocity_command',
                      serialize_message(command_to_msg(tick.command, s))))
        items.append((log_time, 2, f'{prefix}/wip/yaw_torque',
                      serialize_message(arc_to_msg(tick.arc, s))))
        if tick.mpc is not None:
            items.append((log_time, 3, f'{prefix}/wip/drive_torque',
                          serialize_message(mpc_to_msg(tick.mpc, s, period))))
        items.append((log_time, 4, f'{prefix}/wip/wheel_torques',
                      serialize_message(wheel_torques_to_msg(*tick.wheels, s))))
    items.sort(key=lambda item: (item[0], item[1]))
    return items


def write_rerun_bag(bag, out_bag, outputs, run, scenario, prefix=DEFAULT_PREFIX,
                    compression='zstd', allow_partial=False):
    """Copy every recorded topic of ``bag`` and add the recomputed outputs."""
    recorded = read_topics(bag, allow_partial)
    custom = {SCENARIO_KEY: yaml.safe_dump(scenario_to_mapping(scenario), sort_keys=False),
              'wip.rerun_of': str(pathlib.Path(bag).resolve())}
    with Rosbag2McapWriter(out_bag, compression=compression, custom_data=custom) as writer:
        for topic, meta in recorded.items():
            writer.add_topic(topic, meta.type_name, meta.definition or None,
                             meta.offered_qos_profiles, meta.type_hash or None,
                             definition_encoding=meta.definition_encoding or 'ros2msg')
        for key, _ in COMPARED:
            topic, type_name = TOPICS[key]
            writer.add_topic(f'{prefix}{topic}', type_name, qos_profiles=RELIABLE_QOS)
        computed = ((log_time, topic, data) for log_time, _, topic, data in
                    _output_messages(outputs, run, scenario, prefix))
        original = ((m.log_time_ns, m.topic, m.data, m.publish_time_ns)
                    for m in iter_raw_messages(bag, allow_partial=allow_partial))
        for item in heapq.merge(original, computed, key=lambda item: item[0]):
            writer.write(item[1], item[2], item[0],
                         publish_time_ns=item[3] if len(item) > 3 else None)
        return writer.message_counts()


def comparison_figure(run, outputs, path):
    """Plot recorded vs recomputed wheel torques, drive/yaw torques and tilt/yaw-rate estimates."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    origin = outputs[0].stamp_ns - int(round(outputs[0].t * 1e9))
    panels = (('wheel_torques', 'left', 'left wheel torque [N m]'),
              ('wheel_torques', 'right', 'right wheel torque [N m]'),
              ('arc', 'tau_omega', 'yaw torque tau_omega [N m]'),
              ('mpc', 'tau_v', 'drive torque tau_v [N m]'),
              ('estimate', 'theta', 'tilt estimate [rad]'),
              ('estimate', 'omega', 'yaw rate estimate [rad/s]'))
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.0 * len(panels)), sharex=True)
    for ax, (key, field, label) in zip(axes, panels):
        recorded = run.outputs[key]
        if recorded:
            stamps = sorted(recorded)
            ax.plot([(s - origin) / 1e9 for s in stamps],
                    [getattr(recorded[s], field) for s in stamps], color='black',
                    linewidth=1.0, label='recorded')
        pairs = [(tick.t, _recomputed_values(tick, key)) for tick in outputs]
        pairs = [(t, v[field]) for t, v in pairs if v is not None]
        ax.plot([p[0] for p in pairs], [p[1] for p in pairs], color='tab:red',
                linewidth=1.0, linestyle='--', label='re-run (open loop)')
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc='best', fontsize=8)
    axes[-1].set_xlabel('t [s]')
    fig.suptitle('Open-loop re-run against the recording')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ============================================================== scenario

def write_record_as_bag(result, scenario: Scenario, directory, clock=True,
                        compression='zstd', **writer_options):
    """Write an in-process run (``wip_sim.core.runner.run_scenario``) as the node graph's bag.

    The topics, types, stamps and contents are those of a lockstep graph run recorded with
    ``use_sim_time`` (log time = stamp = t_k): ``/clock``, ``/wip/ground_truth``,
    ``/joint_states``, ``/imu/data``, ``/gps/fix``, ``/wip/reference``,
    ``/wip/state_estimate``, ``/wip/velocity_command``, ``/wip/yaw_torque``,
    ``/wip/drive_torque`` (MPC ticks), ``/wip/wheel_torques``. The sensor samples are
    drawn again from the recorded true states with the scenario's sensor models and seed,
    in the runner's order, so they are the ones the runner's controllers used. The
    scenario is stored in ``custom_data['wip.scenario']``.

    Returns
    -------
    dict
        Messages written per topic.
    """
    record = result.record
    truth, est = record['truth'], record['estimate']
    n_ticks = len(est['t'])
    params = scenario.plant.parameters
    sensors = Sensors(params, scenario.sensors, initial_yaw=float(truth['phi'][0]),
                      seed=scenario.seed)
    c = scenario.sensors
    datum = (c.gps_datum_latitude, c.gps_datum_longitude, c.gps_datum_altitude)
    gps_every = max(1, int(round(scenario.rates.control_rate / c.gps_rate)))
    reference = make_reference(scenario.reference)
    observer = WipStateObserver(scenario.controller_model.parameters, scenario.eso)
    mpc_rows = {round(t * scenario.rates.control_rate): i
                for i, t in enumerate(record['mpc']['t'])}
    state_keys = ('x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot')
    custom = {SCENARIO_KEY: yaml.safe_dump(scenario_to_mapping(scenario), sort_keys=False)}
    with Rosbag2McapWriter(directory, compression=compression, custom_data=custom,
                           **writer_options) as bag:
        for key in ('clock', 'truth', 'joint_states', 'imu', 'gps', 'reference', 'estimate',
                    'command', 'arc', 'mpc', 'wheel_torques'):
            if key == 'clock' and not clock:
                continue
            bag.add_topic(TOPICS[key][0], TOPICS[key][1], qos_profiles=RELIABLE_QOS)

        def put(key, msg, stamp):
            bag.write(TOPICS[key][0], serialize_message(msg), stamp)

        for k in range(len(truth['t'])):
            t = float(truth['t'][k])
            s = int(round(t * 1e9))
            state = [float(truth[name][k]) for name in state_keys]
            last = k >= n_ticks
            if clock and not last:
                msg = Clock()
                msg.clock = ns_to_stamp(s)
                put('clock', msg, s)
            put('truth', _ground_truth(truth, k, s), s)
            if last:
                break
            # Sensors in the runner's order (separate random streams per sensor).
            true_state = state
            state, gps_state = sensors.delayed(true_state)
            left, right = sensors.encoders(state)
            pitch, yaw = sensors.imu(state)
            rates = sensors.imu_rates(state)
            joints = JointState(name=[LEFT_JOINT, RIGHT_JOINT], position=[left, right],
                                velocity=list(sensors.wheel_rates(state)),
                                effort=[float(truth['tau_left'][k]),
                                        float(truth['tau_right'][k])])
            joints.header = make_header(s)
            put('joint_states', joints, s)
            put('imu', _imu(pitch, yaw, s, rates, c), s)
            if k % gps_every == 0:
                if sensors.gps_fix_available():
                    put('gps', _fix(*sensors.gps(gps_state), datum, s, c), s)
                else:  # a dropout, as the plant node publishes it
                    fix = _fix(0.0, 0.0, datum, s, c)
                    fix.status.status = NavSatStatus.STATUS_NO_FIX
                    fix.latitude = fix.longitude = fix.altitude = math.nan
                    put('gps', fix, s)
            state = true_state
            put('reference', reference_to_msg(reference.sample(t), s, MAP_FRAME), s)
            estimate = StateEstimate(*(float(est[name][k]) for name in (
                'phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3')),
                observer.epsilon_at(t))
            put('estimate', estimate_to_msg(estimate, float(est['x'][k]), float(est['y'][k]),
                                            not observer.in_ramp(t), s, MAP_FRAME), s)
            cmd = record['command']
            put('command', CommandMsg(
                header=make_header(s), **{f: float(cmd[f][k]) for f in (
                    'v_d', 'omega_d', 'omega_d_dot', 'x_e', 'y_e', 'phi_e')}), s)
            arc = record['arc']
            put('arc', ArcState(header=make_header(s), **{f: float(arc[f][k]) for f in (
                'tau_omega', 'alpha_hat', 'e_omega')}), s)
            row = mpc_rows.get(k)
            if row is not None:
                put('mpc', _mpc_output(record['mpc'], row, s, scenario), s)
            wheels = record['wheels']
            put('wheel_torques', wheel_torques_to_msg(float(wheels['tau_left'][k]),
                                                      float(wheels['tau_right'][k]), s), s)
        return bag.message_counts()


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
    return MpcOutput(
        header=make_header(stamp), tau_v=float(mpc['tau_v'][row]),
        delta_tau=float(mpc['delta_tau'][row]),
        status=MpcOutput.FALLBACK_SHIFTED_PLAN if used_fallback else MpcOutput.SOLVED,
        status_text='', iterations=int(mpc['iterations'][row]),
        solve_time=float(mpc['solve_time'][row]),
        slack_v=slack_v if math.isfinite(slack_v) else 0.0,
        slack_theta=slack_theta if math.isfinite(slack_theta) else 0.0,
        sampling_period=scenario.mpc.sampling_period, used_fallback=used_fallback)


# ============================================================== command line

def rerun(bag, out, scenario_file=None, figures=True, prefix=DEFAULT_PREFIX, quiet=False,
          timing='auto', allow_partial=False):
    """Run the whole tool; returns (metrics dict, comparison dict).

    ``OUT/bag`` must not exist (a bag is never overwritten): checked before anything is
    computed. It is written into a temporary directory beside it and renamed when
    complete, so a failed re-run leaves no half bag that would block the next one.
    """
    from wip_tools.simulate import step_printer
    progress = (lambda text: None) if quiet else step_printer('rerun')
    out = pathlib.Path(out)
    try:
        check_output_directory(out, '--out')
    except ValueError as err:
        raise RerunError(str(err)) from err
    out_bag = out / 'bag'
    if out_bag.exists() or out_bag.is_symlink():
        raise RerunError(f'{out_bag} exists: refusing to overwrite a bag (choose another '
                         '--out or move it away)')
    scenario, source = scenario_for_bag(bag, scenario_file)
    if not quiet:
        print(f'scenario: {source}', file=sys.stderr)
    lost = bag_summary(bag)['problems'] if allow_partial else []
    for line in lost:
        print(f'rerun: warning: partial re-run, {line}', file=sys.stderr)
    progress(f'reading {bag}')
    run = read_recorded_run(bag, allow_partial=allow_partial)
    timing = resolve_timing(run, timing)
    progress(f're-running the controllers (timing: {timing})')
    outputs = rerun_controllers(run, scenario, timing)
    progress(f'{len(outputs)} ticks re-run; comparing with the recording')
    comparison = compare(run, outputs)
    out.mkdir(parents=True, exist_ok=True)
    progress(f'writing {out_bag}')
    work = pathlib.Path(tempfile.mkdtemp(prefix='.bag.partial-', dir=out))
    try:
        counts = write_rerun_bag(bag, work / 'bag', outputs, run, scenario, prefix,
                                 allow_partial=allow_partial)
        _rename_bag(work / 'bag', out_bag)
    finally:
        shutil.rmtree(work, ignore_errors=True)  # ours: created above
    record = run_record(run, outputs, scenario)
    progress('metrics')
    metrics = compute_metrics(record, scenario)
    metrics['rerun'] = {
        'bag': str(pathlib.Path(bag).resolve()),
        'scenario_source': source,
        'open_loop': True,
        'timing': timing,
        'note': 'applied torques and states are the recorded ones; the recomputed torques '
                'were not applied (metrics of the truth group describe the recording)',
        'ticks': len(outputs),
        'invalid_messages_skipped': run.invalid,
        'comparison': comparison,
        'messages_written': counts,
    }
    if lost:
        metrics['partial'] = True
        metrics['lost'] = lost
    from wip_tools.simulate import write_run_outputs
    write_run_outputs(out, record, scenario, metrics, figures=figures, progress=progress)
    write_atomic(out / 'comparison.json', json.dumps(comparison, indent=2) + '\n')
    if figures:
        (out / 'figures').mkdir(exist_ok=True)
        progress('figure rerun_comparison')
        comparison_figure(run, outputs, out / 'figures' / 'rerun_comparison.png')
    progress('done')
    return metrics, comparison


def _rename_bag(source, target):
    """Move the finished bag into place.

    Written in a directory also named ``bag``, so its files already have the names rosbag2 gives
    them: ``bag_<i>.mcap``.
    """
    source.rename(target)


def summary_lines(comparison):
    lines = []
    for key, entry in comparison.items():
        if not entry['compared']:
            lines.append(f'{entry["topic"]}: not recorded, nothing to compare')
            continue
        worst = max(entry['fields'].items(), key=lambda kv: kv[1]['max_abs_difference'])
        lines.append(f'{entry["topic"]}: {entry["compared"]} samples, largest difference '
                     f'{worst[1]["max_abs_difference"]:.3g} on {worst[0]} (recorded up to '
                     f'{worst[1]["max_abs_recorded"]:.3g})')
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog='scripts/rerun', formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Open-loop re-run: feed the recorded sensors, reference and wheel torques of a bag to
freshly built controllers (in-process core, same holds as the runner) and write a bag and
report of what they compute now next to what was recorded.

Examples
--------
    scripts/rerun out/demo/bag --out out/rerun       # the bag's own scenario
    scripts/rerun out/demo/bag --scenario tuned.yaml --out out/tuned
    scripts/rerun robot_run/bag --timing receive --out out/robot""")
    parser.add_argument('bag', help='bag directory or .mcap file')
    parser.add_argument('--scenario', help='scenario YAML with the controller parameters '
                        "(default: the bag's, else the paper's)")
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--prefix', default=DEFAULT_PREFIX,
                        help='namespace of the recomputed topics (default /rerun)')
    parser.add_argument('--timing', choices=TIMINGS, default='auto',
                        help="which recorded command was applied and when the MPC ran: "
                        "'stamps' (lockstep bags, exact), 'receive' (real-time bags, "
                        "from the recorder's receive order); default: stamps if the bag "
                        "holds /clock")
    parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--quiet', action='store_true')
    parser.add_argument('--partial', action='store_true',
                        help='re-run the intact part of a damaged or unfinished bag '
                        '(metrics.json then has partial: true and lists what was lost)')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    try:
        _, comparison = rerun(args.bag, args.out, args.scenario, figures=not args.no_figures,
                              prefix=args.prefix.rstrip('/'), quiet=args.quiet,
                              timing=args.timing, allow_partial=args.partial)
    except (RerunError, BagReadError, BagWriterError, ConfigError, OSError,
            ValueError) as err:
        print(f'rerun: error: {err}', file=sys.stderr)
        return EXIT_USAGE
    if not args.quiet:
        print('\n'.join(summary_lines(comparison)))
        print(f'wrote {pathlib.Path(args.out) / "bag"}, comparison.json, metrics.json')
    return 0


if __name__ == '__main__':
    exit_with(main, 'rerun')
