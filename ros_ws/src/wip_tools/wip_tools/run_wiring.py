"""A robot's wiring as a run had it: joints, wheel signs, IMU mounting, sensor topics.

Offline tools that read a robot's own sensors from a bag (``scripts/identify --source
sensors``) must read them as the ESO node did. The wiring is what the ESO node was given:
its parameters ``left_joint``, ``right_joint``, ``left_wheel_sign``, ``right_wheel_sign``,
``imu_mounting_rpy`` and ``encoders_relative_to_body`` from ROS params files (later files
win, ``/**`` and node sections as ROS applies them:
:func:`wip_bringup.hardware_params.node_parameters`), and the topics it subscribed to, after
the run's remaps.

A hardware-mode run leaves its parameters in the bag (``BAG/params.yaml``: the generated
parameters with the ``--params-file`` files merged in); ``OUT/params.yaml`` beside the bag
holds the generated ones only. The sensor topics are found in the bag: the default names
(``/joint_states``, ``/imu/data``), else ``--remap`` rules, else the one topic of the
bag with that message type (a remap renames a topic, not its type).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Iterable, Mapping, Sequence

#: The node whose parameters describe how the sensors are read.
ESO_NODE = 'eso'
#: Message types of the sensor topics.
JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
IMU_TYPE = 'sensor_msgs/msg/Imu'
#: The file a run leaves its parameters in (in the bag, or beside it in the run's --out).
PARAMS_FILE = 'params.yaml'


class WiringError(ValueError):
    """The wiring cannot be read: the message is one line."""


@dataclasses.dataclass(frozen=True)
class Wiring:
    """How the ESO node read the base's sensors (defaults: the project's conventions)."""

    left_joint: str = 'left_wheel_joint'
    right_joint: str = 'right_wheel_joint'
    left_wheel_sign: float = 1.0
    right_wheel_sign: float = 1.0
    imu_mounting_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    encoders_relative_to_body: bool = True
    #: The params files read, in order (empty: the defaults).
    files: tuple[str, ...] = ()

    def describe(self) -> str:
        source = ', '.join(self.files) if self.files else 'the default wiring'
        return (f'joints {self.left_joint!r} (sign {self.left_wheel_sign:+g}) and '
                f'{self.right_joint!r} (sign {self.right_wheel_sign:+g}), IMU mounting '
                f'{list(self.imu_mounting_rpy)} rad, encoders '
                f'{"against the body" if self.encoders_relative_to_body else "rolling"} '
                f'(from {source})')


def run_params_files(run: str | pathlib.Path) -> list[pathlib.Path]:
    """Return the params file a run left with its bag: ``BAG/params.yaml``, else beside it."""
    run = pathlib.Path(run)
    directory = run if run.is_dir() else run.parent
    for candidate in (directory / PARAMS_FILE, directory.parent / PARAMS_FILE):
        if candidate.is_file():
            return [candidate]
    return []


def load_wiring(files: Iterable[str | pathlib.Path], namespace: str = '') -> Wiring:
    """Return the ESO node's wiring from ROS params ``files`` (later wins)."""
    from wip_bringup.hardware_params import load_params_file, node_parameters
    from wip_bringup.launcher import GraphError
    from wip_control.nodes.hardware_inputs import check_mounting_rpy, check_wheel_sign
    files = [str(f) for f in files]
    try:
        data = [load_params_file(f) for f in files]
    except GraphError as err:
        raise WiringError(str(err)) from err
    flat = node_parameters(ESO_NODE, {}, data, namespace)
    default = Wiring()
    try:
        relative = flat.get('encoders_relative_to_body', default.encoders_relative_to_body)
        if not isinstance(relative, bool):
            raise ValueError(f'encoders_relative_to_body: must be true or false, got '
                             f'{relative!r}')
        wiring = Wiring(
            left_joint=_text(flat, 'left_joint', default.left_joint),
            right_joint=_text(flat, 'right_joint', default.right_joint),
            left_wheel_sign=check_wheel_sign(
                'left_wheel_sign', flat.get('left_wheel_sign', default.left_wheel_sign)),
            right_wheel_sign=check_wheel_sign(
                'right_wheel_sign', flat.get('right_wheel_sign', default.right_wheel_sign)),
            imu_mounting_rpy=check_mounting_rpy(
                'imu_mounting_rpy', flat.get('imu_mounting_rpy', default.imu_mounting_rpy)),
            encoders_relative_to_body=relative, files=tuple(files))
    except ValueError as err:
        raise WiringError(f'{", ".join(files)}: {err}') from err
    if wiring.left_joint == wiring.right_joint:
        raise WiringError(f'{", ".join(files)}: left_joint and right_joint are both '
                          f'{wiring.left_joint!r}')
    return wiring


def _text(flat: Mapping, name: str, default: str) -> str:
    value = flat.get(name, default)
    if not isinstance(value, str) or not value:
        raise ValueError(f'{name}: must be a joint name, got {value!r}')
    return value


def parse_remaps(rules: Iterable[str]) -> list[tuple[str, str]]:
    """``FROM:=TO`` rules as (FROM, TO) absolute topic names; WiringError if malformed."""
    out = []
    for rule in rules:
        source, sep, target = rule.partition(':=')
        source, target = source.strip(), target.strip()
        if not sep or not source or not target:
            raise WiringError(f'--remap {rule!r}: expected FROM:=TO (e.g. '
                              '/joint_states:=/base/joint_states)')
        out.append(tuple('/' + name.lstrip('/') for name in (source, target)))
    return out


def sensor_topic(default: str, type_name: str, topics: Mapping[str, str],
                 remaps: Sequence[tuple[str, str]] = ()) -> str | None:
    """Return the bag topic of the sensor the nodes call ``default``; None if none.

    ``topics``: the bag's topic -> type. A remap of ``default`` wins; then ``default`` if the
    bag has it; then the bag's only topic of ``type_name``. WiringError if several topics
    of that type leave the choice open.
    """
    for source, target in remaps:
        if source == default:
            return target if target in topics else None
    if topics.get(default) == type_name:
        return default
    candidates = sorted(name for name, kind in topics.items() if kind == type_name)
    if len(candidates) > 1:
        raise WiringError(f'{default}: the bag has no such topic and {len(candidates)} '
                          f'topics of type {type_name} ({", ".join(candidates)}): choose '
                          f'one with --remap {default}:=TOPIC')
    return candidates[0] if candidates else None
