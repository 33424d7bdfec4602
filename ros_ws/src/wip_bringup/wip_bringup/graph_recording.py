"""What a simulation run does for its recorder and with its plant's stats.

The end of a recorded run: the recorder drained of what the graph published, a full disk
found in its reports or its log, ``OUT/plant_stats.json`` read back (a mixin of
:class:`wip_bringup.graph_runner.GraphRunner`).
"""

from __future__ import annotations

import json
import time

from .graph_design import expected_recorded, PUBLISHERS
from .run_stop import DiskFull

#: [s] for the recorder to receive the last messages: the wait ends early when the counts
#: are complete, or when they have not changed for DRAIN_STALL (the recorder has nothing
#: left); it goes on while they grow (a recorder behind on a loaded machine catches up).
DRAIN_TIMEOUT = 120.0
DRAIN_STALL = 2.5


class RecordingMixin:
    """The recorder and the plant's stats of :class:`~wip_bringup.graph_runner.GraphRunner`."""

    def plant_stats(self) -> dict | None:
        """``OUT/plant_stats.json``, or None when absent or unreadable.

        The plant could not write it whole: a full disk.
        """
        try:
            stats = json.loads((self.out / 'plant_stats.json').read_text(encoding='utf-8'))
        except (OSError, ValueError):
            return None
        return stats if isinstance(stats, dict) else None

    def where_stopped(self) -> str:
        """' at t = ... s' of simulated time, when the plant has reported progress."""
        t = (self.plant_stats() or {}).get('sim_time_s')
        t = t if isinstance(t, (int, float)) else self.last_sim_time
        return f' at t = {t:.3f} s' if t is not None else ''

    def check_recorder_space(self) -> None:
        """DiskFull if the recorder reports that the disk filled up.

        The run stops there (going on would record nothing more).
        """
        found = self.probe.status_values(': recorder') if self.bag is not None else None
        if found is None:
            return
        message = found[0].message
        if message.startswith('disk full'):   # the recorder finished the bag in time
            raise DiskFull(f'disk full{self.where_stopped()}: the recorder stopped and '
                           f'finished {self.bag} with what fit; the run was stopped there')
        if message.startswith('bag write failed') and ('No space left' in message
                                                       or 'quota' in message):
            raise DiskFull(f'disk full{self.where_stopped()}: the recorder could not write '
                           f'{self.bag} any more (scripts/bag_repair {self.bag} recovers '
                           'every complete chunk); the run was stopped there')

    def recorder_disk_full(self) -> bool:
        """Whether the recorder's log says a write failed for want of space."""
        recorder = self.processes.get('recorder')
        if recorder is None:
            return False
        tail = recorder.log_tail(400)
        return 'No space left on device' in tail or 'Disk quota exceeded' in tail

    def expected_recorded(self) -> dict[str, int]:
        """Messages a lockstep run published per topic, from the plant's tick count.

        Empty when the clock is real time or the tick count is unknown
        (:func:`~wip_bringup.graph_design.expected_recorded`).
        """
        if self.options.clock != 'lockstep':
            return {}
        ticks = (self.plant_stats() or {}).get('ticks')
        if not isinstance(ticks, int):
            return {}
        return expected_recorded(ticks, self.scenario)

    def drain_recorder(self, quiet: bool = False) -> None:
        """Wait until the recorder received everything the graph published.

        Lockstep: until its /diagnostics counts reach :meth:`expected_recorded`; otherwise
        (or if they never do) until the counts of the topics that end with the plant
        stopped changing over two of its /diagnostics messages.
        """
        if 'recorder' not in self.processes:
            return
        expected = self.expected_recorded()
        # Topics that stop when the plant does (in real time the controllers run on timers
        # too: the reference, the MPC, the mixer's watchdog).
        watched = set(expected) or {t for t, p in PUBLISHERS.items() if p == ('plant',)}
        deadline = time.monotonic() + DRAIN_TIMEOUT
        previous = None
        stable_since = None
        while time.monotonic() < deadline:
            if self.processes['recorder'].poll() is not None:
                return
            self.probe.spin(0.1)
            found = self.probe.status_values(': recorder')
            if found is None:
                continue
            _, values = found
            counts = {k[len('received '):]: int(v) for k, v in values.items()
                      if k.startswith('received /') and k[len('received '):] in watched}
            if expected and all(counts.get(t, 0) >= n for t, n in expected.items()):
                return
            if counts != previous:
                previous, stable_since = counts, time.monotonic()
            elif time.monotonic() - stable_since >= DRAIN_STALL:
                if expected and not quiet:
                    self.recorder_shortfall = {
                        t: f'{counts.get(t, 0)}/{n}' for t, n in expected.items()
                        if counts.get(t, 0) < n}
                    self.say(f'warning: the recorder missed messages: '
                             f'{self.recorder_shortfall}')
                return
        self.say(f'warning: the recorder was still receiving after {DRAIN_TIMEOUT:g} s')
