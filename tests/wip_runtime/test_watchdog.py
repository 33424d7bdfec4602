"""The mixer's watchdog (wip_runtime.executors.Watchdog): an rclpy timer, or the spin loop's.

Adopted by a composed spin loop it must call back exactly as the restarted rclpy timer
did: a period after the last kick, then every period on that grid; one call for a stall
longer than a period (an rclpy timer also calls once, not once per missed period). The
clock is faked, so nothing here depends on the machine's speed.
"""

import pytest

pytest.importorskip('rclpy')

from wip_runtime import executors  # noqa: E402
from wip_runtime.intra_process import IntraProcessBus  # noqa: E402

PERIOD = 0.005


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(executors.time, 'monotonic', fake)
    return fake


def test_an_adopted_watchdog_calls_a_period_after_the_last_kick_then_on_its_grid(
        test_node, clock):
    calls = []
    watchdog = executors.Watchdog(test_node, PERIOD, lambda: calls.append(clock.now))
    assert test_node.watchdogs == [watchdog] and not watchdog.timer.is_canceled()
    assert executors.adopt_watchdogs([test_node]) == [watchdog]
    assert watchdog.timer.is_canceled()          # no rclpy timer left to restart
    clock.now += 0.004
    watchdog.kick()                              # a command sent: the period restarts
    clock.now += 0.0049
    watchdog.fire_if_due(clock.now)
    assert calls == []
    clock.now += 0.0001
    watchdog.fire_if_due(clock.now)
    assert calls == [pytest.approx(100.009)]
    clock.now += 0.0051                          # the next call on the grid, not 5 ms later
    watchdog.fire_if_due(clock.now)
    assert len(calls) == 2 and watchdog.due == pytest.approx(100.019)


def test_a_grace_delays_the_first_call_after_a_kick_not_the_grid_after_it(test_node, clock):
    # The MPC's deadline in a composed process: the chain that runs its tick may end a
    # little later than a period after the last; a call just before it would be a second
    # tick of that period.
    calls = []
    watchdog = executors.Watchdog(test_node, PERIOD, lambda: calls.append(clock.now),
                                  grace=0.25 * PERIOD)
    watchdog.adopt()
    watchdog.kick()
    clock.now += PERIOD + 0.001                  # a late chain, within the grace: no call
    watchdog.fire_if_due(clock.now)
    assert calls == []
    watchdog.kick()
    clock.now += 1.25 * PERIOD
    watchdog.fire_if_due(clock.now)              # no chain within the grace: a call
    clock.now += PERIOD
    watchdog.fire_if_due(clock.now)              # then every period, without the grace
    assert calls == [pytest.approx(100.0 + 2.25 * PERIOD + 0.001),
                     pytest.approx(100.0 + 3.25 * PERIOD + 0.001)]


def test_a_stall_longer_than_a_period_gives_one_call_then_a_period_from_now(
        test_node, clock):
    calls = []
    watchdog = executors.Watchdog(test_node, PERIOD, lambda: calls.append(clock.now))
    watchdog.adopt()
    clock.now += 0.1                             # 20 periods without the loop running
    watchdog.fire_if_due(clock.now)
    watchdog.fire_if_due(clock.now)
    assert len(calls) == 1 and watchdog.due == pytest.approx(clock.now + PERIOD)


def test_a_failing_callback_is_reported_not_raised(test_node, clock):
    def fail():
        raise RuntimeError('boom')
    watchdog = executors.Watchdog(test_node, PERIOD, fail)
    watchdog.adopt()
    clock.now += PERIOD
    watchdog.fire_if_due(clock.now)              # logged by the node; the loop goes on
    assert watchdog.due == pytest.approx(clock.now + PERIOD)


def test_an_unadopted_watchdog_is_the_rclpy_timer_restarted_by_each_kick(test_node):
    watchdog = executors.Watchdog(test_node, 10.0, lambda: None)
    watchdog.timer.reset()
    watchdog.kick()
    assert not watchdog.adopted and not watchdog.timer.is_canceled()
    assert 9.0 < watchdog.timer.time_until_next_call() * 1e-9 <= 10.0


def test_a_bus_starts_without_watchdogs():
    # spin_composed reads bus.watchdogs; compose() fills it for a composed process.
    assert IntraProcessBus().watchdogs == []
