"""What a re-run computed against what was recorded: comparison, record, bag and figure."""

from __future__ import annotations

import heapq
import pathlib

import numpy as np
from rclpy.serialization import serialize_message
import yaml

from wip_control.nodes.conversions import (arc_to_msg, command_to_msg, estimate_to_msg,
                                           mpc_to_msg, wheel_torques_to_msg)
from wip_sim.core.record import GROUPS, RunRecord
from wip_sim.core.scenario import Scenario, scenario_to_mapping

from wip_bag.bag_reader import iter_raw_messages, read_topics
from wip_bag.bag_writer import Rosbag2McapWriter
from wip_tools.bag_scenario import SCENARIO_KEY
from wip_tools.rerun_inputs import (COMPARED, DEFAULT_PREFIX, MAP_FRAME, RecordedRun,
                                    RELIABLE_QOS, TOPICS)
from wip_tools.rerun_loop import TickOutputs


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
