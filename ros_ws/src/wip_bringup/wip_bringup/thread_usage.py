"""What each thread of a node process did during a run: CPU, waits, preemptions (Linux /proc).

A process's CPU share says how much; its threads say where. The thread that spins the
nodes (the process's first) runs their code, rclpy's and the synchronous DDS writes; Fast
DDS adds its receive threads (shared memory, UDP) and its timed-events thread. Per thread:
CPU time, voluntary context switches (it waited: for a message, a timer, a lock) and
involuntary ones (it was preempted while it could run). ``scripts/bench`` prints them per
control tick (docs/realtime.md, section 2).
"""

from __future__ import annotations

import os
from typing import Mapping

#: Thread kinds; Fast DDS names its threads "dds.<role>.<id>".
SPINNING = 'spinning'
SHM_RECEIVE = 'DDS shared-memory receive'
UDP_RECEIVE = 'DDS UDP receive'
TIMED_EVENTS = 'DDS timed events'
OTHER = 'other'
#: The kinds in the order they are reported.
KINDS = (SPINNING, SHM_RECEIVE, UDP_RECEIVE, TIMED_EVENTS, OTHER)

#: (cpu [s], voluntary switches, involuntary switches, kind) of a thread.
Counters = tuple[float, int, int, str]


def thread_kind(name: str, is_first: bool) -> str:
    """Return the kind of a thread from its name (``comm``) and whether it is the first."""
    if is_first:
        return SPINNING
    if name.startswith('dds.shm.') and name != 'dds.shm.wdog':
        return SHM_RECEIVE
    if name.startswith('dds.udp.'):
        return UDP_RECEIVE
    if name.startswith('dds.ev.'):
        return TIMED_EVENTS
    return OTHER


def stat_name_and_cpu(stat: str) -> tuple[str, float]:
    """Return the name and the CPU time [s] (user + system) of a proc(5) ``stat`` line."""
    fields = stat.rsplit(')', 1)[1].split()
    return (stat[stat.index('(') + 1:stat.rindex(')')],
            (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK'))


def read_threads(pid: int) -> dict[int, Counters]:
    """Return each live thread's counters by thread id ({} if the process is gone)."""
    threads = {}
    try:
        ids = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return {}
    for entry in ids:
        try:
            with open(f'/proc/{pid}/task/{entry}/stat', encoding='ascii',
                      errors='replace') as stream:
                stat = stream.read()
            with open(f'/proc/{pid}/task/{entry}/status', encoding='ascii',
                      errors='replace') as stream:
                status = dict(line.split(':', 1) for line in stream if ':' in line)
            name, cpu = stat_name_and_cpu(stat)
            thread = int(entry)
            threads[thread] = (cpu, int(status['voluntary_ctxt_switches']),
                               int(status['nonvoluntary_ctxt_switches']),
                               thread_kind(name, thread == pid))
        except (OSError, ValueError, IndexError, KeyError):
            # The thread ended between the listing and the read, or a kernel without
            # these fields: a figure for the bench, never a reason for a run to fail.
            continue
    return threads


def snapshot(pids: Mapping[str, int]) -> dict[str, dict[int, Counters]]:
    """Return the counters of every thread of each named process."""
    return {name: read_threads(pid) for name, pid in pids.items()}


def usage_since(start: Mapping[str, dict[int, Counters]],
                end: Mapping[str, dict[int, Counters]],
                wall_s: float) -> dict[str, dict[str, dict[str, float]]]:
    """Per process and thread kind, what its threads did between two snapshots.

    ``{process: {kind: {'cpu_fraction', 'waits_per_s', 'preempted_per_s', 'threads'}}}``
    over ``wall_s`` [s]. A thread that started after ``start`` counts from zero; one that
    ended before ``end`` is not counted (its last counters are unknown).
    """
    usage: dict[str, dict[str, dict[str, float]]] = {}
    if wall_s <= 0.0:
        return usage
    for process, threads in end.items():
        before = start.get(process, {})
        kinds: dict[str, dict[str, float]] = {}
        for thread, (cpu, waits, preempted, kind) in threads.items():
            cpu0, waits0, preempted0, _ = before.get(thread, (0.0, 0, 0, kind))
            into = kinds.setdefault(kind, {'cpu_fraction': 0.0, 'waits_per_s': 0.0,
                                           'preempted_per_s': 0.0, 'threads': 0})
            into['cpu_fraction'] += (cpu - cpu0) / wall_s
            into['waits_per_s'] += (waits - waits0) / wall_s
            into['preempted_per_s'] += (preempted - preempted0) / wall_s
            into['threads'] += 1
        if kinds:
            usage[process] = {kind: kinds[kind] for kind in KINDS if kind in kinds}
    return usage
