"""``scripts/campaign``: one scenario run many times over parameter distributions or grids.

A campaign file (YAML) names a base scenario, the scenario keys to vary (random draws
and/or a grid), how many runs, and the pass criteria; every run is an in-process
simulation (:func:`~wip_sim.core.runner.run_scenario`) on a Dask worker. The format
is documented in ``docs/campaign.md``; in short::

    name: mass_height_noise
    scenario: ../scenarios/paper.yaml     # a file (relative to this one) or a mapping;
                                          # default: the paper's Section V
    overrides: {duration: 30}             # scenario keys applied to every run
    runs: 40                              # draws (per grid point, with a grid)
    seed: 1                               # draws and run seeds derive from it
    vary:                                 # dotted scenario key -> distribution
      plant.parameters.body_mass: {scale: [0.8, 1.2]}
      sensors.imu_pitch_noise_std: {uniform: [0.0, 0.002]}
      disturbances.longitudinal[0].amplitude: {choice: [-10.0, 10.0]}
    grid:                                 # dotted scenario key -> values (1 or 2 keys)
      sensors.gps_rate: [1.0, 5.0, 10.0]
    criteria: {max_abs_theta_outside_pulses: 0.1}   # see wip_tools/analysis/criteria.py

Outputs in ``--out`` (default ``out/campaign/<name>``): ``runs.jsonl`` (one JSON row per
finished run, appended as runs finish: the campaign can be resumed with ``--resume``),
``runs.csv`` (and ``runs.parquet`` when pyarrow is installed), ``summary.json``,
``summary.txt``, ``figures/*.png`` and a copy of the campaign file. An existing output
is never overwritten without ``--force``.

Examples
--------
    scripts/campaign my_campaign.yaml                      # local cores
    scripts/campaign my_campaign.yaml --workers 2 --out out/c1
    scripts/campaign my_campaign.yaml --scheduler tcp://10.0.0.5:8786
    scripts/campaign my_campaign.yaml --resume             # finish an interrupted campaign
    scripts/campaign --dry-run my_campaign.yaml            # list the runs, run nothing
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import pathlib
import shutil
import sys
import time
import traceback
from typing import Any, Mapping

from wip_runtime.config import ParamError
from wip_tools.analysis.criteria import (criteria_from_mapping, criteria_to_mapping, evaluate,
                                         measure)
from wip_sim.core.scenario import scenario_from_mapping
from wip_runtime.cli import add_exit_codes
from wip_tools.campaign_file import (Campaign, CampaignError, load_campaign, run_specs,
                                     scenario_mapping)
from wip_tools.campaign_results import summarise, summary_text, write_figures, write_table

#: Metrics of a run copied into its row (see wip_tools/analysis/metrics.py for their definitions).
METRIC_COLUMNS = ('max_abs_theta_rad', 'max_abs_theta_outside_pulse_windows_rad',
                  'max_abs_wheel_torque_nm', 'max_abs_delta_tau_v_nm', 'qp_failures',
                  'mpc_ticks', 'convergence_time_s', 'rms_position_error_m',
                  'max_position_error_m', 'rms_heading_error_rad', 'max_abs_v_mps')
#: Measured quantities of the criteria copied into the row (see wip_tools/analysis/criteria.py).
MEASURE_COLUMNS = ('max_speed_outside_pulses', 'convergence_time',
                   'rms_path_error_after_settle', 'max_path_error_after_settle',
                   'final_position_error', 'final_path_error', 'final_oscillation',
                   'final_abs_theta', 'runaway_growth', 'runaway_alarm', 'outcome',
                   'refused_at', 'refusal_hold_error', 'final_speed')


def run_one(spec: Mapping[str, Any], base: Mapping[str, Any],
            criteria: Mapping[str, Any]) -> dict[str, Any]:
    """Simulate one run (on a worker) and return its row.

    Never raises: an exception of the run is reported in the row's ``error`` (the run then fails).

    ``base`` is the campaign's base scenario mapping and ``criteria`` its criteria as a
    mapping (plain data: they travel to the workers once, see :func:`execute`).
    """
    from wip_tools.analysis.metrics import compute_metrics  # worker-side imports
    from wip_sim.core.runner import run_scenario

    row: dict[str, Any] = {'run': spec['run'], **spec['values'], 'seed': spec['seed']}
    start, cpu_start = time.perf_counter(), time.process_time()
    try:
        scenario = scenario_from_mapping(scenario_mapping(base, spec))
        criteria = criteria_from_mapping(criteria)
        result = run_scenario(scenario)
        metrics = compute_metrics(result.record, scenario, fell=result.fell,
                                  duration_s=result.simulated_time_s)
        measured = measure(result.record, scenario, metrics, criteria, result.obstacle)
        failures = evaluate(measured, criteria, scenario.duration)
        row.update({'fell': bool(result.fell), 'fall_time_s': result.fall_time,
                    'simulated_s': result.simulated_time_s})
        row.update({key: metrics.get(key) for key in METRIC_COLUMNS})
        row.update({key: measured.get(key) for key in MEASURE_COLUMNS})
        row.update({'success': not failures, 'failed': ';'.join(sorted(failures)),
                    'reasons': '; '.join(failures.values()), 'error': ''})
    except Exception as err:  # noqa: BLE001 (a failing run is a result, not a crash)
        last = traceback.extract_tb(err.__traceback__)[-1]
        row.update({'fell': None, 'success': False, 'failed': 'error',
                    'reasons': '', 'error': f'{type(err).__name__}: {err} '
                                            f'({pathlib.Path(last.filename).name}:{last.lineno})'})
    row['wall_time_s'] = time.perf_counter() - start
    row['cpu_time_s'] = time.process_time() - cpu_start
    return row


# ----------------------------------------------------------------------------- execution

def _read_done(jsonl: pathlib.Path) -> dict[int, dict]:
    done = {}
    if jsonl.exists():
        for line in jsonl.read_text(encoding='utf-8').splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue        # a line cut by an interruption: that run is done again
            done[int(row['run'])] = row
    return done


def execute(campaign: Campaign, specs: list[dict], jsonl: pathlib.Path,
            scheduler: str | None = None, workers: int | None = None,
            progress: bool = True) -> list[dict]:
    """Run the specs on Dask.

    The cluster is a LocalCluster of ``workers`` processes, or the one at ``scheduler``.
    Each finished row is appended to ``jsonl``. Return all rows, by run.
    """
    from dask.distributed import Client, LocalCluster, as_completed
    from tqdm import tqdm

    done = _read_done(jsonl)
    todo = [s for s in specs if s['run'] not in done]
    if todo:
        if scheduler:
            failure = None
            try:
                client = Client(scheduler, timeout='20s')
            except (OSError, ValueError, TypeError) as err:   # no answer, a bad address
                failure = f'--scheduler {scheduler}: {err}'
            if failure is not None:
                # The half-built Client is garbage now (the exception is gone); collect it
                # here. Left to a later collection, its __del__ can run inside dask's
                # LoopRunner.start, which holds the lock that __del__'s close() then waits
                # for: a deadlock (seen: a test's LocalCluster hung in its constructor).
                gc.collect()
                raise CampaignError(failure)
            cluster = None
        else:
            n = workers or os.cpu_count() or 1
            # One single-threaded process per core: the runner is pure Python (GIL).
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=40)
            client = Client(cluster)
        try:
            # The base scenario and the criteria go to every worker once; a task carries
            # only its run's values.
            base, criteria = client.scatter(
                [campaign.base, criteria_to_mapping(campaign.criteria)], broadcast=True)
            futures = [client.submit(run_one, spec, base, criteria, pure=False,
                                     key=f'run-{spec["run"]}') for spec in todo]
            with jsonl.open('a', encoding='utf-8') as stream, \
                    tqdm(total=len(specs), initial=len(specs) - len(todo), unit='run',
                         disable=not progress, file=sys.stderr,
                         # In a log file (not a terminal) a line every 10 s, not per run.
                         mininterval=0.1 if sys.stderr.isatty() else 10.0) as bar:
                for future in as_completed(futures):
                    row = future.result()
                    done[row['run']] = row
                    stream.write(json.dumps(row) + '\n')
                    stream.flush()
                    bar.update(1)
                    bar.set_postfix(failed=sum(1 for r in done.values() if not r['success']),
                                    refresh=False)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return [done[s['run']] for s in specs]


# ----------------------------------------------------------------------------- CLI

def _fail(message: str) -> int:
    print(f'ERROR: {message}', file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/campaign', formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split('\n\n')[0] + '\nThe campaign file and the outputs: '
        'docs/campaign.md.\n\n' + __doc__[__doc__.index('Examples'):])
    parser.add_argument('campaign', help='campaign YAML file (format: docs/campaign.md)')
    parser.add_argument('--out', help='output folder (default: out/campaign/<name>)')
    parser.add_argument('--scheduler', metavar='ADDRESS',
                        help='address of a Dask scheduler (tcp://host:8786); default: a '
                             'local cluster of --workers processes')
    parser.add_argument('--workers', type=int, default=None,
                        help='local worker processes (default: the number of CPUs)')
    parser.add_argument('--force', action='store_true',
                        help='delete an existing output folder first')
    parser.add_argument('--resume', action='store_true',
                        help='keep the finished runs of an existing output folder of the '
                             'same campaign and do the rest')
    parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    parser.add_argument('--dry-run', action='store_true',
                        help="validate, print the runs' values, run nothing")
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    if args.workers is not None and args.workers < 1:
        return _fail('--workers: must be >= 1')
    if args.force and args.resume:
        return _fail('--force and --resume exclude each other')
    try:
        campaign = load_campaign(args.campaign)
        specs = run_specs(campaign)
    except ParamError as err:
        return _fail(str(err))

    if args.dry_run:
        for spec in specs:
            print(json.dumps({'run': spec['run'], 'seed': spec['seed'], **spec['values']}))
        print(f'{len(specs)} runs of {campaign.base["duration"]:g} s', file=sys.stderr)
        return 0

    out = pathlib.Path(args.out or f'out/campaign/{campaign.name}')
    # One campaign per folder: run_graph's output lock, taken before anything there is
    # removed or written, held until this returns.
    from wip_bringup.launcher import GraphError
    from wip_bringup.output_lock import LOCK_FILE, lock_output
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = lock_output(out, '--out')
    except (GraphError, OSError) as err:
        return _fail(str(err))
    try:
        return _run(campaign, specs, args, out, LOCK_FILE)
    finally:
        os.close(lock)


def _run(campaign, specs, args, out: pathlib.Path, lock_file: str) -> int:
    """Run the campaign into ``out``, whose output lock the caller holds; the exit status."""
    jsonl = out / 'runs.jsonl'
    stamp = out / 'campaign.yaml'
    # A folder holding only the campaign file (a start that failed) has no results.
    if any(p.name not in (stamp.name, lock_file) for p in out.iterdir()):
        if args.force:
            for entry in out.iterdir():    # all but the lock, which this process holds
                if entry.name == lock_file:
                    continue
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry)
                else:
                    entry.unlink()
        elif args.resume:
            if not stamp.exists() or stamp.read_text(encoding='utf-8') != campaign.source:
                return _fail(f'{out}: holds another campaign (its campaign.yaml differs); '
                             'use another --out, or --force to replace it')
        else:
            return _fail(f'{out}: exists and is not empty; use --resume to finish it, '
                         '--force to replace it, or another --out')
    out.mkdir(parents=True, exist_ok=True)
    stamp.write_text(campaign.source, encoding='utf-8')

    print(f'campaign {campaign.name!r}: {len(specs)} runs of {campaign.base["duration"]:g} s '
          f'on {args.scheduler or f"{args.workers or os.cpu_count()} local processes"}',
          file=sys.stderr)
    start = time.perf_counter()
    try:
        rows = execute(campaign, specs, jsonl, scheduler=args.scheduler, workers=args.workers,
                       progress=not args.no_progress)
    except CampaignError as err:     # a scheduler address that does not answer
        return _fail(str(err))
    except KeyboardInterrupt:
        print(f'\ninterrupted: finished runs are in {jsonl}; --resume continues',
              file=sys.stderr)
        return 130
    wall = time.perf_counter() - start
    summary = summarise(campaign, rows)
    summary['campaign_wall_time_s'] = wall
    write_table(rows, out)
    (out / 'summary.json').write_text(json.dumps(summary, indent=2, default=str) + '\n')
    text = summary_text(summary) + (
        f'\nwall time {wall:.1f} s for {summary["simulated_s_sum"]:.0f} s simulated; runs '
        f'took {summary["cpu_time_s_sum"]:.1f} s of CPU in all')
    (out / 'summary.txt').write_text(text + '\n', encoding='utf-8')
    if not args.no_figures:
        write_figures(campaign, rows, summary, out / 'figures')
    print(text)
    print(f'wrote {out}/runs.csv, summary.json, summary.txt'
          + ('' if args.no_figures else ', figures/'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
