"""Shared helpers of the process-level bag tool tests (recorder, replayer).

Each test talks to the tools, started as their own processes, from a node of the test
process in a private rclpy context and a DDS domain of its own (random id 1..101,
localhost discovery), and waits on the graph or on /diagnostics with timeouts, never with
fixed sleeps (discovery takes 0.1 s to 3 s on this host).
"""

import os
import pathlib
import signal
import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticArray
from rosbags.rosbag2 import Reader
import yaml

import ros_harness
from ros_harness import communicate, ros_child_environment
from wip_bag.bag_reader import bag_summary, iter_raw_messages
from wip_bag.bag_repair import mcap_files_by_index

REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
WIP_BAG_SOURCE = REPO_ROOT / 'ros_ws' / 'src' / 'wip_bag'
DISCOVERY_TIMEOUT = 15.0  # [s]; first discovery takes up to ~3 s on this host


def child_environment():
    """Return the tools' environment: this one's, with wip_bag from the source tree first."""
    env = ros_child_environment()
    env['PYTHONPATH'] = os.pathsep.join(
        [str(WIP_BAG_SOURCE)] + [p for p in [env.get('PYTHONPATH')] if p])
    return env


class Tool:
    """A tool process (``python -m wip_bag.<module> ...``) and its /diagnostics status."""

    def __init__(self, node, module, args, status_prefix, preexec_fn=None, env=None):
        self.node = node
        self.process = subprocess.Popen(
            [sys.executable, '-m', f'wip_bag.{module}', *args],
            env={**child_environment(), **(env or {})},
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            preexec_fn=preexec_fn)
        self.status_prefix = status_prefix
        self.status = None  # latest DiagnosticStatus of this tool
        self.values = {}
        self.reports = 0  # statuses of this tool received
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name.startswith(self.status_prefix):
                self.status = status
                self.values = {v.key: v.value for v in status.values}
                self.reports += 1

    @property
    def counts(self):
        """Messages received per topic, from the latest status (``received <topic>``)."""
        return {k[len('received '):]: int(v) for k, v in self.values.items()
                if k.startswith('received ')}

    def spin_until(self, condition, timeout, what, allow_exit=False):
        spin_until(self.node, condition, timeout, what, None if allow_exit else self.process)

    def stop(self, sig=signal.SIGINT, expected_code=0, timeout=20.0):
        if self.process.poll() is None:
            self.process.send_signal(sig)
        output, _ = communicate(self.process, timeout, f'stop on {sig!r}')
        if expected_code is not None:
            assert self.process.returncode == expected_code, output
        return output

    def wait(self, timeout, expected_code=0):
        output, _ = communicate(self.process, timeout)
        assert self.process.returncode == expected_code, output
        return output


def spin_until(node, condition, timeout, what, process=None):
    """Spin the test node (conftest's ``test_node``) until ``condition()``.

    Fails at the timeout [s] or when ``process`` exits (see ros_harness.spin_until).
    """
    ros_harness.spin_until(node.executor_for_test, condition, what, timeout, process=process)


def start_recorder(node, bag, topics=None, *params, preexec_fn=None, env=None):
    """Start the recorder process recording ``topics`` into ``bag``.

    The recorder process recording ``topics`` (None: every topic) into ``bag``, with
    the parameters ``params`` ('name:=value') and ``env`` added to its environment.
    """
    args = ['--ros-args', '-p', f'output:={bag}', '-p', 'discovery_period:=0.1']
    if topics is not None:
        args += ['-p', f'topics:=[{", ".join(topics)}]']
    for param in params:
        args += ['-p', param]
    return Tool(node, 'recorder_node', args, '/recorder', preexec_fn, env)


def assert_metadata_matches_content(directory):
    """metadata.yaml agrees with what the files hold.

    Counted by reading every message, and by rosbags, an independent reader. Returns its
    rosbag2_bagfile_information.
    """
    info = yaml.safe_load((directory / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert info['relative_file_paths'] == [p.name for p in mcap_files_by_index(directory)]
    assert [f['path'] for f in info['files']] == info['relative_file_paths']
    summary = bag_summary(directory)
    assert summary['finished']
    assert info['message_count'] == summary['message_count']
    assert {t['topic_metadata']['name']: t['message_count']
            for t in info['topics_with_message_count']} == {
        topic: v['message_count'] for topic, v in summary['topics'].items()}
    assert info['starting_time']['nanoseconds_since_epoch'] == summary['start_ns']
    assert info['duration']['nanoseconds'] == summary['duration_ns']
    assert sum(f['message_count'] for f in info['files']) == info['message_count']
    for entry in info['files']:
        times = [m.log_time_ns for m in iter_raw_messages(directory / entry['path'])]
        assert entry['message_count'] == len(times)
        assert entry['starting_time']['nanoseconds_since_epoch'] == min(times)
        assert entry['duration']['nanoseconds'] == max(times) - min(times)
    with Reader(directory) as reader:
        assert reader.message_count == info['message_count']
        assert {c.topic: c.msgcount for c in reader.connections} == {
            t['topic_metadata']['name']: t['message_count']
            for t in info['topics_with_message_count']}
    return info
