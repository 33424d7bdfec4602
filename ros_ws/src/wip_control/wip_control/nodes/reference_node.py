"""Reference node: the reference trajectory (x_r, y_r, ϕ_r, υ_r, ω_r, ω̇_r) of the generator.

Publishes ``/wip/reference`` (wip_msgs/ReferenceState) at ``rates.control_rate``, the
reference sampled at the stamp's time (``core.references``: trifolium, circle, line,
figure eight, waypoints), and ``/diagnostics``.

lockstep: one reference per ``/clock`` sample on the control grid (t = k / control_rate,
t = 0 included), stamped with that sample's time, so that the generator finds
reference(t_k) for every estimate(t_k). (A sim-time timer would first fire one period
after t = 0: see ``common.py``.)
realtime: a timer of period 1/``rates.control_rate`` on the node clock; the reference
time is the time since the first tick (the path starts when the node does), the stamp
is the node clock's now.

Parameters (read-only): sections ``reference`` and ``rates``; ``frame_id``,
``clock_mode``, ``diagnostics_period``.
"""

from __future__ import annotations

import sys
import time

from wip_msgs.msg import ReferenceState as ReferenceStateMsg

from ..core.references import make_reference, ReferenceConfig
from ..core.scenario import RatesConfig
from .common import ClockTicker, ControllerNode, RELIABLE_QOS, run_node
from .conversions import reference_to_msg
from .diagnostics import OK
from .parameters import ConfigParameters, declare_plain


class ReferenceNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('reference', 'reference trajectory', ('clock',), **kwargs)
        self.config = ConfigParameters(self, 'reference', ReferenceConfig).config
        self.rates = ConfigParameters(self, 'rates', RatesConfig).config
        self.frame_id = declare_plain(self, 'frame_id', 'map', '',
                                      'frame of the reference position')
        self.reference = make_reference(self.config)
        self.period = 1.0 / self.rates.control_rate
        self.publisher = self.create_publisher(ReferenceStateMsg, '/wip/reference',
                                               RELIABLE_QOS)
        if self.lockstep:
            self.ticker = ClockTicker(self, self.period, self._guarded)
        else:
            self.create_timer(self.period, lambda: self._guarded(self.now_ns()))
        self.diagnostics.state(OK, f'{self.config.kind} reference at '
                               f'{self.rates.control_rate:g} Hz')

    def _guarded(self, stamp_ns: int) -> None:
        try:
            self.publish_at(stamp_ns)
        except Exception as err:  # noqa: B902 - a callback must not stop the node
            self.diagnostics.drop('clock', 'error', f'{type(err).__name__}: {err}')

    def publish_at(self, stamp_ns: int) -> None:
        """Publish the reference at the time of ``stamp_ns`` [ns]."""
        start = time.perf_counter()
        self.diagnostics.input('clock', stamp_ns)
        ref = self.reference.sample(self.time_base.seconds(stamp_ns))
        self.publisher.publish(reference_to_msg(ref, stamp_ns, self.frame_id))
        self.diagnostics.output(stamp_ns, time.perf_counter() - start)


def main(args=None) -> int:
    """Entry point ``reference``."""
    return run_node(ReferenceNode, 'reference', args)


if __name__ == '__main__':
    sys.exit(main())
