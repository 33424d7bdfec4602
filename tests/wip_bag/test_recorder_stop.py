"""When the recorder drains after a stop signal, and when its drain ends (no processes, no DDS).

``wip_bag.recorder_stop.spin`` and ``drain`` with a scripted executor and a simulated
clock: which signals start a drain, that a drain waits for spins without a message (not
for wall time, which a descheduled recorder loses), and that it ends at its bound while
messages keep coming. The same behaviour end to end: ``test_recorder_robust.py`` (a live
launcher's SIGTERM) and ``tests/wip_bringup/test_stop_signals.py`` (the launcher's death).
"""

import signal

import pytest

from wip_bag import recorder_stop

pytestmark = pytest.mark.ros


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class ScriptedExecutor:
    """spin_once: a message while ``messages`` lasts, then nothing; the clock moves on.

    A spin without a message lasts its timeout at least, as a real wait does; ``instant``
    (a set of spin numbers): those return at once without a message, as a spin that served
    one of the recorder's own timers does.
    """

    def __init__(self, node, clock, messages, seconds_per_spin, on_spin=None, instant=()):
        self.node, self.clock = node, clock
        self.messages = messages
        self.seconds_per_spin = seconds_per_spin
        self.on_spin = on_spin
        self.instant = set(instant)
        self.spins = 0

    def add_node(self, node):
        pass

    def spin_once(self, timeout_sec=None):
        self.spins += 1
        if self.on_spin is not None:
            self.on_spin(self.spins)
        if self.spins in self.instant:
            self.clock.now += 1e-4
        elif self.messages is None or self.messages > 0:   # None: they never stop
            self.clock.now += self.seconds_per_spin
            if self.messages is not None:
                self.messages -= 1
            self.node.last_received = self.clock.now
        else:
            self.clock.now += max(self.seconds_per_spin, timeout_sec or 0.0)


class FakeNode:
    context = None

    def __init__(self):
        self.last_received = 0.0
        self.logged = []

    def get_logger(self):
        return self

    def info(self, text):
        self.logged.append(text)


class Signals:
    """What :class:`recorder_stop.StopSignals` records, without installing handlers."""

    def __init__(self):
        self.count = 0
        self.first = None
        self.cut_short = False

    def receive(self, number):
        recorder_stop.StopSignals._on_signal(self, number, None)


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(recorder_stop.time, 'monotonic', fake)
    monkeypatch.setattr(recorder_stop.rclpy, 'ok', lambda context=None: True)
    return fake


@pytest.mark.parametrize('launched, number, drains', [
    (True, signal.SIGINT, True),     # the kernel's signal at the launcher's death
    (True, signal.SIGTERM, False),   # the live launcher's stop, after its own drain
    (True, signal.SIGHUP, False),
    (False, signal.SIGINT, False),   # run by hand: Ctrl-C stops at once
    (False, signal.SIGTERM, False),
])
def test_only_a_launched_recorders_sigint_starts_a_drain(clock, launched, number, drains):
    node, stop = FakeNode(), Signals()
    # Messages keep coming for 20 spins; the signal arrives at the 3rd.
    executor = ScriptedExecutor(node, clock, messages=20, seconds_per_spin=0.01,
                                on_spin=lambda k: stop.receive(number) if k == 3 else None)
    recorder_stop.spin(node, executor, stop, launched)
    assert stop.first == number
    if drains:   # every message, then the quiet spins
        empty = round(recorder_stop.STOP_QUIET / recorder_stop.SPIN_TIMEOUT)
        assert executor.spins == 20 + empty
        assert node.logged == ['stop: drained 0.67 s after the SIGINT (messages at 17 spins); '
                               'ended by nothing for 0.5 s']
    else:
        assert executor.spins == 3 and node.logged == []


def test_a_starved_drain_still_takes_what_came_meanwhile(clock):
    # Each spin comes a second after the previous one (the recorder descheduled on a
    # loaded machine), yet a message is waiting at each of the first 10: wall time since
    # the last message always exceeds the quiet time, and the drain must go on regardless.
    node, stop = FakeNode(), Signals()
    stop.receive(signal.SIGINT)
    executor = ScriptedExecutor(node, clock, messages=10, seconds_per_spin=1.0)
    recorder_stop.drain(node, executor, stop, quiet=0.5, longest=60.0)
    assert executor.messages == 0
    assert executor.spins == 10 + 5   # then five empty spins of 0.1 s


def test_a_drain_ends_at_its_bound_when_messages_never_stop(clock):
    node, stop = FakeNode(), Signals()
    stop.receive(signal.SIGINT)
    executor = ScriptedExecutor(node, clock, messages=None, seconds_per_spin=0.1)
    recorder_stop.drain(node, executor, stop, quiet=0.5, longest=30.0)
    assert executor.spins == pytest.approx(300, abs=1)


@pytest.mark.parametrize('second', [signal.SIGTERM, signal.SIGHUP])
def test_a_second_signal_of_another_kind_ends_a_drain(clock, second):
    node, stop = FakeNode(), Signals()
    stop.receive(signal.SIGINT)
    executor = ScriptedExecutor(node, clock, messages=None, seconds_per_spin=0.1,
                                on_spin=lambda k: stop.receive(second) if k == 7 else None)
    reason, _, _ = recorder_stop.drain(node, executor, stop, quiet=0.5, longest=30.0)
    assert executor.spins == 7 and stop.count == 2 and stop.first == signal.SIGINT
    assert reason == 'a second signal'


def test_the_kernels_repeated_sigint_does_not_end_a_drain(clock):
    # At the launcher's death the kernel sends SIGINT again for each of the launcher's
    # threads that holds this process while it dies: a drain cut at the second one lost
    # the plant's last ticks. Messages for 20 spins, the repeat at the 2nd: every message.
    node, stop = FakeNode(), Signals()
    stop.receive(signal.SIGINT)
    executor = ScriptedExecutor(node, clock, messages=20, seconds_per_spin=0.01,
                                on_spin=lambda k: stop.receive(signal.SIGINT) if k == 2 else None)
    reason, taken, _ = recorder_stop.drain(node, executor, stop, quiet=0.5, longest=30.0)
    assert stop.count == 2 and executor.messages == 0 and taken == 20
    assert reason == 'nothing for 0.5 s'


def test_spins_that_return_at_once_are_not_quiet(clock):
    # Ten spins that serve the recorder's timers (0.1 ms each, no message), then the
    # plant's last samples: five empty spins are not 0.5 s of quiet, so the drain takes them.
    node, stop = FakeNode(), Signals()
    stop.receive(signal.SIGINT)
    executor = ScriptedExecutor(node, clock, messages=3, seconds_per_spin=0.01,
                                instant=range(1, 11))
    reason, taken, seconds = recorder_stop.drain(node, executor, stop, quiet=0.5,
                                                 longest=30.0)
    assert taken == 3 and executor.spins == 10 + 3 + 5
    assert reason == 'nothing for 0.5 s' and seconds >= 0.5
