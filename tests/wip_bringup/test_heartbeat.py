"""Hardware mode's /wip/heartbeat does not depend on the runner's loop.

The mixer faults (zero torque) when no heartbeat came for ``HEARTBEAT_MAX_AGE`` (1 s). The
runner's loop once did not spin for a second on a loaded machine; its probe's timer,
which published the heartbeat then, went 1.0 s stale and the mixer faulted a robot that
balanced. Here the publisher's node is never spun and this thread is held in a pure-Python
loop for twice that age (the runner's loop stuck), while a reader in another context
receives the beats.
"""

from __future__ import annotations

import time

import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Empty  # noqa: E402

from ros_harness import spin_until, spinning_in_background  # noqa: E402
from wip_bringup.hardware_params import HEARTBEAT_MAX_AGE  # noqa: E402
from wip_bringup.hardware_runner import HEARTBEAT_PERIOD  # noqa: E402
from wip_bringup.heartbeat import Heartbeat  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.wallclock]

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)  # the runner's


@pytest.fixture
def two_contexts(domain):
    """Yield the supervisor's node, the mixer's node and its executor, in the test's domain."""
    contexts = []
    nodes = []
    for name in ('run_graph', 'torque_mixer'):
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain)
        contexts.append(context)
        nodes.append(rclpy.create_node(name, context=context))
    executor = SingleThreadedExecutor(context=contexts[1])
    executor.add_node(nodes[1])
    yield nodes[0], nodes[1], executor
    executor.shutdown()
    for node, context in zip(nodes, contexts):
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_the_heartbeat_keeps_its_period_while_the_runners_loop_is_held_up(two_contexts):
    supervisor, mixer, executor = two_contexts
    received: list[float] = []
    mixer.create_subscription(Empty, '/wip/heartbeat',
                              lambda _: received.append(time.monotonic()), QOS)
    publisher = supervisor.create_publisher(Empty, '/wip/heartbeat', QOS)
    heartbeat = Heartbeat(lambda: publisher.publish(Empty()), HEARTBEAT_PERIOD)
    spin_until(executor, lambda: publisher.get_subscription_count() > 0, 'the match')
    try:
        with spinning_in_background(executor, step=0.01):
            # Not armed: nothing (the arm delay; the mixer stays in STARTING).
            time.sleep(3 * HEARTBEAT_PERIOD)
            assert received == []
            heartbeat.arm()
            armed_at = time.monotonic()
            # The runner's loop held up: this thread busy in Python, nothing spun for the
            # supervisor's node.
            end = armed_at + 2 * HEARTBEAT_MAX_AGE
            while time.monotonic() < end:
                pass
            busy_until = time.monotonic()
            heartbeat.stop()
            stopped_at = time.monotonic()
            time.sleep(3 * HEARTBEAT_PERIOD)
    finally:
        heartbeat.stop()
    during = [t for t in received if t <= busy_until]
    assert during, 'no heartbeat while the loop was held up'
    # What the mixer needs: no gap of its fault age, from the arming to the end of the
    # held-up loop (the age limit is the mixer's, not this machine's speed).
    gaps = [b - a for a, b in zip([armed_at, *during], [*during, busy_until])]
    print(f'{len(during)} beats in {busy_until - armed_at:.2f} s held up; largest gap '
          f'{max(gaps):.3f} s')
    assert max(gaps) < HEARTBEAT_MAX_AGE, gaps
    # Stopped: nothing after the last beat in flight (a period's grace for it).
    assert all(t <= stopped_at + HEARTBEAT_PERIOD for t in received), (stopped_at, received)
    assert not heartbeat.armed
