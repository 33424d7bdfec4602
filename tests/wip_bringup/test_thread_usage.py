"""What each thread of a node process did: read from /proc, grouped by kind, per second."""

from __future__ import annotations

import io
import os
import sys
import threading
import time

import pytest

from wip_bringup import thread_usage
from wip_bringup.thread_usage import KINDS, SPINNING, thread_kind

pytestmark = pytest.mark.skipif(not sys.platform.startswith('linux'),
                                reason='thread counters are read from /proc')


def test_fast_dds_threads_are_told_apart_by_name_and_the_first_thread_spins():
    assert thread_kind('controllers', is_first=True) == SPINNING
    assert thread_kind('dds.shm.12165', False) == 'DDS shared-memory receive'
    assert thread_kind('dds.shm.wdog', False) == 'other'      # the segments' watchdog
    assert thread_kind('dds.udp.7412', False) == 'DDS UDP receive'
    assert thread_kind('dds.ev.0', False) == 'DDS timed events'
    assert thread_kind('controllers', False) == 'other'       # rclpy's own threads
    assert set(KINDS) >= {SPINNING, 'other'}


def test_usage_is_the_difference_per_second_by_kind_new_threads_from_zero():
    start = {'controllers': {10: (1.0, 100, 30, SPINNING), 11: (0.5, 40, 1, 'DDS timed events'),
                             12: (0.2, 5, 0, 'other')}}
    end = {'controllers': {10: (1.5, 300, 90, SPINNING), 11: (0.6, 240, 3, 'DDS timed events'),
                           13: (0.1, 20, 2, 'DDS timed events')},    # 12 ended, 13 started
           'gone': {}}
    usage = thread_usage.usage_since(start, end, wall_s=2.0)
    assert list(usage) == ['controllers']                  # a process gone: nothing to say
    assert list(usage['controllers']) == [SPINNING, 'DDS timed events']    # in KINDS' order
    assert usage['controllers'][SPINNING] == pytest.approx(
        {'cpu_fraction': 0.25, 'waits_per_s': 100.0, 'preempted_per_s': 30.0, 'threads': 1})
    assert usage['controllers']['DDS timed events'] == pytest.approx(
        {'cpu_fraction': 0.1, 'waits_per_s': 110.0, 'preempted_per_s': 2.0, 'threads': 2})
    assert thread_usage.usage_since(start, end, wall_s=0.0) == {}


def test_a_thread_that_sleeps_fifty_times_waited_at_least_fifty_times():
    go, done = threading.Event(), threading.Event()

    def sleeper():
        go.wait()
        for _ in range(50):
            time.sleep(0.001)     # a timed sleep blocks: one voluntary switch at least
        done.set()
        time.sleep(5.0)

    thread = threading.Thread(target=sleeper, daemon=True)
    thread.start()
    while thread.native_id is None:
        time.sleep(0.001)
    start = thread_usage.snapshot({'self': os.getpid()})
    go.set()
    assert done.wait(timeout=30.0)
    end = thread_usage.snapshot({'self': os.getpid()})
    mine = end['self'][thread.native_id]
    assert mine[1] - start['self'][thread.native_id][1] >= 50
    assert mine[3] == 'other' and end['self'][os.getpid()][3] == SPINNING
    assert thread_usage.read_threads(2 ** 22 + 1) == {}     # no such process


def test_a_proc_without_the_switch_counts_gives_no_figures_not_an_error(monkeypatch):
    # A run must never fail on its monitoring: a status file without the fields is skipped.
    real_open = open

    def status_without_counts(path, *args, **kwargs):
        if str(path).endswith('/status'):
            return io.StringIO('Name:\tprobe\nState:\tS (sleeping)\n')
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr('builtins.open', status_without_counts)
    assert thread_usage.read_threads(os.getpid()) == {}
