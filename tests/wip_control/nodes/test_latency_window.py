"""The mixer's latency window: the percentiles of the last N latencies, whatever came before.

Criterion: bit for bit ``np.percentile`` of the last ``size`` latencies added (a deque of
that length, what the window replaced), before, at and past the wrap of its ring.
"""

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

pytest.importorskip('rclpy')

from wip_control.nodes.torque_mixer_node import LatencyWindow  # noqa: E402

Q = (50, 99, 100)


@settings(max_examples=200, deadline=None)
@given(size=st.integers(1, 40),
       latencies=st.lists(st.floats(0.0, 0.1, allow_subnormal=False), min_size=1,
                          max_size=130))
def test_the_percentiles_are_those_of_the_last_size_latencies(size, latencies):
    window = LatencyWindow(size)
    for k, latency in enumerate(latencies, start=1):
        window.add(latency)
        assert window.count == k and len(window) == min(k, size)
        expected = np.percentile(np.array(latencies[max(0, k - size):k]), Q)
        assert window.percentiles(Q).tobytes() == expected.tobytes()
