"""Checks of what a user gives the nodes of a run, before any process starts.

Params files (``--params-file``) and topic remappings (``--remap``).

A params file is checked against the one declaration of every node parameter (the ``NODES``
registries of :mod:`wip_control.nodes.settings`, :mod:`wip_bag.settings` and
:mod:`wip_viewer.settings`: name, type, unit, range, default), the way the nodes would
read it: an unknown node section or parameter name (with the nearest known name), a value
of the wrong ROS type (ROS reads ``1`` as an integer, which a double parameter refuses),
out of its range, or a section that the node's own checks refuse
(:func:`~wip_runtime.config.from_mapping`). Without these checks a typo was ignored
with a warning in a node's log, and a bad value stopped a node after the others had
started.

Every problem is one line (:class:`ParamsFileError`, a ``ValueError``); the callers turn it
into exit 2 before anything is written or started.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import re
import typing
from typing import Any, Iterable, Mapping, Sequence

from wip_runtime.config import check_value, ParamError, from_mapping
from wip_description.wiring import check_effort_joints, EffortCommand, WheelJoints

from .params_files import flatten, section_applies
from .ride_through_check import RIDE_THROUGH, ride_through_mismatch, Setting

#: Modules holding a ``NODES`` registry (executable -> (prefix, dataclass) groups) of the
#: nodes a run of wip_bringup starts (the plant's, wip_sim's, is simulation only).
REGISTRY_MODULES = ('wip_control.nodes.settings', 'wip_bag.settings', 'wip_viewer.settings')
#: Parameters every ROS node has, whatever it declares.
ROS_BUILTIN = {'use_sim_time': bool, 'start_type_description_service': bool}
#: Parameter name prefixes every ROS node accepts (QoS overrides of its endpoints).
ROS_BUILTIN_PREFIXES = ('qos_overrides.',)
#: A ROS 2 topic name after the remap's own normalisation: absolute, tokens of letters,
#: digits and underscores that do not start with a digit.
TOPIC_NAME = re.compile(r'^(/[A-Za-z_][A-Za-z0-9_]*)+$')


class ParamsFileError(ValueError):
    """One line: what is wrong in a params file or a remap rule."""


def node_registry() -> dict[str, tuple[tuple[str, type], ...]]:
    """Return, per executable (node name), the (prefix, dataclass) groups it declares."""
    merged: dict[str, tuple[tuple[str, type], ...]] = {}
    for module in REGISTRY_MODULES:
        merged.update(importlib.import_module(module).NODES)
    return merged


@dataclasses.dataclass(frozen=True)
class Declared:
    """One declared parameter: its group (prefix, dataclass), field name, type, metadata."""

    prefix: str
    cls: type
    field: str
    type: Any
    metadata: Mapping[str, Any]


def declarations(node: str) -> dict[str, Declared]:
    """Full parameter name -> :class:`Declared`, for the node ``node`` ({} if unknown)."""
    out = {}
    for prefix, cls in node_registry().get(node, ()):
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            name = f'{prefix}.{field.name}' if prefix else field.name
            out[name] = Declared(prefix, cls, field.name, hints[field.name], field.metadata)
    return out


def _names_a_node(key: str, node: str) -> bool:
    """Whether the section ``key`` names ``node`` in some namespace (a known node's section)."""
    last = str(key).strip().rstrip('/').rsplit('/', 1)[-1]
    return last in ('', '*', '**') or last == node


def _nearest(name: str, candidates: Iterable[str]) -> str:
    candidates = sorted(set(candidates))
    close = [c for c in candidates if c.endswith('.' + name)] or \
        difflib.get_close_matches(name, candidates, n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ''


def _ros_typed(name: str, value: Any, field_type: Any) -> None:
    """Check that ROS takes ``value`` for a parameter of the type of ``field_type``.

    ParamError if ROS would refuse ``value`` for a parameter declared with the type of
    ``field_type`` (rclpy: 'Wrong parameter type'): ROS reads ``1`` as an integer.
    """
    origin = typing.get_origin(field_type)
    if origin is tuple:
        element = typing.get_args(field_type)[0]
        if isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                _ros_typed(f'{name}[{i}]', item, element)
        return
    if field_type is float and isinstance(value, int) and not isinstance(value, bool):
        raise ParamError(f'{name}: expected a floating-point number (ROS reads {value} as '
                          f'an integer: write {value}.0), got {value!r}')
    if field_type is int and isinstance(value, float):
        raise ParamError(f'{name}: expected an integer, got {value!r}')


def _check_value(name: str, value: Any, declared: Declared) -> None:
    if isinstance(value, (list, tuple)) and not value and typing.get_origin(
            declared.type) is tuple:
        raise ParamError(f'{name}: an empty list has no type in a ROS params file (leave '
                          'the parameter out for its default)')
    if isinstance(value, Mapping):
        raise ParamError(f'{name}: expected a value, got a mapping {list(value)[:3]}')
    check_value(name, value, declared.type, declared.metadata)
    _ros_typed(name, value, declared.type)


def check_params_files(files: Sequence[tuple[str, Mapping[str, Any]]], nodes: Sequence[str],
                       generated: Mapping[str, Any] | None = None,
                       namespace: str = '') -> list[str]:
    """Check parsed params files for a run of the nodes ``nodes``.

    Check parsed params files (``(path, {section: {'ros__parameters': {...}}})`` each)
    for a run of the nodes ``nodes``; ``generated`` is the run's own params file, which
    comes first on each command line (the sections a node builds from its parameters are
    checked with it), and that the MPC and the mixer get one ride-through
    (:mod:`.ride_through_check`). Raises :class:`ParamsFileError` (one line) on the first
    problem; returns warnings (a section for a known node that this run does not start).
    """
    registry = node_registry()
    warnings: list[str] = []
    running = [n for n in nodes if n in registry]
    for path, data in files:
        where = f'--params-file {path}'
        for key, section in data.items():
            matched = [n for n in running if section_applies(key, n, namespace)]
            if not matched:
                last = str(key).strip().rstrip('/').rsplit('/', 1)[-1]
                if any(_names_a_node(key, n) for n in registry):
                    where_run = f' under /{namespace.strip("/")}' if namespace else ''
                    warnings.append(f'{where}: section {str(key)!r}: no such node in this '
                                    f'run{where_run} (ignored)')
                    continue
                raise ParamsFileError(f'{where}: unknown node section {str(key)!r}'
                                  f'{_nearest(last, running or registry)}; the nodes of '
                                  f'this run: {", ".join(running)}')
            parameters = flatten(section.get('ros__parameters') or {})
            for name, value in parameters.items():
                if name in ROS_BUILTIN or name.startswith(ROS_BUILTIN_PREFIXES):
                    expected = ROS_BUILTIN.get(name)
                    if expected is bool and not isinstance(value, bool):
                        raise ParamsFileError(f'{where}: {name}: expected true or false, got '
                                          f'{value!r}')
                    continue
                declaring = [(n, declarations(n).get(name)) for n in matched]
                declaring = [(n, d) for n, d in declaring if d is not None]
                if not declaring:
                    known = set().union(*(declarations(n) for n in matched))
                    whom = (f'node {matched[0]}' if len(matched) == 1 else
                            f'any node of section {str(key)!r}')
                    raise ParamsFileError(f'{where}: unknown parameter {name!r} for {whom}'
                                      f'{_nearest(name, known)}')
                for node, declared in declaring:
                    try:
                        _check_value(name, value, declared)
                    except ParamError as err:
                        raise ParamsFileError(f'{where}: node {node}: {err}') from None
    _check_groups(files, running, generated or {}, namespace)
    return warnings


#: Where a value of the run's own params file comes from, in messages.
GENERATED = "the run's own params file"


def _merged(files: Sequence[tuple[str, Mapping[str, Any]]], node: str,
            generated: Mapping[str, Any], namespace: str
            ) -> tuple[dict[str, Any], dict[str, str]]:
    """Return the parameters ``node`` gets, flattened, and where each one comes from.

    The generated file's, then each file's matching sections in order (later wins).
    """
    merged = flatten(generated.get(node, {}).get('ros__parameters', {}))
    sources = dict.fromkeys(merged, GENERATED)
    for path, data in files:
        for key, section in data.items():
            if section_applies(key, node, namespace):
                flat = flatten(section.get('ros__parameters') or {})
                merged.update(flat)
                sources.update(dict.fromkeys(flat, f'{path}, section {str(key)!r}'))
    return merged, sources


def _check_groups(files: Sequence[tuple[str, Mapping[str, Any]]], nodes: Sequence[str],
                  generated: Mapping[str, Any], namespace: str) -> None:
    """Check each node's groups as the node builds them.

    Each node's groups built from its merged parameters (generated file, then each
    file's matching sections in order) as the node builds them: the checks across fields
    of a group (a dataclass's ``validate``).
    """
    ride_through: dict[str, dict[str, Setting]] = {}
    for node in nodes:
        merged, sources = _merged(files, node, generated, namespace)
        given = {name for name, source in sources.items() if source != GENERATED}
        declared = declarations(node)
        if all(name in declared for name in RIDE_THROUGH):
            ride_through[node] = {
                name: Setting(merged[name], sources[name]) if name in merged else
                Setting(_default(declared[name]), 'default') for name in RIDE_THROUGH}
        groups: dict[tuple[str, type], dict[str, Any]] = {}
        for name, value in merged.items():
            entry = declared.get(name)
            if entry is not None:
                groups.setdefault((entry.prefix, entry.cls), {})[entry.field] = (
                    tuple(value) if isinstance(value, list) else value)
        if 'joints' in given or 'left_joint' in given or 'right_joint' in given:
            names = {d.cls for d in declared.values()}
            if EffortCommand in names and WheelJoints in names:
                left = merged.get('left_joint', WheelJoints.left_joint)
                right = merged.get('right_joint', WheelJoints.right_joint)
                try:
                    check_effort_joints(left, right, tuple(merged.get('joints',
                                                                      (left, right))))
                except ParamError as err:
                    raise ParamsFileError(f'--params-file: node {node}: {err}') from None
        for (prefix, cls), values in groups.items():
            if not any((f'{prefix}.{f}' if prefix else f) in given for f in values):
                continue   # the generated values alone: checked where they come from
            try:
                from_mapping(cls, values, prefix or '@')
            except ParamError as err:
                raise ParamsFileError(f'--params-file: node {node}: '
                                  f'{str(err).removeprefix("@.")}') from None
    mismatch = ride_through_mismatch(ride_through)
    if mismatch:
        raise ParamsFileError(f'--params-file: {mismatch}')


def _default(declared: Declared) -> Any:
    return {f.name: f.default for f in dataclasses.fields(declared.cls)}[declared.field]


def check_remap(text: str) -> tuple[str, str]:
    """Parse a ``--remap`` rule ``'FROM:=TO'`` into absolute topic names.

    ``'FROM:=TO'`` -> (FROM, TO) as absolute topic names; :class:`ParamsFileError` on a bad
    rule (not FROM:=TO, or a side that is not a valid ROS topic name).
    """
    source, sep, target = text.partition(':=')
    source, target = source.strip(), target.strip()
    if not sep or not source or not target or ':=' in target:
        raise ParamsFileError(f'--remap: expected FROM:=TO (e.g. /joint_states:=/base/'
                          f'joint_states), got {text!r}')
    names = []
    for side in (source, target):
        name = '/' + side.lstrip('/')
        if not TOPIC_NAME.match(name):
            raise ParamsFileError(f'--remap {text!r}: {side!r} is not a valid ROS topic name '
                              '(letters, digits and underscores in /-separated tokens, '
                              'none starting with a digit)')
        names.append(name)
    return names[0], names[1]


def unmatched_remaps(remaps: Iterable[tuple[str, str]], topics: Iterable[str]) -> list[str]:
    """Return a warning for each rule whose FROM is none of ``topics``.

    It would change nothing.
    """
    topics = set(topics)
    return [f"--remap {source}:={target}: no topic {source} in this run's graph (the rule "
            f'changes nothing){_nearest(source, topics)}'
            for source, target in remaps if source not in topics]


#: Topics of the nodes of a run besides those its caller names (the base's, the
#: controllers'): their other inputs and the viewer's outputs.
OTHER_TOPICS = ('/clock', '/cmd_vel', '/plan', '/odom', '/wip/estop_reset',
                '/wip/ground_truth', '/rosout', '/parameter_events')


def check_run_inputs(paths: Sequence[str], files: Sequence[Mapping[str, Any]],
                     nodes: Sequence[str], generated: Mapping[str, Any],
                     remaps: Sequence[tuple[str, str]], topics: Iterable[str] = (),
                     namespace: str = '') -> list[str]:
    """Check the params files and remappings of a run.

    :func:`check_params_files` of the parsed ``files`` (given as ``paths``) and the
    :func:`unmatched_remaps` warnings against ``topics`` (with :data:`OTHER_TOPICS`, the
    viewer's and the effort topics the files set), for run_graph's hardware mode and
    check_base; GraphError (exit 2) with the one-line problem. Returns the warnings.
    """
    from wip_viewer.viewer_core import VIEWER_TOPICS
    from .launcher import EXIT_USAGE, GraphError
    try:
        warnings = check_params_files(list(zip(paths, files)), nodes, generated, namespace)
    except ParamsFileError as err:
        raise GraphError(str(err), EXIT_USAGE) from None
    effort = {str(flatten(section.get('ros__parameters') or {}).get('effort_topic', ''))
              for data in files for section in data.values()} - {''}
    topics = (set(topics) | set(OTHER_TOPICS) | set(VIEWER_TOPICS)
              | {'/' + topic.lstrip('/') for topic in effort})
    return warnings + unmatched_remaps(remaps, topics)
