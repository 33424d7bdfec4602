"""How a run ends early: stop signals as Ctrl-C, and a full disk.

SIGTERM (systemd, docker stop) and SIGHUP (a closed terminal) stop a run as SIGINT does;
the exit status is 128 + the signal after the whole stop (docs/run_graph.md).
"""

from __future__ import annotations

import contextlib
import errno
import signal
import threading


#: Signals that stop a run as Ctrl-C does: a service manager's stop (systemd, docker
#: stop) and a closed terminal. The exit status of such a stop is 128 + the signal's number,
#: what a shell reports for a process that a signal ended (130 SIGINT, 143 SIGTERM, 129
#: SIGHUP), but after the whole stop: nodes stopped, recorder drained, bag closed,
#: run.json written.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
STOP_EXIT_CODES = tuple(128 + int(number) for number in STOP_SIGNALS)


class StopRequested(KeyboardInterrupt):
    """SIGTERM or SIGHUP as a KeyboardInterrupt.

    SIGTERM or SIGHUP: a KeyboardInterrupt, so that every place that stops cleanly on
    Ctrl-C does on these too; ``signum`` says which.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: The stop signals received in this process, in order (see :func:`stop_raised_in_native_code`).
_received: list[int] = []


def _raise_stop(signum, frame) -> None:
    _received.append(signum)
    raise StopRequested(signum)


def _raise_interrupt(signum, frame) -> None:
    _received.append(signum)
    raise KeyboardInterrupt


@contextlib.contextmanager
def stop_raised_in_native_code():
    """Give back a stop signal's exception that native code turned into another error.

    A signal handler runs at the next Python instruction, which may be inside a native
    call: an exception it raises while pybind11 converts a value (rclpy's take of a
    message) comes out as ``RuntimeError: Unable to convert call argument``, and the stop
    would end as an internal error. A signal received within this block while such an
    error leaves it is raised again as the stop (KeyboardInterrupt or StopRequested).
    """
    mark = len(_received)
    try:
        yield
    except Exception as error:
        if len(_received) == mark:
            raise
        signum = _received[-1]
        if signum == signal.SIGINT:
            raise KeyboardInterrupt from error
        raise StopRequested(signum) from error


@contextlib.contextmanager
def stop_signals():
    """Turn SIGTERM, SIGHUP and SIGINT into exceptions in the main thread.

    SIGTERM and SIGHUP raise :class:`StopRequested` in the main thread while a run is
    in this block, and SIGINT KeyboardInterrupt: set here too, because a program started in
    the background by a non-interactive shell (a CI step, ``cmd &``) inherits SIGINT
    ignored, and Python then installs no handler of its own.
    """
    if threading.current_thread() is not threading.main_thread():
        yield   # handlers can only be set from the main thread; the caller stops it
        return
    previous = {n: signal.signal(n, _raise_stop) for n in (signal.SIGTERM, signal.SIGHUP)}
    previous[signal.SIGINT] = signal.signal(signal.SIGINT, _raise_interrupt)
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def stop_signal_number(error: KeyboardInterrupt) -> int:
    """Return the signal behind a KeyboardInterrupt (SIGINT unless it is a StopRequested)."""
    return error.signum if isinstance(error, StopRequested) else int(signal.SIGINT)


class DiskFull(Exception):
    """An output could not be written: no space left (or a quota); ``where`` names it."""


def is_disk_full(error: BaseException) -> bool:
    return isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT)
