"""``scripts/estop``: engage, release or reset the e-stop of a running graph, without ros2cli.

Examples
--------
    scripts/estop engage --domain 42      # /wip/estop = true: the mixer latches zero torque
    scripts/estop release --domain 42     # /wip/estop = false (the button released)
    scripts/estop reset --domain 42       # /torque_mixer/reset_estop: its answer is printed

The DDS domain is ``--domain``, else ``$ROS_DOMAIN_ID`` (``scripts/run_graph`` prints the
one it uses). ``engage`` and ``release`` wait until the mixer's /wip/estop subscription
has matched (a message published before the match would be lost), publish, and wait for
the reliable delivery. ``reset`` calls the mixer's ``~/reset_estop`` (std_srvs/Trigger),
which refuses while /wip/estop still says true.

Exit status (the tools' table, ``wip_control.tools.cli``): 0 done (reset: the mixer said
success); 1 refused, or nothing answered in ``--timeout`` seconds; 2 bad arguments; 130
Ctrl-C.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from wip_control.tools.cli import add_exit_codes

ACTIONS = ('engage', 'release', 'reset')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='scripts/estop', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('action', choices=ACTIONS)
    parser.add_argument('--domain', type=int, default=None, metavar='ID',
                        help='ROS_DOMAIN_ID of the graph (default: $ROS_DOMAIN_ID)')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help="the vehicle's namespace (run_graph --namespace NS): NS/wip/estop"
                        ' and NS/torque_mixer')
    parser.add_argument('--mixer', default=None, metavar='NODE',
                        help='the mixer node (reset calls NODE/reset_estop; default '
                        'NS/torque_mixer)')
    parser.add_argument('--timeout', type=float, default=10.0, metavar='S',
                        help='longest wait for the mixer [s] (default 10)')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    domain = args.domain
    if domain is None:
        text = os.environ.get('ROS_DOMAIN_ID', '').strip()
        if not text:
            parser.error('no --domain and no $ROS_DOMAIN_ID: give the domain that '
                         'scripts/run_graph printed')
        try:
            domain = int(text)
        except ValueError:
            parser.error(f'ROS_DOMAIN_ID={text!r} is not an integer')
    if not 0 <= domain <= 232:
        parser.error(f'--domain: {domain} is not in 0..232')
    if not args.timeout > 0:
        parser.error('--timeout: must be > 0')
    from .launcher import GraphError, parse_namespace
    try:
        namespace = parse_namespace(args.namespace)
    except GraphError as err:
        parser.error(str(err))
    mixer = args.mixer or f'{namespace}/torque_mixer'
    topic = f'{namespace}/wip/estop'

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Bool
    from std_srvs.srv import Trigger

    from wip_control.nodes.common import RELIABLE_QOS

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain, args=[])
    node = rclpy.create_node('estop_front_door', context=context,
                             start_parameter_services=False)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    deadline = time.monotonic() + args.timeout
    try:
        if args.action in ('engage', 'release'):
            publisher = node.create_publisher(Bool, topic, RELIABLE_QOS)
            while publisher.get_subscription_count() == 0:
                if time.monotonic() > deadline:
                    print(f'estop: nothing subscribes to {topic} in domain {domain} after '
                          f'{args.timeout:g} s: is the graph running there?', file=sys.stderr)
                    return 1
                executor.spin_once(timeout_sec=0.05)
            publisher.publish(Bool(data=args.action == 'engage'))
            publisher.wait_for_all_acked(rclpy.duration.Duration(
                seconds=max(0.1, deadline - time.monotonic())))
            print(f'estop: {topic} = {str(args.action == "engage").lower()} published '
                  f'(domain {domain})')
            return 0
        client = node.create_client(Trigger, f'{mixer.rstrip("/")}/reset_estop')
        while not client.service_is_ready():
            if time.monotonic() > deadline:
                print(f'estop: {client.srv_name} is not available in domain {domain} after '
                      f'{args.timeout:g} s', file=sys.stderr)
                return 1
            executor.spin_once(timeout_sec=0.05)
        future = client.call_async(Trigger.Request())
        while not future.done() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        if not future.done():
            print(f'estop: {client.srv_name} did not answer in {args.timeout:g} s',
                  file=sys.stderr)
            return 1
        response = future.result()
        print(f'estop: reset {"done" if response.success else "refused"}: {response.message}')
        return 0 if response.success else 1
    except KeyboardInterrupt:
        return 130
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


if __name__ == '__main__':
    from wip_control.tools.cli import exit_with
    exit_with(main, 'estop')
