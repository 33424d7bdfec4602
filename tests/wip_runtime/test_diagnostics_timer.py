"""/diagnostics every 0.1 s while a node starts, then at its period (nodes/diagnostics.py).

A launcher waits for a status of every node sent after its view of the graph is complete,
up to a whole period at the steady 1 s. The timer's period is checked directly
(timer callbacks called by hand: no dependence on the machine's speed), and once through
an executor on the wall clock.
"""

import time

import pytest

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402

from wip_runtime import diagnostics  # noqa: E402

FAST_NS, STEADY_NS = 100_000_000, 1_000_000_000


def test_the_timer_is_fast_while_the_node_starts_and_steady_after(test_node):
    state = {'starting': True}
    calls = []
    timer = diagnostics.create_diagnostics_timer(test_node, lambda: calls.append(1), 1.0,
                                                 starting=lambda: state['starting'])
    assert timer.timer_period_ns == FAST_NS
    timer.callback()
    assert calls == [1] and timer.timer_period_ns == FAST_NS
    state['starting'] = False
    timer.callback()
    assert calls == [1, 1] and timer.timer_period_ns == STEADY_NS


def test_the_start_up_rate_ends_after_the_start_up_time_even_if_the_node_never_starts(
        test_node, monkeypatch):
    timer = diagnostics.create_diagnostics_timer(test_node, lambda: None, 2.0)
    timer.callback()
    assert timer.timer_period_ns == FAST_NS
    monkeypatch.setattr(diagnostics, 'STARTUP_TIME', 0.0)
    timer.callback()
    assert timer.timer_period_ns == 2 * STEADY_NS


def test_a_controllers_diagnostics_slow_down_at_its_first_input(test_node):
    node_diagnostics = diagnostics.NodeDiagnostics(test_node, 'test role', ('state',))
    timer = node_diagnostics.timer
    timer.callback()
    assert timer.timer_period_ns == FAST_NS     # waiting for inputs
    node_diagnostics.input('state', 0)
    timer.callback()
    assert timer.timer_period_ns == STEADY_NS
    assert diagnostics.NodeDiagnostics(test_node, 'no timer', (), period=0.0).timer is None


def test_a_starting_node_reports_several_times_a_second(test_node):
    # Through an executor: statuses of a node that waits for inputs arrive at 10 Hz. Only
    # a lower bound well below 10 per second is asserted (a loaded machine delays timers).
    received = []
    test_node.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda msg: received.extend(s for s in msg.status if 'starting test' in s.name), 50)
    diagnostics.NodeDiagnostics(test_node, 'starting test', ('state',))
    deadline = time.monotonic() + 60.0
    started = None
    while len(received) < 6 and time.monotonic() < deadline:
        test_node.executor_for_test.spin_once(timeout_sec=0.05)
        if received and started is None:
            started = time.monotonic()
    assert len(received) >= 6
    # Five periods after the first status: 0.5 s at 10 Hz, 5 s at the steady 1 Hz.
    assert time.monotonic() - started < 4.0
