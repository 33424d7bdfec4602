"""``scripts/run_graph``: run a scenario through the ROS 2 node graph, or the controllers alone.

The command line (:func:`main`) and the run's summary; a simulation run is
:mod:`wip_bringup.graph_runner`, hardware mode :mod:`wip_bringup.hardware`. What a run does,
step by step: docs/run_graph.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import tempfile
from typing import Any

from wip_runtime.cli import add_exit_codes, bounded, exit_with

from .graph_runner import GraphOptions, GraphResult, run_graph
from .hardware import add_arguments, run_from_args
from .launcher import EXIT_FELL, EXIT_OK
from .run_result import print_result
from .run_stop import STOP_EXIT_CODES, stop_signals
from .runner_base import options_from_args
from .view_options import add_view_arguments

DESCRIPTION = """\
Run a scenario through the ROS 2 node graph: the six controllers composed in one process
(default), one process per node (--layout separate) or, recorded in lockstep, with the
plant in the same process (--layout single). --mode hardware (alias --no-plant) runs the
controllers alone, in real time, against a real base's topics (--params-file, --remap).

A simulation runs in a private DDS domain on this host; hardware mode uses your ROS
network settings (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS). Outputs
in --out: params.yaml, scenario.yaml, logs/, run.json (and plant_stats.json). What a run
does, step by step, its outputs and how it stops: docs/run_graph.md."""

EPILOG = """\
Examples
  scripts/run_graph                                   # paper scenario, lockstep
  scripts/run_graph --duration 10 --out /tmp/g10
  scripts/run_graph --scenario my.yaml --record out/my/bag --out out/my/run
  scripts/run_graph --clock realtime --duration 20
  scripts/run_graph --mode hardware --params-file my_base.yaml   # a real base, no plant
  scripts/run_graph --clock realtime --foxglove         # watch it live in Foxglove

Exit status: 0 the scenario ran to its end; 1 the vehicle fell; 2 bad arguments, scenario
or outputs (also: another run holds --out or the bag); 3 a node failed, or a timeout
(discovery, start or stall); 4 the disk filled up; 5 (with --clock realtime) the
controllers never engaged; 130/143/129 stopped by SIGINT/SIGTERM/SIGHUP (what ran is
saved). Hardware mode: 0 the controllers engaged and the run ended without a safety fault
(at the end of --duration, by Ctrl-C, SIGTERM, SIGHUP or your e-stop); 1 the vehicle fell
or the safety layer went to FAULT after engaging (the message gives the mixer's reason);
5 the controllers never engaged (no inputs from the base, or the estimate never settled:
the message says which); 2, 3, 4 as above."""


def run_graph_benchmark(scenario_path: str | None, layout: str = GraphOptions.layout,
                        record: bool = False) -> dict[str, Any]:
    """Run the whole scenario once through the lockstep graph, for ``scripts/bench``.

    In a temporary directory, recorded (every topic, as ``--record``) or not; returns its
    real-time factor, per-tick loop time and CPU, the final true state, and with
    ``record`` the bag's message count and check (``bag_info``).

    Returns ``{'failed': message, 'exit_code': code}`` if the run did not complete.
    """
    with tempfile.TemporaryDirectory(prefix='wip_bench_graph_') as out:
        bag = os.path.join(out, 'bag') if record else None
        result = run_graph(GraphOptions(scenario=scenario_path, clock='lockstep',
                                        out=os.path.join(out, 'run'), quiet=True,
                                        layout=layout, record=bag))
        checked = _bag_check(bag) if bag and result.exit_code == EXIT_OK else {}
    stats = result.plant_stats or {}
    if result.exit_code != EXIT_OK or not stats.get('real_time_factor'):
        return {'failed': result.message, 'exit_code': result.exit_code}
    ticks = stats['ticks']
    loop = stats.get('clock_to_torques_s') or {}
    return {'layout': layout, 'recorded': record, **checked,
            'final_state': stats.get('final_state'),
            'real_time_factor': stats['real_time_factor'], 'sim_time_s': stats['sim_time_s'],
            'wall_time_s': stats['wall_time_s'], 'ticks': ticks,
            'startup_s': result.startup_s,
            'clock_to_torques_us': {'mean': loop.get('mean_us'), 'p99': loop.get('p99_us')},
            'cpu_per_tick_us': {name: 1e6 * cpu / ticks for name, cpu in result.cpu_s.items()}}


def _bag_check(bag: str) -> dict[str, Any]:
    """Return the recorded bag's message count and ``bag_info``'s problems with it."""
    from wip_bag.bag_info import bag_information  # noqa: PLC0415 (only when recording)
    info = bag_information(bag)
    return {'bag_messages': info['message_count'], 'bag_problems': info['problems']}


def outcome_word(exit_code: int) -> str:
    """OK, STOPPED (by a signal: what ran is saved) or FAILED."""
    if exit_code == EXIT_OK:
        return 'OK'
    return 'STOPPED' if exit_code in STOP_EXIT_CODES else 'FAILED'


def format_result(result: GraphResult) -> str:
    """Human-readable summary of a run: outcome, timings, where the outputs are."""
    lines = [f'{outcome_word(result.exit_code)}: {result.message}']
    stats = result.plant_stats or {}
    if stats.get('real_time_factor'):
        lines.append(f'simulated {stats["sim_time_s"]:.2f} s in {stats["wall_time_s"]:.2f} s '
                     f'wall: {stats["real_time_factor"]:.2f}x real time '
                     f'({stats["ticks"]} ticks, start-up {result.startup_s or 0:.1f} s)')

        def fmt(key):
            entry = stats.get(key) or {}
            if not entry.get('count'):
                return 'n/a'
            return f'mean {entry["mean_us"]:.0f} us, p99 {entry["p99_us"]:.0f} us'
        lines.append(f'per tick: /clock published -> wheel torques received '
                     f'{fmt("clock_to_torques_s")} (plant publishing {fmt("publish_s")}, '
                     f'then the controllers {fmt("wait_for_torques_s")}); plant step '
                     f'{fmt("step_s")}')
    ticks = stats.get('ticks')
    if result.cpu_s and ticks:
        per_tick = {n: 1e6 * c / ticks for n, c in result.cpu_s.items()}
        lines.append(f'CPU per tick: {sum(per_tick.values()):.0f} us in all ('
                     + ', '.join(f'{n} {v:.0f}' for n, v in sorted(
                         per_tick.items(), key=lambda item: -item[1])) + ')')
    failed = {n: c for n, c in result.node_exit_codes.items()
              if c not in (0, None, EXIT_FELL)}
    if failed and result.exit_code != 0:
        lines.append('node exit codes: ' + ', '.join(f'{n}={c}' for n, c in failed.items()))
    lines.append(f'outputs: {result.out} (run.json, params.yaml, scenario.yaml, logs/)')
    if result.bag is not None:
        lines.append(f'bag: {result.bag}   report: scripts/report '
                     f'{shlex.quote(str(result.bag))} --out DIR')
    return '\n'.join(lines)


#: The layout of a recorded lockstep run: the plant and the controllers in one process,
#: whose own messages take the intra-process bus while DDS carries the recorder's copies;
#: the bag holds the same topics and counts as the composed layout's
#: (docs/decisions/recording-speed.md has the measurements).
RECORDED_LOCKSTEP_LAYOUT = 'single'
#: rmw_fastrtps's publication mode of every writer of a process (SYNCHRONOUS by default).
PUBLICATION_MODE_VARIABLE = 'RMW_FASTRTPS_PUBLICATION_MODE'


def default_layout(clock: str, record: str | None) -> str:
    """Return the layout when ``--layout`` is not given.

    A recorded lockstep run takes the fastest layout that records every topic; any other
    run the composed one, as on a robot.
    """
    return RECORDED_LOCKSTEP_LAYOUT if clock == 'lockstep' and record else GraphOptions.layout


def build_parser() -> argparse.ArgumentParser:
    """``scripts/run_graph``'s options, both modes."""
    parser = argparse.ArgumentParser(
        prog='scripts/run_graph', description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--mode', choices=('simulation', 'hardware'), default='simulation',
                        help="simulation: the plant and the controllers; hardware: the "
                        "controllers alone against a real base's topics (real time)")
    parser.add_argument('--no-plant', action='store_true', help='same as --mode hardware')
    parser.add_argument('--scenario', help='scenario YAML file (default: paper Section V)')
    parser.add_argument('--clock', choices=('lockstep', 'realtime'), default=None,
                        help='lockstep (deterministic, faster than real time; the default) or '
                        'realtime; hardware mode is always realtime')
    parser.add_argument('--record', metavar='DIR',
                        help='record every graph topic into this rosbag2 directory')
    parser.add_argument('--duration', type=bounded(float, 0.0, 1e6, True), metavar='S',
                        help='override the scenario duration [s]; hardware mode: stop after '
                        'this long [s of wall time] (default: at Ctrl-C)')
    parser.add_argument('--out', default=None, metavar='DIR',
                        help='run directory: params, logs, timings (default out/graph, '
                        'hardware mode out/hardware)')
    parser.add_argument('--discovery-timeout', type=bounded(float, 0.0, 3600.0, True),
                        default=60.0, metavar='S',
                        help='wall time allowed for the graph to connect [s]')
    parser.add_argument('--stall-timeout', type=bounded(float, 0.0, 3600.0, True),
                        default=30.0, metavar='S',
                        help='wall time without simulated progress before giving up [s]')
    parser.add_argument('--startup-retries', type=bounded(int, 0, 10), default=1,
                        metavar='N',
                        help='start the graph again after a stall on the first ticks '
                        '(a start-up message lost to DDS discovery), at most N times')
    parser.add_argument('--quiet', action='store_true', help='no progress output')
    add_view_arguments(parser)
    add_arguments(parser)
    add_exit_codes(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.no_plant or args.mode == 'hardware':
        if args.clock == 'lockstep':
            parser.error('--mode hardware runs in real time: --clock lockstep is not possible')
        args.out = args.out or 'out/hardware'
        return run_from_args(args)
    if args.params_files or args.remaps:
        parser.error('--params-file and --remap are options of --mode hardware')
    options = GraphOptions(**options_from_args(
        args, clock=args.clock or 'lockstep', out=args.out or 'out/graph',
        stall_timeout=args.stall_timeout, startup_retries=args.startup_retries,
        layout=args.layout or default_layout(args.clock or 'lockstep', args.record)))
    with stop_signals():   # SIGTERM, SIGHUP stop the run as Ctrl-C does
        result = run_graph(options)
    return print_result(result, format_result)


if __name__ == '__main__':
    exit_with(main, 'run_graph')
