"""The ``main`` of a node process: rclpy's start, the stop signals, the nodes' spin, the end."""

from __future__ import annotations

import signal
import sys
import time
from typing import Callable, Sequence

import rclpy
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .cli import answer_node_help, EXIT_USAGE
from .composition import compose
from .config import ParamError
from .executors import make_executor, spin_composed
from .launched import end_with_launcher

#: The signals that asked the process to stop since :func:`take_over_stop_signals`.
stop_requests: list[int] = []


def request_stop(signum, frame) -> None:
    """Note a stop signal; the spin loop, which returns to Python regularly, checks it."""
    # Only a flag: raising here (KeyboardInterrupt) would land inside whatever callback is
    # running, which rclpy's executor then logs as FATAL with a stack on a normal Ctrl-C.
    stop_requests.append(signum)


def take_over_stop_signals() -> None:
    """From now on SIGINT and SIGTERM only append to :data:`stop_requests`."""
    stop_requests.clear()
    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)


def ignore_stop_signals() -> None:
    """Ignore SIGINT and SIGTERM: a second signal must not cut the clean-up short."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def init_rclpy(program: str, args, signal_handler_options) -> bool:
    """``rclpy.init``; False after one line on stderr when rcl refuses the ROS arguments.

    The ROS arguments are those of the command line; rcl refuses, for example, a remap rule
    to an invalid name or a malformed ``-p``. No traceback is printed.
    """
    try:
        rclpy.init(args=args, signal_handler_options=signal_handler_options)
    except _rclpy_impl.RCLError as err:
        reason = str(err).split(', at /', 1)[0]   # rcl's source location is no help here
        print(f'{program}: error: bad ROS arguments: {reason}', file=sys.stderr)
        return False
    return True


def package_of(factory) -> str:
    """Return the ROS package of a node class (its top-level Python package)."""
    return str(getattr(factory, '__module__', 'wip_control')).split('.')[0]


def run_node(node_factory: Callable[[], Node], program: str, args=None,
             on_stop: Callable[[Node], None] | None = None) -> int:
    """Jazzy ``main`` of one node: :func:`run_nodes` with a single node."""
    return run_nodes([(node_factory, on_stop)], program, args)


def run_nodes(nodes: Sequence[tuple[Callable[[], Node], Callable[[Node], None] | None]],
              program: str, args=None) -> int:
    """Jazzy ``main``: init, build the nodes, spin them until shutdown, clean up.

    The nodes spin in one executor. Return the exit status.

    ``nodes``: (factory, on_stop) pairs. Several nodes in one process is ROS 2
    composition done by hand (rclpy has no component container): each node keeps its
    name, parameters (the ``--params-file`` sections by node name) and topics; they share
    one context and one executor, so a control tick costs one process wake-up instead of
    one per node (docs/realtime.md has the measurements).

    A configuration error (a parameter out of range, of the wrong type, an unknown choice)
    makes the process refuse to start: the message, which names the parameter, goes to
    stderr and the status is 2 (EXIT_USAGE: the tools' table, :mod:`.cli`).

    ``on_stop(node)`` runs on SIGINT/SIGTERM before the node is destroyed, with the
    context still valid so that it can publish (the mixer's last zero command). rclpy's
    own signal handler shuts the context down before any ``finally`` runs, so when a node
    has ``on_stop`` the process takes SIGINT and SIGTERM over itself (they set a flag
    that the spin loop, which returns to Python every :data:`.executors.SPIN_TIMEOUT`, checks:
    raising from the handler would land inside a callback, which rclpy's executor
    logs as FATAL with a stack).

    The nodes are composed by :func:`.composition.compose` (one sim clock; messages between
    them skip DDS while no one outside the process subscribes; ``gc.freeze`` after start-up)
    and spun by :func:`.executors.spin_composed`, as ``wip_sim``'s simulator nodes are.
    """
    if answer_node_help(program, package_of(nodes[0][0]), args):
        return 0
    end_with_launcher()
    handles_signals = any(on_stop is not None for _, on_stop in nodes)
    if not init_rclpy(program, args, SignalHandlerOptions.NO if handles_signals
                      else SignalHandlerOptions.ALL):
        return EXIT_USAGE
    if handles_signals:
        take_over_stop_signals()
    built_nodes: list[Node] = []
    status = 0
    stopping = False
    try:
        executor = make_executor()
        bus = compose(executor, [factory for factory, _ in nodes], built_nodes)
        first = built_nodes[0]
        first.get_logger().debug(f'executor: {type(executor).__name__}')
        spin_composed(executor, first, bus, lambda: not stop_requests)
        stopping = bool(stop_requests)
    except (KeyboardInterrupt, ExternalShutdownException):
        stopping = True
    except (ParamError, ParameterException) as err:
        print(f'{program}: error: {err}', file=sys.stderr)
        status = EXIT_USAGE
    finally:
        built = list(zip(built_nodes, [on_stop for _, on_stop in nodes]))
        if handles_signals and stopping and rclpy.ok():
            _stop_nodes(program, built)
        for node, _ in built:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


def _stop_nodes(program: str,
                built: Sequence[tuple[Node, Callable[[Node], None] | None]]) -> None:
    """Run each node's ``on_stop``, with the context still up; report what fails."""
    ignore_stop_signals()   # a second signal must not skip the destruction that follows
    for node, on_stop in built:
        if on_stop is None:
            continue
        try:
            on_stop(node)
        except Exception as err:  # noqa: BLE001 - report, then clean up anyway
            print(f'{program}: stopping: {type(err).__name__}: {err}', file=sys.stderr)


#: [s] a simulator that ends by itself waits this long at most for its readers'
#: acknowledgements (:func:`wait_for_acknowledgements`).
ACK_TIMEOUT = 10.0
#: [s] the same wait after a stop signal: shorter, since whoever stops the run waits for it.
STOP_ACK_TIMEOUT = 3.0


def wait_for_acknowledgements(nodes: Sequence[Node], timeout: float = ACK_TIMEOUT
                              ) -> list[str]:
    """Wait until every reliable reader has acknowledged every sample.

    The readers are those of the nodes' publishers, and the wait lasts at most ``timeout``
    in all. Return the topics of the readers that had not acknowledged; the log names them
    too.

    A reliable writer's unacknowledged samples die with its process: a simulator that
    exits right after its last sample can leave a recorder without it.
    """
    deadline = time.monotonic() + timeout
    late = []
    for node in nodes:
        for publisher in node.publishers:
            left = max(0.0, deadline - time.monotonic())
            if not publisher.wait_for_all_acked(Duration(seconds=left)):
                late.append(publisher.topic_name)
                node.get_logger().warning(
                    f'{publisher.topic_name}: a reader had not acknowledged every sample '
                    f'{timeout:g} s after the end (frozen or dead): it may lack the last ones')
    return late
