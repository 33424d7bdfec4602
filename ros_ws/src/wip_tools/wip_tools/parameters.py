"""The parameter reference: every node parameter and every scenario key.

With unit, range, default and description, generated from the declarations (nothing is written
twice).

Node parameters come from the registries ``NODES`` of :mod:`wip_control.nodes.settings`,
:mod:`wip_sim.settings`, :mod:`wip_bag.settings` and :mod:`wip_viewer.settings`
(executable -> the config dataclasses it declares, with their prefix); scenario keys from
:class:`~wip_sim.core.scenario.Scenario`. ``--markdown`` prints docs/parameters.md.

    ros2 run wip_tools parameters [--markdown] [--node NAME]
    scripts/simulate --list-parameters
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import sys
import typing
from typing import Any, NamedTuple

from wip_sim.core.scenario import Scenario, TOP_LEVEL_RANGES, TOP_LEVEL_SCALARS
from wip_runtime.cli import add_exit_codes, EXIT_USAGE, exit_with

#: Modules holding a ``NODES`` registry, one per package with nodes.
REGISTRY_MODULES = ('wip_control.nodes.settings', 'wip_sim.settings', 'wip_bag.settings',
                    'wip_viewer.settings')
#: Header of the generated docs/parameters.md.
MARKDOWN_TITLE = '# Parameter reference'


class Row(NamedTuple):
    """One parameter: dotted name, unit, default, admissible values, description."""

    name: str
    unit: str
    default: str
    range: str
    description: str


def node_registry() -> dict[str, tuple[tuple[str, type], ...]]:
    """Return executable -> ``(prefix, dataclass)`` groups, over every package's registry."""
    return {executable: groups for executable, (_, groups) in _registry().items()}


def node_package(executable: str) -> str:
    """Return the ROS package whose executable ``executable`` is."""
    return _registry()[executable][0]


def _registry() -> dict[str, tuple[str, tuple[tuple[str, type], ...]]]:
    merged: dict[str, tuple[str, tuple[tuple[str, type], ...]]] = {}
    for module_name in REGISTRY_MODULES:
        for executable, groups in importlib.import_module(module_name).NODES.items():
            if executable in merged:
                raise ValueError(f'{module_name}: executable {executable!r} registered twice')
            merged[executable] = (module_name.split('.')[0], groups)
    return merged


def _number(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f'{value:g}' if math.isfinite(value) else str(value)
    return str(value)


def _component(value: Any) -> str:
    """Return a disturbance component (a small dataclass) as ``kind(field=value, ...)``.

    Only the fields that differ from their defaults, as one would write them in the YAML
    file.
    """
    fields = [f for f in dataclasses.fields(value)
              if f.name != 'kind' and getattr(value, f.name) != f.default]
    inner = ', '.join(f'{f.name}={_value(getattr(value, f.name))}' for f in fields)
    return f'{getattr(value, "kind", type(value).__name__)}({inner})'


def _value(value: Any) -> str:
    if dataclasses.is_dataclass(value):
        return _component(value)
    if isinstance(value, tuple):
        return '[' + ', '.join(_value(v) for v in value) + ']'
    if isinstance(value, str):
        return repr(value) if value == '' else value
    return _number(value)


def _range(field_type: Any, meta: dict) -> str:
    if meta.get('choices'):
        return 'one of: ' + ', '.join(_number(c) for c in meta['choices'])
    element = field_type
    if typing.get_origin(field_type) is tuple:
        element = typing.get_args(field_type)[0]
    if element is bool:
        return 'true, false'
    if element is str:
        return 'any'
    low, high = meta.get('minimum'), meta.get('maximum')
    if low is None and high is None:
        return 'any'
    left = '(' if meta.get('exclusive_minimum') else '['
    text = f'{left}{_number(low) if low is not None else "-inf"}, ' \
           f'{_number(high) if high is not None else "inf"}]'
    if typing.get_origin(field_type) is tuple:
        text += ' each'
    return text


def config_rows(cls: type, prefix: str) -> list[Row]:
    """Rows of the fields of config dataclass ``cls``, named ``prefix + field``.

    A nested dataclass section is listed field by field; one with a field of the section's
    own name is read flat from its parent's mapping (PlantParams: ``plant.model``,
    ``plant.wheel_friction``), so its keys are listed there.
    A tuple of small dataclasses (disturbance components) is listed once with its
    default, then the keys of one element as ``name[i].key``.
    """
    rows = []
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        field_type = hints[field.name]
        name = f'{prefix}{field.name}'
        if dataclasses.is_dataclass(field_type):
            inner = dataclasses.fields(field_type)
            if any(f.name == field.name for f in inner):
                rows += config_rows(field_type, prefix)
            else:
                rows += config_rows(field_type, name + '.')
            continue
        meta = dict(field.metadata)
        default = (field.default if field.default is not dataclasses.MISSING
                   else field.default_factory())
        args = typing.get_args(field_type)
        if args and dataclasses.is_dataclass(args[0]):
            rows.append(Row(name, meta.get('unit', ''), _value(default),
                            f'list of {args[0].__name__}', meta.get('description', '')))
            continue
        unit = meta.get('unit', '')
        if not unit and _range(field_type, meta) == 'any':
            unit = '-'  # a string: a name or a path
        rows.append(Row(name, unit, _value(default), _range(field_type, meta),
                        meta.get('description', '')))
    return rows


def node_rows(executable: str) -> list[Row]:
    """Every parameter ``executable`` declares (see :func:`node_registry`)."""
    rows = []
    for prefix, cls in node_registry()[executable]:
        rows += config_rows(cls, f'{prefix}.' if prefix else '')
    return rows


def scenario_rows() -> list[Row]:
    """Every key of a scenario file."""
    rows = []
    hints = typing.get_type_hints(Scenario)
    for field in dataclasses.fields(Scenario):
        field_type = hints[field.name]
        if dataclasses.is_dataclass(field_type):
            if field_type.__name__ == 'DisturbanceParams':
                from wip_sim.core.disturbances import DisturbanceComponent
                rows += config_rows(field_type, f'{field.name}.')
                rows += config_rows(DisturbanceComponent, f'{field.name}.<channel>[i].')
            else:
                rows += config_rows(field_type, f'{field.name}.')
            continue
        unit, span = TOP_LEVEL_RANGES[field.name]
        rows.append(Row(field.name, unit, _value(field.default), span,
                        TOP_LEVEL_SCALARS[field.name][1]))
    return rows


def _text_table(rows: list[Row]) -> str:
    width = max(len(r.name) for r in rows)
    unit = max(len(r.unit) for r in rows)
    default = min(max(len(r.default) for r in rows), 24)
    span = min(max(len(r.range) for r in rows), 28)
    return '\n'.join(f'  {r.name:<{width}}  {r.unit:<{unit}}  {r.default:<{default}}  '
                     f'{r.range:<{span}}  {r.description}' for r in rows)


def parameter_table(nodes: list[str] | None = None, scenario: bool = True) -> str:
    """Plain-text reference: node by node, then the scenario keys."""
    registry = node_registry()
    parts = []
    for executable in (sorted(registry) if nodes is None else nodes):
        parts.append(f'node {executable} (ros2 run {node_package(executable)} {executable}):\n'
                     + _text_table(node_rows(executable)))
    if scenario:
        parts.append('scenario file keys (scripts/simulate --scenario, plant scenario_file):\n'
                     + _text_table(scenario_rows()))
    return '\n\n'.join(parts) + '\n'


def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def _markdown_table(rows: list[Row]) -> list[str]:
    lines = ['| name | unit | default | range | description |',
             '|---|---|---|---|---|']
    lines += [f'| `{r.name}` | {_cell(r.unit)} | `{_cell(r.default)}` | {_cell(r.range)} | '
              f'{_cell(r.description)} |' for r in rows]
    return lines


def markdown() -> str:
    """docs/parameters.md."""
    registry = node_registry()
    lines = [MARKDOWN_TITLE, '',
             'Generated by `ros2 run wip_tools parameters --markdown > docs/parameters.md` '
             'from the declarations (the `NODES` registries of wip_control.nodes.settings, '
             'wip_sim.settings, wip_bag.settings, wip_viewer.settings and the scenario '
             'dataclasses); a test checks that this file equals the generated text. Unit `-`: '
             'a string; `1`: dimensionless. A node refuses to start on a value outside the '
             'range, naming the parameter. `ros2 run wip_control controllers` runs the six '
             'controller nodes in one process, each with its own parameters below.', '',
             '## Nodes', '']
    for executable in sorted(registry):
        lines += [f'### {executable}', '', f'`ros2 run {node_package(executable)} {executable}`',
                  '']
        for prefix, cls in registry[executable]:
            summary = (cls.__doc__ or '').strip().splitlines()[0] if cls.__doc__ else ''
            where = f'`{prefix}.*`' if prefix else 'top level'
            lines += [f'{cls.__name__} ({where}): {summary}', '']
            lines += _markdown_table(config_rows(cls, f'{prefix}.' if prefix else ''))
            lines.append('')
    lines += ['## Scenario file keys', '',
              'Every key is optional; `<channel>` is yaw, longitudinal or tilt.', '']
    lines += _markdown_table(scenario_rows())
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='parameters', description='Print every node parameter and scenario key with '
        'unit, default, range and description.')
    parser.add_argument('--markdown', action='store_true',
                        help='print docs/parameters.md (Markdown tables)')
    parser.add_argument('--node', action='append', metavar='NAME',
                        help='only this node (executable name; repeatable); no scenario keys')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown())
        return 0
    registry = node_registry()
    for name in args.node or []:
        if name not in registry:
            print(f'parameters: error: unknown node {name!r}; expected one of '
                  f'{sorted(registry)}', file=sys.stderr)
            return EXIT_USAGE
    sys.stdout.write(parameter_table(args.node, scenario=not args.node))
    return 0


if __name__ == '__main__':
    exit_with(main, 'parameters')
