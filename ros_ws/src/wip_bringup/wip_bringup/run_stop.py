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


def _raise_stop(signum, frame) -> None:
    raise StopRequested(signum)


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
    previous[signal.SIGINT] = signal.signal(signal.SIGINT, signal.default_int_handler)
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
