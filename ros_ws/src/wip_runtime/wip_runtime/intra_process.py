"""Intra-process delivery between the controller nodes of one process (composed layout).

rclcpp's intra-process communication, done for rclpy (which has none): a message that a
node of a composed process (``ros2 run wip_control controllers``) publishes on a topic
that another node of the same process subscribes is handed to that subscription's
callback directly, without serialisation, DDS and the executor's take. In the composed
controllers a control tick publishes about 11 messages and delivers about 19; rclpy
spends tens of microseconds on each in native code (taking, deserialising, dispatching,
measured with py-spy: half the process's samples), against a few for a Python call
(docs/realtime.md has the numbers).

Rules (what stays observable):

- **Outside subscribers see every message.** A publisher knows how many subscriptions
  it matches from DDS's matched events (``on_matched``, delivered by the executor before
  any message that arrives after the match), and asks DDS again
  (``get_subscription_count``, ~2 us) when its count is older than
  :data:`MATCH_COUNT_MAX_AGE`: a publication costs no query. When the process's DDS participant
  matches its own endpoints (Fast DDS's default), that count includes the subscriptions of
  this process: if it is more than they, someone outside listens (the plant, a recorder, a
  viewer, a user's ``ros2 topic echo``), the message is published to DDS exactly as without
  this module, and the local subscriptions receive it from DDS too (one path per message,
  so nothing is delivered twice). Otherwise it goes to the local subscriptions alone. In a
  composed process a volatile publisher whose topic no one subscribes publishes nothing
  (DDS would deliver it to no one either: the effort command in simulation).
- **A participant that ignores its own endpoints** (Fast DDS's participant property
  ``fastdds.ignore_local_endpoints``, which run_graph's DDS profile sets; the bus's
  ``dds_ignores_local``) never delivers a message of this process to this process: the
  count is then of outside subscriptions alone, and a message goes to DDS when someone
  outside listens **and** to the local subscriptions through the bus, always. A recorder
  or a viewer then costs the composed process one DDS write per message, not a DDS write
  plus a take and a deserialisation per local subscription.
- **Order.** Local deliveries go through one FIFO queue that the process's spin loop
  drains after every ``spin_once`` (:meth:`IntraProcessBus.drain`), so a callback never
  runs inside another (no re-entrance into a node's input synchronisation) and messages
  are delivered in the order they were published. A message published by a callback of
  the drain is queued behind the others, as DDS would deliver it after the callback.
- **The same entities.** Every DDS publisher and subscription still exists, so the graph
  (``ros2 topic info``, the match counts on /diagnostics, ``run_graph``'s endpoint check)
  is unchanged; only the bytes stop flowing where no one outside needs them.
- **Shared, not copied.** Local subscribers receive the publisher's message object, as
  rclcpp's intra-process subscribers get a shared const pointer: the nodes build a new
  message per publication and never modify one they received.
- **Values, not messages, where both sides know them.** A publisher that declares the
  value its messages are made from (``direct_type``: an immutable core object, the ESO's
  ``PoseEstimate`` say) publishes it with :meth:`IntraProcessPublisher.publish_value`; a
  local subscription that declared a ``direct`` callback for that value type gets
  ``(stamp_ns, value)`` instead of a message, and the message is built only for DDS (an
  outside subscriber) or for a local subscription without such a callback. The queue,
  its order and the DDS rules above are the same for both paths; the subscriber applies
  the same input rules to both (``ControllerNode.subscribe_input``).

When an outside subscriber leaves, messages that DDS still holds for a local subscription
may be taken after later local ones: the nodes' input synchronisation (:mod:`.sync`) drops
an input older than one it has. This happens once, when the subscriber leaves.

Pure Python (no rclpy import): tested without ROS, and with rclpy in
``tests/wip_control/nodes/test_intra_process.py``.
"""

from __future__ import annotations

import collections
import time
from typing import Any, Callable, Iterable

Callback = Callable[[Any], None]
#: ``direct(stamp_ns, value)``: a subscription's callback for a publisher's value.
DirectCallback = Callable[[int, Any], None]

#: [s] of steady time a publisher uses its DDS match count before it asks DDS again. The
#: matched events keep the count current; the query is the safety net for an event missed
#: (one before the node joined an executor, say).
MATCH_COUNT_MAX_AGE = 1.0


class IntraProcessPublisher:
    """Wraps an rclpy publisher; ``publish`` chooses DDS, the local queue, or nothing.

    Unattached (a node alone in its process, or ``use_intra_process_comms`` false) it is
    the plain rclpy publisher. Every other attribute is the wrapped publisher's
    (``topic_name``, ``get_subscription_count``, ``handle``...).
    """

    # No __slots__: like an rclpy Publisher, an instance's ``publish`` can be replaced
    # (tests record what a node sends that way).

    def __init__(self, publisher, msg_type, skip_unmatched: bool = True,
                 direct_type: type | None = None) -> None:
        self.publisher = publisher
        self.msg_type = msg_type
        self.topic_name = publisher.topic_name
        #: False for a transient-local publisher: a late subscriber gets its history.
        self.skip_unmatched = skip_unmatched
        #: The type of the values :meth:`publish_value` publishes (None: messages only).
        self.direct_type = direct_type
        self._bus: IntraProcessBus | None = None
        self._local: tuple[Callback, ...] = ()
        #: For :meth:`publish_value`: every local subscription in order, each taking the
        #: item (stamp_ns, value, message); whether one of them needs the message.
        self._items: tuple[Callable[[tuple], None], ...] = ()
        self._items_need_msg = False
        #: DDS's match count, and the steady time [s] after which it is asked again.
        self._matched = 0
        self._matched_until = 0.0

    def __getattr__(self, name: str):
        return getattr(self.publisher, name)

    def get_subscription_count(self) -> int:
        """Subscriptions this publisher reaches: DDS's matches, and the bus's.

        Where DDS ignores the process's own endpoints, the local subscriptions are not among
        its matches, yet they receive every message (through the bus).
        """
        count = self._refresh_match_count(time.monotonic())
        if self._bus is not None and self._bus.dds_ignores_local:
            count += len(self._local)
        return count

    def on_matched(self, status) -> None:
        """DDS matched a subscription or lost one (the publisher's matched event)."""
        self._matched = status.current_count
        self._matched_until = time.monotonic() + MATCH_COUNT_MAX_AGE

    def _refresh_match_count(self, now: float) -> int:
        self._matched = self.publisher.get_subscription_count()
        self._matched_until = now + MATCH_COUNT_MAX_AGE
        return self._matched

    @property
    def local_subscriptions(self) -> int:
        """Subscriptions of this process that receive this publisher's messages locally."""
        return len(self._local)

    def attach(self, bus: 'IntraProcessBus', callbacks: Iterable[Callback],
               direct: Iterable[DirectCallback | None] = ()) -> None:
        """Deliver to ``callbacks`` through ``bus`` while no one outside subscribes.

        ``direct``: for each of ``callbacks``, its subscription's callback for this
        publisher's values, or None (that subscription gets a message built from the value).
        """
        self._bus = bus
        self._local = tuple(callbacks)
        direct = tuple(direct) or (None,) * len(self._local)
        self._items = tuple(_item_callback(cb, dc) for cb, dc in zip(self._local, direct))
        self._items_need_msg = None in direct

    def reaches_anyone(self) -> bool:
        """Whether :meth:`publish` would send a message now, to DDS or to this process.

        False only for an attached volatile publisher that no subscription reaches: a node
        need not build a message that would go nowhere.
        """
        if self._bus is None or self._local or not self.skip_unmatched:
            return True
        now = time.monotonic()
        return bool(self._matched if now < self._matched_until
                    else self._refresh_match_count(now))

    def publish_value(self, stamp_ns: int, value, to_msg: Callable[[Any, int], Any]) -> None:
        """Publish ``to_msg(value, stamp_ns)``, handing ``value`` itself to local subscriptions.

        Who receives what follows :meth:`publish`'s rules; the message is built only for
        DDS or for a local subscription without a direct callback.
        """
        bus = self._bus
        if bus is None or not self._items:
            if self.reaches_anyone():
                self.publish(to_msg(value, stamp_ns))
            return
        now = time.monotonic()
        matched = (self._matched if now < self._matched_until
                   else self._refresh_match_count(now))
        msg = None
        if bus.dds_ignores_local:
            if matched or not self.skip_unmatched:
                msg = to_msg(value, stamp_ns)
                self.publisher.publish(msg)
                bus.published_dds += 1
        elif matched > len(self._local):     # someone outside: DDS, for everyone
            self.publisher.publish(to_msg(value, stamp_ns))
            bus.published_dds += 1
            return
        if msg is None and self._items_need_msg:
            msg = to_msg(value, stamp_ns)
        bus.post(self._items, (stamp_ns, value, msg))

    def publish(self, msg) -> None:
        bus = self._bus
        if bus is None:                      # a node alone in its process: plain rclpy
            self.publisher.publish(msg)
            return
        now = time.monotonic()
        matched = (self._matched if now < self._matched_until
                   else self._refresh_match_count(now))
        local = self._local
        if bus.dds_ignores_local:            # DDS: outside alone; the bus: this process
            if matched or not (local or self.skip_unmatched):
                self.publisher.publish(msg)
                bus.published_dds += 1
            if local:
                bus.post(local, msg)
        elif matched > len(local):           # someone outside: DDS, for everyone
            self.publisher.publish(msg)
            bus.published_dds += 1
        elif local:
            bus.post(local, msg)
        elif not self.skip_unmatched:        # transient local: kept for late joiners
            self.publisher.publish(msg)


def _item_callback(callback: Callback,
                   direct: DirectCallback | None) -> Callable[[tuple], None]:
    """Return a local subscription's callback of an item (stamp_ns, value, message)."""
    if direct is None:
        return lambda item: callback(item[2])
    return lambda item: direct(item[0], item[1])


def local_match_count(node: Any, kind: str, topic: str) -> int:
    """Local endpoints a node's endpoint on ``topic`` reaches through the bus, not DDS.

    ``kind`` is 'subscriptions' (of a publisher) or 'publishers' (of a subscription). They
    are counted (``node.local_matches``) where DDS ignores the process's own endpoints; else
    DDS matches them and this is 0.
    """
    return getattr(node, 'local_matches', {}).get((kind, topic), 0)


class IntraProcessBus:
    """The local subscriptions of one process by topic, and the queue of deliveries."""

    def __init__(self, on_error: Callable[[str, BaseException], None] | None = None,
                 dds_ignores_local: bool = False) -> None:
        #: The process's DDS participant does not match its own endpoints (see the rules).
        self.dds_ignores_local = dds_ignores_local
        #: topic -> [(message type, callback, direct callback or None, its value type)]
        self.subscriptions: dict[str, list[tuple]] = collections.defaultdict(list)
        self._queue: collections.deque = collections.deque()
        self._on_error = on_error
        #: Messages delivered locally (one per message, whatever the number of callbacks),
        #: and published to DDS by an attached publisher because someone outside listens.
        self.delivered = 0
        self.published_dds = 0
        self.errors = 0
        #: Watchdogs whose deadlines the spin loop keeps (``executors.adopt_watchdogs``).
        self.watchdogs: list = []

    def add_subscription(self, topic: str, msg_type: type, callback: Callback,
                         direct: DirectCallback | None = None,
                         value_type: type | None = None) -> None:
        """Deliver ``topic``'s messages to ``callback``.

        Or its publishers' values of ``value_type`` to ``direct(stamp_ns, value)``.
        """
        self.subscriptions[topic].append((msg_type, callback, direct, value_type))

    def attach(self, publisher: IntraProcessPublisher) -> int:
        """Attach ``publisher`` to the local subscriptions of its topic and type.

        Return their count. There may be none; the publisher then publishes only while a
        subscription is matched.
        """
        local = [entry for entry in self.subscriptions.get(publisher.topic_name, ())
                 if entry[0] is publisher.msg_type]
        value_type = publisher.direct_type
        publisher.attach(self, [entry[1] for entry in local],
                         [entry[2] if value_type is not None and entry[3] is value_type
                          else None for entry in local])
        return len(local)

    def post(self, callbacks: tuple[Callback, ...], msg) -> None:
        self._queue.append((callbacks, msg))

    @property
    def pending(self) -> int:
        return len(self._queue)

    def drain(self, limit: int | None = None) -> int:
        """Deliver the queued messages, and those the callbacks publish meanwhile; how many.

        At most ``limit`` of them when given: a loop closed within the process (the plant
        and the controllers of the single layout) would otherwise never return to the
        executor, and messages from other processes, services and timers would wait for
        the end of the run.
        """
        queue = self._queue
        count = 0
        left = -1 if limit is None else limit
        while queue and left != 0:
            left -= 1
            callbacks, msg = queue.popleft()
            count += 1
            for callback in callbacks:
                try:
                    callback(msg)
                except Exception as err:  # noqa: BLE001 - the other callbacks still get it
                    self.errors += 1
                    if self._on_error is not None:
                        self._on_error(getattr(msg, '__class__', type(msg)).__name__, err)
        self.delivered += count
        return count
