"""How the recorder stops: stop signals as a flag, its spin loop, the drain after a SIGINT.

A recorder that a launcher started first takes what the graph already sent when a SIGINT
(the launcher's death) stops it (:func:`drain`); the signals only set a flag, so nothing
cuts the bag's close short (docs/decisions/stopping-and-data-safety.md).
"""

import math
import signal
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor

SPIN_TIMEOUT = 0.1  # [s] of one spin_once; bounds the reaction time to a shutdown
#: After a SIGINT to a recorder that a launcher started [s, wall]: it keeps receiving until
#: nothing has arrived for STOP_QUIET, at most STOP_DRAIN. At the launcher's death every node
#: gets its signal at once, and the recorder may still be behind the publishers (seconds on
#: a loaded machine). A live launcher drains it before it stops it (SIGTERM: at once), and a
#: recorder run by hand stops at once.
STOP_QUIET = 0.5
#: [s] that a quiet time may fall short of STOP_QUIET: the rounding of a sum of spin times.
QUIET_SLACK = 1e-9
STOP_DRAIN = 30.0
#: The signals that stop the recorder: Ctrl-C, a service manager's stop, a closed terminal.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def make_executor(context=None):
    """EventsExecutor when this rclpy has it (10x lower latency), else SingleThreaded."""
    try:
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    except (ImportError, AttributeError, RuntimeError):
        return SingleThreadedExecutor(context=context)


class StopSignals:
    """Stop signals as a flag instead of an exception.

    SIGINT, SIGTERM and SIGHUP set a flag (counted) instead of raising: the spin loop
    and the stop's drain look at it, and the close that follows cannot be cut by one.
    ``cut_short``: a SIGTERM or SIGHUP came after the first signal, which ends a drain. A
    repeated SIGINT does not: at the launcher's death the kernel sends its death signal
    again each time it hands this process to another of the dying launcher's threads, and
    such a repeat is no one's request (docs/decisions/stopping-and-data-safety.md).
    """

    def __init__(self):
        self.count = 0
        self.first: int | None = None   # the first signal's number
        self.cut_short = False
        for number in STOP_SIGNALS:
            signal.signal(number, self._on_signal)

    def _on_signal(self, number, frame):
        if not self.count:
            self.first = number
        elif number != signal.SIGINT:
            self.cut_short = True
        self.count += 1


def spin(node, executor, stop=None, launched=False):
    """Spin until a stop signal; then :func:`drain` if it was a launched recorder's SIGINT.

    The drain's end goes to the log: why it ended, how long it took.

    Spin with a timeout (the EventsExecutor's spin() ignores SIGINT, ros-from-pip.md).
    ``launched``: started by a wip launcher, which stops it with SIGTERM once it has drained
    it; a SIGINT then means that the launcher died (the kernel's death signal) or someone
    else stops the run, and what the graph already sent is still coming.
    """
    executor.add_node(node)
    while rclpy.ok(context=node.context) and not (stop and stop.count):
        executor.spin_once(timeout_sec=SPIN_TIMEOUT)
    # The signal, not getppid(), tells the launcher's death: the kernel sends the death
    # signal when the thread that started this process exits, and first hands the process
    # to another thread of the dying launcher, so getppid() still names the launcher then
    # (seen: the recorder stopped at once and lost the plant's last ticks).
    if stop is not None and launched and stop.first == signal.SIGINT:
        reason, taken, seconds = drain(node, executor, stop)
        node.get_logger().info(f'stop: drained {seconds:.2f} s after the SIGINT (messages at '
                               f'{taken} spins); ended by {reason}')


def drain(node, executor, stop, quiet=STOP_QUIET, longest=STOP_DRAIN):
    """Receive what is still coming after the first stop signal.

    Return why the drain ended, the spins that took messages and its length [s].
    It receives until nothing arrived for ``quiet`` [s], at most ``longest`` [s], or until
    ``stop.cut_short``. Quiet means consecutive spins without a message that both number
    ``quiet / SPIN_TIMEOUT`` and last ``quiet`` in all. Not wall time since the last message:
    a recorder descheduled for longer than ``quiet`` on a loaded machine finds the messages
    that came meanwhile at its next spin. Not a count of spins alone: a spin that serves one
    of the recorder's own timers returns at once without a message, and such spins ended
    drains before the plant's last samples had come
    (docs/decisions/stopping-and-data-safety.md).
    """
    started = time.monotonic()
    timeout = min(SPIN_TIMEOUT, quiet)
    empty_needed = max(1, math.ceil(quiet / timeout - 1e-9))
    empty, empty_since = 0, started
    taken = 0
    while True:
        if not rclpy.ok(context=node.context):
            reason = 'shut down'
        elif stop.cut_short:
            reason = 'a second signal'
        elif empty >= empty_needed and time.monotonic() - empty_since >= quiet - QUIET_SLACK:
            reason = f'nothing for {quiet:g} s'
        elif time.monotonic() - started >= longest:
            reason = f'the {longest:g} s bound'
        else:
            before = node.last_received
            spun = time.monotonic()
            executor.spin_once(timeout_sec=timeout)
            if node.last_received == before:
                empty, empty_since = empty + 1, (empty_since if empty else spun)
            else:
                empty, taken = 0, taken + 1
            continue
        return reason, taken, time.monotonic() - started
