"""The safety monitor's test harness: a fake clock that feeds every input every tick.

Times are seconds of a fake monotonic clock advanced by the tests: H = 5 ms ticks, as the
mixer's 200 Hz timer.
"""

from wip_control.core.eso import StateEstimate
from wip_control.core.safety import ACTIVE, DriveStatus, SafetyMonitor, SHADOW
from wip_control.core.safety_config import SafetyParams

H = 0.005                   # tick period [s]
TAU_MAX = 15.0              # [N m], the default MixerParams
RATE = 1.0e4                # [N m/s], the default MixerParams: 50 N m per tick, no limit
ESTIMATE = StateEstimate(phi=0.1, omega=0.2, f1=0.3, x_v=1.0, v=0.5, f2=-0.4, theta=0.02,
                         theta_dot=-0.1, f3=0.5, epsilon=0.01)


class Clock:
    """Drives a monitor: feeds every input every tick, like a healthy graph."""

    def __init__(self, monitor, t=100.0):
        self.monitor, self.t = monitor, t
        self.tau_v, self.tau_omega, self.status = 4.0, 0.6, DriveStatus.SOLVED
        self.estimate, self.settled = ESTIMATE, True

    def feed(self):
        m = self.monitor
        m.estimate(self.t, self.estimate, self.settled)
        m.yaw_torque(self.t, self.tau_omega)
        m.drive_torque(self.t, self.tau_v, self.status)

    def tick(self, feed=True):
        self.t += H
        if feed:
            self.feed()
        return self.monitor.update(self.t)


def active(config=SafetyParams(), rate=RATE, **kwargs):
    """Return a monitor driven to ACTIVE, with its clock."""
    monitor = SafetyMonitor(config, TAU_MAX, rate, H, **kwargs)
    clock = Clock(monitor)
    for _ in range(int(config.settle_time / H) + 3):
        decision = clock.tick()
    assert decision.state in (ACTIVE, SHADOW), decision
    return monitor, clock


def assert_zeroed(decision, state, *words):
    assert (decision.tau_left, decision.tau_right, decision.zeroed) == (0.0, 0.0, True)
    assert decision.command == (0.0, 0.0)
    assert decision.state == state, decision
    for word in words:
        assert word in decision.reason, (word, decision.reasons)
