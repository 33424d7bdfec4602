"""``scripts/bench``: benchmarks, measured side by side in one run and printed as ratios.

Machines here are shared and noisy, so absolute times mean little; every comparison is
made within one invocation, interleaved where possible:

1. **MPC tick vs bare DAQP.** The 900 MPC calls of the paper run (recorded from the
   in-process runner) are replayed: a whole tick of :class:`LongitudinalMpc` (QP build +
   ProxSuite update + solve, persistent workspace) against a bare DAQP solve of the very
   same QP matrices, interleaved tick by tick (goal: tick / DAQP ≤ 4).
2. **In-process real-time factor** of the 90 s scenario, by wall clock and by CPU time
   side by side, with the load average (goal: ≥ 100×, which makes a campaign of 500
   runs of 90 s take minutes); then the same scenario on each plant model (paper, full,
   mujoco), interleaved run by run (goal for mujoco: ≥ 20×); and the reproducibility
   check: the scenario in three processes at once, their records compared bit for bit.
3. **Graph real-time factor** in lockstep (if the node graph is available; ``--no-graph``
   skips it), per layout (separate, composed, single: the plant in the controllers'
   process), unrecorded and recorded (``--record``: every topic, the bag checked), next
   to the in-process one (goals: ≥ 5× recorded or not, within 10× of in-process) and
   with its final state compared with the in-process run's.
5. **Push recovery against the physical limit** (first): after a 1 m/s
   push (10 m/s² for 0.1 s) on a line and a circle at 0.5 m/s, the peak excursion ahead
   of the reference, in-process, beside the clairvoyant lower bound of
   :mod:`wip_tools.analysis.push_bound` (an LP over the torque sequence for the true
   plant and the MPC's limits), as a ratio: the paper's plant, the full plant with the
   body 20 % heavier and the centre of mass 10 % higher, each without and with a consumer
   IMU's noise (``--push-seeds N`` seeds, default 40: the median and the 10th-90th
   percentile of the runs' ratios, each run against the bound from the state the push
   found, and the medians of the seeds' two halves) (goals: <= 1.15x on the paper plant
   clean, <= 1.3x with mismatch or noise).
4. **Real time**: the controllers at 200 Hz against the stand-in base (its own process),
   per layout (separate, composed, composed at SCHED_FIFO priority, the same with the base
   and the controllers each pinned to a CPU of its own, and composed at SCHED_FIFO with idle
   CPUs kept awake by a PM QoS request, ``--cpu-latency 0``, where permitted, unpinned and
   pinned): their CPU share of one core, the
   sensor -> command latency (p50, p99, max) and the oldest command the base held while
   balancing, beside the in-process cost of the same loop (``--no-realtime`` skips it;
   six runs of S s each plus their start-up: about 4-5 min at the default S), and the floor of
   rclpy: the CPU share of a process that only receives the base's two sensor streams with empty
   callbacks (:mod:`wip_tools.rclpy_floor`), and the nodes' own code fed directly, back to
   back against paced at 200 Hz (:mod:`wip_tools.node_cost`).

Examples
--------
    scripts/bench                      # everything
    scripts/bench --no-graph --json out/bench.json
    scripts/bench --push-only          # only the push recovery against its bound
    scripts/bench --push-only --push-seeds 2    # the same, quick (2 seeds per noisy case)
    scripts/bench --realtime-only      # only section 4 (with the in-process run it compares)
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np

from .analysis.bench_mpc import _format, bench_mpc_against_daqp
from wip_control.core.model import STATE_NAMES
from wip_sim.core.plant import MODELS, PlantParams
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import load_scenario
from wip_runtime.cli import add_exit_codes, bounded
from wip_tools.realtime_bench import section_realtime


def _environment() -> dict:
    commit = ''
    try:
        # The checkout this code is in (the workspace links its sources), wherever the
        # bench is started from: it writes its outputs into the working directory.
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True,
                                text=True, check=False, timeout=5,
                                cwd=os.path.dirname(os.path.realpath(__file__))).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    # The interpreter behind the venv: an optimised build and a plain source build of the
    # same version give different figures (docs/realtime.md).
    return {'commit': commit, 'python': platform.python_version(),
            'python_executable': os.path.realpath(sys.executable),
            'machine': platform.machine(), 'cpus': os.cpu_count(),
            **{name: importlib.metadata.version(name) for name in ('numpy', 'proxsuite', 'daqp')}}


def bench_in_process(scenario, repeats: int) -> dict:
    """Whole in-process runs: the median real-time factor by wall time and by CPU time.

    Simulated time over wall time is what a user waits; over this process's CPU time it
    is what the runner costs, and stays meaningful when other processes share the cores
    (a campaign runs one scenario per core, so its throughput is cores × the CPU factor).
    """
    wall_factors, cpu_factors = [], []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        result = run_scenario(scenario)
        wall = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
        wall_factors.append(result.simulated_time_s / wall)
        cpu_factors.append(result.simulated_time_s / cpu if cpu > 0 else float('inf'))
    return {'runs': repeats, 'real_time_factor_median': statistics.median(wall_factors),
            'real_time_factors': wall_factors,
            'cpu_real_time_factor_median': statistics.median(cpu_factors),
            'cpu_real_time_factors': cpu_factors,
            # The state at the end, to compare with the lockstep graph's (bit for bit).
            'final_state': {name: float(result.record.groups['truth'][name][-1])
                            for name in STATE_NAMES},
            'load_average_1min': os.getloadavg()[0] if hasattr(os, 'getloadavg') else None}


def bench_plant_models(scenario, repeats: int) -> dict:
    """Return the in-process real-time factor of ``scenario`` on each plant model.

    The models are interleaved run by run (the machine's load drifts alike for all); the
    factors are medians by wall and by CPU time, per model. A model that cannot be built
    (mujoco not installed) is reported as skipped.
    """
    per_model = {model: dataclasses.replace(scenario, plant=dataclasses.replace(
        scenario.plant, model=PlantParams(model))) for model in MODELS}
    factors: dict[str, dict[str, list[float]]] = {m: {'wall': [], 'cpu': []} for m in MODELS}
    skipped: dict[str, str] = {}
    for _ in range(repeats):
        for model, variant in per_model.items():
            if model in skipped:
                continue
            start, cpu_start = time.perf_counter(), time.process_time()
            try:
                result = run_scenario(variant)
            except ImportError as err:
                skipped[model] = str(err)
                continue
            wall = time.perf_counter() - start
            cpu = time.process_time() - cpu_start
            factors[model]['wall'].append(result.simulated_time_s / wall)
            factors[model]['cpu'].append(result.simulated_time_s / cpu if cpu > 0
                                         else float('inf'))
    out: dict = {model: {'skipped': reason} for model, reason in skipped.items()}
    for model, measured in factors.items():
        if model not in skipped:
            out[model] = {'real_time_factor_median': statistics.median(measured['wall']),
                          'cpu_real_time_factor_median': statistics.median(measured['cpu']),
                          'runs': len(measured['wall'])}
    return out


def bench_graph(scenario_path: str | None, layout: str = 'composed',
                record: bool = False) -> dict | None:
    """Real-time factor of the lockstep node graph, recorded or not."""
    try:
        from wip_bringup.graph import run_graph_benchmark  # optional, needs ROS
    except ImportError as err:
        return {'skipped': f'node graph not available: {err}'}
    return run_graph_benchmark(scenario_path, layout, record=record)


#: A child of :func:`bench_reproducibility`: the scenario in-process, its record saved.
_REPRODUCE = textwrap.dedent("""
    import sys
    import numpy as np
    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import load_scenario
    result = run_scenario(load_scenario(sys.argv[1] or None))
    np.savez(sys.argv[2], **{f'{g}.{c}': v for g, cols in result.record.groups.items()
                             for c, v in cols.items()})
""")
#: Channels that are measured timings, not results.
TIMING_CHANNELS = ('mpc.solve_time',)


def bench_reproducibility(scenario_path: str | None, processes: int = 3) -> dict:
    """Run the scenario in-process in ``processes`` fresh interpreters at once.

    Reports whether their records are the same bit for bit (every channel but measured
    timings).
    """
    with tempfile.TemporaryDirectory(prefix='wip_bench_repro_') as directory:
        outputs = [os.path.join(directory, f'run{i}.npz') for i in range(processes)]
        children = [subprocess.Popen([sys.executable, '-c', _REPRODUCE, scenario_path or '',
                                      out], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True) for out in outputs]
        for child in children:
            output, _ = child.communicate()
            if child.returncode != 0:
                return {'failed': f'a run exited {child.returncode}: {output[-300:]}'}
        first, *others = [np.load(out) for out in outputs]
        channels = [c for c in first.files if c not in TIMING_CHANNELS]
        differing = sorted({c for other in others for c in channels
                            if other.files != first.files
                            or not np.array_equal(first[c], other[c], equal_nan=True)})
        return {'processes': processes, 'channels': len(channels),
                'samples': int(first['truth.t'].size), 'differing_channels': differing,
                'identical': not differing}


def final_state_difference(graph: dict | None, in_process: dict | None) -> float | None:
    """Return the largest difference between two final states (None if one is missing).

    The graph's messages carry the IMU rates through a quaternion and body rates, which
    round, so a lockstep run ends within rounding of the in-process one, not bit for bit.
    """
    if not graph or not in_process:
        return None
    return max(abs(graph[name] - in_process[name]) for name in in_process)


def _print_graph_row(graph: dict | None, layout: str, record: bool, in_process: dict,
                     final: dict | None, report: dict, key: str) -> None:
    """Print one lockstep row of section 3 and store its ratio to in-process in report."""
    label = f'{layout}{", recorded" if record else ""}'
    if not graph or 'real_time_factor' not in graph:
        print(f'-> {label}: {graph}')
        return
    ratio = in_process['real_time_factor_median'] / graph['real_time_factor']
    report[f'in_process_over_{key}'] = ratio
    cpu = graph['cpu_per_tick_us']
    print(f'{label}: per tick: /clock -> wheel torques mean '
          f'{graph["clock_to_torques_us"]["mean"]:.0f} us, p99 '
          f'{graph["clock_to_torques_us"]["p99"]:.0f} us; CPU '
          f'{sum(cpu.values()):.0f} us in all (' + ', '.join(
              f'{n} {v:.0f}' for n, v in sorted(cpu.items(), key=lambda item: -item[1]))
          + ')')
    difference = final_state_difference(graph.get('final_state'), final)
    report[f'{key}_final_state_difference'] = difference
    same = ('' if difference is None else
            '; final state = in-process bit for bit' if difference == 0.0 else
            f'; final state within {difference:.1e} of in-process')
    bag = ('' if not record else f'; bag {graph.get("bag_messages")} messages, '
           + ('checked OK' if not graph.get('bag_problems') else
              f'PROBLEMS: {graph["bag_problems"]}'))
    goal = 'recorded >= 5x' if record else 'graph >= 5x, ratio <= 10'
    print(f'-> {label}: graph {graph["real_time_factor"]:.1f}x real time; in-process / '
          f'graph = {ratio:.1f}{same}{bag} (goals: {goal})')


def _section_mpc(scenario, repeats: int, report: dict) -> None:
    """1. The MPC tick against a bare DAQP solve of the same QPs."""
    print(f'== 1. MPC tick (build + ProxSuite) vs bare DAQP on the QPs of {scenario.name!r}')
    recorded = run_scenario(scenario, record_mpc_inputs=True)
    mpc = bench_mpc_against_daqp(recorded.mpc_inputs, scenario.controller_model.parameters,
                                 scenario.mpc, repeats=repeats)
    report['mpc'] = mpc
    print(_format(mpc))
    print(f'-> MPC tick / bare DAQP solve = {mpc["ratio_tick"]:.1f}x (goal <= 4x)')


def _section_in_process(scenario, args, report: dict) -> dict:
    """2. The in-process real-time factor, per plant model, and the reproducibility."""
    print(f'\n== 2. In-process real-time factor, {scenario.duration:.0f} s scenario')
    in_process = bench_in_process(scenario, args.repeats)
    report['in_process'] = in_process
    load = in_process['load_average_1min']
    print(f'-> {in_process["real_time_factor_median"]:.1f}x real time by wall clock, '
          f'{in_process["cpu_real_time_factor_median"]:.1f}x by CPU time (medians of '
          f'{args.repeats}; goal >= 100x'
          + (f'; load average {load:.1f} on {os.cpu_count()} CPUs' if load is not None else '')
          + ')')
    models = bench_plant_models(scenario, args.repeats)
    report['in_process_per_plant_model'] = models
    print('-> per plant model, interleaved: ' + '; '.join(
        f'{model} {row["real_time_factor_median"]:.1f}x wall, '
        f'{row["cpu_real_time_factor_median"]:.1f}x CPU' if 'skipped' not in row
        else f'{model} skipped ({row["skipped"]})' for model, row in models.items())
        + ' (goal for mujoco >= 20x)')

    repro = bench_reproducibility(args.scenario)
    report['reproducibility'] = repro
    print('-> reproducibility: ' + (
        f'{repro["processes"]} processes at once, {repro["channels"]} channels of '
        f'{repro["samples"]} samples: '
        + ('bit-identical' if repro['identical']
           else f'DIFFER in {", ".join(repro["differing_channels"])}')
        if 'failed' not in repro else repro['failed']) + ' (goal: bit-identical)')
    return in_process


def _section_graph(scenario_path: str | None, in_process: dict, report: dict) -> None:
    """3. The lockstep graph per layout, unrecorded and recorded."""
    print('\n== 3. Node graph in lockstep, same scenario, per layout, unrecorded and '
          'recorded (--record: every topic)')
    final = in_process.get('final_state')
    for layout in ('separate', 'composed', 'single'):
        for record in (False, True):
            key = ('graph' if layout == 'composed' else f'graph_{layout}') + (
                '_recorded' if record else '')
            report[key] = graph = bench_graph(scenario_path, layout, record)
            _print_graph_row(graph, layout, record, in_process, final, report, key)


def _section_push(report: dict, seeds: int) -> None:
    """5. Push recovery: the measured excursion beside the clairvoyant bound."""
    from .analysis.push_recovery import HALVES_TOLERANCE, push_recovery_rows
    print('\n== 5. Push recovery: 1 m/s push (10 m/s^2 for 0.1 s) at 10 s, reference at '
          '0.5 m/s; peak excursion ahead of the reference against the clairvoyant bound '
          'from the state the push found (noisy rows: medians and the 10th-90th percentile '
          f'of the ratio over {seeds} seeds; the medians of the halves agree within '
          f'{HALVES_TOLERANCE}); mismatched: body +20 %, centre of mass +10 %')
    rows = push_recovery_rows(seeds=tuple(range(seeds)))
    report['push_recovery'] = rows
    print(f'{"reference":9s} {"plant":16s} {"sensors":7s} {"bound":>7s} {"excursion":>9s} '
          f'{"ratio":>7s} {"p10-p90":>11s} {"seeds: halves":28s} {"from rest":>9s} '
          f'{"goal":>9s}')
    for row in rows:
        print(_push_line(row, HALVES_TOLERANCE))
    met = sum(row['met'] for row in rows)
    print(f'-> {met} of {len(rows)} goals met (goals: <= 1.15x on the paper plant clean, '
          '<= 1.3x with mismatch or noise; bound and ratio from the state the push found, '
          'from rest beside it)')


def _push_line(row: dict, tolerance: float) -> str:
    """Return one case's row of the table of section 5 (medians over a noisy case's seeds).

    The halves' verdict needs :data:`HALVES_SEEDS` seeds in each ('-' with fewer).
    """
    from .analysis.push_recovery import HALVES_SEEDS
    plant = 'paper' if row['plant'] == 'paper' else 'full, mismatched'
    head = (f'{row["reference"]:9s} {plant:16s} {"noise" if row["noise"] else "clean":7s} ')
    if row['fell']:
        return head + f'FELL in {row["falls"]} of {row["runs"]} runs; goal NOT MET'
    spread, halves = '', ''
    if row['runs'] > 1:
        low, high = row['halves']
        seeds, half = row['seeds'], len(row['seeds']) // 2
        spread = f'{row["ratio_p10"]:.2f}-{row["ratio_p90"]:.2f}x'
        halves = (f'{row["runs"]}: {seeds[0]}-{seeds[half - 1]} {low:.3f}, '
                  f'{seeds[half]}-{seeds[-1]} {high:.3f} '
                  + ('-' if half < HALVES_SEEDS else 'ok' if abs(low - high) <= tolerance
                     else 'DIFFER'))
    return (head + f'{row["bound_m"]:5.3f} m {row["measured_m"]:7.3f} m {row["ratio"]:6.3f}x '
            f'{spread:>11s} {halves:28s} {row["ratio_rest"]:8.3f}x <= {row["goal"]:.2f}x '
            + ('met' if row['met'] else 'NOT MET') + _impact_note(row))


def _impact_note(row: dict) -> str:
    """Return a note of the runs set against the bound at the impact rate ('' if none)."""
    faster = row['runs'] - row.get('rate_kept', row['runs'])
    return f' ({faster} of {row["runs"]} runs at the impact rate)' if faster else ''


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='scripts/bench', formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split('\n\n')[0] + '\nSections: 1 MPC tick vs bare DAQP, 2 '
        'in-process real-time factor, 3 node graph\nin lockstep, 4 real time against the '
        'stand-in base, 5 push recovery against its bound\n(docs/benchmarks.md).\n\n'
        + __doc__[__doc__.index('Examples'):])
    parser.add_argument('--scenario', help='scenario file (default: the paper Section V)')
    parser.add_argument('--repeats', type=int, default=5, help='passes / runs per benchmark')
    parser.add_argument('--no-graph', action='store_true', help='skip the node-graph run')
    parser.add_argument('--no-realtime', action='store_true',
                        help='skip the real-time runs against the stand-in base')
    parser.add_argument('--realtime-seconds', type=float, default=20.0, metavar='S',
                        help='length of each real-time run [s] (default 20)')
    parser.add_argument('--arm-delay', type=bounded(float, 0.0, 3600.0), default=None,
                        metavar='S',
                        help='seconds from every node up to the arming in each real-time '
                        "run (default: hardware mode's --arm-delay, 2)")
    only = parser.add_mutually_exclusive_group()
    only.add_argument('--push-only', action='store_true',
                      help='only the push recovery against its bound (section 5)')
    only.add_argument('--realtime-only', action='store_true',
                      help='only the real-time section (4), beside an in-process run')
    parser.add_argument('--push-seeds', type=int, default=40, metavar='N',
                        help='noise seeds per noisy push case, 0..N-1, compared in two '
                        'halves (default 40; 2 for a quick look)')
    parser.add_argument('--json', help='also write the results to this JSON file')
    add_exit_codes(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.push_seeds < 1:
        print('ERROR: --repeats and --push-seeds must be >= 1', file=sys.stderr)
        return 2
    if args.realtime_only and (args.no_graph or args.no_realtime):
        parser.error('--realtime-only runs the real-time section: not with --no-graph or '
                     '--no-realtime')
    scenario = load_scenario(args.scenario)
    report: dict = {'environment': _environment(), 'scenario': scenario.name}
    env = report['environment']
    print(f"bench: commit {env['commit'] or '?'}, Python {env['python']} "
          f"({env['python_executable']}), {env['cpus']} CPUs", flush=True)
    if args.realtime_only:
        # Section 4 sets the controllers' CPU beside the in-process loop's: that run alone.
        report['in_process'] = in_process = bench_in_process(scenario, args.repeats)
        section_realtime(args.realtime_seconds, in_process, report, args.arm_delay)
        _write_json(args.json, report)
        return 0

    _section_push(report, args.push_seeds)
    if args.push_only:
        _write_json(args.json, report)
        return 0
    _section_mpc(scenario, args.repeats, report)
    in_process = _section_in_process(scenario, args, report)
    if not args.no_graph:
        _section_graph(args.scenario, in_process, report)
    if not args.no_graph and not args.no_realtime:
        section_realtime(args.realtime_seconds, in_process, report, args.arm_delay)
    _write_json(args.json, report)
    return 0


def _write_json(path: str | None, report: dict) -> None:
    if path:
        with open(path, 'w', encoding='utf-8') as stream:
            json.dump(report, stream, indent=2, default=str)


if __name__ == '__main__':
    from wip_runtime.cli import exit_with
    exit_with(main, 'bench')
