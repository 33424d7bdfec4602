"""node_cost's scheduler counters per tick: what the kernel counts for the measuring thread."""

import sys
import time

import pytest

from wip_tools import node_cost

pytestmark = pytest.mark.skipif(not sys.platform.startswith('linux'),
                                reason='/proc/thread-self is Linux')


def test_each_sleep_is_a_voluntary_switch_and_a_spin_is_none():
    before = node_cost._scheduler_counters()
    for _ in range(5):
        time.sleep(0.002)
    slept = node_cost._scheduler_counters()
    end = time.thread_time() + 0.003
    while time.thread_time() < end:   # on the CPU throughout: nothing to wait for
        pass
    spun = node_cost._scheduler_counters()
    per_sleep = node_cost._per_tick(before, slept, 5)
    assert per_sleep['voluntary_switches'] >= 1.0, per_sleep
    assert node_cost._per_tick(slept, spun, 1)['voluntary_switches'] == 0.0
    # The process's CPU time grows by at least the spin's thread CPU time.
    assert spun['process_cpu_us'] - slept['process_cpu_us'] >= 2500.0


def test_unknown_counters_give_none():
    assert node_cost._per_tick(None, {'migrations': 1.0}, 10) is None
