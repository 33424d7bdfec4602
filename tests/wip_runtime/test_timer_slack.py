"""A node process's spinning thread gets a short timer slack.

The composed spin loop calls the EventsExecutor's ``spin_once(timeout_sec=0)`` about once
a control tick; that is a timed wait, which Linux may end up to the thread's timer slack
late (50 µs by default). ``make_executor`` shortens the slack of the thread that makes it
(the one that spins), and threads it starts later inherit it.
"""

from __future__ import annotations

import sys
import threading

import pytest

pytest.importorskip('rclpy')

pytestmark = pytest.mark.skipif(not sys.platform.startswith('linux'),
                                reason='timer slack is a Linux setting')


def in_a_thread(function):
    """Run ``function`` in a thread of its own (the slack is per thread); its result."""
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault('value', function()))
    thread.start()
    thread.join(timeout=30)
    return result['value']


def test_make_executor_shortens_the_slack_of_its_thread_and_of_threads_started_later(context):
    from wip_runtime.executors import make_executor, set_timer_slack, TIMER_SLACK_NS, timer_slack

    def scenario():
        assert set_timer_slack(50_000)
        assert timer_slack() == 50_000
        executor = make_executor(context=context)
        try:
            own = timer_slack()
            inherited = in_a_thread(timer_slack)
        finally:
            executor.shutdown()
        return own, inherited

    assert in_a_thread(scenario) == (TIMER_SLACK_NS, TIMER_SLACK_NS)
    assert TIMER_SLACK_NS < 50_000


def test_without_prctl_the_executor_is_made_all_the_same(monkeypatch, context):
    from wip_runtime import executors

    def no_libc(*args, **kwargs):
        raise OSError('no libc here')

    monkeypatch.setattr(executors.ctypes, 'CDLL', no_libc)
    assert executors.set_timer_slack() is False
    assert executors.timer_slack() is None
    executor = executors.make_executor(context=context)
    executor.shutdown()
