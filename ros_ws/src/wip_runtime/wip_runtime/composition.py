"""ROS 2 composition by hand: several nodes in one process, messages between them direct."""

from __future__ import annotations

import difflib
import gc
from typing import Any, Callable, Sequence

import rclpy
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSDurabilityPolicy, QoSProfile

from .dds_profile import process_ignores_local_endpoints
from .executors import adopt_watchdogs
from .intra_process import IntraProcessBus, IntraProcessPublisher


class IntraProcessNode(Node):
    """A node whose publishers and subscriptions a composed process may connect directly.

    The connection is made by :func:`connect_intra_process` (:mod:`.intra_process`). The
    controller nodes and the plant are such nodes. Call :meth:`init_intra_process` before
    creating the publishers and subscriptions; rclpy's own (parameter events, rosout) are
    not connected.
    """

    def init_intra_process(self, enabled: bool) -> None:
        self.use_intra_process_comms = enabled
        self.intra_publishers: list[IntraProcessPublisher] = []
        #: (message type, topic, callback, direct callback or None, its value type)
        self.intra_subscriptions: list[tuple] = []
        #: (subscription taking serialized messages, callbacks it also serves)
        self.raw_subscriptions: list[tuple[Any, list[Callable]]] = []

    def add_intra_subscription(self, msg_type, subscription, callback: Callable,
                               direct: Callable | None = None,
                               value_type: type | None = None) -> None:
        """Also deliver the process's own messages of ``subscription``'s topic to ``callback``.

        Which must be the subscription's. ``direct(stamp_ns, value)``: the process's
        publishers of values of ``value_type`` on the topic hand them to it instead
        (:meth:`.intra_process.IntraProcessPublisher.publish_value`).
        """
        self.intra_subscriptions.append((msg_type, subscription.topic_name, callback,
                                         direct, value_type))

    def create_publisher(self, msg_type, topic, qos_profile, **kwargs):
        """Create rclpy's publisher wrapped in an :class:`IntraProcessPublisher`.

        The wrapper publishes nothing while no subscription is matched (volatile topics),
        and in a composed process hands messages to the process's own subscriptions
        directly. ``direct_type``: the type of the values the node publishes with
        ``publish_value``.
        """
        direct_type = kwargs.pop('direct_type', None)
        if not hasattr(self, 'intra_publishers'):   # rclpy's own, from Node.__init__
            return super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        wrapper: list[IntraProcessPublisher] = []
        if kwargs.get('event_callbacks') is None:
            # The match count from DDS's matched events: no query per publication.
            kwargs['event_callbacks'] = PublisherEventCallbacks(
                matched=lambda status: wrapper and wrapper[0].on_matched(status))
        publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        volatile = (not isinstance(qos_profile, QoSProfile)
                    or qos_profile.durability != QoSDurabilityPolicy.TRANSIENT_LOCAL)
        wrapped = IntraProcessPublisher(publisher, msg_type, skip_unmatched=volatile,
                                        direct_type=direct_type)
        wrapper.append(wrapped)
        self.intra_publishers.append(wrapped)
        return wrapped


def undeclared_overrides(node: Node, declared_elsewhere=()) -> list[str]:
    """One line per parameter override given to ``node`` that it does not declare.

    rclpy keeps such an override silently unused (a ``-p max_tilt:=0.2`` without its
    ``mpc.`` prefix, a misspelt name): the node says so, with the names it meant if any.
    ``declared_elsewhere``: names another node of the same process declares (a ``-p`` of
    a composed process reaches every node in it). A node's ``retired_parameters`` (name ->
    what replaced it) name the replacement of a parameter of an older version.
    """
    retired = getattr(node, 'retired_parameters', {})
    overrides = getattr(node, '_parameter_overrides', None) or {}
    declared = [name for name in getattr(node, '_parameters', {})]
    lines = []
    for name in sorted(overrides):
        if node.has_parameter(name) or name in declared_elsewhere:
            continue
        meant = [d for d in declared if d.endswith('.' + name)] or \
            difflib.get_close_matches(name, declared, n=2, cutoff=0.8)
        hint = (f' ({retired[name]})' if name in retired else
                f' (did you mean {" or ".join(repr(m) for m in meant)}?)' if meant else '')
        lines.append(f'parameter {name!r} is not a parameter of this node and is ignored'
                     + hint)
    return lines


def warn_undeclared_overrides(nodes, warned=None) -> None:
    """Log :func:`undeclared_overrides` of each node (one node or a list), each name once."""
    nodes = list(nodes) if isinstance(nodes, (list, tuple)) else [nodes]
    everywhere = set()
    for node in nodes:
        everywhere.update(getattr(node, '_parameters', {}))
    warned = set() if warned is None else warned
    for node in nodes:
        for line in undeclared_overrides(node, everywhere):
            if line not in warned:
                warned.add(line)
                node.get_logger().warning(line)


def compose(executor, factories: Sequence[Callable[[], Node]],
            built: list[Node]) -> IntraProcessBus | None:
    """ROS 2 composition by hand.

    For :func:`.node_main.run_nodes` and the simulator nodes' main: build each node into
    ``built`` (as it is made, so that the caller destroys what was built if a later factory
    fails) and add it to ``executor``; warn of overrides no node declares; one sim clock
    (:func:`share_sim_clock`); intra-process delivery (:func:`connect_intra_process`, the bus
    to drain, or None) with the nodes' watchdogs adopted into the spin loop
    (:func:`.executors.adopt_watchdogs`); then move the start-up's objects out of the
    garbage collector's reach (``gc.freeze``), so that the collections that still run
    during control (young objects only) do not walk them.
    """
    for factory in factories:
        built.append(factory())
        executor.add_node(built[-1])
    warn_undeclared_overrides(built)
    share_sim_clock(built)
    bus = connect_intra_process(built)
    if bus is not None:
        bus.watchdogs = adopt_watchdogs(built)
    gc.collect()
    gc.freeze()
    return bus


def connect_intra_process(nodes: Sequence[Node]) -> IntraProcessBus | None:
    """Connect the publishers of ``nodes`` to the same process's subscriptions.

    The connection is made by :mod:`.intra_process`. Return the bus that the spin loop must
    drain, or None if there is nothing to connect (fewer than two nodes with
    ``use_intra_process_comms``).
    """
    members = [n for n in nodes
               if isinstance(n, IntraProcessNode) and n.use_intra_process_comms]
    if len(members) < 2:
        return None
    logger = members[0].get_logger()

    def on_error(kind: str, err: BaseException) -> None:
        if bus.errors <= 5 or bus.errors % 1000 == 0:
            logger.error(f'an intra-process callback failed on a {kind} (#{bus.errors}), '
                         f'node goes on: {type(err).__name__}: {err}')

    bus = IntraProcessBus(on_error, dds_ignores_local=process_ignores_local_endpoints(
        rclpy.utilities.get_rmw_implementation_identifier()))
    for node in members:
        for msg_type, topic, callback, direct, value_type in node.intra_subscriptions:
            bus.add_subscription(topic, msg_type, callback, direct, value_type)
    connected = []
    for node in members:
        for publisher in node.intra_publishers:
            local = bus.attach(publisher)
            if local:
                connected.append(f'{publisher.topic_name} -> {local}')
    if bus.dds_ignores_local:
        count_local_matches(members)
    shared = share_raw_subscriptions(members)
    if shared:
        connected.append(f'one take for {", ".join(shared)}')
    logger.debug(f'intra-process (DDS ignores local endpoints: {bus.dds_ignores_local}): '
                 f'{", ".join(connected) or "no topic"}')
    return bus


def share_raw_subscriptions(members: Sequence[IntraProcessNode]) -> list[str]:
    """One DDS subscription per outside input: drop a node's duplicate of a raw subscription.

    In a composed process the ESO takes the base's sensor messages serialized, and the mixer
    (its wiring checks) subscribed the same topics as messages: each sample was taken twice
    from DDS and also converted to a Python message by rclpy (docs/realtime.md has the
    cost). Where a node's subscription has the topic, type and QoS of another node's raw
    subscription (``ControllerNode.subscribe``) and no node of the process publishes that
    topic (the bus delivers those), the duplicate is destroyed and its callback served
    by the raw one, with the object decoded once. The graph shows one subscription of the
    topic in this process fewer. Returns the topics shared.
    """
    published = {p.topic_name for node in members for p in node.intra_publishers}
    leaders = {}
    for node in members:
        for subscription, followers in getattr(node, 'raw_subscriptions', ()):
            if subscription.topic_name not in published:
                leaders.setdefault((subscription.topic_name, subscription.msg_type),
                                   (subscription, followers))
    shared = []
    for node in members:
        for subscription in list(node.subscriptions):
            leader = leaders.get((subscription.topic_name, subscription.msg_type))
            if (leader is None or subscription is leader[0] or subscription.raw
                    or subscription.qos_profile != leader[0].qos_profile):
                continue
            leader[1].append(subscription.callback)
            shared.append(subscription.topic_name)
            node.destroy_subscription(subscription)
    return shared


def count_local_matches(members: Sequence[IntraProcessNode]) -> None:
    """Count, per node, the endpoints its endpoints reach through the bus (``local_matches``).

    Where DDS ignores the process's own endpoints its match counts leave these out; the
    /diagnostics match counts and the plant's start check add them back
    (:func:`~.intra_process.local_match_count`).
    """
    publishers = [(p.topic_name, p.msg_type) for node in members
                  for p in node.intra_publishers]
    for node in members:
        matches: dict[tuple[str, str], int] = {}
        for publisher in node.intra_publishers:
            key = ('subscriptions', publisher.topic_name)
            matches[key] = matches.get(key, 0) + publisher.local_subscriptions
        for msg_type, topic, *_ in node.intra_subscriptions:
            key = ('publishers', topic)
            matches[key] = matches.get(key, 0) + publishers.count((topic, msg_type))
        node.local_matches = matches


def share_sim_clock(nodes: Sequence[Node]) -> Node | None:
    """Drive the clocks of every node on sim time from the first one's /clock subscription.

    Each rclpy node has a time source of its own, and with ``use_sim_time`` each subscribes
    /clock: in one process that is one delivery per node per tick (in lockstep, 6 of the
    composed controllers' ~20 deliveries per control tick) for the same value. The others'
    subscriptions are removed and their clocks attached to the first node's time source,
    so every node's clock still reads the same sim time. (Turning ``use_sim_time`` off at
    run time then works for the first node alone; it is read-only in this project.)
    Returns the node that keeps the subscription, None if fewer than two use sim time.
    """
    on_sim_time = [n for n in nodes if n.get_parameter('use_sim_time').value]
    if len(on_sim_time) < 2:
        return None
    # A node whose ClockTicker drives its time source (the reference node) keeps it: then
    # the process has one /clock subscription.
    on_sim_time.sort(key=lambda n: not getattr(n, 'clock_ticker_drives_time', False))
    source = on_sim_time[0]._time_source    # rclpy has no public accessor
    for node in on_sim_time[1:]:
        node._time_source.detach_node()
        source.attach_clock(node.get_clock())
    return on_sim_time[0]
