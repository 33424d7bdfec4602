"""Declarative parameters: one place for every parameter's name, unit, default and range.

Each component of the core declares a frozen dataclass whose fields are made with
:func:`param`. The same declaration serves three readers:

- the scenario loader (:mod:`wip_control.core.scenario`), which builds the dataclass
  from a YAML mapping and names the offending key on a typo or an out-of-range value;
- the ROS node wrappers, which declare one ROS parameter per field with the unit and
  range in its descriptor;
- the documentation (``scripts/simulate --list-parameters``).

Example
-------
>>> @dataclasses.dataclass(frozen=True)
... class ArcConfig:
...     yaw_gain: float = param(20.0, '1/s', 'k_ω of eq. (12)', minimum=0.0)
>>> from_mapping(ArcConfig, {'yaw_gain': 10.0}, 'arc').yaw_gain
10.0
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Mapping


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range.

    The message always starts with the dotted path of the offending key.
    """


def param(default: Any, unit: str, description: str, *, minimum: float | None = None,
          maximum: float | None = None, choices: tuple | None = None,
          exclusive_minimum: bool = False) -> Any:
    """A dataclass field with its unit, description and admissible range.

    Parameters
    ----------
    default : value used when the key is absent. Tuples for vector values.
    unit : SI unit, e.g. ``'N m'``, ``'rad/s'``, or ``'1'`` for dimensionless.
    description : what the parameter does, citing the paper's equation if any.
    minimum, maximum : inclusive bounds for numbers (per element for tuples).
    exclusive_minimum : if true the minimum itself is not admissible (``> minimum``).
    choices : admissible values for strings.
    """
    metadata = {'unit': unit, 'description': description, 'minimum': minimum,
                'maximum': maximum, 'choices': choices,
                'exclusive_minimum': exclusive_minimum}
    if isinstance(default, (list, dict)):
        raise TypeError('use a tuple for vector defaults (dataclass fields are shared)')
    return dataclasses.field(default=default, metadata=metadata)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _check_number(path: str, value: Any, meta: Mapping[str, Any], want_int: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'{path}: expected a number, got {value!r}')
    if want_int and not float(value).is_integer():
        raise ConfigError(f'{path}: expected an integer, got {value!r}')
    if not math.isfinite(value):
        raise ConfigError(f'{path}: must be finite, got {value!r}')
    lo, hi = meta.get('minimum'), meta.get('maximum')
    if lo is not None:
        if meta.get('exclusive_minimum') and not value > lo:
            raise ConfigError(f'{path}: must be > {lo}, got {value!r}')
        if value < lo:
            raise ConfigError(f'{path}: must be >= {lo}, got {value!r}')
    if hi is not None and value > hi:
        raise ConfigError(f'{path}: must be <= {hi}, got {value!r}')
    return int(value) if want_int else float(value)


def check_value(path: str, value: Any, field_type: Any, meta: Mapping[str, Any]) -> Any:
    """Validate and normalise one value against its declared type and metadata."""
    origin = typing.get_origin(field_type)
    if field_type is float:
        return _check_number(path, value, meta, want_int=False)
    if field_type is int:
        return _check_number(path, value, meta, want_int=True)
    if field_type is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'{path}: expected true or false, got {value!r}')
        return value
    if field_type is str:
        if not isinstance(value, str):
            raise ConfigError(f'{path}: expected a string, got {value!r}')
        choices = meta.get('choices')
        if choices and value not in choices:
            raise ConfigError(f'{path}: {value!r} is not one of {list(choices)}')
        return value
    if origin is tuple:
        args = typing.get_args(field_type)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f'{path}: expected a list, got {value!r}')
        if len(args) == 2 and args[1] is Ellipsis:
            element_types = [args[0]] * len(value)
        else:
            element_types = list(args)
            if len(value) != len(element_types):
                raise ConfigError(f'{path}: expected {len(element_types)} values, '
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
        raise ConfigError(f'{path}: expected a mapping, got {mapping!r}')
    types = _field_types(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        key = unknown[0]
        raise ConfigError(f'{path}.{key}: unknown key; expected one of {sorted(fields)}')
    values = {}
    for name, value in mapping.items():
        values[name] = check_value(f'{path}.{name}', value, types[name],
                                   fields[name].metadata)
    instance = cls(**values)
    validate = getattr(instance, 'validate', None)
    if callable(validate):
        try:
            validate()
        except ConfigError as err:
            raise ConfigError(f'{path}.{err}') from err
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
