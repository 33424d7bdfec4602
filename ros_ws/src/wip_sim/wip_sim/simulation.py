"""The plant and the six controller nodes in one process: ``ros2 run wip_sim simulation``.

ROS 2 composition of a whole simulation (``scripts/run_graph --layout single``): the plant
(:mod:`wip_sim.plant_node`) and reference, eso, trajectory_generator, arc, mpc and
torque_mixer keep their names, parameters (params-file sections by node name), topics and
/diagnostics, and share one process and one executor. A lockstep tick then crosses no
process boundary: the controllers hand their messages to each other directly
(``wip_runtime.intra_process``), and the plant's topics go through DDS within the
process, without a transport or a thread switch. It ends when the plant does, with its
exit status. Measured (docs/realtime.md): the fastest lockstep layout.

``--with-viewer`` (before ``--ros-args``) adds the viewer node (``wip_viewer.viewer_node``,
its name and ``viewer`` parameters as alone): its 200 Hz inputs then come from the
intra-process bus, none lost and none taken from DDS, and only its few outputs go to DDS
(run_graph does this for a recorded run in the single layout:
docs/decisions/recording-speed.md).
"""

from __future__ import annotations

import functools
import sys

from wip_sim.simulator_main import run_simulator_node
from wip_control.nodes.controllers import NODE_CLASSES
from wip_runtime.cli import split_ros_args

from .plant_node import EXIT_CONFIG, PlantNode
from .settings import WITH_VIEWER


def main(args=None) -> int:
    """Entry point ``simulation``."""
    argv = list(sys.argv if args is None else args)
    own, ros_args = split_ros_args(argv[1:])
    companions = tuple(NODE_CLASSES)
    if WITH_VIEWER in own:
        own.remove(WITH_VIEWER)
        argv = [*argv[:1], *own, *ros_args]
        from wip_viewer.viewer_node import ViewerNode   # only then: rendering imports
        # A simulation's viewer feeds a recording: its writers keep what is not acknowledged.
        companions += (functools.partial(ViewerNode, keep_unacknowledged=True),)
    return run_simulator_node(PlantNode, 'simulation', argv, config_status=EXIT_CONFIG,
                              on_end=PlantNode.publish_diagnostics, companions=companions)


if __name__ == '__main__':
    sys.exit(main())
