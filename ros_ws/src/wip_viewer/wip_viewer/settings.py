"""Parameters of the viewer and Foxglove bridge nodes, and the registry of both.

Declared like every node parameter (:mod:`wip_control.nodes.settings`); no rclpy import,
so the parameter reference is generated from :data:`NODES`.
"""

from __future__ import annotations

import dataclasses

from wip_control.core.config import param
from wip_control.nodes.settings import TEXT

from .viewer_core import ViewerConfig

DEFAULT_PORT = 8765


@dataclasses.dataclass(frozen=True)
class FoxgloveSettings:
    """Parameters of the ``foxglove_bridge`` node."""

    host: str = param('127.0.0.1', TEXT, 'address to serve on (127.0.0.1: this machine only)')
    port: int = param(DEFAULT_PORT, '1', 'TCP port of the WebSocket server; 0: any free port',
                      minimum=0, maximum=65535)
    topics: tuple[str, ...] = param((), TEXT, 'topics to offer; empty: every topic')
    discovery_period: float = param(0.5, 's', 'wall period of the graph polling for new '
                                    'topics', minimum=0.01, maximum=60.0)


#: executable -> the (prefix, dataclass) groups it declares.
NODES: dict[str, tuple[tuple[str, type], ...]] = {
    'viewer': (('viewer', ViewerConfig),),
    'foxglove_bridge': (('', FoxgloveSettings),),
}
