"""The record a fit reads: a bag (with a robot's wiring) or a scripts/simulate run.

A bag's /joint_states and /imu/data are read by the ESO node's own conversions with the
robot's wiring (:mod:`wip_tools.run_wiring`), its other topics through
:func:`wip_tools.report.record_from_bag`; a record saved as timeseries.npz is loaded as is.
"""

from __future__ import annotations

import math
import pathlib
from typing import Iterable, Mapping

import numpy as np

from wip_tools.identify_signals import IdentifyError

#: The bag topics a fit reads: default name -> (group, message type).
BAG_TOPICS = {'/wip/ground_truth': ('truth', 'wip_msgs/msg/GroundTruth'),
              '/wip/state_estimate': ('estimate', 'wip_msgs/msg/StateEstimate'),
              '/wip/wheel_torques': ('wheels', 'wip_msgs/msg/WheelTorques'),
              '/joint_states': ('encoders', 'sensor_msgs/msg/JointState'),
              '/imu/data': ('imu', 'sensor_msgs/msg/Imu')}


def _sensor_converters(wiring):
    """Return the (encoders, imu) row functions: the ESO node's conversions for ``wiring``.

    A message they cannot read (the joints absent, no orientation...) gives None: the row
    is skipped, as the ESO node drops it.
    """
    from wip_runtime.messages import InvalidMessage
    from wip_control.nodes.hardware_inputs import (body_pitch_yaw, body_pitch_yaw_rates,
                                                   mounting_inverse, signed_efforts,
                                                   signed_wheel_angles)
    inverse = mounting_inverse(wiring.imu_mounting_rpy)

    def encoders(m):
        try:
            return signed_wheel_angles(m, wiring.left_joint, wiring.right_joint,
                                       wiring.left_wheel_sign, wiring.right_wheel_sign)
        except (InvalidMessage, ValueError, IndexError):
            return None

    def imu(m):
        try:
            pitch, yaw = body_pitch_yaw(m, inverse)
            return (pitch, yaw, *body_pitch_yaw_rates(m, inverse, pitch))
        except (InvalidMessage, ValueError):
            return None

    def efforts(m):
        # The joints' effort state, in their own signs: the sign maps both ways.
        names = list(m.name)
        if len(m.effort) != len(names) or wiring.left_joint not in names or \
                wiring.right_joint not in names:
            return None
        left = float(m.effort[names.index(wiring.left_joint)])
        right = float(m.effort[names.index(wiring.right_joint)])
        if not math.isfinite(left + right):
            return None
        return signed_efforts(left, right, wiring.left_wheel_sign, wiring.right_wheel_sign)
    return encoders, imu, efforts


#: Where a bag's wheel torques come from (``torques``): the base's joint effort state, or
#: the controllers' commands.
TORQUE_SOURCES = ('auto', 'efforts', 'commands')


def load_record(path: str | pathlib.Path, wiring=None,
                remaps: Iterable[tuple[str, str]] = (), torques: str = 'auto') -> dict:
    """Return a record from a bag (directory or .mcap) or a timeseries.npz of scripts/simulate.

    A bag's /joint_states and /imu/data are read with ``wiring`` (a
    :class:`wip_tools.run_wiring.Wiring`, default the project's conventions) by the ESO
    node's own conversions; its topics are found as :func:`run_wiring.sensor_topic` says.
    ``torques``: the wheels group from the JointState efforts ('efforts': what the motors
    applied, the effort of a sample taken as the torque over the period that ended at
    it), from /wip/wheel_torques ('commands': stamped with the sensor sample they answer,
    so they lag the motors by the controllers' latency and the motor lag), or 'auto'
    (efforts where the base reports non-zero ones). The record's ``torque_source`` says
    which.
    """
    if torques not in TORQUE_SOURCES:
        raise IdentifyError(f'torques {torques!r}: expected one of {list(TORQUE_SOURCES)}')
    path = pathlib.Path(path)
    if not path.exists():
        raise IdentifyError(f'{path}: no such file or directory')
    if path.is_dir() and (path / 'timeseries.npz').exists() and not any(path.glob('*.mcap')):
        path = path / 'timeseries.npz'
    if path.suffix == '.npz':
        from wip_sim.core.record import RunRecord
        try:
            return RunRecord.load_npz(path)
        except (OSError, ValueError, KeyError) as err:
            raise IdentifyError(f'{path}: not a readable timeseries.npz ({err})') from err
    from wip_tools import report  # rosbag2
    from wip_tools.run_wiring import Wiring
    wiring = Wiring() if wiring is None else wiring
    topics, efforts = _bag_topics(path, remaps, wiring)
    try:
        record = report.record_from_bag(path, topics)
    except report.ReportError as err:
        raise IdentifyError(str(err)) from err
    out = {g: record[g] for g in ('truth', 'estimate', 'wheels', 'encoders', 'imu')
           if g in record}
    out['torque_source'] = 'commands'
    joint_topic = next((n for n, (g, _) in topics.items() if g == 'encoders'), None)
    if torques != 'commands' and joint_topic is not None:
        _use_efforts(out, path, joint_topic, efforts, record, torques)
    return out


def _bag_topics(path: pathlib.Path, remaps, wiring) -> tuple[dict, object]:
    """Return the bag's topics of BAG_TOPICS, {topic: (group, row)}, and the efforts' row."""
    from wip_bag.bag_reader import BagReadError, read_topics
    from wip_tools import report  # rosbag2
    from wip_tools.run_wiring import sensor_topic, WiringError
    try:
        kinds = {name: meta.type_name for name, meta in read_topics(path).items()}
    except BagReadError as err:
        raise IdentifyError(str(err)) from err
    encoders, imu, efforts = _sensor_converters(wiring)
    convert = dict(report.TOPICS, **{'/joint_states': ('encoders', encoders),
                                     '/imu/data': ('imu', imu)})
    topics = {}
    for default, (group, type_name) in BAG_TOPICS.items():
        try:
            name = sensor_topic(default, type_name, kinds, list(remaps))
        except WiringError as err:
            raise IdentifyError(str(err)) from err
        if name is not None:
            topics[name] = (group, convert[default][1])
    if not topics:
        raise IdentifyError(f'{path}: none of the topics {sorted(BAG_TOPICS)} (or of their '
                            'types) is in the bag')
    return topics, efforts


def _use_efforts(out: dict, path, joint_topic: str, efforts, record, torques: str) -> None:
    """Set ``out``'s wheels group from the joints' efforts where the base reports them."""
    from wip_tools import report  # rosbag2
    try:
        applied = report.record_from_bag(path, {joint_topic: ('wheels', efforts)})
    except report.ReportError:
        applied = None
    wheels = applied['wheels'] if applied is not None else None
    usable = wheels is not None and len(wheels['t']) > 2 and (
        np.any(wheels['tau_left'] != 0.0) or np.any(wheels['tau_right'] != 0.0))
    if usable:
        # The same time origin as the rest; each effort acted over the period that
        # ended at its sample: it is stamped with the sample before.
        t = wheels['t'] + (applied.attributes['time_origin_ns']
                           - record.attributes['time_origin_ns']) * 1e-9
        period = float(np.median(np.diff(t)))
        out['wheels'] = {'t': np.concatenate([[t[0] - period], t[:-1]]),
                         'tau_left': wheels['tau_left'], 'tau_right': wheels['tau_right']}
        out['torque_source'] = 'efforts'
    elif torques == 'efforts':
        raise IdentifyError(f'{joint_topic}: no effort of both wheel joints (the base '
                            'does not report its effort state); use the commands')


def run_plant_model(run: str | pathlib.Path) -> str | None:
    """Return the plant model of a simulated run's scenario.yaml (in the bag or beside it)."""
    run = pathlib.Path(run)
    directory = run if run.is_dir() else run.parent
    for candidate in (directory / 'scenario.yaml', directory.parent / 'scenario.yaml'):
        if candidate.is_file():
            try:
                from wip_sim.core.scenario import load_scenario
                return load_scenario(candidate).plant.model.model
            except (ValueError, OSError):
                return None
    return None


def choose_model(record: Mapping, run: str | pathlib.Path, source: str) -> str:
    """'paper' or 'full' for ``--model auto``.

    Without ground truth the record is a robot's (or a base's): the full plant's rows. A
    simulation's rows are those of its plant, from its scenario.yaml ('paper' if none).
    """
    if source != 'truth' and not _has(record, 'truth'):
        return 'full'
    model = run_plant_model(run)
    return 'paper' if model in (None, 'paper') else 'full'


def _has(record: Mapping, group: str) -> bool:
    return group in record and len(record[group]['t']) > 0


def best_source(record: Mapping) -> str:
    """Return the best source of the signals.

    truth (a simulation's), else the sensors, else the state estimate (which the ESOs'
    lag and filtering bias: docs/identification.md).
    """
    if _has(record, 'truth'):
        return 'truth'
    if _has(record, 'encoders') and _has(record, 'imu'):
        return 'sensors'
    return 'estimate'
