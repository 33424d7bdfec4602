"""``scripts/estop``: engage, release or reset the e-stop of a running graph, without ros2cli.

Light on purpose: only rclpy and ``wip_bringup.ros_env`` are imported (no numpy, no node
code), since the start-up of this command is part of the e-stop's latency
(docs/real-base.md, "E-stop").
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from typing import TYPE_CHECKING

from wip_runtime.cli import add_exit_codes

if TYPE_CHECKING:
    from .ros_env import RosNetwork

ACTIONS = ('engage', 'release', 'reset')
#: Longest wait for the acknowledgement of a publication [s].
ACK_WAIT = 1.0
#: Copies of an engage sent after the first, 0.05 s apart.
ENGAGE_COPIES = 3

DESCRIPTION = """\
Engage, release or reset the e-stop of a running graph (no ros2cli needed). engage and
release publish /wip/estop (true: the mixer latches zero torque; false: the button
released) once the mixer's own subscription has matched; reset calls the mixer's
~/reset_estop, which refuses while /wip/estop says true or said it within
safety.estop_hold_time.

The ROS network is yours, as in hardware mode ($ROS_DOMAIN_ID and
$ROS_AUTOMATIC_DISCOVERY_RANGE as you set them, ROS's defaults where you did not);
--domain overrides the domain. Latency and a faster, persistent e-stop:
docs/real-base.md (E-stop)."""

EPILOG = """\
Examples
  scripts/estop engage                  # /wip/estop = true: the mixer latches zero torque
  scripts/estop release                 # /wip/estop = false (the button released)
  scripts/estop reset                   # /torque_mixer/reset_estop: its answer is printed
  scripts/estop engage --domain 42      # a simulation's private domain (run_graph prints it)

Exit status: 0 done (reset: the mixer said success); 1 refused, or nothing answered in
--timeout seconds; 2 bad arguments; 130 Ctrl-C."""


@dataclasses.dataclass(frozen=True)
class Target:
    """Where the command goes: the domain, the network, the mixer and its e-stop topic."""

    domain: int
    network: RosNetwork
    mixer: str
    topic: str


def process_age() -> float:
    """Seconds since this process started (its start-up included); NaN without /proc."""
    try:
        with open('/proc/self/stat', encoding='ascii') as stream:
            start_ticks = int(stream.read().rsplit(')', 1)[1].split()[19])
        return (time.clock_gettime(time.CLOCK_BOOTTIME)
                - start_ticks / os.sysconf('SC_CLK_TCK'))
    except (OSError, ValueError, IndexError, AttributeError):
        return math.nan


def build_parser() -> argparse.ArgumentParser:
    """``scripts/estop``'s options."""
    parser = argparse.ArgumentParser(prog='scripts/estop', description=DESCRIPTION,
                                     epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('action', choices=ACTIONS)
    parser.add_argument('--domain', type=int, default=None, metavar='ID',
                        help='ROS_DOMAIN_ID of the graph (default: yours, as hardware mode '
                        'uses it: $ROS_DOMAIN_ID if you set it, else 0)')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help="the vehicle's namespace (run_graph --namespace NS): NS/wip/estop"
                        ' and NS/torque_mixer')
    parser.add_argument('--mixer', default=None, metavar='NODE',
                        help='the mixer node (reset calls NODE/reset_estop; default '
                        'NS/torque_mixer)')
    parser.add_argument('--timeout', type=float, default=10.0, metavar='S',
                        help='longest wait for the mixer [s] (default 10)')
    add_exit_codes(parser)
    return parser


def target(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Target:
    """Return where the command goes; a usage error (exit 2) if an argument is bad."""
    # Not wip_bringup.launcher nor the nodes' modules (numpy, scipy: a few tenths of a
    # second of start-up, part of the e-stop's latency).
    from wip_runtime.dds_profile import use_node_profile
    from .ros_env import GraphError, parse_namespace, use_user_ros_environment
    try:
        network = use_user_ros_environment()
    except GraphError as err:
        parser.error(str(err))
    domain = network.domain_id if args.domain is None else args.domain
    if not 0 <= domain <= 232:
        parser.error(f'--domain: {domain} is not in 0..232')
    if not args.timeout > 0:
        parser.error('--timeout: must be > 0')
    try:
        namespace = parse_namespace(args.namespace)
    except GraphError as err:
        parser.error(str(err))
    # The graph's Fast DDS profile where the user has none (reliable repairs in
    # milliseconds; wip_bringup.processes.graph_environment).
    use_node_profile(os.environ)
    return Target(domain, network, args.mixer or f'{namespace}/torque_mixer',
                  f'{namespace}/wip/estop')


def publish_estop(node, executor, to: Target, engage: bool, deadline: float,
                  timeout: float, node_ready_after: float) -> int:
    """Engage or release: wait for the mixer's subscription, publish, wait for delivery."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Bool
    # The mixer's subscription: reliable, volatile (wip_runtime.qos).
    publisher = node.create_publisher(
        Bool, to.topic, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    mixer_namespace, _, mixer_name = to.mixer.rpartition('/')

    def mixer_matched() -> bool:
        # The mixer's own subscription, not any (a recorder's also matches).
        return publisher.get_subscription_count() > 0 and any(
            info.node_name == mixer_name
            and info.node_namespace == (mixer_namespace or '/')
            for info in node.get_subscriptions_info_by_topic(to.topic))

    while not mixer_matched():
        if time.monotonic() > deadline:
            print(f'estop: {to.mixer} does not subscribe to {to.topic} in domain {to.domain} '
                  f'(discovery range {to.network.discovery_range}) after '
                  f'{timeout:g} s: is the graph running there?', file=sys.stderr)
            return 1
        executor.spin_once(timeout_sec=0.02)
    matched_after = process_age()
    message = Bool(data=engage)
    publisher.publish(message)
    # The reliable delivery to every matched reader (a reader of a process that
    # died without saying so never acknowledges: not waited for past ACK_WAIT).
    publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=ACK_WAIT))
    if message.data:
        # Again, in case the mixer's side matched only after the first copy (DDS
        # matches each side on its own): an engaged e-stop latches, copies are free.
        for _ in range(ENGAGE_COPIES):
            executor.spin_once(timeout_sec=0.05)
            publisher.publish(message)
        publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=ACK_WAIT))
    print(f'estop: {to.topic} = {str(engage).lower()} published '
          f'(domain {to.domain}; {node_ready_after:.2f} s after this command started '
          f'its node was up, {matched_after:.2f} s {to.mixer} matched)')
    return 0


def call_reset(node, executor, to: Target, deadline: float, timeout: float) -> int:
    """Reset: call the mixer's ``~/reset_estop`` and print its answer."""
    from std_srvs.srv import Trigger
    client = node.create_client(Trigger, f'{to.mixer.rstrip("/")}/reset_estop')
    while not client.service_is_ready():
        if time.monotonic() > deadline:
            print(f'estop: {client.srv_name} is not available in domain {to.domain} after '
                  f'{timeout:g} s', file=sys.stderr)
            return 1
        executor.spin_once(timeout_sec=0.05)
    future = client.call_async(Trigger.Request())
    while not future.done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    if not future.done():
        print(f'estop: {client.srv_name} did not answer in {timeout:g} s',
              file=sys.stderr)
        return 1
    response = future.result()
    print(f'estop: reset {"done" if response.success else "refused"}: {response.message}')
    return 0 if response.success else 1


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    to = target(parser, args)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=to.domain, args=[])
    node = rclpy.create_node('estop_front_door', context=context,
                             start_parameter_services=False, enable_rosout=False)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node_ready_after = process_age()
    deadline = time.monotonic() + args.timeout
    try:
        if args.action in ('engage', 'release'):
            return publish_estop(node, executor, to, args.action == 'engage', deadline,
                                 args.timeout, node_ready_after)
        return call_reset(node, executor, to, deadline, args.timeout)
    except KeyboardInterrupt:
        return 130
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


if __name__ == '__main__':
    from wip_runtime.cli import exit_with
    exit_with(main, 'estop')
