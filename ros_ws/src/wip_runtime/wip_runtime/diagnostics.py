"""/diagnostics of the controller nodes (diagnostic_msgs/DiagnosticArray).

Every node has one :class:`NodeDiagnostics`. The node reports what happens (inputs
received, inputs dropped and why, outputs with their compute time, the reason for what
it commands); a steady-clock timer publishes one DiagnosticStatus per period
(default 1 s of wall time, so diagnostics keep coming when the simulation clock stops;
every 0.1 s until the node's first input or output, :func:`create_diagnostics_timer`):

- level: ERROR if the node says so, WARN if inputs were dropped in the last period or
  the node says so, else OK; message: the node's reason (or the latest drop);
- values: outputs, output rate per wall second and per second of stamps (simulated
  time in lockstep), age of each input (node clock minus its last stamp), counts of
  received and dropped inputs per reason, compute time per output (mean and max), DDS
  match counts of every publisher and subscription (see :meth:`NodeDiagnostics._match_counts`).
"""

from __future__ import annotations

import collections
import time
from typing import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from .intra_process import local_match_count

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
#: Drops of one kind logged individually before the log goes quiet (then every 1000th).
_LOGGED_DROPS = 5
#: ROS infrastructure topics left out of the match counts.
_NOT_COUNTED = ('/diagnostics', '/rosout', '/parameter_events')
#: Period of /diagnostics while a node starts [s of wall time]. A launcher waits for a
#: status of every node sent after its view of the graph is complete (the match counts in
#: it; wip_bringup.runner_base): at the steady period that wait would last up to a whole
#: period at every start (measured: docs/node-graph.md).
STARTUP_PERIOD = 0.1
#: The start lasts until the node says it has started, at most this long [s of wall time].
STARTUP_TIME = 10.0


def create_diagnostics_timer(node: Node, callback: Callable[[], None], period: float,
                             starting: Callable[[], bool] = lambda: True):
    """Return a steady-clock timer that calls ``callback`` every ``period`` [s] of wall time.

    Every :data:`STARTUP_PERIOD` instead while ``starting()`` holds, during the first
    :data:`STARTUP_TIME` seconds at most.
    """
    started = time.monotonic()
    period_ns = int(round(period * 1e9))
    timer = None

    def tick() -> None:
        if timer.timer_period_ns != period_ns and (
                not starting() or time.monotonic() - started >= STARTUP_TIME):
            timer.timer_period_ns = period_ns
        callback()

    timer = node.create_timer(min(STARTUP_PERIOD, period), tick,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
    return timer


class NodeDiagnostics:
    """Counters and state of one node, published on /diagnostics.

    Parameters
    ----------
    node : the node (its clock gives the input ages).
    role : short description, e.g. ``'extended state observer'``.
    inputs : names of the inputs whose age is reported.
    period : publishing period [s] of wall time; 0 disables the timer.
    """

    def __init__(self, node: Node, role: str, inputs: Sequence[str],
                 period: float = 1.0) -> None:
        self._node = node
        self.name = f'{node.get_fully_qualified_name()}: {role}'
        self.inputs = tuple(inputs)
        self.last_stamp: dict[str, int | None] = {n: None for n in self.inputs}
        self.received: collections.Counter = collections.Counter()
        self.dropped: collections.Counter = collections.Counter()  # (input, reason)
        self.outputs = 0
        self.last_output_ns: int | None = None
        self.compute_total = 0.0
        self.compute_max = 0.0
        self.level = OK
        self.message = 'waiting for inputs'
        self.values: dict[str, str] = {}
        #: Called before each status is made: values that change every tick are formatted
        #: there, once per status, not once per tick.
        self.reporters: list[Callable[[], None]] = []
        self.last_drop = ''
        self._drops_reported = 0
        self._previous = (time.monotonic(), 0, None)  # wall time, outputs, last stamp
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.timer = None if period <= 0.0 else create_diagnostics_timer(
            node, self.publish, period,
            starting=lambda: self.outputs == 0 and not self.received)

    # -- reports from the node -------------------------------------------------------------
    def input(self, name: str, stamp_ns: int) -> None:
        """Count an input message that arrived (valid or not)."""
        self.received[name] += 1
        self.last_stamp[name] = stamp_ns

    def drop(self, name: str, kind: str, detail: str = '') -> None:
        """Count a dropped input by ``kind`` ('invalid', 'stale', ...) and log it."""
        key = (name, kind)
        self.dropped[key] += 1
        self.last_drop = f'dropped {name} ({kind}){": " + detail if detail else ""}'
        count = self.dropped[key]
        if count <= _LOGGED_DROPS or count % 1000 == 0:
            self._node.get_logger().warning(f'{self.last_drop} (#{count} of this kind)')

    def output(self, stamp_ns: int, compute_time: float) -> None:
        """Count a published output; ``compute_time`` [s] from inputs to message."""
        self.outputs += 1
        self.last_output_ns = stamp_ns
        self.compute_total += compute_time
        if compute_time > self.compute_max:   # not max(): a call per output of every node
            self.compute_max = compute_time

    @property
    def compute_count(self) -> int:
        """Outputs with a compute time: every output."""
        return self.outputs

    def state(self, level: int, message: str) -> None:
        """Why the node commands what it commands (or why it does not)."""
        self.level, self.message = level, message

    # -- publishing ------------------------------------------------------------------------
    def status(self) -> DiagnosticStatus:
        """Return the DiagnosticStatus of now (also resets the per-period rates)."""
        for reporter in self.reporters:
            reporter()
        wall, outputs, stamp = time.monotonic(), self.outputs, self.last_output_ns
        wall0, outputs0, stamp0 = self._previous
        self._previous = (wall, outputs, stamp)
        n_drops = sum(self.dropped.values())
        new_drops = n_drops - self._drops_reported
        self._drops_reported = n_drops
        level, message = self.level, self.message
        if new_drops and level == OK:
            level, message = WARN, f'{message}; {new_drops} input(s) dropped, last: ' \
                                   f'{self.last_drop}'
        now_ns = self._node.get_clock().now().nanoseconds
        values = [
            KeyValue(key='outputs', value=str(outputs)),
            KeyValue(key='output rate [1/s wall]',
                     value=f'{(outputs - outputs0) / max(wall - wall0, 1e-9):.1f}'),
        ]
        if stamp is not None and stamp0 is not None and stamp > stamp0:
            values.append(KeyValue(key='output rate [1/s of stamps]',
                                   value=f'{(outputs - outputs0) * 1e9 / (stamp - stamp0):.1f}'))
        for name in self.inputs:
            last = self.last_stamp[name]
            age = 'never received' if last is None else f'{(now_ns - last) * 1e-9:.4f}'
            values.append(KeyValue(key=f'age {name} [s]', value=age))
            values.append(KeyValue(key=f'received {name}', value=str(self.received[name])))
        for (name, reason), count in sorted(self.dropped.items()):
            values.append(KeyValue(key=f'dropped {name} ({reason})', value=str(count)))
        if self.compute_count:
            values.append(KeyValue(key='compute time mean [us]',
                                   value=f'{1e6 * self.compute_total / self.compute_count:.1f}'))
            values.append(KeyValue(key='compute time max [us]',
                                   value=f'{1e6 * self.compute_max:.1f}'))
        values += [KeyValue(key=k, value=v) for k, v in self.values.items()]
        values += self._match_counts()
        return DiagnosticStatus(level=level, name=self.name, message=message,
                                hardware_id=self._node.get_name(), values=values)

    def _match_counts(self) -> list[KeyValue]:
        """DDS match counts of the node's endpoints, as each endpoint sees them.

        ``matched subscriptions <topic>`` (of a publisher) and ``matched publishers
        <topic>`` (of a subscription). DDS matches every pair on both sides on its own, and
        a reliable volatile reader that has not matched the writer yet loses what the
        writer sends; the ROS graph view does not show this, these counts do. The graph
        runner starts a lockstep run only when both sides of every designed pair count
        each other (a first message lost stalls it).
        """
        values = []
        for publisher in self._node.publishers:
            if publisher.topic_name not in _NOT_COUNTED:
                count = (publisher.get_subscription_count()
                         + local_match_count(self._node, 'subscriptions', publisher.topic_name))
                values.append(KeyValue(key=f'matched subscriptions {publisher.topic_name}',
                                       value=str(count)))
        for subscription in self._node.subscriptions:
            if subscription.topic_name not in _NOT_COUNTED:
                count = (subscription.get_publisher_count()
                         + local_match_count(self._node, 'publishers', subscription.topic_name))
                values.append(KeyValue(key=f'matched publishers {subscription.topic_name}',
                                       value=str(count)))
        return values

    def publish(self) -> None:
        """Publish the status (timer callback; never raises into the executor)."""
        try:
            array = DiagnosticArray(status=[self.status()])
            array.header.stamp = self._node.get_clock().now().to_msg()
            self.publisher.publish(array)
        except Exception as err:  # noqa: BLE001 - diagnostics must not stop the node
            self._node.get_logger().error(f'diagnostics failed: {err!r}')
