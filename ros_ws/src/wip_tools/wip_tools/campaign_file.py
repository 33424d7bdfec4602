"""Campaign files: parse and validate one, and draw its runs (docs/campaign.md)."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import pathlib
import re
from typing import Any, Mapping

import numpy as np
import yaml

from wip_runtime.config import check_number, ParamError
from wip_tools.analysis.criteria import Criteria, criteria_from_mapping
from wip_sim.core.scenario import load_scenario, scenario_from_mapping, scenario_to_mapping

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


class CampaignError(ParamError):
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
    try:
        return check_number(where, value, {}, want_int=False)
    except ParamError as err:
        raise CampaignError(str(err)) from None


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
    base = _base_scenario(data, source_dir)
    runs = data.get('runs', 1)
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise CampaignError(f'campaign.runs: expected an integer >= 1, got {runs!r}')
    seed = data.get('seed', 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise CampaignError(f'campaign.seed: expected an integer >= 0, got {seed!r}')
    vary = _vary(data, base)
    grid = _grid(data, base, vary)
    try:
        criteria = criteria_from_mapping(data.get('criteria'), 'campaign.criteria')
    except ParamError as err:
        raise CampaignError(str(err)) from err
    campaign = Campaign(name=name, description=description, base=base, runs=runs, seed=seed,
                        vary=vary, grid=grid, criteria=criteria)
    if campaign.total_runs > MAX_RUNS:
        raise CampaignError(f'campaign.runs: {campaign.total_runs} runs in all (runs x grid '
                            f'points) is more than {MAX_RUNS}')
    return campaign


def _base_scenario(data: Mapping, source_dir: pathlib.Path | None) -> dict:
    """Return the full scenario mapping of ``scenario`` with the ``overrides`` applied."""
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
    except ParamError as err:
        raise CampaignError(f'campaign.scenario: {err}') from err

    overrides = data.get('overrides') or {}
    if not isinstance(overrides, Mapping):
        raise CampaignError(f'campaign.overrides: expected a mapping, got {overrides!r}')
    base = _merge(base, overrides, 'campaign.overrides')
    try:
        return scenario_to_mapping(scenario_from_mapping(base))
    except ParamError as err:
        raise CampaignError(f'campaign.overrides: {err}') from err


def _vary(data: Mapping, base: dict) -> dict:
    """Return the ``vary`` section: dotted key -> (distribution, arguments)."""
    vary_data = data.get('vary') or {}
    if not isinstance(vary_data, Mapping):
        raise CampaignError(f'campaign.vary: expected a mapping of scenario keys, got '
                            f'{vary_data!r}')
    vary = {}
    for key, spec in vary_data.items():
        parts = _split_key(key, 'campaign.vary')
        base_value = _get(base, parts, key, 'campaign.vary')
        vary[key] = _parse_distribution(key, spec, base_value)
    return vary


def _grid(data: Mapping, base: dict, vary: Mapping) -> dict:
    """Return the ``grid`` section: dotted key -> values (1 or 2 keys)."""
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
    return grid


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
            except ParamError as err:
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
