"""What the bring-up modes share about the graph's processes: exit codes, layouts, names.

Simulation (:mod:`wip_bringup.graph`) and hardware mode (:mod:`wip_bringup.hardware`) start the
same executables the way ``ros2 run`` does (:mod:`wip_bringup.processes`), with real-time
scheduling (:mod:`wip_bringup.scheduling`), in a DDS domain of their own, watch them through a
probe node (:mod:`wip_bringup.probe`), and stop them the same way; their outputs are locked
(:mod:`wip_bringup.output_lock`). Both modes import these modules; neither imports the other's
internals.
"""

from __future__ import annotations

from wip_runtime.cli import EXIT_DISK_FULL as CLI_EXIT_DISK_FULL
from wip_runtime.cli import EXIT_NOT_ENGAGED as CLI_EXIT_NOT_ENGAGED
from wip_viewer.viewer_core import MODEL_TOPICS, VIEWER_TOPICS as VIEWER_TOPIC_TYPES

from .ros_env import (GraphError, parse_namespace, ROS_DEFAULTS_VARIABLE,  # noqa: F401
                      ros_network, RosNetwork, use_user_ros_environment)


# The exit-code table of every tool (wip_runtime.cli): 0 ok, 1 the vehicle fell (or a
# safety fault while engaged), 2 usage or input error, 3 internal error (a node crashed, the
# graph stalled), 4 disk full, 5 the controllers never engaged, 130 Ctrl-C (143 SIGTERM,
# 129 SIGHUP: 128 + the signal, run_stop.STOP_SIGNALS).
EXIT_OK, EXIT_FELL, EXIT_USAGE, EXIT_FAILED = 0, 1, 2, 3
EXIT_TIMEOUT = EXIT_FAILED
EXIT_INTERRUPTED = 130
#: The disk (or a quota) filled up: recording stopped and what fit was finalised.
EXIT_DISK_FULL = CLI_EXIT_DISK_FULL
#: The controllers never engaged (hardware mode, a real-time simulation).
EXIT_NOT_ENGAGED = CLI_EXIT_NOT_ENGAGED
#: Published by the viewer node (standard messages for 3-D viewers; nothing in the
#: control loop subscribes to them).
VIEWER_TOPICS = tuple(VIEWER_TOPIC_TYPES) + tuple(MODEL_TOPICS)

#: Process layouts of the controller nodes: 'separate' (one process per node, as six
#: `ros2 run`), 'composed' (the six nodes in one process, `ros2 run wip_control
#: controllers`, one executor) or, in simulation only, 'single' (the plant too: `ros2 run
#: wip_sim simulation`). Same nodes, names, parameters and topics in every layout.
LAYOUTS = ('separate', 'composed', 'single')
#: The layouts with a process of their own for the plant, and so those of hardware mode.
CONTROLLER_LAYOUTS = ('separate', 'composed')
#: Processes that hold several nodes, each keeping its own name.
MULTI_NODE_PROCESSES = ('controllers', 'simulation')

#: Executable of each node: (package, executable).
EXECUTABLES = {
    'reference': ('wip_control', 'reference'),
    'eso': ('wip_control', 'eso'),
    'trajectory_generator': ('wip_control', 'trajectory_generator'),
    'arc': ('wip_control', 'arc'),
    'mpc': ('wip_control', 'mpc'),
    'torque_mixer': ('wip_control', 'torque_mixer'),
    'controllers': ('wip_control', 'controllers'),
    'simulation': ('wip_sim', 'simulation'),
    'plant': ('wip_sim', 'plant'),
    'recorder': ('wip_bag', 'recorder'),
    'viewer': ('wip_viewer', 'viewer'),
    'foxglove_bridge': ('wip_viewer', 'foxglove_bridge'),
}


#: Topics that stay global under a namespace: the diagnostic aggregator listens on
#: /diagnostics (statuses carry the node's full name, namespace included), and a
#: simulation's /clock is the time of every node of its ROS domain; /tf and /tf_static are
#: every robot's (tf's convention: the frames carry the robot's prefix).
GLOBAL_TOPICS = ('/diagnostics', '/clock', '/rosout', '/parameter_events', '/tf',
                 '/tf_static')
#: The run's inputs from outside the graph, recorded with --record: the references (a
#: teleop's /cmd_vel, a planner's /plan) and the e-stop (button, reset topic, the
#: supervisor's heartbeat). A reset through the mixer's service is no topic: the mixer's
#: /diagnostics (recorded) show its effect.
INPUT_TOPICS = ('/cmd_vel', '/plan', '/wip/estop', '/wip/estop_reset', '/wip/heartbeat')


def in_namespace(topic: str, namespace: str) -> str:
    """Return the name a node of ``namespace`` gives its topic ``topic``.

    ``topic`` is written absolute, as in the graph's tables; the nodes use relative names,
    so it resolves under their namespace. :data:`GLOBAL_TOPICS` stay as they are.
    """
    if not namespace or topic in GLOBAL_TOPICS:
        return topic
    return namespace + '/' + topic.lstrip('/')


PROBE_PERIOD = 0.5  # [s] wall: process polling and probe spinning
GRACE_PERIOD = 5.0  # [s] after SIGINT before SIGKILL (controllers)
RECORDER_GRACE_PERIOD = 60.0  # [s] the recorder writes the rest of its queue first
