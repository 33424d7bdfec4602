"""Soak test: hardware mode against the stand-in base, many long real-time runs.

The hardware-mode acceptance matrix: the stand-in base in its own process (full plant, 1 kHz)
and the controllers (the default composed layout unless ``--layout``) run for
``--seconds`` on a line and on a circle, ``--runs`` times each, with and without one busy
competing process (``python3 -c 'while True: pass'``), optionally freezing the controller
process (SIGSTOP/SIGCONT) for each of ``--freeze`` milliseconds during every run. A run
passes when the base ran its time without falling and stayed near the path (distance to
the path ≤ ``--max-path-error`` after the first 15 s, the settling of the paper's initial
errors). One row per run goes to ``OUT/soak.csv``; the table is printed.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import pathlib
import subprocess
import sys
import time
from typing import Any, Sequence

import numpy as np

from wip_runtime.cli import check_output_directory, EXIT_FAILED, EXIT_OK, EXIT_USAGE, exit_with

from wip_bringup.standin_run import BASE, freeze_process, line_scenario, run_against_standin
from wip_runtime.cli import add_exit_codes

#: Path speed [m/s] of both references; the circle's radius [m].
SPEED = 0.5
CIRCLE_RADIUS = 2.0
#: Distance to the path is judged after this time [s] (the paper's initial errors settle).
SETTLING_TIME = 15.0
BUSY_LOOP = [sys.executable, '-c', 'while True: pass']


def scenario_for(path: str) -> dict[str, Any]:
    if path == 'line':
        return line_scenario(SPEED)
    return line_scenario(SPEED, kind='circle', circle_radius=CIRCLE_RADIUS,
                         circle_speed=SPEED)


def distance_to_path(path: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Geometric distance to the reference path.

    Line along +x through the origin; circle of CIRCLE_RADIUS about the origin.
    """
    if path == 'line':
        return np.abs(y)
    return np.abs(np.hypot(x, y) - CIRCLE_RADIUS)


@dataclasses.dataclass
class SoakRow:
    path: str
    load: str
    run: int
    layout: str
    seconds: float
    passed: bool
    fell: bool
    base_code: int | None
    simulated_s: float
    max_tilt_rad: float
    max_path_error_m: float
    rms_path_error_m: float
    freezes_ms: str
    safety_faults: int
    latency_p99_ms: float
    latency_max_ms: float
    controller_cpu_fraction: float
    rt_priority: bool


def one_run(directory: pathlib.Path, path: str, load: str, index: int, seconds: float,
            layout: str, freezes_ms: Sequence[float], max_path_error: float,
            record: bool = False, position_source: str = 'gps') -> SoakRow:
    busy = subprocess.Popen(BUSY_LOOP) if load == 'busy' else None
    done: list[float] = []

    def inject(_runner, processes):
        # Spread the freezes over the run, the first after the settling time.
        if not freezes_ms:
            return
        gap = (seconds - SETTLING_TIME) / (len(freezes_ms) + 1)
        start = time.monotonic()
        target = processes.get('controllers') or next(iter(processes.values()))
        for k, ms in enumerate(freezes_ms):
            wake = start + SETTLING_TIME + (k + 1) * gap
            time.sleep(max(0.0, wake - time.monotonic()))
            if target.poll() is not None:
                return
            done.append(1e3 * freeze_process(target.pid, ms / 1e3))

    try:
        conventions = dict(BASE, position_source=position_source)
        run = run_against_standin(directory, conventions, seconds, scenario=scenario_for(path),
                                  layout=layout, record=record,
                                  during=inject if freezes_ms else None)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    stats = run.stats
    truth = {k: np.asarray(v, dtype=float) for k, v in stats['truth'].items()}
    late = truth['t'] > SETTLING_TIME
    if position_source == 'wheels':
        # Dead reckoning's frame starts where the robot stood: the path is about that point.
        truth['x'], truth['y'] = truth['x'] - truth['x'][0], truth['y'] - truth['y'][0]
    error = distance_to_path(path, truth['x'][late], truth['y'][late])
    max_error = float(error.max()) if error.size else math.inf
    rms_error = float(np.sqrt(np.mean(error ** 2))) if error.size else math.inf
    summary = run.summary()
    latency = summary['sensor_to_command_latency_ms'] or {}
    faults = sum(1 for e in run.result.safety_events if e['state'] == 'FAULT'
                 and e['t'] < (run.result.wall_time_s or math.inf) - 2.0)
    simulated = float(stats.get('sim_time_s', 0.0))
    fell = bool(stats['fell'])
    # A run whose freezes did not all happen (the run ended first) did not test them.
    passed = (not fell and run.base_code == 0 and simulated >= seconds - 0.01
              and max_error <= max_path_error and len(done) == len(freezes_ms))
    return SoakRow(path=path, load=load, run=index, layout=layout, seconds=seconds,
                   passed=passed, fell=fell, base_code=run.base_code,
                   simulated_s=simulated,
                   max_tilt_rad=float(np.abs(truth['theta']).max()),
                   max_path_error_m=max_error, rms_path_error_m=rms_error,
                   freezes_ms=' '.join(f'{m:.0f}' for m in done), safety_faults=faults,
                   latency_p99_ms=float(latency.get('p99', math.nan)),
                   latency_max_ms=float(latency.get('max', math.nan)),
                   controller_cpu_fraction=float(
                       summary['controller_cpu_fraction'] or math.nan),
                   rt_priority=run.base_priority > 0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='scripts/soak', formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split('\n\n')[0] + """

Examples
--------
    scripts/soak --runs 1 --seconds 20 --out /tmp/soak     # a quick look
    scripts/soak --paths line --loads busy --freeze 60     # one case, a 60 ms freeze
    scripts/soak --record-runs --out out/soak-bags         # keep a bag per run

A run fails (exit 1 at the end) when the base fell or stopped early, the path error
after 15 s exceeded --max-path-error, or a freeze did not happen before the run ended.""")
    parser.add_argument('--out', default='out/soak',
                        help='output directory (default: %(default)s)')
    parser.add_argument('--runs', type=int, default=5, help='runs per case (default: 5)')
    parser.add_argument('--seconds', type=float, default=60.0,
                        help='run time after the release [s] (default: 60)')
    parser.add_argument('--paths', nargs='+', default=['line', 'circle'],
                        choices=['line', 'circle'])
    parser.add_argument('--loads', nargs='+', default=['quiet', 'busy'],
                        choices=['quiet', 'busy'],
                        help="'busy': one competing busy-loop process during the run")
    parser.add_argument('--layout', default='composed', choices=['composed', 'separate'])
    parser.add_argument('--freeze', nargs='*', type=float, default=[20.0, 60.0, 150.0],
                        metavar='MS', help='freeze the controller process for each of these '
                        'durations [ms] during every run (default: 20 60 150; none: '
                        '--freeze with no value)')
    parser.add_argument('--record-runs', action='store_true',
                        help='record each run to OUT/<case>/bag (for diagnosis; costs CPU)')
    parser.add_argument('--position-source', default='gps', choices=['gps', 'wheels'],
                        help="the controllers' position_source (wheels: dead reckoning, "
                        'no GPS; default: %(default)s)')
    parser.add_argument('--max-path-error', type=float, default=0.6,
                        help='largest distance to the path after 15 s [m] (default: 0.6)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    if args.runs < 1 or not math.isfinite(args.seconds) or args.seconds <= SETTLING_TIME:
        print(f'soak: error: need --runs >= 1 and --seconds > {SETTLING_TIME:g}',
              file=sys.stderr)
        return EXIT_USAGE
    if any(not (0.0 < m < 10_000.0) for m in args.freeze):
        print('soak: error: --freeze durations must be in (0, 10000) ms', file=sys.stderr)
        return EXIT_USAGE
    try:
        out = check_output_directory(args.out)
    except ValueError as error:
        print(f'soak: error: {error}', file=sys.stderr)
        return EXIT_USAGE
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm  # only the tool needs it
    cases = [(p, load, k) for p in args.paths for load in args.loads
             for k in range(args.runs)]
    rows: list[SoakRow] = []
    fields = [f.name for f in dataclasses.fields(SoakRow)]
    with open(out / 'soak.csv', 'w', newline='', encoding='utf-8') as stream:
        writer = csv.DictWriter(stream, fieldnames=fields)
        writer.writeheader()
        for path, load, k in tqdm(cases, unit='run', file=sys.stderr):
            row = one_run(out / f'{path}_{load}_{k}', path, load, k, args.seconds,
                          args.layout, args.freeze, args.max_path_error, args.record_runs,
                          args.position_source)
            rows.append(row)
            writer.writerow(dataclasses.asdict(row))
            stream.flush()
    # The path error in mm: the stand-in's runs track within millimetres, which [m] with two
    # decimals printed as 0.00.
    print(f'{"path":7s} {"load":6s} passed  max|θ| [rad]  path error max/RMS [mm]  '
          'latency p99/max [ms]  CPU')
    for path in args.paths:
        for load in args.loads:
            group = [r for r in rows if r.path == path and r.load == load]
            print(f'{path:7s} {load:6s} {sum(r.passed for r in group)}/{len(group)}   '
                  f'{max(r.max_tilt_rad for r in group):.3f}         '
                  f'{1e3 * max(r.max_path_error_m for r in group):6.1f} / '
                  f'{1e3 * max(r.rms_path_error_m for r in group):<6.1f}          '
                  f'{max(r.latency_p99_ms for r in group):.1f} / '
                  f'{max(r.latency_max_ms for r in group):.1f}           '
                  f'{np.mean([r.controller_cpu_fraction for r in group]):.0%}')
    print(f'freezes per run [ms]: {" ".join(f"{m:g}" for m in args.freeze) or "none"}; '
          f'real-time priority: {all(r.rt_priority for r in rows)}; rows: {out / "soak.csv"}')
    return EXIT_OK if all(r.passed for r in rows) else EXIT_FAILED


if __name__ == '__main__':
    exit_with(main, 'soak')
