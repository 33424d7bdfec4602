"""Hardware mode of ``scripts/run_graph``: the controller nodes alone, against a real base.

Its options (:func:`add_arguments`, also ``scripts/run_graph``'s) and its command line; the
run is :mod:`wip_bringup.hardware_runner`. What it does, step by step: docs/run_graph.md.
"""

from __future__ import annotations

import argparse
import sys

from wip_runtime.cli import add_exit_codes, bounded

from .hardware_outcome import format_result
from .hardware_runner import HardwareOptions, run_hardware
from .launcher import LAYOUTS
from .run_result import print_result
from .run_stop import stop_signals
from .runner_base import options_from_args
from .scheduling import parse_cpus
from .view_options import add_view_arguments

DESCRIPTION = """\
The controller nodes alone, in real time, against a real base's topics (hardware mode of
scripts/run_graph): the scenario's controller sections, your --params-file files (the
base's joint names, wheel signs, IMU mounting, datum) and --remap rules applied to every
node. The controllers engage once every node is up and the /wip/heartbeat this process
publishes has started (--arm-delay); at the stop the base gets zero effort commands.

It uses your ROS network settings (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE,
ROS_STATIC_PEERS; ROS's defaults where unset). Outputs in --out: params.yaml,
scenario.yaml, logs/, run.json (safety events, node rates). What it does, step by step:
docs/run_graph.md."""

EPILOG = """\
Examples
  scripts/run_graph --mode hardware --params-file my_base.yaml
  scripts/run_graph --no-plant --scenario line.yaml --params-file my_base.yaml \\
      --remap /joint_states:=/base/joint_states --remap /imu/data:=/base/imu \\
      --record out/robot/bag --duration 60

Exit status: 0 the controllers engaged and the run ended without a safety fault (stopped
by SIGINT, SIGTERM or SIGHUP, by an e-stop of yours, or at the end of --duration); 1 the
vehicle fell or the safety layer went to FAULT after engaging (the message gives the
mixer's reason); 5 the controllers never engaged (no inputs from the base, or the estimate
never settled: the message gives the mixer's last reason); 2 bad arguments or outputs
(also: another run holds --out or the bag); 3 a node failed or the nodes did not come up
in time; 4 the disk filled up (an output could not be written)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the hardware-mode options of ``scripts/run_graph``."""
    parser.add_argument('--params-file', action='append', default=[], metavar='FILE',
                        dest='params_files',
                        help='hardware mode: extra ROS params file for every node, after the '
                             "scenario's (repeatable; later wins): the base's joint names, "
                             'wheel signs, IMU mounting, datum...')
    parser.add_argument('--remap', action='append', default=[], metavar='FROM:=TO',
                        dest='remaps',
                        help='hardware mode: topic remapping applied to every node '
                             '(repeatable), e.g. /imu/data:=/base/imu')
    parser.add_argument('--arm-delay', type=bounded(float, 0.0, 3600.0), default=2.0,
                        metavar='S',
                        help='hardware mode: seconds after every node is up before the '
                             '/wip/heartbeat starts and the controllers may engage')
    parser.add_argument('--layout', choices=LAYOUTS, default=None,
                        help='controller processes: separate (one per node, as six ros2 '
                        'run), composed (the six nodes in one process, one executor: '
                        'ros2 run wip_control controllers) or, simulation only, single '
                        '(the plant too: ros2 run wip_sim simulation); default: '
                        f'{HardwareOptions.layout}, and single for a recorded lockstep '
                        'simulation (the fastest with every topic; docs/realtime.md)')
    parser.add_argument('--rt-priority', type=bounded(int, 0, 99), default=0, metavar='N',
                        help='run the controller processes with SCHED_FIFO priority N '
                        '(1..99; default 0: the normal policy), set once every node is up; '
                        'needs root or CAP_SYS_NICE')
    parser.add_argument('--cpu-affinity', type=_cpus_argument, default=(), metavar='LIST',
                        help='pin the controller processes to these CPUs, e.g. 1 or 0,1')
    parser.add_argument('--cpu-latency', type=bounded(int, 0, 1_000_000), default=None,
                        metavar='US',
                        help='while the controllers run, ask the kernel (PM QoS, '
                        '/dev/cpu_dma_latency, machine-wide) that idle CPUs wake within US '
                        'microseconds; 0 keeps them polling instead of sleeping: less CPU '
                        'and latency for the controllers, more power (docs/realtime.md); '
                        'needs root')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run every node and topic under this ROS namespace (e.g. '
                        'robot1: /robot1/cmd_vel, frames robot1/odom, robot1/base_link); '
                        'two vehicles in one domain (docs/driving.md)')
    parser.add_argument('--no-heartbeat', action='store_true',
                        help='hardware mode: no /wip/heartbeat (and no arm delay): '
                             'the mixer engages as soon as its inputs are ready')


def _cpus_argument(text: str) -> tuple[int, ...]:
    try:
        return parse_cpus(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def build_parser() -> argparse.ArgumentParser:
    """``python -m wip_bringup.hardware``'s options (``scripts/run_graph --mode hardware``)."""
    parser = argparse.ArgumentParser(
        prog='scripts/run_graph --mode hardware', description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', help='scenario YAML (its controller sections)')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='stop after this long [s of wall time] (default: Ctrl-C)')
    parser.add_argument('--out', default='out/hardware', metavar='DIR',
                        help='run directory (default out/hardware)')
    parser.add_argument('--record', metavar='DIR', help='record into this rosbag2 directory')
    parser.add_argument('--discovery-timeout', type=float, default=60.0, metavar='S')
    parser.add_argument('--quiet', action='store_true')
    add_view_arguments(parser)
    add_arguments(parser)
    add_exit_codes(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_from_args(args)


def run_from_args(args: argparse.Namespace) -> int:
    """Run hardware mode from parsed arguments (also used by ``wip_bringup.graph``)."""
    options = HardwareOptions(**options_from_args(
        args, params_files=list(args.params_files), remaps=list(args.remaps), out=args.out,
        arm_delay=args.arm_delay, heartbeat=not args.no_heartbeat,
        layout=args.layout or HardwareOptions.layout))
    with stop_signals():   # SIGTERM, SIGHUP stop the run as Ctrl-C does
        result = run_hardware(options)
    return print_result(result, format_result)


if __name__ == '__main__':
    sys.exit(main())
