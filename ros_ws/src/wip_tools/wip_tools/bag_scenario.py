"""The scenario of a bag: one lookup rule for every tool that reads bags (report, rerun).

A bag's own scenario is, in this order:

1. the YAML in its ``metadata.yaml`` ``custom_data['wip.scenario']`` (written by the
   recorder's ``scenario_file`` parameter and by ``scripts/rerun``'s bags);
2. ``scenario.yaml`` in the bag directory (``scripts/run_graph --record`` copies the run's
   scenario there).

The bag is its directory or any file in it (``BAG/bag_0.mcap`` finds the same scenario as
``BAG``). Nothing outside the bag directory is looked at: a file beside it may belong to
another run.

``--scenario FILE`` is applied **over** the bag's own scenario: a partial file (say, only
``mpc: {input_weight: 0.5}``) changes those keys and keeps every other value of the run
that was recorded (its reference, limits, rates, datum). Without a scenario of its own the
bag is read with the defaults (the paper's Section V), and the source says so.
"""

from __future__ import annotations

import pathlib
from typing import Any, Mapping

from wip_bag.bag_reader import read_metadata_file
from wip_runtime.config import ParamError, load_yaml_text
from wip_control.core.controller_settings import read_scenario_file
from wip_sim.core.scenario import Scenario, scenario_from_mapping

SCENARIO_KEY = 'wip.scenario'          # custom_data key of the scenario YAML in a bag
SCENARIO_FILE_NAME = 'scenario.yaml'   # beside the bag's files, in its directory


def bag_directory(bag: str | pathlib.Path) -> pathlib.Path:
    """Return the bag directory of a bag given as its directory or as a file in it."""
    path = pathlib.Path(bag)
    return path if path.is_dir() else path.parent


def own_scenario(bag: str | pathlib.Path) -> tuple[dict[str, Any] | None, str]:
    """Return (the bag's own scenario as a mapping, or None; where it came from)."""
    directory = bag_directory(bag)
    metadata = directory / 'metadata.yaml'
    if metadata.is_file():
        try:
            info = read_metadata_file(metadata)
        except Exception:  # noqa: BLE001 - a broken metadata.yaml: the next source
            info = {}
        custom = info.get('custom_data') if isinstance(info, dict) else None
        text = custom.get(SCENARIO_KEY) if isinstance(custom, dict) else None
        if isinstance(text, str) and text:
            where = f'{metadata} (custom_data)'
            return _mapping(load_yaml_text(text, where), where), where
    candidate = directory / SCENARIO_FILE_NAME
    if candidate.is_file():
        data = read_scenario_file(candidate)
        if data is None:
            # Never the default scenario in its place: an empty file is a run cut short
            # (a full disk), and the defaults would give metrics of another scenario.
            raise ParamError(f'{candidate}: empty scenario file (cut short when it was '
                              'written?); remove it and give the scenario with --scenario')
        return _mapping(data, str(candidate)), str(candidate)
    return None, 'none in the bag'


def scenario_for_bag(bag: str | pathlib.Path,
                     override: str | pathlib.Path | None = None) -> tuple[Scenario, str]:
    """(Scenario, where it came from): the bag's own, with ``override`` applied over it.

    Raises ParamError (naming the file and the key) on an unreadable or invalid scenario.
    """
    base, where = own_scenario(bag)
    if base is None:
        where = "defaults (the paper's Section V): no scenario in the bag"
        base = {}
    if override is not None:
        path = pathlib.Path(override)
        base = merged(base, _mapping(read_scenario_file(path), str(path)))
        where = f'{path} over {where}'
    try:
        return scenario_from_mapping(base), where
    except ParamError as err:
        raise ParamError(f'{where}: {err}') from err


def merged(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` over ``base``, section by section (lists and values are replaced)."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merged(out[key], value)
        else:
            out[key] = value
    return out


def _mapping(data: Any, where: str) -> dict[str, Any]:
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ParamError(f'{where}: a scenario is a mapping of sections, got '
                          f'{type(data).__name__}')
    return dict(data)
