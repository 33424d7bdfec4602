"""Hardware mode's arming heartbeat, published from a thread of its own.

The mixer faults when no /wip/heartbeat came for ``safety.max_estop_age``
(:data:`~.hardware_params.HEARTBEAT_MAX_AGE`). A timer of the runner's probe would beat
only while the runner's loop spins; this thread needs only its process to be scheduled,
and ends with it: the heartbeat still stops when the supervisor dies (docs/run_graph.md,
arming).
"""

from __future__ import annotations

import threading
import time
from typing import Callable


class Heartbeat:
    """Call ``publish`` every ``period`` [s] from a daemon thread, from :meth:`arm` on.

    :meth:`stop` ends the beats and waits for the thread: call it before the publisher
    is destroyed.
    """

    def __init__(self, publish: Callable[[], None], period: float) -> None:
        self._publish = publish
        self.period = period
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name='heartbeat', daemon=True)

    @property
    def armed(self) -> bool:
        return self._thread.is_alive()

    def arm(self) -> None:
        if not self._stopped.is_set() and self._thread.ident is None:
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stopped.set()
        if self._thread.ident is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        next_beat = time.monotonic()
        while not self._stopped.is_set():
            self._publish()
            # On the period's grid; after a stall of the thread (this beat late), a period
            # from now: no burst of the beats missed.
            next_beat += self.period
            now = time.monotonic()
            if next_beat <= now:
                next_beat = now + self.period
            self._stopped.wait(next_beat - now)
