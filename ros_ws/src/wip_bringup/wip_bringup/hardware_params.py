"""Hardware mode's parameters: remap rules, the user's params files and the generated file.

What ROS applies: a ``--remap`` rule, the params-file keys (``/**``, node sections) with a
later file winning, and the controllers' generated parameters in real time without a plant.
"""

from __future__ import annotations

import pathlib
from typing import Any, Iterable, Mapping

from wip_runtime.config import ParamError, load_yaml_text
from wip_control.core.controller_settings import ControllerParams

from .launcher import EXIT_USAGE, GraphError
from .params_check import check_remap, ParamsFileError
from .params_files import DEFAULT_JOINTS, flatten, graph_parameters, section_applies

#: The mixer's ``safety.max_estop_age`` in hardware mode [s].
HEARTBEAT_MAX_AGE = 1.0


def parse_remap(text: str, namespace: str = '') -> tuple[str, str]:
    """Parse a ``--remap`` rule ``'FROM:=TO'`` into absolute topic names.

    ``'FROM:=TO'`` -> (FROM, TO) as absolute topic names; GraphError on bad syntax or a
    side that is not a valid ROS topic name. A relative name is the nodes' one under
    ``namespace`` (rcl resolves both sides of a rule in the node's namespace):
    'imu/data:=base/imu' follows a vehicle's namespace, '/imu/data:=...' matches only a
    node of the root namespace.
    """
    try:
        check_remap(text)   # FROM:=TO, both sides valid ROS topic names
    except ParamsFileError as err:
        raise GraphError(str(err), EXIT_USAGE) from None
    source, _, target = text.partition(':=')
    return tuple(name if name.startswith('/') else f'{namespace}/{name}'
                 for name in (source.strip(), target.strip()))


def remapped(topic: str, remaps: Iterable[tuple[str, str]]) -> str:
    """Return the name ``topic`` has after the remaps (the first rule that matches, as in ROS)."""
    for source, target in remaps:
        if source == topic:
            return target
    return topic


def load_params_file(path: str | pathlib.Path) -> dict[str, Any]:
    """Return a ROS params YAML ``{node: {ros__parameters: {...}}}``; GraphError if malformed."""
    path = pathlib.Path(path)
    try:
        data = load_yaml_text(path.read_bytes(), f'--params-file {path}')
    except OSError as err:
        raise GraphError(f'--params-file {path}: {err.strerror or err}', EXIT_USAGE) from err
    except ParamError as err:
        raise GraphError(str(err), EXIT_USAGE) from err
    if not isinstance(data, Mapping):
        raise GraphError(f'--params-file {path}: expected a mapping of node names',
                         EXIT_USAGE)
    for node, section in data.items():
        if not (isinstance(section, Mapping) and isinstance(
                section.get('ros__parameters'), Mapping)):
            raise GraphError(f'--params-file {path}: {node!r} has no ros__parameters '
                             'mapping', EXIT_USAGE)
    return dict(data)


def node_parameters(node: str, generated: Mapping[str, Any],
                    params_files: Iterable[Mapping[str, Any]],
                    namespace: str = '') -> dict[str, Any]:
    """Return the parameters ``node`` gets from the params files, flattened.

    The parameters ``node`` (under ``namespace``) gets, flattened
    (``'model.wheel_radius'``): the generated params file's, then each extra file's
    matching sections in order (later wins).
    """
    flat = flatten(generated.get(node, {}).get('ros__parameters', {}))
    for data in params_files:
        for key, section in data.items():
            if section_applies(key, node, namespace):
                flat.update(flatten(section['ros__parameters']))
    return flat


def hardware_parameters(scenario: ControllerParams, recorder: Mapping[str, Any] | None = None,
                        joints: tuple[str, str] = DEFAULT_JOINTS,
                        heartbeat: bool = True) -> dict[str, dict]:
    """Return the generated params file of a hardware run.

    It holds the controller nodes of
    :func:`~wip_bringup.params_files.graph_parameters` in real time, no plant (there the
    reference starts when the safety layer engages); with ``heartbeat``, the mixer requires
    /wip/heartbeat (``safety.max_estop_age``).
    """
    data = graph_parameters(scenario, 'realtime', None, joints, recorder=recorder,
                            plant=False)
    if heartbeat:
        mixer = data['torque_mixer']['ros__parameters']
        mixer.setdefault('safety', {})['max_estop_age'] = HEARTBEAT_MAX_AGE
    return data
