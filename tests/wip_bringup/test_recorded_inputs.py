"""``--record`` keeps the run's inputs: the references and the e-stop's topics.

A recorded lockstep run while this test publishes, as a user's teleop, planner, e-stop
button and reset would, on /cmd_vel, /plan, /wip/estop (false: released) and
/wip/estop_reset: each is in the bag, with the messages as sent, and the mixer's
/diagnostics say what the reset did.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

pytest.importorskip('rclpy')
from ros_harness import spinning_in_background  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_the_runs_inputs_are_in_the_bag(tmp_path, test_node, domain):
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from nav_msgs.msg import Path
    from std_msgs.msg import Bool, Empty
    from wip_bag.bag_reader import read_bag
    publishers = {
        '/cmd_vel': (test_node.create_publisher(TwistStamped, '/cmd_vel', 10), TwistStamped),
        '/plan': (test_node.create_publisher(Path, '/plan', 10), Path),
        '/wip/estop': (test_node.create_publisher(Bool, '/wip/estop', 10), Bool),
        '/wip/estop_reset': (test_node.create_publisher(Empty, '/wip/estop_reset', 10), Empty),
    }
    stop = threading.Event()
    sent = {topic: 0 for topic in publishers}

    def publish() -> None:
        while not stop.wait(0.05):
            for topic, (publisher, kind) in publishers.items():
                message = kind()
                if kind is TwistStamped:
                    message.twist.linear.x = 0.25
                elif kind is Path:
                    message.header.frame_id = 'map'
                    message.poses.append(PoseStamped())
                publisher.publish(message)
                sent[topic] += 1

    thread = threading.Thread(target=publish, daemon=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    with spinning_in_background(test_node.executor_for_test):
        thread.start()
        try:
            done = subprocess.run(
                [sys.executable, '-m', 'wip_bringup.graph', '--duration', '20', '--quiet',
                 '--record', str(tmp_path / 'bag'), '--out', str(tmp_path / 'run')],
                env=env, capture_output=True, text=True, timeout=600)
        finally:
            stop.set()
            thread.join()
    assert done.returncode == 0, done.stderr
    counts: dict[str, int] = {}
    first: dict[str, object] = {}
    for topic, _type, _t, message in read_bag(tmp_path / 'bag', topics=list(publishers)):
        counts[topic] = counts.get(topic, 0) + 1
        first.setdefault(topic, message)
    print(f'sent {sent}; in the bag {counts}')
    assert set(counts) == set(publishers), counts
    assert all(counts[t] >= 5 for t in publishers), counts
    assert first['/cmd_vel'].twist.linear.x == 0.25
    assert first['/plan'].header.frame_id == 'map' and len(first['/plan'].poses) == 1
    assert first['/wip/estop'].data is False
    # A reset leaves its trace in the mixer's /diagnostics (the service's too).
    resets = [kv.value for _t, _type, _s, array in read_bag(tmp_path / 'bag',
                                                            topics=['/diagnostics'])
              for status in array.status for kv in status.values
              if kv.key == 'last e-stop reset']
    assert resets and resets[-1].startswith('done via /wip/estop_reset at '), resets[-1:]
