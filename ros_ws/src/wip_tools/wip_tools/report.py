"""``scripts/report``: metrics and figures of a recorded run, from its rosbag2 bag.

Examples
--------
    scripts/report out/demo/bag --out out/demo/report
    scripts/report robot_bag --out out/robot --scenario my_robot.yaml
    scripts/report BAG --out DIR --no-figures

The bag's messages become the record the in-process runner builds, and the outputs are
written by the same code as ``scripts/simulate``: the same metrics for the same run. The
record groups and their topics, the time origin, the scenario used and the integrity
check: docs/recording.md ("What scripts/report reads").
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import sys
from typing import Any, Iterable

import numpy as np

from wip_runtime.config import ParamError
from wip_tools.analysis.metrics import compute_metrics
from wip_control.core.mpc_plan import HELD_STATUS_TEXT
from wip_sim.core.record import GROUPS, RunRecord
from wip_sim.core.scenario import Scenario
from wip_runtime.cli import check_output_directory, EXIT_FAILED, EXIT_OK, EXIT_USAGE, exit_with

from wip_bag.bag_reader import bag_summary, BagReadError, read_bag
from wip_tools.bag_scenario import scenario_for_bag
from wip_runtime.cli import add_exit_codes

#: Stamps beyond this [s] are wall-clock (epoch) times, not simulation times (~3 years).
WALL_CLOCK_THRESHOLD_S = 1e8


def _truth(m) -> tuple:
    return (m.x, m.y, m.phi, m.x_v, m.theta, m.omega, m.v, m.theta_dot, m.tau_d1, m.tau_d2,
            m.tau_d3, m.tau_left, m.tau_right)


def _mpc(m) -> tuple | None:
    if m.status_text == HELD_STATUS_TEXT:
        # A tick of the re-solve grid without a solve (lockstep, docs/history/mpc.md §10): not an
        # MPC tick of the record (the runner records its solves only).
        return None
    return (m.tau_v, m.delta_tau, float(m.status), float(m.iterations), m.solve_time,
            float(bool(m.used_fallback)), m.slack_v, m.slack_theta)


#: The wheel joints of /joint_states (the plant's and the controllers' default names).
WHEEL_JOINTS = ('left_wheel_joint', 'right_wheel_joint')


def _encoders(m) -> tuple | None:
    names = list(m.name)
    if not all(joint in names for joint in WHEEL_JOINTS) or len(m.position) != len(names):
        return None    # other joints (a robot's own names): not the record's encoders
    return tuple(float(m.position[names.index(joint)]) for joint in WHEEL_JOINTS)


@functools.cache
def _conversions():
    """Import wip_control's message conversions once.

    They import the ROS message packages: only when a bag has IMU messages.
    """
    from wip_control.nodes import conversions  # noqa: PLC0415
    return conversions


def _imu(m) -> tuple | None:
    conversions = _conversions()
    q, w = m.orientation, m.angular_velocity
    if m.orientation_covariance[0] == -1.0 or not conversions.imu_has_rates(m):
        return None
    try:
        pitch, yaw = conversions.pitch_yaw_from_quaternion(q.x, q.y, q.z, q.w)
        return (pitch, yaw, *conversions.euler_rates_from_body(pitch, (w.x, w.y, w.z)))
    except conversions.InvalidMessage:
        return None


#: topic -> (group, row of the columns after 't').
TOPICS = {
    '/joint_states': ('encoders', _encoders),
    '/imu/data': ('imu', _imu),
    '/wip/ground_truth': ('truth', _truth),
    '/wip/reference': ('reference', lambda m: (m.x, m.y, m.phi, m.v, m.omega)),
    '/wip/state_estimate': ('estimate', lambda m: (
        m.phi, m.omega, m.f1, m.x_v, m.v, m.f2, m.theta, m.theta_dot, m.f3, m.x, m.y)),
    '/wip/velocity_command': ('command', lambda m: (
        m.v_d, m.omega_d, m.omega_d_dot, m.x_e, m.y_e, m.phi_e)),
    '/wip/yaw_torque': ('arc', lambda m: (m.tau_omega, m.alpha_hat, m.e_omega)),
    '/wip/wheel_torques': ('wheels', lambda m: (m.left, m.right)),
    '/wip/drive_torque': ('mpc', _mpc),
}


class ReportError(Exception):
    """The bag or the scenario cannot be used."""


def _stamp_ns(message) -> int:
    stamp = message.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def record_from_bag(bag: str | pathlib.Path,
                    topics: dict[str, tuple] | None = None,
                    allow_partial: bool = False) -> RunRecord:
    """Return the :class:`RunRecord` of a bag (see the module docstring for the mapping).

    Rows are sorted by stamp (a stable sort: messages with equal stamps keep the bag's
    order). Groups whose topic is absent are empty.
    """
    topics = TOPICS if topics is None else topics
    rows: dict[str, list[tuple[int, tuple]]] = {group: [] for group, _ in topics.values()}
    try:
        for topic, _, _, message in read_bag(bag, topics=list(topics),
                                             allow_partial=allow_partial):
            group, convert = topics[topic]
            row = convert(message)
            if row is not None:
                rows[group].append((_stamp_ns(message), row))
    except BagReadError as err:
        raise ReportError(str(err)) from err
    if not any(rows.values()):
        raise ReportError(f'{bag}: none of the topics {sorted(topics)} has a message')
    # The run starts with the plant's first sample (the truth), on a robot with the first
    # state estimate; other nodes (the reference) may have published before.
    for group in ('truth', 'estimate', *rows):
        if rows.get(group):
            first = min(s for s, _ in rows[group])
            break
    origin = first if first * 1e-9 > WALL_CLOCK_THRESHOLD_S else 0
    groups = {}
    for group in GROUPS:
        columns = GROUPS[group]
        group_rows = sorted(rows.get(group, []), key=lambda row: row[0])
        if group_rows:
            t = np.array([(s - origin) / 1e9 for s, _ in group_rows])
            data = np.array([values for _, values in group_rows], dtype=float)
        else:
            t = np.zeros(0)
            data = np.zeros((0, len(columns) - 1))
        groups[group] = {'t': t, **{name: data[:, i].copy()
                                    for i, name in enumerate(columns[1:])}}
    return RunRecord(groups, attributes={'source': str(bag), 'time_origin_ns': origin})


def scenario_for(bag: str | pathlib.Path,
                 scenario_path: str | pathlib.Path | None) -> tuple[Scenario, str]:
    """Return the scenario of a report and where it came from.

    It is the bag's own, with ``scenario_path`` over it (:mod:`wip_tools.bag_scenario`,
    the rule rerun uses too).
    """
    try:
        return scenario_for_bag(bag, scenario_path)
    except ParamError as err:
        raise ReportError(str(err)) from err


def report(bag: str | pathlib.Path, out: str | pathlib.Path,
           scenario_path: str | pathlib.Path | None = None, figures: bool = True,
           quiet: bool = True, allow_partial: bool = False) -> dict[str, Any]:
    """Write the report of ``bag`` into ``out``; returns the metrics.

    ``allow_partial``: report the intact part of a damaged bag (``partial: true``).

    Raises
    ------
    ReportError
        If the bag cannot be read, has no usable message, or the scenario is invalid.
    """
    from wip_tools.simulate import step_printer, write_run_outputs  # matplotlib lazily

    try:
        check_output_directory(out, '--out')
    except ValueError as err:
        raise ReportError(str(err)) from err
    progress = (lambda text: None) if quiet else step_printer('report')
    scenario, source = scenario_for(bag, scenario_path)
    if not quiet:
        print(f'report: scenario {scenario.name!r} from {source}', file=sys.stderr)
    lost = []
    if allow_partial:
        try:
            lost = bag_summary(bag)['problems']
        except BagReadError as err:
            raise ReportError(str(err)) from err
        for line in lost:
            print(f'report: warning: partial report, {line}', file=sys.stderr)
    progress(f'reading {bag}')
    record = record_from_bag(bag, allow_partial=allow_partial)
    progress(f'{sum(len(record[g]["t"]) for g in GROUPS)} messages read; metrics')
    if 'truth' not in record and 'estimate' not in record:
        raise ReportError(f'{bag}: no /wip/ground_truth and no /wip/state_estimate: '
                          'nothing to report')
    record.attributes['scenario'] = scenario.name
    metrics = compute_metrics(record, scenario)
    metrics['source'] = {'bag': str(bag), 'scenario': source,
                         'messages': {group: int(len(record[group]['t']))
                                      for group in GROUPS}}
    if lost:
        metrics['partial'] = True
        metrics['lost'] = lost
    write_run_outputs(pathlib.Path(out), record, scenario, metrics, figures=figures,
                      progress=progress)
    progress('done')
    return metrics


def main(argv: Iterable[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/report', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', help='rosbag2 directory (or a single .mcap file)')
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--scenario', help='scenario YAML (default: BAG/scenario.yaml, '
                        'else the paper scenario)')
    parser.add_argument('--no-figures', action='store_true',
                        help='skip the figures (report.html then has none)')
    parser.add_argument('--quiet', action='store_true', help='no summary')
    parser.add_argument('--partial', action='store_true',
                        help='report the intact part of a damaged or unfinished bag '
                        '(metrics.json then has partial: true and lists what was lost)')
    add_exit_codes(parser)
    args = parser.parse_args(None if argv is None else list(argv))
    try:
        metrics = report(args.bag, args.out, args.scenario, figures=not args.no_figures,
                         quiet=args.quiet, allow_partial=args.partial)
    except ReportError as err:
        print(f'ERROR: {err}', file=sys.stderr)
        return EXIT_USAGE
    if not args.quiet:
        from wip_tools.simulate import summary
        print(summary(metrics))
        from wip_tools.analysis.report_page import claims
        scenario, _ = scenario_for(args.bag, args.scenario)
        print("the paper's claims [claim]: met?  " + '; '.join(
            f'{quantity} [{claim}]: {verdict}'
            for quantity, claim, _, verdict in claims(metrics, scenario)))
        out = pathlib.Path(args.out)
        print(f'wrote {out / "metrics.json"}, {out / "report.html"}'
              + ('' if args.no_figures else f' and figures (PNG, SVG) in {out / "figures"}'))
    return EXIT_FAILED if metrics['fell'] else EXIT_OK


if __name__ == '__main__':
    exit_with(main, 'report')
