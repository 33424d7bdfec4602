"""Declarative parameters: one place for every parameter's name, unit, default and range.

Each component of the core declares a frozen dataclass whose fields are made with
:func:`param`. The same declaration serves three readers:

- the scenario loaders (:mod:`wip_control.core.controller_settings`,
  ``wip_sim.core.scenario``), which build the dataclass from a YAML mapping and name the
  offending key on a typo or an out-of-range value;
- the ROS node wrappers, which declare one ROS parameter per field with the unit and
  range in its descriptor;
- the documentation (``scripts/simulate --list-parameters``).

Example
-------
>>> @dataclasses.dataclass(frozen=True)
... class ArcParams:
...     yaw_gain: float = param(20.0, '1/s', 'k_ω of eq. (12)', minimum=0.0)
>>> from_mapping(ArcParams, {'yaw_gain': 10.0}, 'arc').yaw_gain
10.0
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from typing import Any, Mapping

import yaml


class ParamError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range.

    The message always starts with the dotted path of the offending key.
    """


#: Generic physical limits by unit, used where a declaration gives no bound of its own:
#: unit -> (largest magnitude, smallest admissible value of a quantity that must be > 0).
#: They are deliberately wide (a 10 t vehicle, a 10 km path, 100 m/s) and only there to
#: refuse the absurd (``body_mass: 1e300``, ``eso.epsilon: 1e-300``) before anything runs,
#: so the QP size, the memory and the run time stay sane. A parameter whose unit is not
#: listed gets ``GENERIC_LIMIT``.
UNIT_LIMITS: dict[str, tuple[float, float]] = {
    'm': (1e4, 1e-6), 'kg': (1e4, 1e-6), 'kg m^2': (1e4, 1e-9), 's': (1e5, 1e-4),
    'Hz': (1e5, 1e-3), 'rad': (100.0, 1e-9), 'deg': (360.0, 1e-9), 'm/s': (100.0, 1e-6),
    'rad/s': (100.0, 1e-6), 'm/s^2': (1e3, 1e-6), 'rad/s^2': (1e3, 1e-6),
    'N m': (1e4, 1e-6), 'N m/s': (1e7, 1e-6), 'N m s/rad': (1e6, 1e-9),
    'counts/rev': (1e9, 1.0), '1': (1e9, 1e-12),
    'rad/s^2 (yaw, tilt) or m/s^2 (longitudinal)': (1e3, 1e-6),
}
GENERIC_LIMIT = (1e9, 1e-12)
#: Most elements a variable-length list may have (waypoints, disturbance components).
MAX_LIST_LENGTH = 10000


def param(default: Any, unit: str, description: str, *, minimum: float | None = None,
          maximum: float | None = None, choices: tuple | None = None,
          exclusive_minimum: bool = False, max_length: int | None = None) -> Any:
    """Return a dataclass field with its unit, description and admissible range.

    Parameters
    ----------
    default : value used when the key is absent. Tuples for vector values.
    unit : SI unit, e.g. ``'N m'``, ``'rad/s'``, or ``'1'`` for dimensionless.
    description : what the parameter does, citing the paper's equation if any.
    minimum, maximum : inclusive bounds for numbers (per element for tuples). A numeric
        parameter always has both: when one is not given, the generic limit of its unit
        (:data:`UNIT_LIMITS`) is used, so every number has an upper bound.
    exclusive_minimum : if true the minimum itself is not admissible (``> minimum``); a
        value must then also be at least the unit's smallest positive value (``floor``).
    choices : admissible values (strings, or numbers such as a wheel sign ±1).
    max_length : most elements of a variable-length tuple (default ``MAX_LIST_LENGTH``).
    """
    if isinstance(default, (list, dict)):
        raise TypeError('use a tuple for vector defaults (dataclass fields are shared)')
    numeric = (_is_number(default) and not choices) or (
        isinstance(default, tuple) and all(_is_number(v) for v in default)
        and not (default == () and maximum is None and minimum is None))
    floor = None
    if numeric:
        largest, smallest = UNIT_LIMITS.get(unit, GENERIC_LIMIT)
        if maximum is None:
            maximum = largest
        if minimum is None:
            minimum = -largest
        if exclusive_minimum:
            floor = minimum + smallest
    metadata = {'unit': unit, 'description': description, 'minimum': minimum,
                'maximum': maximum, 'choices': choices,
                'exclusive_minimum': exclusive_minimum, 'floor': floor,
                'max_length': MAX_LIST_LENGTH if max_length is None else max_length}
    return dataclasses.field(default=default, metadata=metadata)


#: Unit of a string parameter (a name, a path): its range is 'any' unless it has choices.
TEXT = '-'


def like(cls: type, name: str, default: Any = None, description: str | None = None) -> Any:
    """Return a field with the unit and range of ``cls.name`` (one declaration of a range)."""
    field = {f.name: f for f in dataclasses.fields(cls)}[name]
    metadata = dict(field.metadata)
    if description is not None:
        metadata['description'] = description
    return dataclasses.field(default=field.default if default is None else default,
                             metadata=metadata)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _show(value: Any, limit: int = 60) -> str:
    """repr() for an error message, shortened (a 5000-digit int cannot even be printed)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        return f'an integer of about {int(value.bit_length() * 0.30103) + 1} digits'
    try:
        text = repr(value)
    except ValueError:
        text = f'a {type(value).__name__}'
    return text if len(text) <= limit else text[:limit - 3] + '...'


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


#: Largest magnitude accepted for a float (an int beyond has no float or no use).
_LARGEST_FLOAT_INPUT = 1e300


def check_number(path: str, value: Any, meta: Mapping[str, Any], want_int: bool) -> float:
    """Return ``value`` as an int (``want_int``) or a float; ParamError naming ``path`` else.

    The one check of a number in the project: a scenario key, a node parameter, a params
    file, a command-line option (:func:`.cli.bounded`) and the robot's parameters. ``meta``
    is a :func:`param` field's metadata (``minimum``, ``maximum``, ``exclusive_minimum``,
    ``floor``; each optional). A bool is not a number, nor is a non-finite float.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamError(f'{path}: expected a number, got {_show(value)}')
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ParamError(f'{path}: must be finite, got {_show(value)}')
        if want_int and not value.is_integer():
            raise ParamError(f'{path}: expected an integer, got {_show(value)}')
    # An int is compared exactly (a 5000-digit seed must not overflow float()).
    lo, hi = meta.get('minimum'), meta.get('maximum')
    if lo is not None:
        if meta.get('exclusive_minimum') and not value > lo:
            raise ParamError(f'{path}: must be > {lo}, got {_show(value)}')
        if value < lo:
            raise ParamError(f'{path}: must be >= {lo}, got {_show(value)}')
    floor = meta.get('floor')
    if floor is not None and value < floor:
        raise ParamError(f'{path}: must be >= {floor:g} (a smaller value is not physically '
                          f'meaningful), got {_show(value)}')
    if hi is not None and value > hi:
        raise ParamError(f'{path}: must be <= {hi}, got {_show(value)}')
    if not want_int and abs(value) > _LARGEST_FLOAT_INPUT:
        # An int this large has no float (OverflowError) or none any quantity needs.
        raise ParamError(f'{path}: out of range, got {_show(value)}')
    return int(value) if want_int else float(value)


def check_value(path: str, value: Any, field_type: Any, meta: Mapping[str, Any]) -> Any:
    """Validate and normalise one value against its declared type and metadata."""
    origin = typing.get_origin(field_type)
    if field_type is float or field_type is int:
        number = check_number(path, value, meta, want_int=field_type is int)
        choices = meta.get('choices')
        if choices and number not in choices:
            raise ParamError(f"{path}: must be {' or '.join(map(str, choices))}, "
                              f'got {_show(value)}')
        return number
    if field_type is bool:
        if not isinstance(value, bool):
            raise ParamError(f'{path}: expected true or false, got {_show(value)}')
        return value
    if field_type is str:
        if not isinstance(value, str):
            raise ParamError(f'{path}: expected a string, got {_show(value)}')
        choices = meta.get('choices')
        if choices and value not in choices:
            raise ParamError(f'{path}: {_show(value)} is not one of {list(choices)}')
        return value
    if origin is tuple:
        args = typing.get_args(field_type)
        if not isinstance(value, (list, tuple)):
            raise ParamError(f'{path}: expected a list, got {_show(value)}')
        if len(args) == 2 and args[1] is Ellipsis:
            longest = meta.get('max_length') or MAX_LIST_LENGTH
            if len(value) > longest:
                raise ParamError(f'{path}: at most {longest} values, got {len(value)}')
            element_types = [args[0]] * len(value)
        else:
            element_types = list(args)
            if len(value) != len(element_types):
                raise ParamError(f'{path}: expected {len(element_types)} values, '
                                  f'got {len(value)}')
        return tuple(check_value(f'{path}[{i}]', v, t, meta)
                     for i, (v, t) in enumerate(zip(value, element_types)))
    if dataclasses.is_dataclass(field_type):
        if isinstance(value, field_type):
            return value
        return from_mapping(field_type, value, path)
    if origin is typing.Union:  # Optional[...]
        args = [a for a in typing.get_args(field_type) if a is not type(None)]
        if value is None:
            return None
        return check_value(path, value, args[0], meta)
    raise TypeError(f'{path}: unsupported field type {field_type!r}')


def from_mapping(cls: type, mapping: Mapping[str, Any] | None, path: str) -> Any:
    """Build config dataclass ``cls`` from a mapping, rejecting unknown keys.

    ``path`` is the dotted location of ``mapping`` in the scenario file, used in errors.
    """
    if mapping is None:
        mapping = {}
    if not isinstance(mapping, Mapping):
        raise ParamError(f'{path}: expected a mapping, got {mapping!r}')
    types = _field_types(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        key = unknown[0]
        raise ParamError(f'{path}.{key}: unknown key; expected one of {sorted(fields)}')
    values = {}
    for name, value in mapping.items():
        values[name] = check_value(f'{path}.{name}', value, types[name],
                                   fields[name].metadata)
    instance = cls(**values)
    validate = getattr(instance, 'validate', None)
    if callable(validate):
        try:
            validate()
        except ParamError as err:
            raise ParamError(f'{path}.{err}') from err
    return instance


def to_mapping(instance: Any) -> dict[str, Any]:
    """Plain dict (lists for tuples, nested dicts) of a config dataclass."""
    out = {}
    for f in dataclasses.fields(instance):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            value = to_mapping(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def describe(cls: type) -> list[dict[str, Any]]:
    """One row per field: name, type, default, unit, description, range."""
    types = _field_types(cls)
    rows = []
    for f in dataclasses.fields(cls):
        rows.append({'name': f.name, 'type': types[f.name], 'default': f.default,
                     **{k: f.metadata.get(k) for k in
                        ('unit', 'description', 'minimum', 'maximum', 'choices')}})
    return rows


# -- strict YAML --------------------------------------------------------------------------

class _StrictLoader(yaml.SafeLoader):
    """SafeLoader with two fixes for configuration files.

    - A duplicate key is an error (PyYAML keeps the last one silently).
    - ``1e12`` is a float, as in YAML 1.2 (PyYAML's YAML 1.1 resolver wants a dot,
      ``1.0e12``, and reads ``1e12`` as the string '1e12').
    """


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode,
                       deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            hash(key)
        except TypeError:
            raise yaml.constructor.ConstructorError(
                'while constructing a mapping', node.start_mark,
                'found an unhashable key', key_node.start_mark) from None
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f'duplicate key {key!r} on line {key_node.start_mark.line + 1} '
                f'(first on line {seen[key]}; YAML would silently keep the last)', None)
        seen[key] = key_node.start_mark.line + 1
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                              _construct_mapping)
_StrictLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r'^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$'),
    list('-+0123456789'))


def load_yaml_text(data: bytes | str, source: str) -> Any:
    """Parse a configuration file's content strictly; any problem is one ParamError.

    ``source`` names the file in the message. Refused: bytes that are not UTF-8, invalid
    YAML, duplicate keys, and numbers Python cannot even convert (a 5000-digit integer).
    """
    if isinstance(data, bytes):
        try:
            data = data.decode('utf-8')
        except UnicodeDecodeError as err:
            raise ParamError(f'{source}: not a UTF-8 text file (byte {err.start}: '
                              f'{data[err.start:err.start + 1]!r})') from None
    try:
        return yaml.load(data, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as err:
        text = ' '.join(str(err).split())
        raise ParamError(f'{source}: not valid YAML: {text}') from None
    except (ValueError, OverflowError, RecursionError) as err:
        # int('9' * 5000) is a ValueError since Python 3.11; deep nesting a RecursionError.
        if 'digits' in str(err):
            raise ParamError(f'{source}: a number has more than 4300 digits') from None
        raise ParamError(f'{source}: a value cannot be read: {str(err)[:120]}') from None
