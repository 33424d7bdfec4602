"""The recorder never loses a recording: SIGKILL, a full disk, a bad path, split files.

Each test runs ``python -m wip_bag.recorder_node`` as its own process (see
bagtools_helpers) and checks the bag with ``rosbags``, an independent rosbag2 reader, after
``scripts/bag_repair`` where the recorder could not close it. Messages are std_msgs/String
carrying their index, so "every message, in order" is an exact comparison.
"""

import os
import resource
import signal
import time

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rclpy.qos import QoSProfile
from rosbags.rosbag2 import Reader
from std_msgs.msg import String

from bagtools_helpers import (assert_metadata_matches_content, DISCOVERY_TIMEOUT, spin_until,
                             start_recorder)
from wip_bag.bag_info import bag_information
from wip_bag.bag_reader import read_bag
from wip_bag.bag_repair import mcap_files_by_index, read_file_contents, repair_bag
from wip_bag.recorder_stop import STOP_DRAIN
from wip_runtime.launched import LAUNCHER_PID_VARIABLE

# The recorder must keep up with 500 Hz publishing and a publish may not block for
# 0.2 s: a wall-clock test (pytest.ini).
pytestmark = [pytest.mark.ros, pytest.mark.wallclock]

PUBLISH_PERIOD = 0.002  # [s]: 500 Hz, above every rate of the project's graph
SPLIT_TIMEOUT = 30.0  # [s]: a split normally comes within 1 s of publishing


def _newest_file_is_flushed_and_young(bag, max_age: float = 0.6) -> bool:
    """Whether the newest file of a bag being recorded is flushed and young.

    It holds a complete chunk and began (by the recorder's receive times, system time) less
    than ``max_age`` [s] ago, so that with max_bag_duration 1 s no split can come before a
    kill that follows at once.
    """
    files = mcap_files_by_index(bag)
    if not files:
        return False
    stats = read_file_contents(files[-1]).stats
    return stats.count > 0 and time.time_ns() - stats.start_ns < max_age * 1e9


def _publish_for(node, publisher, seconds, start, make=str, stop=None):
    """Publish make(k) for k = start, start+1 ... at PUBLISH_PERIOD for ``seconds``.

    Spinning the test node in between; returns the next k.
    """
    k = start
    next_time = time.monotonic()
    end = next_time + seconds
    while time.monotonic() < end and not (stop and stop()):
        publisher.publish(String(data=make(k)))
        k += 1
        # Late (a loaded machine), go on from now: catching up would publish a burst of
        # hundreds at once, more than the subscriptions' queues keep.
        next_time = max(next_time + PUBLISH_PERIOD, time.monotonic())
        node.executor_for_test.spin_once(timeout_sec=max(0.0, next_time - time.monotonic()))
    return k


def test_sigkill_mid_run_then_repair_keeps_every_complete_chunk(test_node, tools, tmp_path):
    bag = tmp_path / 'killed'
    topic = f'/robust_{os.getpid()}/kill'
    recorder = start_recorder(test_node, bag, [topic], 'flush_period:=0.2',
                              'max_bag_duration:=1.0')
    tools.append(recorder)
    publisher = test_node.create_publisher(String, topic, QoSProfile(depth=1000))
    recorder.spin_until(lambda: publisher.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        'the recorder to subscribe')
    k = _publish_for(test_node, publisher, 2.0, 0)
    # The recorder splits by the receive times it logs (max_bag_duration 1 s). A starved
    # recorder (a fresh-clone run with two busy processes) received these 2 s of messages
    # within less than 1 s of its own time and was killed in its first file: publish on
    # until it has opened its second one.
    k = _publish_for(test_node, publisher, SPLIT_TIMEOUT, k,
                     stop=lambda: len(mcap_files_by_index(bag)) >= 2)
    assert len(mcap_files_by_index(bag)) >= 2, f'no split within {SPLIT_TIMEOUT} s more'
    # What the recorder reported written (diagnostics) must survive the kill once a flush
    # period (0.2 s) has passed since: publish on until its report says so, then 1 s more
    # (5 flush periods). A starved recorder (two busy processes) had reported 944 messages
    # received but written only 853 when a fixed second later it was killed.
    reported = recorder.counts.get(topic, 0)
    assert reported > 100
    k = _publish_for(test_node, publisher, SPLIT_TIMEOUT, k,
                     stop=lambda: int(recorder.values.get('messages written', 0)) >= reported)
    assert int(recorder.values.get('messages written', 0)) >= reported, recorder.values
    # Then 1 s more (5 flush periods), and on until the file being written holds a flushed
    # chunk and is young enough that no split comes before the kill: a file that a split
    # opened holds no chunk for up to a flush period, and a kill at a fixed time after the
    # start (about 3 s, a multiple of max_bag_duration) found the newest file still empty.
    flushed_after = time.monotonic() + 1.0
    k = _publish_for(test_node, publisher, SPLIT_TIMEOUT, k,
                     stop=lambda: (time.monotonic() >= flushed_after
                                   and _newest_file_is_flushed_and_young(bag)))
    assert _newest_file_is_flushed_and_young(bag), 'no young file with a flushed chunk'
    recorder.process.send_signal(signal.SIGKILL)  # mid-run: messages still arriving
    recorder.wait(10.0, expected_code=-signal.SIGKILL)

    files = mcap_files_by_index(bag)
    assert len(files) >= 2  # split by duration: finished files and the killed one
    contents = [read_file_contents(f) for f in files]
    assert [c.finished for c in contents] == [True] * (len(files) - 1) + [False]
    in_complete_chunks = sum(c.stats.count for c in contents)

    result = repair_bag(bag)  # into a new bag: killed_repaired
    repaired = result.out
    assert result.files[-1].action == 'rewritten'
    info = assert_metadata_matches_content(repaired)
    # Every message of every complete chunk, nothing else, in publication order.
    assert info['message_count'] == in_complete_chunks
    with Reader(repaired) as reader:
        data = [bytes(d) for _, _, d in reader.messages()]
    assert len(data) == in_complete_chunks
    indices = [int(m.message.data) for m in read_bag(repaired)]
    assert indices == list(range(len(indices)))
    assert reported <= len(indices) <= k


def test_a_full_disk_is_reported_and_harms_nobody(test_node, tools, tmp_path):
    bag = tmp_path / 'full'
    topic = f'/robust_{os.getpid()}/full'
    limit = 200 * 1024  # [bytes]: the recorder's "disk" fills after ~50 messages of 4 KiB

    def small_disk():  # in the child: writes past `limit` fail with EFBIG (SIGXFSZ ignored)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    recorder = start_recorder(test_node, bag, [topic], 'flush_period:=0.1',
                              'chunk_size:=16384', 'compression:=none', preexec_fn=small_disk)
    tools.append(recorder)
    publisher = test_node.create_publisher(String, topic, QoSProfile(depth=1000))
    # An unaffected consumer of the same topic: it must get every message throughout.
    got = []
    test_node.create_subscription(String, topic, lambda m: got.append(m.data),
                                  QoSProfile(depth=1000))
    recorder.spin_until(lambda: publisher.get_subscription_count() >= 2, DISCOVERY_TIMEOUT,
                        'the subscriptions')
    payload = os.urandom(1536).hex()  # 3 KiB of text (stored uncompressed)

    def failed():
        return (recorder.status is not None
                and recorder.status.level == DiagnosticStatus.ERROR)

    k = _publish_for(test_node, publisher, 8.0, 0, lambda k: f'{k}:{payload}', stop=failed)
    recorder.spin_until(failed, 5.0, 'the recorder to report the write failure')
    assert 'write failed' in recorder.status.message
    assert 'File too large' in recorder.status.message
    assert 'bag_repair' in recorder.status.message
    # Publishing goes on at full rate: the recorder holds nobody back.
    started = time.monotonic()
    k = _publish_for(test_node, publisher, 0.4, k, lambda k: f'{k}:{payload}')
    assert time.monotonic() - started < 0.4 + 0.2  # no publish call blocked
    spin_until(test_node, lambda: len(got) == k, 5.0, 'the other subscriber')
    recorder.spin_until(lambda: int(recorder.values.get(
        'messages dropped (write failure)', 0)) > 0, 3.0, 'the drop count')
    assert recorder.process.poll() is None  # still up, reporting
    output = recorder.stop(signal.SIGINT, expected_code=1)
    assert '[ERROR]' in output and 'recording stopped' in output

    result = repair_bag(bag)
    repaired = result.out
    assert_metadata_matches_content(repaired)
    indices = [int(m.message.data.split(':')[0]) for m in read_bag(repaired)]
    assert indices == list(range(len(indices)))
    assert 0 < len(indices) == result.metadata['message_count']
    assert sum(os.path.getsize(f) for f in mcap_files_by_index(repaired)) <= limit
    with Reader(repaired) as reader:
        assert reader.message_count == len(indices)


def test_an_unwritable_path_fails_clearly_at_start(test_node, tools, tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('not a directory')  # fails for root too, unlike permissions
    recorder = start_recorder(test_node, blocker / 'bag', ['/x'])
    tools.append(recorder)
    # An output path that cannot be created is a usage error of the exit table (2).
    output = recorder.wait(30.0, expected_code=2)
    assert '[ERROR]' in output
    assert f'cannot create the bag {blocker / "bag"}: Not a directory' in output


def test_split_by_size_while_recording_then_sigterm(test_node, tools, tmp_path):
    bag = tmp_path / 'split'
    topic = f'/robust_{os.getpid()}/split'
    recorder = start_recorder(test_node, bag, [topic], 'max_bag_size:=60000',
                         'chunk_size:=16384', 'compression:=zstd')
    tools.append(recorder)
    publisher = test_node.create_publisher(String, topic, QoSProfile(depth=1000))
    recorder.spin_until(lambda: publisher.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        'the recorder to subscribe')
    n = 400  # of 512 random hex digits each (about 2:1 compressible): ~100 kB compressed

    k = 0
    next_time = time.monotonic()
    while k < n:
        publisher.publish(String(data=f'{k}:{os.urandom(256).hex()}'))
        k += 1
        next_time += PUBLISH_PERIOD
        test_node.executor_for_test.spin_once(
            timeout_sec=max(0.0, next_time - time.monotonic()))
    recorder.spin_until(lambda: recorder.counts.get(topic, 0) == n, 10.0,
                        'the recorder to receive everything')
    output = recorder.stop(signal.SIGTERM)
    assert 'closed' in output
    info = assert_metadata_matches_content(bag)
    assert len(info['relative_file_paths']) >= 3
    assert [int(m.message.data.split(':')[0]) for m in read_bag(bag)] == list(range(n))
    with Reader(bag) as reader:
        assert reader.message_count == n
    bag_info = bag_information(bag)
    assert bag_info['problems'] == []
    assert {t['name']: t['count'] for t in bag_info['topics']} == {topic: n}


def test_launched_recorder_stopped_by_its_live_launcher_closes_while_messages_keep_coming(
        test_node, tools, tmp_path):
    # A launcher that is alive stops its recorder with SIGTERM once it has drained it; a
    # base of a real robot goes on publishing. The recorder must close at once, not wait
    # for the topics to fall quiet (they never do) until the drain's 30 s bound.
    bag = tmp_path / 'launched'
    topic = f'/robust_{os.getpid()}/launched'
    recorder = start_recorder(test_node, bag, [topic],
                              env={LAUNCHER_PID_VARIABLE: str(os.getpid())})
    tools.append(recorder)
    publisher = test_node.create_publisher(String, topic, QoSProfile(depth=1000))
    recorder.spin_until(lambda: publisher.get_subscription_count() >= 1, DISCOVERY_TIMEOUT,
                        'the recorder to subscribe')
    k = _publish_for(test_node, publisher, SPLIT_TIMEOUT, 0,
                     stop=lambda: recorder.counts.get(topic, 0) >= 100)
    recorder.process.send_signal(signal.SIGTERM)
    k = _publish_for(test_node, publisher, STOP_DRAIN - 10.0, k,
                     stop=lambda: recorder.process.poll() is not None)
    assert recorder.process.poll() is not None, (
        f'still recording {STOP_DRAIN - 10.0:g} s after SIGTERM while messages kept coming')
    assert 'closed' in recorder.wait(10.0)
    received = [int(m.message.data) for m in read_bag(bag)]
    assert received == list(range(len(received))) and 100 <= len(received) <= k
