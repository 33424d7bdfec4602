"""Parameters of the viewer and Foxglove bridge nodes, and the registry of both.

Declared like every node parameter (:func:`wip_runtime.config.param`); no rclpy import,
so the parameter reference is generated from :data:`NODES`.
"""

from __future__ import annotations

import dataclasses

from wip_description.params import ModelParams
from wip_description.sensors import SensorParams
from wip_description.wiring import WheelJoints, WheelSigns
from wip_runtime.config import like, param, TEXT

from .viewer_core import ViewerParams

DEFAULT_PORT = 8765


@dataclasses.dataclass(frozen=True)
class FoxgloveParams:
    """Parameters of the ``foxglove_bridge`` node."""

    host: str = param('127.0.0.1', TEXT, 'address to serve on (127.0.0.1: this machine only)')
    port: int = param(DEFAULT_PORT, '1', 'TCP port of the WebSocket server; 0: any free port',
                      minimum=0, maximum=65535)
    topics: tuple[str, ...] = param((), TEXT, 'topics to offer; empty: every topic')
    discovery_period: float = param(0.5, 's', 'wall period of the graph polling for new '
                                    'topics', minimum=0.01, maximum=60.0)


@dataclasses.dataclass(frozen=True)
class EncoderMounting:
    """Where the wheel encoders sit: decides the wheels' parent link in the robot model."""

    encoders_relative_to_body: bool = like(SensorParams, 'encoders_relative_to_body')


#: The robot model's parameters (``viewer.robot_model``), named as the controllers' are, so
#: that a params file's ``/**:`` section describes the base to both.
ROBOT_MODEL_GROUPS = (('model', ModelParams), ('', WheelJoints), ('', WheelSigns),
                      ('', EncoderMounting))

#: executable -> the (prefix, dataclass) groups it declares.
NODES: dict[str, tuple[tuple[str, type], ...]] = {
    'viewer': (('viewer', ViewerParams), *ROBOT_MODEL_GROUPS),
    'foxglove_bridge': (('', FoxgloveParams),),
}
