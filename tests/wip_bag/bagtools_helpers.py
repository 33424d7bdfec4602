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
import time

from diagnostic_msgs.msg import DiagnosticArray
import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
WIP_BAG_SOURCE = REPO_ROOT / 'ros_ws' / 'src' / 'wip_bag'
DISCOVERY_TIMEOUT = 15.0  # [s]; first discovery takes up to ~3 s on this host


def child_environment():
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(
        [str(WIP_BAG_SOURCE)] + [p for p in [env.get('PYTHONPATH')] if p])
    env.pop('_ROS_WHEELS_BOOTSTRAP_COMPLETE', None)
    return env


class Tool:
    """A tool process (``python -m wip_bag.<module> ...``) and its /diagnostics status."""

    def __init__(self, node, module, args, status_prefix, preexec_fn=None):
        self.node = node
        self.process = subprocess.Popen(
            [sys.executable, '-m', f'wip_bag.{module}', *args], env=child_environment(),
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            preexec_fn=preexec_fn)
        self.status_prefix = status_prefix
        self.status = None  # latest DiagnosticStatus of this tool
        self.values = {}
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name.startswith(self.status_prefix):
                self.status = status
                self.values = {v.key: v.value for v in status.values}

    def spin_until(self, condition, timeout, what, allow_exit=False):
        spin_until(self.node, condition, timeout, what,
                   None if allow_exit else self.process)

    def stop(self, sig=signal.SIGINT, expected_code=0, timeout=20.0):
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            output, _ = self.process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            output, _ = self.process.communicate()
            pytest.fail(f'{self.process.args} did not stop on {sig!r}:\n{output}')
        if expected_code is not None:
            assert self.process.returncode == expected_code, output
        return output

    def wait(self, timeout, expected_code=0):
        try:
            output, _ = self.process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            output, _ = self.process.communicate()
            pytest.fail(f'{self.process.args} did not exit within {timeout} s:\n{output}')
        assert self.process.returncode == expected_code, output
        return output


def spin_until(node, condition, timeout, what, process=None):
    deadline = time.monotonic() + timeout
    while not condition():
        if process is not None and process.poll() is not None:
            pytest.fail(f'{process.args[2]} exited ({process.returncode}) while waiting for '
                        f'{what}:\n{process.stdout.read()}')
        if time.monotonic() > deadline:
            pytest.fail(f'timeout ({timeout} s) waiting for {what}')
        node.executor_for_test.spin_once(timeout_sec=0.01)


@pytest.fixture
def tools():
    """Started tools; killed at the end even when a test fails."""
    started = []
    yield started
    for tool in started:
        if tool.process.poll() is None:
            tool.process.kill()
            tool.process.communicate()
