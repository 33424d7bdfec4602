"""``scripts/simulate``: run a scenario in-process and write metrics, time series, figures.

Examples
--------
    scripts/simulate --out out/paper                 # the paper's Section V
    scripts/simulate --scenario my.yaml --out out/my
    scripts/simulate --dump-scenario > my.yaml       # every key with its default
    scripts/simulate --list-parameters               # units, defaults, ranges
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import yaml

from wip_runtime.config import ParamError
from wip_tools.analysis.metrics import compute_metrics
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import load_scenario, Scenario, scenario_to_mapping
from wip_runtime.cli import (check_output_directory, EXIT_FAILED, EXIT_OK, EXIT_USAGE, exit_with,
                             write_atomic)
from .parameters import parameter_table
from wip_runtime.cli import add_exit_codes


def progress_printer(stream=sys.stderr):
    """Return a progress callback printing sim time and real-time factor about once a second."""
    start = time.perf_counter()
    interactive = stream.isatty()

    def show(t: float, duration: float) -> None:
        elapsed = time.perf_counter() - start
        factor = t / elapsed if elapsed > 0 else float('inf')
        line = f'  sim {t:6.1f} / {duration:.1f} s   {factor:5.1f}x real time'
        if interactive:
            stream.write('\r' + line)
            stream.flush()
        elif int(t) % 10 == 0:
            stream.write(line + '\n')
    return show


def step_printer(program: str, stream=sys.stderr):
    """Return a progress callback for the long steps of a command (reading a bag, each figure).

    It prints ``program: [elapsed] step`` on ``stream`` (stderr: stdout stays the result).
    """
    start = time.perf_counter()

    def show(text: str) -> None:
        stream.write(f'{program}: [{time.perf_counter() - start:5.1f} s] {text}\n')
        stream.flush()
    return show


def write_run_outputs(out: pathlib.Path, record, scenario: Scenario, metrics: dict,
                      figures: bool = True, progress=None) -> list[pathlib.Path]:
    """Write the outputs of a run into ``out``.

    metrics.json, timeseries.npz, scenario.yaml, figures/ (PNG and SVG) and report.html
    into ``out``; ``progress(text)`` is told each step.
    """
    out.mkdir(parents=True, exist_ok=True)
    # Each file whole or not at all (a crash or Ctrl-C never leaves half a file).
    write_atomic(out / 'metrics.json', json.dumps(metrics, indent=2) + '\n')
    partial = out / '.timeseries.npz.tmp.npz'
    record.save_npz(partial)
    os.replace(partial, out / 'timeseries.npz')
    write_atomic(out / 'scenario.yaml', yaml.safe_dump(scenario_to_mapping(scenario),
                                                       sort_keys=False))
    paths = []
    if figures:
        from .analysis.figures import write_figures  # matplotlib only when asked
        paths = write_figures(record, scenario, out / 'figures', progress=progress)
    from .analysis.report_page import write_report_page
    write_report_page(out, metrics, scenario, paths, progress=progress)
    return paths


def simulate(scenario_path: str | None, out_dir: str, figures: bool = True,
             quiet: bool = False) -> int:
    """Run one scenario and write its outputs; returns a process exit code."""
    try:
        scenario = load_scenario(scenario_path)
        out = check_output_directory(out_dir)
    except (ParamError, ValueError) as err:
        print(f'ERROR: {err}', file=sys.stderr)
        return EXIT_USAGE
    if not quiet:
        print(f'scenario {scenario.name!r}: {scenario.duration:.0f} s, plant model '
              f'{scenario.plant.model.model!r}', file=sys.stderr)
    result = run_scenario(scenario, progress=None if quiet else progress_printer())
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    metrics['wall_time_s'] = result.wall_time_s
    metrics['real_time_factor'] = result.simulated_time_s / result.wall_time_s
    if not quiet:
        print('', file=sys.stderr)
    paths = write_run_outputs(out, result.record, scenario, metrics, figures,
                              progress=None if quiet else step_printer('simulate'))
    if not quiet:
        print('', file=sys.stderr)
        print(summary(metrics))
        print(f'wrote {out / "metrics.json"}, {out / "timeseries.npz"}'
              + (f' and {len(paths)} figures in {out / "figures"}' if paths else ''))
    return EXIT_FAILED if metrics['fell'] else EXIT_OK


def summary(metrics: dict) -> str:
    """Return a few human-readable lines of the key metrics."""
    def fmt(value, unit=''):
        return 'n/a' if value is None else f'{value:.3g}{unit}'

    def solve_us(quantile):
        seconds = metrics['mpc_solve_time_s'][quantile]
        return seconds * 1e6 if seconds else None
    lines = [
        f'fell: {metrics["fell"]}   simulated {metrics["duration_s"]:.1f} s',
        f'max |theta| {fmt(metrics["max_abs_theta_rad"], " rad")}  (outside pulse windows '
        f'{fmt(metrics["max_abs_theta_outside_pulse_windows_rad"], " rad")})',
        f'max |wheel torque| {fmt(metrics["max_abs_wheel_torque_nm"], " N m")}   '
        f'max |delta tau_v| {fmt(metrics["max_abs_delta_tau_v_nm"], " N m")}   '
        f'QP failures {metrics["qp_failures"]} / {metrics["mpc_ticks"]}',
        f'convergence {fmt(metrics["convergence_time_s"], " s")}   '
        f'RMS position error (t >= 10 s) {fmt(metrics["rms_position_error_m"], " m")}   '
        f'max {fmt(metrics["max_position_error_m"], " m")}',
        f'MPC solve p50 {fmt(solve_us("p50"), " us")}   p99 {fmt(solve_us("p99"), " us")}',
    ]
    if 'real_time_factor' in metrics:
        lines.append(f'real-time factor {metrics["real_time_factor"]:.1f}x')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/simulate', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', help='scenario YAML file (default: paper Section V)')
    parser.add_argument('--out', default='out/simulate', help='output directory')
    parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--quiet', action='store_true', help='no progress or summary')
    parser.add_argument('--dump-scenario', action='store_true',
                        help='print the scenario (default or --scenario) as YAML and exit')
    parser.add_argument('--list-parameters', action='store_true',
                        help='print every node parameter and scenario key with unit, '
                        'default, range; exit')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    if args.list_parameters:
        print(parameter_table())
        return 0
    if args.dump_scenario:
        try:
            scenario = load_scenario(args.scenario)
        except ParamError as err:
            print(f'ERROR: {err}', file=sys.stderr)
            return EXIT_USAGE
        print(yaml.safe_dump(scenario_to_mapping(scenario), sort_keys=False), end='')
        return 0
    return simulate(args.scenario, args.out, figures=not args.no_figures, quiet=args.quiet)


if __name__ == '__main__':
    exit_with(main, 'simulate')
