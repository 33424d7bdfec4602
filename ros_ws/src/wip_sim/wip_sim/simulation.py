"""The plant and the six controller nodes in one process: ``ros2 run wip_sim simulation``.

ROS 2 composition of a whole simulation (``scripts/run_graph --layout single``): the plant
(:mod:`wip_sim.plant_node`) and reference, eso, trajectory_generator, arc, mpc and
torque_mixer keep their names, parameters (params-file sections by node name), topics and
/diagnostics, and share one process and one executor. A lockstep tick then crosses no
process boundary: the controllers hand their messages to each other directly
(``wip_control.nodes.intra_process``), and the plant's topics go through DDS within the
process, without a transport or a thread switch. It ends when the plant does, with its
exit status. Measured (docs/realtime.md): the fastest lockstep layout.
"""

from __future__ import annotations

import sys

from wip_control.nodes.common import run_simulator_node
from wip_control.nodes.controllers import NODE_CLASSES

from .plant_node import EXIT_CONFIG, PlantNode


def main(args=None) -> int:
    """Entry point ``simulation``."""
    return run_simulator_node(PlantNode, 'simulation', args, config_status=EXIT_CONFIG,
                              on_end=PlantNode.publish_diagnostics, companions=NODE_CLASSES)


if __name__ == '__main__':
    sys.exit(main())
