"""Clock modes of the nodes, their time base, and the lockstep ticker on /clock.

Clock modes (parameter ``clock_mode`` of every node)
----------------------------------------------------
``'lockstep'``: deterministic simulation. The plant owns ``/clock``, every controller node
runs with ``use_sim_time`` and computes its output for stamp t_k only when all its inputs
for t_k have arrived (:mod:`.sync`). Nothing depends on wall-clock timing, so a run
reproduces the in-process runner (``wip_sim/core/runner.py``) step for step.

``'realtime'``: the plant (or a robot) runs on its own clock; the nodes compute on the
arrival of their primary input with the latest other inputs, and the MPC and the
reference run on timers of the node clock.

Why the lockstep nodes do not use sim-time timers for their ticks: a ROS timer first
fires one period *after* it starts, so a timer started at t = 0 never fires for t_0 = 0,
the first sample of the run, and the whole lockstep graph would wait for it. Verified
with rclpy 7.1.6 (both ``EventsExecutor`` and ``SingleThreadedExecutor``): a 0.1 s
timer on sim time driven by /clock = 0, 0.005, ... fires at 0.1, 0.2, 0.3, not at 0.
A timer would also alias to the next sample if a stamp were off the timer's grid by a
nanosecond of rounding. So, in lockstep, the reference node publishes on each ``/clock``
sample of its grid (:class:`ClockTicker`) and the MPC ticks on the stamps of its inputs
(:func:`.sync.is_decimated_tick`), both including t = 0 exactly like the runner.
"""

from __future__ import annotations

from typing import Callable

from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from .composition import IntraProcessNode
from .qos import CLOCK_QOS
from .stamps import stamp_to_ns
from .sync import on_grid


class TimeBase:
    """Float seconds of a stamp for the core, relative to an origin.

    Lockstep: origin 0, so t is the simulation time (t = ns / 1e9, correctly rounded).
    Real time: the stamps are wall-clock times (about 1.7e9 s, whose float spacing is
    0.24 us); the core only needs time differences and the ESO's ramp origin, so the
    origin is the first stamp converted, which keeps nanosecond resolution.
    """

    def __init__(self, lockstep: bool) -> None:
        self.origin_ns: int | None = 0 if lockstep else None

    def seconds(self, stamp_ns: int) -> float:
        if self.origin_ns is None:
            self.origin_ns = int(stamp_ns)
        return (int(stamp_ns) - self.origin_ns) / 1e9


def warn_lockstep_without_sim_time(node: Node, mode: str) -> str:
    """``mode``, after a warning if it is lockstep on the wall clock."""
    if mode == 'lockstep' and not node.get_parameter('use_sim_time').value:
        node.get_logger().warning('clock_mode lockstep without use_sim_time: input ages '
                                  'and diagnostics use the wall clock')
    return mode


class ClockTicker:
    """Calls ``callback(stamp_ns)`` for each new /clock sample on a ``period`` [s] grid.

    The lockstep replacement of a sim-time timer (see the module docstring): one call per
    grid sample including t = 0, strictly increasing, never aliased.

    On sim time the ticker's subscription also drives the node's clock (rclpy's
    ``TimeSource.clock_callback``, before the tick) and the time source's own /clock
    subscription is removed: one delivery per sample instead of two of the same message.
    Every clock attached to that time source (:func:`.composition.share_sim_clock`) still
    reads sim time.
    """

    def __init__(self, node: Node, period: float, callback: Callable[[int], None],
                 topic: str = '/clock') -> None:
        self.period = float(period)
        self._callback = callback
        self._node = node
        self.last_ns: int | None = None
        self.subscription = node.create_subscription(Clock, topic, self._on_clock, CLOCK_QOS)
        if isinstance(node, IntraProcessNode):   # the plant's /clock in a composed process
            node.add_intra_subscription(Clock, self.subscription, self._on_clock)
        self._time_source = None
        source = getattr(node, '_time_source', None)   # rclpy has no public accessor
        if (source is not None and getattr(source, '_clock_sub', None) is not None
                and source._clock_sub.topic_name == self.subscription.topic_name):
            source.detach_node()      # its subscription goes; its clocks stay attached
            self._time_source = source
            node.clock_ticker_drives_time = True     # see share_sim_clock

    def _on_clock(self, msg: Clock) -> None:
        if self._time_source is not None:
            try:
                self._time_source.clock_callback(msg)
            except ValueError as err:   # rclpy refuses a negative time; the clock keeps its
                diagnostics = getattr(self._node, 'diagnostics', None)     # last value
                if diagnostics is not None:
                    diagnostics.drop('clock', 'invalid', f'node clock not set: {err}')
        stamp_ns = stamp_to_ns(msg.clock)
        if self.last_ns is not None and stamp_ns <= self.last_ns:
            return
        if not on_grid(stamp_ns, self.period):
            return
        self.last_ns = stamp_ns
        self._callback(stamp_ns)
