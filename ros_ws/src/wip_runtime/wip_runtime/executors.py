"""Executors of the node processes: their choice, timer slack, guarded spinning."""

from __future__ import annotations

import ctypes
import sys
import time
from typing import Callable, Sequence

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from .intra_process import IntraProcessBus

#: One spin_once of the EventsExecutor [s]: bounds the reaction time to a shutdown.
SPIN_TIMEOUT = 0.1


#: [ns] Timer slack of a node process's threads (Linux's default: 50 000). The kernel may
#: end a timed wait this late; the EventsExecutor's ``spin_once(timeout_sec=0)`` is such a
#: wait (asio's ``run_one_for``), which the composed spin loop makes about once a tick.
TIMER_SLACK_NS = 1000
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30


def set_timer_slack(slack_ns: int = TIMER_SLACK_NS) -> bool:
    """Set the calling thread's timer slack (Linux prctl); threads it starts later inherit it.

    Returns False where it cannot (not Linux). Threads at a real-time priority have none.
    """
    try:
        return _prctl(_PR_SET_TIMERSLACK, int(slack_ns)) == 0
    except (OSError, AttributeError):   # not Linux, or a libc without prctl
        return False


def timer_slack() -> int | None:
    """Return the calling thread's timer slack [ns] (None where unknown)."""
    try:
        return _prctl(_PR_GET_TIMERSLACK, 0)
    except (OSError, AttributeError):
        return None


def _prctl(option: int, value: int) -> int:
    if not sys.platform.startswith('linux'):
        raise OSError('prctl is a Linux call')
    return ctypes.CDLL(None, use_errno=True).prctl(option, value, 0, 0, 0)


def make_executor(context=None):
    """EventsExecutor (10x lower latency) if this rclpy has it, else SingleThreadedExecutor.

    Verified with rclpy 7.1.6: the EventsExecutor fires sim-time timers driven by /clock and
    steady-clock timers, and runs one-argument subscription callbacks; it must be driven by
    ``spin_once(timeout_sec=...)`` (its ``spin()`` ignores SIGINT). The thread that will
    spin it gets a short timer slack (:data:`TIMER_SLACK_NS`).
    """
    set_timer_slack()
    try:
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    except (ImportError, AttributeError, RuntimeError):
        return SingleThreadedExecutor(context=context)


def spin_once_or_stop(executor, timeout_sec: float = SPIN_TIMEOUT, context=None) -> None:
    """``executor.spin_once``; an error raised once the context is shut down is a stop.

    On SIGINT rclpy shuts the context down while the executor may be busy, and rclpy's
    EventsExecutor then sometimes fails inside pybind11 ("Unable to convert call argument
    '0' to Python object", seen under load). That is raised as ExternalShutdownException,
    which every entry point treats as a clean stop; any other error propagates.
    """
    try:
        executor.spin_once(timeout_sec=timeout_sec)
    except (KeyboardInterrupt, ExternalShutdownException):
        raise
    except Exception as err:  # noqa: BLE001 - re-raised unless the context is shut down
        if rclpy.ok(context=context):
            raise
        raise ExternalShutdownException(f'{type(err).__name__}: {err}') from err


_callback_failures = 0


def spin_once_guarded(executor, node: Node, timeout_sec: float = SPIN_TIMEOUT) -> bool:
    """``executor.spin_once``; an exception from a callback is logged, not fatal. False then.

    The nodes' own callbacks never raise (``ControllerNode.subscribe``), but rclpy's
    callbacks are not theirs: with ``use_sim_time`` rclpy's /clock subscription raises
    ValueError on a message with a negative time, which would end the node. A controller
    keeps running (its safety layer judges its inputs); the log says what happened.
    """
    global _callback_failures  # noqa: PLW0603 - one count per process
    try:
        executor.spin_once(timeout_sec=timeout_sec)
        return True
    except (KeyboardInterrupt, ExternalShutdownException):
        raise
    except Exception as err:  # noqa: BLE001 - any callback error, see the docstring
        if not rclpy.ok(context=node.context):
            # The context was shut down (SIGINT) while the executor was busy: rclpy's
            # EventsExecutor then sometimes fails inside pybind11 ("Unable to convert
            # call argument '0' to Python object", seen under load). That is a stop.
            raise ExternalShutdownException(f'{type(err).__name__}: {err}') from err
        _callback_failures += 1
        if _callback_failures <= 5 or _callback_failures % 1000 == 0:
            node.get_logger().error(f'a callback failed (#{_callback_failures}), node goes '
                                    f'on: {type(err).__name__}: {err}')
        return False


#: Intra-process deliveries between two turns of the executor: about one control tick of
#: the single layout (some 20 deliveries), so a message from another process (cmd_vel, an
#: e-stop, a service call) waits at most about a tick (docs/decisions/recording-speed.md).
DRAIN_BATCH = 20


class Watchdog:
    """A callback every ``period`` [s] of steady time that passes without a :meth:`kick`.

    An rclpy steady-clock timer, restarted by each kick, until a composed spin loop
    adopts it (:func:`adopt_watchdogs`): then the loop keeps the deadline itself, as the
    timeout of its wait. Restarting an rclpy timer wakes the thread that the
    EventsExecutor keeps for the timer's clock, twice per restart: at 200 Hz that was
    about 400 wake-ups a second of a thread that does nothing else
    (docs/realtime.md, section 2).

    ``grace`` [s]: adopted, the first call after a kick comes a period and this much
    after it (then every period on that grid): the work a kick stands for often comes a
    little later than a period after the last (the stages before it vary in time), and a
    call just before it would be a second, needless one. The rclpy timer has none.
    """

    def __init__(self, node: Node, period: float, callback: Callable[[], None],
                 clock: Clock | None = None, grace: float = 0.0) -> None:
        self.period = period
        self.grace = grace
        self.callback = callback
        self.node = node
        #: The rclpy timer while not adopted (cancelled once adopted), on ``clock`` (the
        #: steady clock unless given; adopted, the spin loop keeps steady time).
        self.timer = node.create_timer(period, callback,
                                       clock=clock or Clock(clock_type=ClockType.STEADY_TIME))
        self.adopted = False
        #: Steady time [s] of the next call when adopted.
        self.due = 0.0
        node.watchdogs = [*getattr(node, 'watchdogs', ()), self]

    def adopt(self) -> None:
        """Stop the rclpy timer; the spin loop calls :meth:`fire_if_due` from now on."""
        self.timer.cancel()
        self.adopted = True
        self.due = time.monotonic() + self.period

    def kick(self) -> None:
        """Restart the period (the callback's work was just done some other way)."""
        if self.adopted:
            self.due = time.monotonic() + self.period + self.grace
        else:
            self.timer.reset()

    def fire_if_due(self, now: float) -> None:
        """Call back if the deadline has passed; the next one a period later.

        On the timer's grid, as an rclpy timer, unless a whole period was missed (a
        stalled process): then a period from now, one call for the stall.
        """
        if now < self.due:
            return
        self.due += self.period
        if self.due <= now:
            self.due = now + self.period
        try:
            self.callback()
        except Exception as err:  # noqa: BLE001 - as a timer callback: reported, not fatal
            self.node.get_logger().error(f'watchdog callback failed: '
                                         f'{type(err).__name__}: {err}')


def adopt_watchdogs(nodes: Sequence[Node]) -> list[Watchdog]:
    """Adopt every :class:`Watchdog` of ``nodes`` into the spin loop; return them."""
    adopted = [w for node in nodes for w in getattr(node, 'watchdogs', ())]
    for watchdog in adopted:
        watchdog.adopt()
    return adopted


def spin_composed(executor, node: Node, bus: IntraProcessBus | None,
                  running: Callable[[], bool]) -> None:
    """Spin while the context is up and ``running()``.

    Spin (:func:`spin_once_guarded`, errors reported by ``node``) while the context is
    up and ``running()``; after each spin_once, deliver up to :data:`DRAIN_BATCH`
    intra-process messages (:meth:`~.intra_process.IntraProcessBus.drain`): a lockstep loop
    closed within the process still lets the executor serve other processes' messages.
    The bus's adopted watchdogs (``bus.watchdogs``) are kept here: the wait for the
    executor ends at the next one's deadline.
    """
    if bus is None:
        while rclpy.ok() and running():
            spin_once_guarded(executor, node)
        return
    watchdogs = bus.watchdogs
    while rclpy.ok() and running():
        # Messages waiting on the bus: take what the executor has ready, without waiting.
        timeout = 0.0 if bus.pending else SPIN_TIMEOUT
        if watchdogs:
            timeout = min(timeout, max(0.0, min(w.due for w in watchdogs) - time.monotonic()))
        spin_once_guarded(executor, node, timeout)
        bus.drain(DRAIN_BATCH)
        if watchdogs:
            now = time.monotonic()
            for watchdog in watchdogs:
                watchdog.fire_if_due(now)
