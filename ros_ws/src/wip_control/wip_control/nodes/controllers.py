"""The six controller nodes in one process: ``ros2 run wip_control controllers``.

ROS 2 composition for rclpy: reference, eso, trajectory_generator, arc, mpc and
torque_mixer keep their names, parameters (``--ros-args --params-file`` sections by node
name), topics and /diagnostics, exactly as when each runs on its own with ``ros2 run``,
but share one process, one rclpy context and one executor. A control tick then wakes one
process instead of six; ``scripts/run_graph --layout composed`` and hardware mode use it
(docs/realtime.md: CPU and latency of both layouts, measured). Do not pass
``-r __node:=NAME`` here: it would rename all six.
"""

from __future__ import annotations

import sys

from .arc_node import ArcNode
from wip_runtime.node_main import run_nodes
from .eso_node import EsoNode
from .mpc_node import MpcNode
from .reference_node import ReferenceNode
from .torque_mixer_node import TorqueMixerNode
from .trajectory_generator_node import TrajectoryGeneratorNode

#: Node classes in the order of the control chain (the executor serves them all).
NODE_CLASSES = (ReferenceNode, EsoNode, TrajectoryGeneratorNode, ArcNode, MpcNode,
                TorqueMixerNode)


def main(args=None) -> int:
    """Entry point ``controllers``: on SIGINT/SIGTERM the mixer sends a last zero command."""
    return run_nodes([(cls, TorqueMixerNode.send_stop_command if cls is TorqueMixerNode
                       else None) for cls in NODE_CLASSES], 'controllers', args)


if __name__ == '__main__':
    sys.exit(main())
