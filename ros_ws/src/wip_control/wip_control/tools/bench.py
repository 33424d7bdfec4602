"""``scripts/bench``: benchmarks, measured side by side in one run and printed as ratios.

Machines here are shared and noisy, so absolute times mean little; every comparison is
made within one invocation, interleaved where possible:

1. **MPC tick vs bare DAQP.** The 900 MPC calls of the paper run (recorded from the
   in-process runner) are replayed: a whole tick of :class:`LongitudinalMpc` (QP build +
   ProxSuite update + solve, persistent workspace) against a bare DAQP solve of the very
   same QP matrices, interleaved tick by tick (goal: tick / DAQP ≤ 4).
2. **In-process real-time factor** of the 90 s scenario (goal: ≥ 30×).
3. **Graph real-time factor** in lockstep (if the node graph is available; ``--no-graph``
   skips it), next to the in-process one (goal: ≥ 5×, and within 10× of in-process).

Examples
--------
    scripts/bench                      # everything
    scripts/bench --no-graph --json out/bench.json
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import time

from ..analysis.bench_mpc import _format, bench_mpc_against_daqp
from ..core.runner import run_scenario
from ..core.scenario import load_scenario


def _environment() -> dict:
    commit = ''
    try:
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True,
                                text=True, check=False, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return {'commit': commit, 'python': platform.python_version(),
            'machine': platform.machine(), 'cpus': os.cpu_count(),
            **{name: importlib.metadata.version(name) for name in ('numpy', 'proxsuite', 'daqp')}}


def bench_in_process(scenario, repeats: int) -> dict:
    """Wall time of whole in-process runs; the median real-time factor."""
    factors = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = run_scenario(scenario)
        wall = time.perf_counter() - start
        factors.append(result.simulated_time_s / wall)
    return {'runs': repeats, 'real_time_factor_median': statistics.median(factors),
            'real_time_factors': factors}


def bench_graph(scenario_path: str | None) -> dict | None:
    """Real-time factor of the lockstep node graph (None if the graph is not available)."""
    try:
        from wip_sim.graph import run_graph_benchmark  # noqa: PLC0415 (optional, needs ROS)
    except ImportError as err:
        return {'skipped': f'node graph not available: {err}'}
    return run_graph_benchmark(scenario_path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='scripts/bench', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', help='scenario file (default: the paper Section V)')
    parser.add_argument('--repeats', type=int, default=5, help='passes / runs per benchmark')
    parser.add_argument('--no-graph', action='store_true', help='skip the node-graph run')
    parser.add_argument('--json', help='also write the results to this JSON file')
    args = parser.parse_args(argv)
    if args.repeats < 1:
        print('ERROR: --repeats must be >= 1', file=sys.stderr)
        return 2
    scenario = load_scenario(args.scenario)
    report: dict = {'environment': _environment(), 'scenario': scenario.name}

    print(f'== 1. MPC tick (build + ProxSuite) vs bare DAQP on the QPs of {scenario.name!r}')
    recorded = run_scenario(scenario, record_mpc_inputs=True)
    mpc = bench_mpc_against_daqp(recorded.mpc_inputs, scenario.controller_model.parameters,
                                 scenario.mpc, repeats=args.repeats)
    report['mpc'] = mpc
    print(_format(mpc))
    print(f'-> MPC tick / bare DAQP solve = {mpc["ratio_tick"]:.1f}x (goal <= 4x)')

    print(f'\n== 2. In-process real-time factor, {scenario.duration:.0f} s scenario')
    in_process = bench_in_process(scenario, args.repeats)
    report['in_process'] = in_process
    print(f'-> {in_process["real_time_factor_median"]:.1f}x real time (median of '
          f'{args.repeats}; goal >= 30x)')

    if not args.no_graph:
        print('\n== 3. Node graph in lockstep, same scenario')
        graph = bench_graph(args.scenario)
        report['graph'] = graph
        if graph and 'real_time_factor' in graph:
            ratio = in_process['real_time_factor_median'] / graph['real_time_factor']
            report['in_process_over_graph'] = ratio
            cpu = graph['cpu_per_tick_us']
            print(f'per tick: /clock -> wheel torques mean '
                  f'{graph["clock_to_torques_us"]["mean"]:.0f} us, p99 '
                  f'{graph["clock_to_torques_us"]["p99"]:.0f} us; CPU {sum(cpu.values()):.0f} us '
                  'in all (' + ', '.join(f'{n} {v:.0f}' for n, v in sorted(
                      cpu.items(), key=lambda item: -item[1])) + ')')
            print(f'-> graph {graph["real_time_factor"]:.1f}x real time; in-process / graph = '
                  f'{ratio:.1f} (goals: graph >= 5x, ratio <= 10)')
        else:
            print(f'-> {graph}')
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as stream:
            json.dump(report, stream, indent=2, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
