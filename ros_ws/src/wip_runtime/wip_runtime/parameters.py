"""ROS parameters declared from config dataclasses: the one way a node declares one.

Every field of a config dataclass (see :mod:`wip_runtime.config`) becomes one ROS
parameter named ``<section>.<field>`` (or ``<field>`` when the section is ``''``, for
the node-level settings) with a descriptor carrying its unit, description and range.
Which node declares which dataclasses is listed in :mod:`wip_control.nodes.settings`
(importable without rclpy, so the parameter reference is generated from it). Values are
validated by the same :func:`~wip_runtime.config.from_mapping` as a scenario file, so a
params file with a typo'd value fails with the same message, and a parameter set at run time
to a bad value is rejected with the reason.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Callable

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from .config import check_value, ParamError, from_mapping


class OutOfRangeError(ParamError, InvalidParameterValueException):
    """An override outside the declared range.

    A ParamError (one line naming the parameter) that is also the exception rclpy raises for it.
    """

    def __init__(self, message: str) -> None:
        ParamError.__init__(self, message)


def _ros_default(value: Any, field_type: Any) -> Any:
    # The default's Python type fixes the ROS parameter type (rclpy ignores the
    # descriptor's type), so a float field with an integer default must become 0.0.
    if field_type is float:
        return float(value)
    if isinstance(value, tuple) and not value:
        # An empty list has no element type (rclpy would make it a byte array): declare
        # by type; an unset parameter then reads as () (see _from_ros).
        element = typing.get_args(field_type)[0]
        return {str: Parameter.Type.STRING_ARRAY, float: Parameter.Type.DOUBLE_ARRAY,
                int: Parameter.Type.INTEGER_ARRAY, bool: Parameter.Type.BOOL_ARRAY}[element]
    if isinstance(value, tuple):
        if all(isinstance(v, bool) for v in value):
            return list(value)
        if all(isinstance(v, str) for v in value):
            return list(value)
        return [float(v) for v in value]
    return value


def _descriptor(name: str, field: dataclasses.Field, field_type: Any,
                read_only: bool) -> ParameterDescriptor:
    meta = field.metadata
    unit = meta.get('unit', '')
    text = meta.get('description', '')
    descriptor = ParameterDescriptor(name=name, description=f'{text} [{unit}]' if unit else text,
                                     read_only=read_only)
    low, high = meta.get('minimum'), meta.get('maximum')
    constraints = []
    if meta.get('choices'):
        constraints.append('one of: ' + ', '.join(map(str, meta['choices'])))
    if low is not None or high is not None:
        constraints.append(f'range [{low}, {high}]' + (' (minimum excluded)'
                                                       if meta.get('exclusive_minimum') else ''))
    descriptor.additional_constraints = '; '.join(constraints)
    finite = (low is not None and high is not None and math.isfinite(low)
              and math.isfinite(high) and not meta.get('exclusive_minimum'))
    if finite and field_type is float:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(low), to_value=float(high), step=0.0)]
    elif finite and field_type is int:
        descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high),
                                                 step=1)]
    return descriptor


class RosParams:
    """Declares a config dataclass as ROS parameters and keeps the built instance current.

    Parameters
    ----------
    node : the node to declare on.
    section : prefix of the parameter names (``'mpc'`` gives ``mpc.max_tilt``); ``''``:
        no prefix (``left_joint``).
    config_cls : the frozen config dataclass.
    on_change : called with the new config instance after a valid run-time change; if
        ``None`` the parameters are read-only.
    defaults : an instance whose values replace the class defaults (a default that
        depends on the node's scenario, e.g. the plant's datum); ``None``: the class's.
    """

    def __init__(self, node: Node, section: str, config_cls: type,
                 on_change: Callable[[Any], None] | None = None,
                 defaults: Any | None = None) -> None:
        self._node = node
        self._section = section
        self._prefix = f'{section}.' if section else ''
        self._cls = config_cls
        self._on_change = on_change
        self._types = typing.get_type_hints(config_cls)
        self._fields = {f.name: f for f in dataclasses.fields(config_cls)}
        values = {}
        for name, field in self._fields.items():
            full = self._prefix + name
            default = field.default if defaults is None else getattr(defaults, name)
            descriptor = _descriptor(full, field, self._types[name], on_change is None)
            try:
                param = node.declare_parameter(full, _ros_default(default, self._types[name]),
                                               descriptor)
            except InvalidParameterValueException:
                # rclpy refused an override outside the descriptor's range: say it in the
                # words of from_mapping (`port: must be <= 65535, got 70000`).
                override = getattr(node, '_parameter_overrides', {}).get(full)
                try:
                    check_value(full, _from_ros(getattr(override, 'value', None)),
                                self._types[name], field.metadata)
                except ParamError as err:
                    raise OutOfRangeError(str(err)) from None
                raise
            values[name] = _from_ros(param.value)
        self.config = self._build(values)
        node.add_on_set_parameters_callback(self._validate_change)

    def _build(self, values: dict[str, Any]) -> Any:
        # Raises ParamError naming the parameter: the node refuses to start on a bad
        # params file rather than running with a silently different value.
        try:
            return from_mapping(self._cls, values, self._section or '@')
        except ParamError as err:
            if self._section:
                raise
            # Top-level names: the message starts with the bare name (`left_wheel_sign: ...`).
            raise ParamError(str(err).removeprefix('@.')) from None

    def _validate_change(self, parameters: list[Parameter]) -> SetParametersResult:
        mine = [p for p in parameters if p.name.startswith(self._prefix)
                and p.name[len(self._prefix):] in self._fields]
        if not mine:
            return SetParametersResult(successful=True)
        if self._on_change is None:
            return SetParametersResult(successful=False,
                                       reason=f'{mine[0].name} is read-only at run time')
        values = {n: getattr(self.config, n) for n in self._fields}
        for p in mine:
            values[p.name[len(self._prefix):]] = _from_ros(p.value)
        try:
            new_config = self._build(values)
        except ParamError as err:
            return SetParametersResult(successful=False, reason=str(err))
        self.config = new_config
        self._on_change(new_config)
        return SetParametersResult(successful=True)


def _from_ros(value: Any) -> Any:
    if value is None:
        return ()  # an array parameter declared by type and never set
    if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
        return tuple(value)
    return value
