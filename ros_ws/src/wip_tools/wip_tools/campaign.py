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
import copy
import csv
import dataclasses
import itertools
import gc
import json
import math
import os
import pathlib
import re
import shutil
import sys
import time
import traceback
from typing import Any, Iterable, Mapping

import numpy as np
import yaml

from wip_control.core.config import ConfigError
from wip_tools.analysis.criteria import (Criteria, criteria_from_mapping, criteria_to_mapping,
                                       evaluate, measure)
from wip_sim.core.scenario import load_scenario, scenario_from_mapping, scenario_to_mapping
from wip_control.tools.cli import add_exit_codes

#: Keys of a campaign file.
CAMPAIGN_KEYS = ('name', 'description', 'scenario', 'overrides', 'runs', 'seed', 'vary',
                 'grid', 'criteria')
#: Distribution kinds of ``vary`` and their number of arguments.
DISTRIBUTIONS = {
    'uniform': 'uniform: [low, high] -> U(low, high)',
    'log_uniform': 'log_uniform: [low, high] (both > 0) -> exp(U(ln low, ln high))',
    'normal': 'normal: [mean, std] -> N(mean, std^2)',
    'scale': 'scale: [low, high] -> base value * U(low, high)',
    'integers': 'integers: [low, high] -> an integer in [low, high]',
    'choice': 'choice: [a, b, ...] -> one of the values, equally likely',
}
#: Upper bound on the runs of one campaign (a typo like 1e7 runs is a mistake).
MAX_RUNS = 100_000
#: Metrics of a run copied into its row (see wip_tools/analysis/metrics.py for their definitions).
METRIC_COLUMNS = ('max_abs_theta_rad', 'max_abs_theta_outside_pulse_windows_rad',
                  'max_abs_wheel_torque_nm', 'max_abs_delta_tau_v_nm', 'qp_failures',
                  'mpc_ticks', 'convergence_time_s', 'rms_position_error_m',
                  'max_position_error_m', 'rms_heading_error_rad', 'max_abs_v_mps')
#: Measured quantities of the criteria copied into the row (see wip_tools/analysis/criteria.py).
MEASURE_COLUMNS = ('max_speed_outside_pulses', 'convergence_time',
                   'rms_path_error_after_settle', 'max_path_error_after_settle',
                   'final_position_error', 'final_path_error', 'final_oscillation',
                   'final_abs_theta', 'runaway_growth')


class CampaignError(ConfigError):
    """A campaign file or option is wrong; the message names the key."""


# ----------------------------------------------------------------------------- file format

@dataclasses.dataclass(frozen=True)
class Campaign:
    """A parsed and validated campaign file."""

    name: str
    description: str
    base: dict                      # full scenario mapping, overrides applied
    runs: int                       # draws per grid point
    seed: int
    vary: dict                      # key -> (kind, args)
    grid: dict                      # key -> list of values
    criteria: Criteria
    source: str = ''

    @property
    def grid_points(self) -> list[dict]:
        if not self.grid:
            return [{}]
        keys = list(self.grid)
        return [dict(zip(keys, values)) for values in itertools.product(*self.grid.values())]

    @property
    def total_runs(self) -> int:
        return self.runs * len(self.grid_points)


_INDEX = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$')


def _split_key(key: str, where: str) -> list:
    """Split a parameter key into its parts.

    'disturbances.longitudinal[0].amplitude' -> ['disturbances', 'longitudinal', 0,
    'amplitude'].
    """
    if not isinstance(key, str) or not key:
        raise CampaignError(f'{where}: a key must be a dotted scenario key, got {key!r}')
    parts: list = []
    for token in key.split('.'):
        match = _INDEX.match(token)
        if not match:
            raise CampaignError(f'{where}.{key}: not a dotted scenario key '
                                '(e.g. plant.parameters.body_mass, pose[0])')
        parts.append(match.group(1))
        parts.extend(int(i) for i in re.findall(r'\[(\d+)\]', match.group(2)))
    return parts


def _get(mapping: Any, parts: list, key: str, where: str) -> Any:
    node = mapping
    for part in parts:
        if isinstance(part, int):
            if not isinstance(node, list) or part >= len(node):
                raise CampaignError(f'{where}.{key}: index [{part}] out of range (the base '
                                    f'scenario has {len(node) if isinstance(node, list) else 0}'
                                    ' elements there)')
        elif not isinstance(node, dict) or part not in node:
            options = sorted(node) if isinstance(node, dict) else []
            raise CampaignError(f'{where}.{key}: not a scenario key ({part!r} unknown'
                                + (f'; expected one of {options}' if options else '') + ')')
        node = node[part]
    return node


def _set(mapping: dict, parts: list, value: Any) -> None:
    node = mapping
    for part in parts[:-1]:
        node = node[part]
    node[parts[-1]] = value


def _merge(base: dict, overrides: Mapping, where: str) -> dict:
    """Deep merge: mappings merge key by key, anything else replaces."""
    out = copy.deepcopy(base)
    for key, value in overrides.items():
        if key not in out:
            raise CampaignError(f'{where}.{key}: not a scenario key; expected one of '
                                f'{sorted(out)}')
        if isinstance(value, Mapping) and isinstance(out[key], dict):
            out[key] = _merge(out[key], value, f'{where}.{key}')
        else:
            out[key] = copy.deepcopy(value)
    return out


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CampaignError(f'{where}: expected a finite number, got {value!r}')
    return float(value)


def _parse_distribution(key: str, spec: Any, base_value: Any) -> tuple[str, list]:
    where = f'campaign.vary.{key}'
    if not isinstance(spec, Mapping) or len(spec) != 1:
        raise CampaignError(f'{where}: expected one of {{{", ".join(DISTRIBUTIONS)}}}: '
                            f'[...], got {spec!r}')
    kind, args = next(iter(spec.items()))
    if kind not in DISTRIBUTIONS:
        raise CampaignError(f'{where}: unknown distribution {kind!r}; expected one of '
                            f'{list(DISTRIBUTIONS)}')
    if not isinstance(args, list) or not args:
        raise CampaignError(f'{where}.{kind}: expected a list ({DISTRIBUTIONS[kind]})')
    if kind == 'choice':
        return kind, list(args)
    if len(args) != 2:
        raise CampaignError(f'{where}.{kind}: expected 2 values ({DISTRIBUTIONS[kind]}), '
                            f'got {len(args)}')
    a, b = (_number(v, f'{where}.{kind}') for v in args)
    if kind in ('uniform', 'scale', 'integers', 'log_uniform') and a > b:
        raise CampaignError(f'{where}.{kind}: low {a:g} > high {b:g}')
    if kind == 'normal' and b < 0.0:
        raise CampaignError(f'{where}.normal: std must be >= 0, got {b:g}')
    if kind == 'log_uniform' and a <= 0.0:
        raise CampaignError(f'{where}.log_uniform: low must be > 0, got {a:g}')
    if kind == 'integers' and not (a.is_integer() and b.is_integer()):
        raise CampaignError(f'{where}.integers: expected integer bounds, got {args}')
    if kind == 'scale' and (isinstance(base_value, bool)
                            or not isinstance(base_value, (int, float))):
        raise CampaignError(f'{where}.scale: the base value {base_value!r} is not a number')
    return kind, [a, b]


def _draw(kind: str, args: list, base_value: Any, rng: np.random.Generator) -> Any:
    if kind == 'uniform':
        return float(rng.uniform(args[0], args[1]))
    if kind == 'log_uniform':
        return float(math.exp(rng.uniform(math.log(args[0]), math.log(args[1]))))
    if kind == 'normal':
        return float(rng.normal(args[0], args[1]))
    if kind == 'scale':
        return float(base_value) * float(rng.uniform(args[0], args[1]))
    if kind == 'integers':
        return int(rng.integers(int(args[0]), int(args[1]) + 1))
    value = args[int(rng.integers(len(args)))]
    return copy.deepcopy(value)


def campaign_from_mapping(data: Any, source_dir: pathlib.Path | None = None,
                          default_name: str = 'campaign') -> Campaign:
    """Validate a parsed campaign file; every run's scenario is checked too."""
    if not isinstance(data, Mapping):
        raise CampaignError(f'campaign: expected a mapping at the top level, got '
                            f'{type(data).__name__}')
    for key in data:
        if key not in CAMPAIGN_KEYS:
            raise CampaignError(f'campaign.{key}: unknown key; expected one of '
                                f'{list(CAMPAIGN_KEYS)}')
    name = data.get('name', default_name)
    description = data.get('description', '')
    for key, value in (('name', name), ('description', description)):
        if not isinstance(value, str):
            raise CampaignError(f'campaign.{key}: expected a string, got {value!r}')
    if not re.match(r'^[A-Za-z0-9_.-]+$', name):
        raise CampaignError(f'campaign.name: use letters, digits, _ . - only (it names the '
                            f'output folder), got {name!r}')

    scenario = data.get('scenario')
    try:
        if scenario is None:
            base = scenario_to_mapping(load_scenario(None))
        elif isinstance(scenario, str):
            path = pathlib.Path(scenario)
            if not path.is_absolute() and source_dir is not None:
                path = source_dir / path
            base = scenario_to_mapping(load_scenario(path))
        elif isinstance(scenario, Mapping):
            base = scenario_to_mapping(scenario_from_mapping(scenario))
        else:
            raise CampaignError(f'campaign.scenario: expected a file name or a mapping, got '
                                f'{scenario!r}')
    except CampaignError:
        raise
    except ConfigError as err:
        raise CampaignError(f'campaign.scenario: {err}') from err

    overrides = data.get('overrides') or {}
    if not isinstance(overrides, Mapping):
        raise CampaignError(f'campaign.overrides: expected a mapping, got {overrides!r}')
    base = _merge(base, overrides, 'campaign.overrides')
    try:
        base = scenario_to_mapping(scenario_from_mapping(base))
    except ConfigError as err:
        raise CampaignError(f'campaign.overrides: {err}') from err

    runs = data.get('runs', 1)
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise CampaignError(f'campaign.runs: expected an integer >= 1, got {runs!r}')
    seed = data.get('seed', 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise CampaignError(f'campaign.seed: expected an integer >= 0, got {seed!r}')

    vary_data = data.get('vary') or {}
    if not isinstance(vary_data, Mapping):
        raise CampaignError(f'campaign.vary: expected a mapping of scenario keys, got '
                            f'{vary_data!r}')
    vary = {}
    for key, spec in vary_data.items():
        parts = _split_key(key, 'campaign.vary')
        base_value = _get(base, parts, key, 'campaign.vary')
        vary[key] = _parse_distribution(key, spec, base_value)

    grid_data = data.get('grid') or {}
    if not isinstance(grid_data, Mapping):
        raise CampaignError(f'campaign.grid: expected a mapping of scenario keys, got '
                            f'{grid_data!r}')
    if len(grid_data) > 2:
        raise CampaignError(f'campaign.grid: at most 2 keys (a 1-D or 2-D grid), got '
                            f'{len(grid_data)}')
    grid = {}
    for key, values in grid_data.items():
        parts = _split_key(key, 'campaign.grid')
        _get(base, parts, key, 'campaign.grid')
        if key in vary:
            raise CampaignError(f'campaign.grid.{key}: also in campaign.vary; vary it in '
                                'one place')
        if not isinstance(values, list) or not values:
            raise CampaignError(f'campaign.grid.{key}: expected a non-empty list of values')
        grid[key] = list(values)

    try:
        criteria = criteria_from_mapping(data.get('criteria'), 'campaign.criteria')
    except ConfigError as err:
        raise CampaignError(str(err)) from err
    campaign = Campaign(name=name, description=description, base=base, runs=runs, seed=seed,
                        vary=vary, grid=grid, criteria=criteria)
    if campaign.total_runs > MAX_RUNS:
        raise CampaignError(f'campaign.runs: {campaign.total_runs} runs in all (runs x grid '
                            f'points) is more than {MAX_RUNS}')
    return campaign


def load_campaign(path: str | pathlib.Path) -> Campaign:
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as err:
        raise CampaignError(f'campaign file {str(path)!r}: {err.strerror}') from err
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        first = str(err).splitlines()[0] if str(err) else 'parse error'
        raise CampaignError(f'campaign file {str(path)!r} is not valid YAML: {first}') from err
    campaign = campaign_from_mapping(data, path.parent, default_name=path.stem)
    return dataclasses.replace(campaign, source=text)


# ----------------------------------------------------------------------------- runs

def run_specs(campaign: Campaign) -> list[dict]:
    """One spec per run: its id, the values drawn (by dotted key) and its scenario seed.

    Run ``i`` draws from its own generator, seeded by (campaign seed, i): a run's
    values do not depend on the number of workers, on the order of completion, or on
    which runs were already done (resume). Its scenario ``seed`` (sensor and
    disturbance noise) is ``campaign seed * 1_000_003 + i`` unless ``seed`` is varied.
    Every run's scenario is built and validated here (about 2 ms a run), so that a bad
    draw stops the campaign before it starts: :class:`CampaignError` names the run and
    the key.
    """
    specs = []
    run = 0
    for point in campaign.grid_points:
        for _ in range(campaign.runs):
            rng = np.random.default_rng(np.random.SeedSequence((campaign.seed, run)))
            values: dict[str, Any] = {key: copy.deepcopy(value) for key, value in point.items()}
            for key, (kind, args) in campaign.vary.items():
                parts = _split_key(key, 'campaign.vary')
                values[key] = _draw(kind, args, _get(campaign.base, parts, key, 'campaign.vary'),
                                    rng)
            seed = values['seed'] if 'seed' in values else campaign.seed * 1_000_003 + run
            spec = {'run': run, 'values': values, 'seed': seed}
            try:
                scenario_from_mapping(scenario_mapping(campaign.base, spec))
            except ConfigError as err:
                shown = ', '.join(f'{k} = {v!r}' for k, v in values.items())
                raise CampaignError(f'campaign: run {run} ({shown}) is not a valid scenario: '
                                    f'{err}') from err
            specs.append(spec)
            run += 1
    return specs


def scenario_mapping(base: Mapping[str, Any], spec: Mapping[str, Any]) -> dict:
    """Return the full scenario mapping of one run: ``base`` with the run's values and seed."""
    scenario = copy.deepcopy(dict(base))
    for key, value in spec['values'].items():
        _set(scenario, _split_key(key, 'campaign'), copy.deepcopy(value))
    scenario['seed'] = spec['seed']
    return scenario


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
        measured = measure(result.record, scenario, metrics, criteria)
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


# ----------------------------------------------------------------------------- outputs

def write_table(rows: list[dict], out: pathlib.Path) -> list[pathlib.Path]:
    """runs.csv (and runs.parquet when pyarrow is installed)."""
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    written = [out / 'runs.csv']
    with (out / 'runs.csv').open('w', newline='', encoding='utf-8') as stream:
        writer = csv.DictWriter(stream, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ('' if row.get(k) is None else row.get(k)) for k in columns})
    try:
        import pyarrow  # noqa: F401 (optional)
        import pyarrow.parquet as pq
    except ImportError:
        return written
    table = pyarrow.Table.from_pylist([{k: row.get(k) for k in columns} for row in rows])
    pq.write_table(table, out / 'runs.parquet')
    written.append(out / 'runs.parquet')
    return written


def _values(rows: Iterable[dict], key: str) -> np.ndarray:
    out = [row.get(key) for row in rows]
    return np.array([np.nan if v is None or isinstance(v, str) else float(v) for v in out])


def summarise(campaign: Campaign, rows: list[dict]) -> dict[str, Any]:
    """Return counts and rates against the criteria, percentiles of the main errors."""
    n = len(rows)
    failures: dict[str, int] = {}
    for row in rows:
        for name in filter(None, (row.get('failed') or '').split(';')):
            failures[name] = failures.get(name, 0) + 1
    successes = sum(1 for r in rows if r['success'])
    falls = sum(1 for r in rows if r.get('fell'))
    qp = _values(rows, 'qp_failures')
    summary: dict[str, Any] = {
        'campaign': campaign.name, 'runs': n, 'successes': successes,
        'success_rate': successes / n if n else None,
        'falls': falls, 'errors': sum(1 for r in rows if r.get('error')),
        'failed_criteria': failures,
        'qp_failures_total': int(np.nansum(qp)) if n else 0,
        'criteria': criteria_to_mapping(campaign.criteria),
        'varied': {k: {'distribution': kind, 'args': args}
                   for k, (kind, args) in campaign.vary.items()},
        'grid': campaign.grid,
        'wall_time_s_sum': float(np.nansum(_values(rows, 'wall_time_s'))),
        'cpu_time_s_sum': float(np.nansum(_values(rows, 'cpu_time_s'))),
        'simulated_s_sum': float(np.nansum(_values(rows, 'simulated_s'))),
    }
    percentiles = {}
    for key in ('max_abs_theta_rad', 'max_abs_theta_outside_pulse_windows_rad',
                'max_abs_wheel_torque_nm', 'max_abs_delta_tau_v_nm', 'rms_position_error_m',
                'rms_path_error_after_settle', 'max_abs_v_mps'):
        values = _values(rows, key)
        values = values[np.isfinite(values)]
        if len(values):
            percentiles[key] = {'p50': float(np.percentile(values, 50)),
                                'p95': float(np.percentile(values, 95)),
                                'max': float(np.max(values))}
    summary['percentiles'] = percentiles
    if campaign.grid:
        cells = []
        keys = list(campaign.grid)
        for point in campaign.grid_points:
            members = [r for r in rows if all(r.get(k) == v for k, v in point.items())]
            cells.append({**point, 'runs': len(members),
                          'success_rate': (sum(r['success'] for r in members) / len(members)
                                           if members else None)})
        summary['grid_cells'] = cells
        summary['grid_keys'] = keys
    return summary


def summary_text(summary: dict) -> str:
    c = summary['criteria']
    lines = [f'campaign {summary["campaign"]!r}: {summary["runs"]} runs',
             f'success: {summary["successes"]} / {summary["runs"]} '
             f'({100 * (summary["success_rate"] or 0):.1f} %)   falls {summary["falls"]}   '
             f'QP failures {summary["qp_failures_total"]}   run errors {summary["errors"]}',
             'criteria: no fall' if c['no_fall'] else 'criteria:',
             ]
    active = [f'{k} <= {v}' for k, v in c.items()
              if k.startswith('max_') and v is not None]
    lines[-1] += ', ' + ', '.join(active) if active else ''
    if summary['failed_criteria']:
        lines.append('failed: ' + ', '.join(f'{k} {v}' for k, v in
                                            sorted(summary['failed_criteria'].items(),
                                                   key=lambda kv: -kv[1])))
    for key, p in summary['percentiles'].items():
        lines.append(f'{key}: p50 {p["p50"]:.4g}  p95 {p["p95"]:.4g}  max {p["max"]:.4g}')
    for cell in summary.get('grid_cells', []):
        point = ', '.join(f'{k} = {cell[k]}' for k in summary['grid_keys'])
        rate = cell['success_rate']
        lines.append(f'  {point}: {cell["runs"]} runs, success '
                     + ('n/a' if rate is None else f'{100 * rate:.0f} %'))
    return '\n'.join(lines)


def write_figures(campaign: Campaign, rows: list[dict], summary: dict,
                  out: pathlib.Path) -> list[pathlib.Path]:
    """Success rate, error distributions, and a heatmap over a 2-D grid."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    success = np.array([bool(r['success']) for r in rows])

    # 1. Success rate: overall, and binned along each varied (or 1-D grid) parameter.
    varied = list(campaign.vary) + list(campaign.grid)
    numeric = [k for k in varied if np.all(np.isfinite(_values(rows, k)))]
    fig, axes = plt.subplots(1, 1 + len(numeric), figsize=(4 + 3.5 * len(numeric), 3.2),
                             squeeze=False)
    ax = axes[0, 0]
    ax.bar(['success', 'fail'], [success.sum(), (~success).sum()], color=['tab:green', 'tab:red'])
    ax.set_title(f'{100 * success.mean():.1f} % of {len(rows)} runs pass')
    for ax, key in zip(axes[0, 1:], numeric):
        x = _values(rows, key)
        unique = np.unique(x)
        if len(unique) <= 12:
            centers = unique
            members = [x == u for u in unique]
            width = 0.8 * (np.min(np.diff(unique)) if len(unique) > 1 else 1.0)
        else:
            edges = np.linspace(np.min(x), np.max(x), 9)
            index = np.clip(np.digitize(x, edges) - 1, 0, 7)
            centers = 0.5 * (edges[:-1] + edges[1:])
            members = [index == i for i in range(8)]
            width = 0.9 * (edges[1] - edges[0])
        rate = [success[m].mean() if np.any(m) else np.nan for m in members]
        ax.bar(centers, rate, width=width if width > 0 else 1.0, color='tab:blue',
               edgecolor='black', linewidth=0.5)
        for center, m in zip(centers, members):
            if np.any(m):   # pass / runs above each bar: a 0 % bar is still readable
                ax.text(center, 1.07, f'{int(success[m].sum())}/{int(m.sum())}',
                        ha='center', va='bottom', fontsize=6)
        ax.set_ylim(0, 1.15)
        ax.set_xlabel(key, fontsize=8)
        ax.set_ylabel('success rate')
    fig.tight_layout()
    paths.append(out / 'success_rate.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # 2. Error distributions.
    keys = [('max_abs_theta_outside_pulse_windows_rad', '|θ| max outside pulses [rad]'),
            ('rms_path_error_after_settle', 'RMS path error after settle [m]'),
            ('max_abs_wheel_torque_nm', 'max |τ wheel| [N·m]'),
            ('max_abs_delta_tau_v_nm', 'max |Δτυ| [N·m]')]
    limits = {'max_abs_wheel_torque_nm': campaign.criteria.max_wheel_torque,
              'max_abs_delta_tau_v_nm': campaign.criteria.max_delta_tau_v,
              'max_abs_theta_outside_pulse_windows_rad':
                  campaign.criteria.max_abs_theta_outside_pulses,
              'rms_path_error_after_settle': campaign.criteria.max_rms_path_error_after_settle}
    fig, axes = plt.subplots(1, len(keys), figsize=(14, 3.2))
    for ax, (key, label) in zip(axes, keys):
        values = _values(rows, key)
        values = values[np.isfinite(values)]
        if len(values):
            # Equal values (a limit met by every run) still get a visible bar.
            pad = 0.5 * max(float(np.ptp(values)), 1e-3 * float(np.max(np.abs(values))), 1e-9)
            ax.hist(values, bins=min(30, max(5, len(values) // 3)),
                    range=(float(np.min(values)) - pad, float(np.max(values)) + pad),
                    color='tab:gray')
        if limits.get(key) is not None:
            ax.axvline(limits[key], color='tab:red', linestyle='--', label='limit')
            ax.legend(fontsize=7)
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel('runs')
    fig.tight_layout()
    paths.append(out / 'error_distributions.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # 3. Heatmaps over a 2-D grid: success rate, and the median RMS path error.
    if len(campaign.grid) == 2:
        (kx, xs), (ky, ys) = campaign.grid.items()
        rate = np.full((len(ys), len(xs)), np.nan)
        error = np.full((len(ys), len(xs)), np.nan)
        label = np.full((len(ys), len(xs)), '', dtype=object)
        for i, y in enumerate(ys):
            for j, x in enumerate(xs):
                cell = [r for r in rows if r.get(kx) == x and r.get(ky) == y]
                if cell:
                    passed = sum(bool(r['success']) for r in cell)
                    rate[i, j] = passed / len(cell)
                    label[i, j] = f'{passed}/{len(cell)}'
                    values = _values(cell, 'rms_path_error_after_settle')
                    if np.any(np.isfinite(values)):
                        error[i, j] = np.nanmedian(values)
        fig, axes = plt.subplots(1, 2, figsize=(2.4 * len(xs) + 5, 0.8 * len(ys) + 2.2))
        panels = ((rate, 'success rate', 'RdYlGn', dict(vmin=0, vmax=1)),
                  (error, 'median RMS path error after settle [m]', 'viridis', {}))
        for ax, (data, title, cmap, scale) in zip(axes, panels):
            image = ax.imshow(data, origin='lower', cmap=cmap, aspect='auto', **scale)
            ax.set_xticks(range(len(xs)), [str(v) for v in xs])
            ax.set_yticks(range(len(ys)), [str(v) for v in ys])
            ax.set_xlabel(kx, fontsize=8)
            ax.set_ylabel(ky, fontsize=8)
            for i in range(len(ys)):
                for j in range(len(xs)):
                    text = label[i, j] if data is rate else (
                        f'{data[i, j]:.3g}' if np.isfinite(data[i, j]) else 'n/a')
                    ax.text(j, i, text, ha='center', va='center', fontsize=8)
            fig.colorbar(image, ax=ax)
            ax.set_title(title, fontsize=9)
        fig.suptitle(campaign.name, fontsize=10)
        fig.tight_layout()
        paths.append(out / 'heatmap.png')
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths


# ----------------------------------------------------------------------------- CLI

def _fail(message: str) -> int:
    print(f'ERROR: {message}', file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='scripts/campaign', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
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
    except ConfigError as err:
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
