"""Node-level parameters of the control nodes, and which node declares which groups.

The core's config dataclasses hold the control parameters; the small frozen dataclasses
here hold what only a node has (clock mode, triggers, periods, ...; a base's wiring, joint
names, wheel signs, IMU mounting and the GPS datum, is :mod:`wip_description.wiring`'s),
declared with the same :func:`~wip_runtime.config.param` so the range checks come from
the declaration. :data:`NODES` is the registry: executable ->
``(prefix, dataclass)`` groups it declares (prefix ``''``: names without a section).
No rclpy import here: the parameter reference (``ros2 run wip_tools parameters``,
docs/parameters.md) is generated from this module.
"""

from __future__ import annotations

import dataclasses

from ..core.arc import ArcParams
from ..core.eso import EsoParams
from ..core.mixer import MixerParams
from ..core.mpc_config import MpcParams
from wip_description.params import ModelParams
from ..core.position import PositionParams
from ..core.references import ReferenceParams
from ..core.runaway import RunawayParams
from ..core.safety_config import SafetyParams
from ..core.controller_settings import RatesParams
from wip_description.sensors import SensorParams
from ..core.trajectory_generator import TrajectoryGeneratorParams
from ..core.wiring_check import WiringCheckParams
from wip_description.wiring import (DatumParams, EffortCommand, ImuMounting, WheelJoints,
                                    WheelSigns)
from wip_runtime.config import like, param, TEXT

CLOCK_MODES = ('lockstep', 'realtime')
#: The nodes are drop-in controllers for a real base; the graph runner sets 'lockstep'.
DEFAULT_CLOCK_MODE = 'realtime'
POSITION_SOURCES = ('gps', 'odometry', 'wheels')
REALTIME_STARTS = ('first_tick', 'engaged')
REALTIME_TRIGGERS = ('state_estimate', 'timer')
ODOMETRY_OUTPUTS = ('realtime', 'always', 'off')


@dataclasses.dataclass(frozen=True)
class ControllerNodeParams:
    """Declared by every controller node (nodes/common.py ControllerNode)."""

    use_intra_process_comms: bool = param(
        True, '1', 'composed process: a message to a node of the same process skips DDS '
        'unless one outside subscribes the topic (docs/decisions/node-settings.md)')
    clock_mode: str = param(DEFAULT_CLOCK_MODE, TEXT, "'lockstep' (deterministic simulation "
                            "on /clock, exact-time input sets) or 'realtime' (latest inputs, "
                            'timers)', choices=CLOCK_MODES)
    diagnostics_period: float = param(1.0, 's', 'period of the /diagnostics messages (wall '
                                      'time); 0: none', minimum=0.0, maximum=3600.0)
    max_stamp_lead: float = param(
        0.5, 's', 'real time: an input stamped more than this ahead of the node clock is '
        'refused (docs/decisions/node-settings.md)', minimum=0.0, exclusive_minimum=True,
        maximum=3600.0)


@dataclasses.dataclass(frozen=True)
class EsoNodeParams:
    """Node-level settings of the ESO node."""

    encoders_relative_to_body: bool = like(SensorParams, 'encoders_relative_to_body')
    gps_period: float = param(1.0 / SensorParams().gps_rate, 's', 'period of the GPS fixes '
                              '(lockstep: a fix is expected every round(gps_period / '
                              'eso.sample_period) samples)', minimum=0.0,
                              exclusive_minimum=True, maximum=3600.0)
    position_source: str = param('gps', TEXT, "'gps': NavSatFix on /gps/fix about the datum; "
                                 "'odometry': nav_msgs/Odometry on /odom (real time only); "
                                 "'wheels': dead reckoning (indoors, no GPS)",
                                 choices=POSITION_SOURCES)
    max_datum_distance: float = param(
        5000.0, 'm', 'a first GPS fix farther than this from datum.* is refused (a datum '
        'copied from elsewhere): no torque until restarted with the right datum',
        minimum=0.0, exclusive_minimum=True)
    frame_id: str = param('map', TEXT, 'frame of the planar position x, y')
    odometry_output: str = param(
        'realtime', TEXT, "the estimate as nav_msgs/Odometry on /odom: 'realtime' (not in "
        "lockstep), 'always' or 'off' (docs/decisions/node-settings.md)",
        choices=ODOMETRY_OUTPUTS)
    odometry_decimation: int = param(
        4, '1', '/odom carries every n-th estimate (4: 50 Hz at the 200 Hz control rate)',
        minimum=1, maximum=1000)
    odometry_frame_id: str = param('odom', TEXT, '/odom header.frame_id (REP 105; the same '
                                   'plane as frame_id: the estimate has no map/odom offset)')
    odometry_child_frame_id: str = param('base_link', TEXT, '/odom child_frame_id (frame '
                                         'of the twist)')
    odometry_position_std: float = param(
        0.5, 'm', '/odom: standard deviation put on x and y in the pose covariance (the '
        'position follows GPS fixes of about this noise)', minimum=0.0, maximum=1000.0)
    odometry_heading_std: float = param(
        0.05, 'rad', '/odom: standard deviation put on the heading (yaw)', minimum=0.0,
        maximum=100.0)
    odometry_speed_std: float = param(
        0.05, 'm/s', '/odom: standard deviation put on the twist linear.x', minimum=0.0,
        maximum=100.0)
    odometry_yaw_rate_std: float = param(
        0.02, 'rad/s', '/odom: standard deviation put on the twist angular.z',
        minimum=0.0, maximum=100.0)
    odometry_tf: bool = param(
        True, '1', 'with every /odom message, its pose as the transform odometry_frame_id -> '
        'odometry_child_frame_id on /tf (diff_drive_controller: enable_odom_tf)')
    map_to_odom_tf: bool = param(
        True, '1', 'while /odom is on, identity frame_id -> odometry_frame_id on /tf_static '
        '(the estimate has no drift frame); false when a localisation node publishes it')


@dataclasses.dataclass(frozen=True)
class YawInputGainScale:
    """The one ESO value the ARC needs: the scale of the yaw input gain.

    From which it computes α̂(0) = 1/ĝ1 with the model (``core.control_step.initial_alpha``).
    """

    yaw_input_gain_scale: float = like(EsoParams, 'yaw_input_gain_scale')


@dataclasses.dataclass(frozen=True)
class SafetyRideThrough:
    """The safety-layer values the MPC needs: how long a late input is ridden through.

    Real time: inputs older than ``max_estimate_age`` hold the MPC's tick (the mixer
    bridges), older than ``max_estimate_age + bridge_time`` make it INPUT_INVALID.
    """

    max_estimate_age: float = like(SafetyParams, 'max_estimate_age')
    bridge_time: float = like(SafetyParams, 'bridge_time')


@dataclasses.dataclass(frozen=True)
class WheelTorqueLimit:
    """The one mixer value the MPC needs: τmax, which bounds its drive torque.

    2 τmax − |τω|, core.mixer.drive_torque_limit.
    """

    max_wheel_torque: float = like(MixerParams, 'max_wheel_torque')


@dataclasses.dataclass(frozen=True)
class ObstacleRefusalParams:
    """The generator values the reference node needs: when and where a refusal holds.

    A commanded reference restarts at rest there (core/obstacle_refusal.py).
    """

    obstacle_back_off: float = like(TrajectoryGeneratorParams, 'obstacle_back_off')
    obstacle_refuse_delay: float = like(TrajectoryGeneratorParams, 'obstacle_refuse_delay')


@dataclasses.dataclass(frozen=True)
class MpcPeriod:
    """The MPC values the mixer needs: its sampling and re-solve periods, its push trigger.

    From which the mixer computes the ticks at which (in lockstep) it awaits a drive torque.
    """

    sampling_period: float = like(MpcParams, 'sampling_period')
    fast_resolve_period: float = like(MpcParams, 'fast_resolve_period')
    push_trigger: bool = like(MpcParams, 'push_trigger')


@dataclasses.dataclass(frozen=True)
class MixerNodeParams:
    """Node-level settings of the torque mixer node."""

    effort_topic: str = param('effort_controller/commands', TEXT, 'topic of the '
                              'ros2_control JointGroupEffortController command '
                              '(std_msgs/Float64MultiArray)')


@dataclasses.dataclass(frozen=True)
class ReferenceNodeParams:
    """Node-level settings of the reference node."""

    frame_id: str = param('map', TEXT, 'frame of the reference position')
    realtime_start: str = param('first_tick', TEXT, "realtime: the path starts at the node's "
                                "first tick ('first_tick') or when the safety layer first "
                                "sends torque ('engaged': the first /wip/wheel_torques not "
                                'zeroed)', choices=REALTIME_STARTS)
    realtime_trigger: str = param('state_estimate', TEXT, "realtime: a sample per "
                                  "/wip/state_estimate at its stamp ('state_estimate') or per "
                                  "tick of a timer at rates.control_rate ('timer') "
                                  '(docs/decisions/node-settings.md)',
                                  choices=REALTIME_TRIGGERS)


#: Parameters that existed before and what replaces them, for the warning a params file
#: that still sets one gets (``ControllerNode.retired_parameters``).
RETIRED = {
    'mpc_period': "the mixer reads the MPC's period from 'mpc.sampling_period'",
    'alpha_initial': "the ARC computes alpha_hat(0) = 1/g1 from 'model.*' and "
                     "'eso.yaw_input_gain_scale'",
    'max_input_age': "the MPC holds a tick on inputs older than 'safety.max_estimate_age' "
                     "(the mixer bridges) and is INPUT_INVALID past 'safety.bridge_time' more",
}

_BASE = (('', ControllerNodeParams),)

#: executable -> the (prefix, dataclass) groups it declares, in declaration order.
NODES: dict[str, tuple[tuple[str, type], ...]] = {
    'reference': (*_BASE, ('reference', ReferenceParams), ('rates', RatesParams),
                  ('', ReferenceNodeParams), ('trajectory_generator', ObstacleRefusalParams)),
    'eso': (*_BASE, ('eso', EsoParams), ('position', PositionParams),
            ('model', ModelParams), ('mixer', WheelTorqueLimit), ('', EsoNodeParams),
            ('', WheelJoints),
            ('', WheelSigns), ('', ImuMounting), ('datum', DatumParams)),
    'trajectory_generator': (*_BASE, ('trajectory_generator', TrajectoryGeneratorParams)),
    'arc': (*_BASE, ('arc', ArcParams), ('rates', RatesParams), ('model', ModelParams),
            ('eso', YawInputGainScale)),
    'mpc': (*_BASE, ('mpc', MpcParams), ('model', ModelParams), ('mixer', WheelTorqueLimit),
            ('rates', RatesParams), ('safety', SafetyRideThrough)),
    'torque_mixer': (*_BASE, ('mixer', MixerParams), ('rates', RatesParams),
                     ('mpc', MpcPeriod), ('safety', SafetyParams), ('', MixerNodeParams),
                     ('', WheelJoints), ('', EffortCommand), ('', WheelSigns),
                     ('wiring_check', WiringCheckParams), ('model', ModelParams),
                     ('', ImuMounting), ('runaway', RunawayParams)),
}
