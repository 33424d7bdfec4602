"""Parameters of the simulator nodes (plant, stand-in base) and the registry of both.

Declared like every node parameter (:mod:`wip_control.nodes.settings`); no rclpy import,
so the parameter reference is generated from :data:`NODES`.
"""

from __future__ import annotations

import dataclasses

from wip_control.nodes.settings import CLOCK_MODES
from wip_description.wiring import DatumParams, EffortCommand, ImuMounting, WheelJoints, WheelSigns
from wip_runtime.config import param, TEXT
from wip_sim.core.scenario import Scenario

#: Command-line flag of ``ros2 run wip_sim simulation`` (before ``--ros-args``) that
#: composes the viewer node too. Here, not in :mod:`wip_sim.simulation`, so that a launcher
#: reads it without importing the nodes.
WITH_VIEWER = '--with-viewer'
#: The plant's answer to a start request once it has started (a launcher whose first
#: request's answer was lost or late reads it as started).
ALREADY_STARTED = 'already started'


def _scenario_file():
    return param('', TEXT, "scenario YAML file (wip_sim.core.scenario: plant, initial state, "
                 "sensors, rates); '': the paper's Section V")


@dataclasses.dataclass(frozen=True)
class PlantNodeParams:
    """Node-level settings of the plant (the scenario file holds the simulation)."""

    scenario_file: str = _scenario_file()
    clock_mode: str = param('lockstep', TEXT, "'lockstep': publish /clock and step when the "
                            "wheel torques of the current tick arrived; 'realtime': step on "
                            'a wall timer with the latest torques', choices=CLOCK_MODES)
    map_frame: str = param('map', TEXT, 'frame of the ground truth position')
    imu_frame: str = param('imu_link', TEXT, 'frame_id of /imu/data')
    gps_frame: str = param('gps_link', TEXT, 'frame_id of /gps/fix')
    autostart: bool = param(True, '1', 'start by itself once the endpoints are matched; '
                            'false: wait for the ~/start service')
    hold_until_engaged: bool = param(
        True, '1', 'realtime: hold the vehicle at its initial state (sensors published, time '
        'stopped) until the first wheel torques not zeroed by the safety layer; false: free '
        '(docs/decisions/sim-parameters.md)')
    hold_at_end: bool = param(
        False, '1', 'realtime: at the end of the scenario (not after a fall) keep publishing '
        "the last state's sensors, frozen, until stopped, so that the controllers are "
        'stopped while their inputs still come')
    max_torque_age: float = param(0.05, 's', 'realtime: wheel torques older than this (stamp '
                                  'against the wall clock) are replaced by zero', minimum=0.0,
                                  exclusive_minimum=True, maximum=3600.0)
    stats_file: str = param('', TEXT, 'JSON file of per-tick timings written at exit; '
                            'empty: none')


@dataclasses.dataclass(frozen=True)
class StartHandshake:
    """Matched subscriptions the plant waits for before its first step (``start.*``)."""

    expected_sensor_subscribers: int = param(1, '1', 'matched subscriptions each sensor '
                                             'topic needs before the start', minimum=0,
                                             maximum=100)
    expected_ground_truth_subscribers: int = param(0, '1', 'matched subscriptions '
                                                   '/wip/ground_truth needs before the start',
                                                   minimum=0, maximum=100)
    expected_clock_subscribers: int = param(0, '1', 'matched subscriptions /clock needs '
                                            'before the start (lockstep)', minimum=0,
                                            maximum=100)


@dataclasses.dataclass(frozen=True)
class StandinParams:
    """Node-level settings of the stand-in base."""

    scenario_file: str = _scenario_file()
    imu_frame: str = param('imu_link', TEXT, 'frame_id of /imu/data')
    gps_frame: str = param('gps_link', TEXT, 'frame_id of /gps/fix')
    odom_frame: str = param('odom', TEXT, 'frame_id of /odom')
    publish_odometry: bool = param(False, '1', 'also publish nav_msgs/Odometry on /odom')
    hold_until_engaged: bool = param(True, '1', 'frozen at the initial state until the first '
                                     'non-zero command (someone holds the robot)')
    exit_after_fall: float = param(1.0, 's', 'keep publishing this long after a fall, then '
                                   'exit with code 1 (fell)', minimum=0.0, maximum=3600.0)
    duration: float = param(0.0, 's', 'exit with code 0 after this long from the release; 0: '
                            'until SIGINT', minimum=0.0, maximum=1e6)
    truth_period: float = param(0.02, 's', 'sampling of the ground truth in the stats file',
                                minimum=0.0, exclusive_minimum=True, maximum=60.0)
    stats_file: str = param('', TEXT, 'JSON statistics written at exit; empty: none')
    sensor_bunch: int = param(1, '1', 'deliver the encoder and IMU samples in bunches of '
                              'this many (each with its own sample stamp), as a USB or CAN '
                              'bridge that buffers them: every N-th period the last N at '
                              'once; 1: each when taken', minimum=1, maximum=10)


@dataclasses.dataclass(frozen=True)
class PositionFault:
    """A fault injected into the stand-in's position outputs (``position_fault.*``).

    What the safety layer must catch: a receiver that jumps (``offset``) or a position
    source that stops moving (``freeze``), on /gps/fix and /odom alike.
    """

    kind: str = param('none', TEXT, "'none', 'offset' (the fixes moved by offset) or "
                      "'freeze' (the last fix before the start repeated)",
                      choices=('none', 'offset', 'freeze'))
    start: float = param(0.0, 's', 'the fault begins this long after the release',
                         minimum=0.0, maximum=1e6)
    duration: float = param(0.0, 's', 'the fault lasts this long; 0: for good', minimum=0.0,
                            maximum=1e6)
    offset: tuple[float, float] = param((0.0, 0.0), 'm', "east and north offset of 'offset'",
                                        minimum=-1e7, maximum=1e7)


@dataclasses.dataclass(frozen=True)
class CommandTiming:
    """The stand-in's expected command period (its default is the scenario's)."""

    expected_command_period: float = param(
        Scenario().control_period, 's', "period of the controllers' commands (deadline "
        "statistics); default: the scenario file's control period", minimum=0.0,
        exclusive_minimum=True, maximum=60.0)


#: executable -> the (prefix, dataclass) groups it declares. The stand-in's datum and
#: expected_command_period default to the scenario file's values at run time; the plant
#: takes its datum from the scenario file only.
NODES: dict[str, tuple[tuple[str, type], ...]] = {
    'plant': (('', PlantNodeParams), ('', WheelJoints), ('start', StartHandshake)),
    'standin_base': (('', StandinParams), ('', WheelJoints), ('', EffortCommand),
                     ('', WheelSigns), ('', ImuMounting), ('', CommandTiming),
                     ('datum', DatumParams), ('position_fault', PositionFault)),
}
