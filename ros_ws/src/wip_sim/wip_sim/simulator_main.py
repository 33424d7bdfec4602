"""The ``main`` of a simulator node (plant, stand-in base): a run that ends by itself."""

from __future__ import annotations

import sys
from typing import Callable, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from wip_runtime.cli import answer_node_help
from wip_runtime.composition import compose
from wip_runtime.config import ParamError
from wip_runtime.executors import make_executor, SPIN_TIMEOUT, spin_composed, spin_once_or_stop
from wip_runtime.launched import end_with_launcher
from wip_runtime.node_main import (ignore_stop_signals, init_rclpy, package_of,
                                   STOP_ACK_TIMEOUT, stop_requests, take_over_stop_signals,
                                   wait_for_acknowledgements)


def run_simulator_node(node_factory: Callable[[], Node], program: str, args=None, *,
                       config_status: int, on_end: Callable[[Node], None] | None = None,
                       companions: Sequence[Callable[[], Node]] = ()) -> int:
    """Run the ``main`` of a simulator node (plant, stand-in base) that ends by itself.

    Spins until SIGINT or SIGTERM or until the node sets ``exit_code`` (the end of its scenario, a
    fall...), which is then the status; ``on_end(node)`` runs in that case, before the
    clean-up. A configuration error prints its message and returns ``config_status``.
    The node's ``write_stats()`` always runs (an OSError is reported, not raised).

    ``companions``: more nodes in the same process and executor (the controllers, for
    ``ros2 run wip_sim simulation``), composed by ``wip_runtime.composition.compose`` as in
    ``wip_runtime.node_main.run_nodes``;
    the simulator node takes part in the intra-process delivery if it is an
    ``wip_runtime.composition.IntraProcessNode``.
    """
    if answer_node_help(program, package_of(node_factory), args):
        return 0
    end_with_launcher()
    # SIGINT and SIGTERM only set a flag that the spin loop checks (as in run_nodes): with
    # rclpy's handlers a KeyboardInterrupt raised late could cut write_stats() short and
    # leave an empty stats file.
    if not init_rclpy(program, args, SignalHandlerOptions.NO):
        return config_status
    take_over_stop_signals()
    built: list[Node] = []
    status = 0
    try:
        executor = make_executor()
        bus = compose(executor, [node_factory, *companions], built)
        node = built[0]
        if companions:
            # A controller's callback error is reported and the run goes on, as in
            # run_nodes (the safety layer judges what follows).
            spin_composed(executor, built[1], bus,
                          lambda: node.exit_code is None and not stop_requests)
        else:
            # The simulator alone: an error of its own callbacks ends the run. spin_once
            # with a timeout: the EventsExecutor's spin() ignores SIGINT.
            while rclpy.ok() and node.exit_code is None and not stop_requests:
                spin_once_or_stop(executor, SPIN_TIMEOUT)
        if node.exit_code is not None:
            status = node.exit_code
            if on_end is not None:
                on_end(node)
            node.unacknowledged_topics = wait_for_acknowledgements(built)
        elif stop_requests:
            # Stopped by a signal (run_graph's stop, or the launcher's death): what a reader
            # (the recorder, still draining) has not acknowledged would die with this process.
            node.unacknowledged_topics = wait_for_acknowledgements(built, STOP_ACK_TIMEOUT)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParamError, ParameterException) as err:
        print(f'{program}: error: {err}', file=sys.stderr)
        status = config_status
    finally:
        _finish(program, built)
    return status


def _finish(program: str, built: Sequence[Node]) -> None:
    """Write the simulator node's stats (if it was built), then destroy every node."""
    ignore_stop_signals()   # a second signal must not cut the stats or the clean-up short
    if built:   # the simulator node was built (a companion may have failed)
        try:
            built[0].write_stats()
        except OSError as err:
            print(f'{program}: cannot write stats: {err}', file=sys.stderr)
    for built_node in built:
        built_node.destroy_node()
    rclpy.try_shutdown()
