"""The ROS params file of one graph run, made from a scenario (one source of truth).

:func:`graph_parameters` maps the controller settings of a scenario
(:class:`~wip_control.core.controller_settings.ControllerParams`) to the
parameters of every node of the graph (the sections each node declares from the core's
config dataclasses, ``wip_control.nodes.*_node``);
:func:`write_params_file` writes them as one params YAML::

    plant:
      ros__parameters:
        scenario_file: /path/scenario.yaml
        clock_mode: lockstep
        ...
    eso:
      ros__parameters:
        use_sim_time: true
        clock_mode: lockstep
        eso: {yaw_gains: [...], epsilon: 0.01, ...}   # flattened by ROS to eso.yaw_gains
        ...

Sections of config dataclasses are written with :func:`~wip_runtime.config.to_mapping`
and then typed from the dataclass field types, because the type of a ROS parameter is the
type of its value: a ``float`` field is always written as a float (``25.0``, never ``25``,
which ROS would reject as an integer for a double parameter), an ``int`` field as an int,
tuples as lists of their element type.

Node to sections (ROS prefix <- scenario key)
--------------------------------------------
========================  =================================================================
``plant``                 scenario_file, clock_mode, left_joint, right_joint (the datum
                          and all the simulation come from the scenario file)
``reference``             reference <- reference, rates <- rates
``eso``                   eso <- eso, position <- position, model <-
                          controller_model.parameters; encoders_relative_to_body <-
                          sensors.encoders_relative_to_body, gps_period = 1/sensors.gps_rate,
                          left_joint, right_joint, datum.* <- sensors.gps_datum_*
``trajectory_generator``  trajectory_generator <- trajectory_generator
``arc``                   arc <- arc, rates <- rates, model <-
                          controller_model.parameters, eso.yaw_input_gain_scale <- same
``mpc``                   mpc <- mpc, model <- controller_model.parameters,
                          mixer.max_wheel_torque <- mixer.max_wheel_torque, rates <- rates
``torque_mixer``          mixer <- mixer, rates <- rates, mpc.sampling_period <- same,
                          left_joint, right_joint, joints
``recorder`` (optional)   output, topics, compression, discovery_period
========================  =================================================================

Every node gets ``clock_mode``; in lockstep every node but the plant gets
``use_sim_time: true`` (the plant owns ``/clock``).
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import typing
from typing import Any, Mapping

import yaml

from wip_runtime.config import to_mapping
from wip_control.core.controller_settings import ControllerParams
from wip_runtime.cli import write_atomic

CLOCK_MODES = ('lockstep', 'realtime')
#: Node names of the graph, in start order (the plant last: it waits for the others).
CONTROLLER_NODES = ('reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                    'torque_mixer')
DEFAULT_JOINTS = ('left_wheel_joint', 'right_wheel_joint')


def _typed(value: Any, field_type: Any) -> Any:
    """``value`` as the ROS parameter value of a field of type ``field_type``."""
    origin = typing.get_origin(field_type)
    if field_type is float:
        return float(value)
    if field_type is int:
        return int(value)
    if field_type is bool or field_type is str:
        return value
    if origin is tuple:
        args = typing.get_args(field_type)
        element = args[0]
        values = list(value)
        if not values:
            # An empty YAML list has no element type: ROS could not declare it.
            raise ValueError('an empty list cannot be written as a ROS parameter')
        return [_typed(v, element) for v in values]
    if origin is typing.Union:
        args = [a for a in typing.get_args(field_type) if a is not type(None)]
        if value is None:
            raise ValueError('None cannot be written as a ROS parameter')
        return _typed(value, args[0])
    raise TypeError(f'unsupported field type {field_type!r}')


def config_section(instance: Any) -> dict[str, Any]:
    """One config dataclass as a flat mapping of ROS parameter values (see module doc)."""
    hints = typing.get_type_hints(type(instance))
    plain = to_mapping(instance)
    out = {}
    for field in dataclasses.fields(instance):
        if dataclasses.is_dataclass(hints[field.name]):
            raise TypeError(f'{type(instance).__name__}.{field.name}: nested sections are '
                            'not ROS parameters')
        try:
            out[field.name] = _typed(plain[field.name], hints[field.name])
        except ValueError as err:
            raise ValueError(f'{type(instance).__name__}.{field.name}: {err}') from err
    return out


def controller_sections(scenario: ControllerParams, lockstep: bool,
                        joints: tuple[str, str],
                        eso_extra: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Return the sections of each controller node, from the scenario's controller half.

    Without ``clock_mode`` and ``use_sim_time`` (:func:`graph_parameters` adds them).
    """
    left, right = joints
    sensors = scenario.sensors
    datum = {'latitude': float(sensors.gps_datum_latitude),
             'longitude': float(sensors.gps_datum_longitude),
             'altitude': float(sensors.gps_datum_altitude)}
    rates = config_section(scenario.rates)
    model = config_section(scenario.controller_model.parameters)
    mixer = config_section(scenario.mixer)
    nodes: dict[str, dict[str, Any]] = {
        # In real time the path starts when the safety layer engages, which is when the
        # plant (hold_until_engaged) or a base's holder lets the vehicle go.
        'reference': {'reference': config_section(scenario.reference), 'rates': rates,
                      **({} if lockstep else {'realtime_start': 'engaged'})},
        'eso': {
            'eso': config_section(scenario.eso),
            'position': config_section(scenario.position),
            'model': model,
            'encoders_relative_to_body': bool(sensors.encoders_relative_to_body),
            'gps_period': 1.0 / float(sensors.gps_rate),
            'left_joint': left, 'right_joint': right,
            'datum': dict(datum),
            **(eso_extra or {}),
        },
        'trajectory_generator': {
            'trajectory_generator': config_section(scenario.trajectory_generator)},
        'arc': {'arc': config_section(scenario.arc), 'rates': rates,
                'model': model,
                'eso': {'yaw_input_gain_scale': float(scenario.eso.yaw_input_gain_scale)}},
        'mpc': {'mpc': config_section(scenario.mpc), 'model': model,
                'mixer': {'max_wheel_torque': mixer['max_wheel_torque']}, 'rates': rates},
        'torque_mixer': {'mixer': mixer, 'rates': rates, 'model': model,
                         'mpc': {'sampling_period': float(scenario.mpc.sampling_period),
                                 'fast_resolve_period':
                                     float(scenario.mpc.fast_resolve_period),
                                 'push_trigger': bool(scenario.mpc.push_trigger)},
                         'left_joint': left, 'right_joint': right,
                         'joints': [left, right]},
    }
    return nodes


def graph_parameters(scenario: ControllerParams, clock_mode: str = 'lockstep',
                     scenario_path: str | pathlib.Path | None = None,
                     joints: tuple[str, str] = DEFAULT_JOINTS,
                     plant_extra: Mapping[str, Any] | None = None,
                     recorder: Mapping[str, Any] | None = None,
                     plant: bool = True,
                     eso_extra: Mapping[str, Any] | None = None) -> dict[str, dict]:
    """``{node_name: {'ros__parameters': {...}}}`` of every node of a graph run.

    Parameters
    ----------
    scenario : the run's scenario.
    clock_mode : 'lockstep' or 'realtime'.
    scenario_path : file the plant loads (it must hold ``scenario``); ``None``: '' (the
        plant's default, the paper scenario; only right for the default scenario).
    joints : (left, right) wheel joint names.
    plant_extra : more plant parameters (start handshake, stats file, ...).
    recorder : parameters of a ``recorder`` node; ``None``: no recorder section.
    plant : include the plant's section (false: a real base, hardware mode).
    eso_extra : more ESO parameters (the odometry output when the viewer runs).
    """
    if clock_mode not in CLOCK_MODES:
        raise ValueError(f'clock_mode: {clock_mode!r} is not one of {list(CLOCK_MODES)}')
    lockstep = clock_mode == 'lockstep'
    left, right = joints
    nodes = controller_sections(scenario, lockstep, joints, eso_extra)
    out: dict[str, dict] = {}
    for name in CONTROLLER_NODES:
        parameters = {'clock_mode': clock_mode, **nodes[name]}
        if lockstep:
            parameters['use_sim_time'] = True
        out[name] = {'ros__parameters': parameters}
    if plant:
        parameters = {'scenario_file': '' if scenario_path is None else str(scenario_path),
                      'clock_mode': clock_mode, 'left_joint': left, 'right_joint': right,
                      **(plant_extra or {})}
        out['plant'] = {'ros__parameters': parameters}
    if recorder is not None:
        parameters = dict(recorder)
        if lockstep:
            # Bag log times in simulation time, like the messages' stamps.
            parameters.setdefault('use_sim_time', True)
        out['recorder'] = {'ros__parameters': parameters}
    return out


def flatten(parameters: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested parameter mapping -> ``{'section.field': value}`` as ROS reads it."""
    flat = {}
    for key, value in parameters.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + '.'))
        else:
            flat[name] = value
    return flat


def section_applies(key: str, node: str, namespace: str = '') -> bool:
    """Whether rcl gives the params-file section ``key`` to ``node`` under ``namespace``.

    As rcl reads a params file: a key without a leading slash is in the root namespace
    (``eso`` is ``/eso``, so it misses ``/robot/eso``), ``*`` stands for one name and ``**``
    for any number of them, none included (``/**/eso`` is ``/eso`` and ``/robot/eso``).
    """
    pattern = ''.join('(/[^/]+)*' if token == '**' else '/[^/]+' if token == '*'
                      else '/' + re.escape(token)
                      for token in str(key).strip().split('/') if token)
    full_name = ''.join(f'/{part}' for part in (*namespace.split('/'), node) if part)
    return bool(pattern) and re.fullmatch(pattern, full_name) is not None


def namespaced_params(text: str, namespace: str) -> str:
    """Return the text of a generated params file under ``namespace``.

    Under a namespace, the generated params file's node keys ('eso') become the
    nodes' full names ('/robot1/eso': a key without a leading slash names a node of
    the root namespace only), and the odometry frames get the namespace as a prefix
    ('robot1/odom', 'robot1/base_link': the usual frame_prefix of a robot among
    several; 'map' stays shared). A --params-file of the user comes after it.
    """
    header = ''.join(line for line in text.splitlines(keepends=True)
                     if line.startswith('#'))
    data = yaml.safe_load(text) or {}
    prefix = namespace.lstrip('/') + '/'

    def prefixed(frame: str) -> str:   # once: a retried start reads its own output
        frame = str(frame).lstrip('/')
        return frame if frame.startswith(prefix) else prefix + frame
    out = {}
    for key, section in data.items():
        if not str(key).startswith('/'):
            key = f'{namespace}/{key}'
        params = (section or {}).get('ros__parameters') if isinstance(section, dict) else None
        if key == f'{namespace}/eso' and isinstance(params, dict):
            params.setdefault('odometry_frame_id', 'odom')
            params.setdefault('odometry_child_frame_id', 'base_link')
            for name in ('odometry_frame_id', 'odometry_child_frame_id'):
                params[name] = prefixed(params[name])
        if key == f'{namespace}/viewer' and isinstance(params, dict):
            viewer = params.setdefault('viewer', {})
            viewer['child_frame_id'] = prefixed(viewer.get('child_frame_id', 'base_link'))
            viewer['frame_prefix'] = prefix
        out[key] = section
    return header + yaml.safe_dump(out, sort_keys=False)


class _NoAliasDumper(yaml.SafeDumper):
    """Block-style YAML without anchors/aliases (``&id001``), which rcl's parser rejects."""

    def ignore_aliases(self, data: Any) -> bool:
        return True


def write_params_file(scenario: ControllerParams, path: str | pathlib.Path, clock_mode: str,
                      scenario_path: str | pathlib.Path | None,
                      joints: tuple[str, str] = DEFAULT_JOINTS,
                      plant_extra: Mapping[str, Any] | None = None,
                      recorder: Mapping[str, Any] | None = None,
                      eso_extra: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write the params YAML of a graph run (see :func:`graph_parameters`); returns the path."""
    data = graph_parameters(scenario, clock_mode, scenario_path, joints, plant_extra,
                            recorder, eso_extra=eso_extra)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f'# ROS parameters of a wip-ros graph run (scenario {scenario.name!r}, '
              f'clock {clock_mode}),\n# written by wip_bringup.params_files from the '
              'scenario; use with --ros-args --params-file.\n')
    text = yaml.dump(data, Dumper=_NoAliasDumper, sort_keys=False, default_flow_style=False,
                     width=99)
    write_atomic(path, header + text)  # whole or not at all (a full disk)
    return path
