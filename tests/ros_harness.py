"""The harness of the node tests, written once.

Nodes spun by one executor in this process (callbacks run here, so an exception in one fails the
test), waits with deadlines instead of sleeps, node processes that are always stopped.

Import it as ``from ros_harness import ...`` (``tests/`` is on ``sys.path`` through
``tests/conftest.py``); the fixture ``harnesses`` of ``conftest.py`` closes what a test made.
Needs rclpy: import it after ``pytest.importorskip('rclpy')``.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import subprocess
import threading
import time
from typing import Callable, Iterator

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from wip_runtime.launched import LAUNCHER_PID_VARIABLE

TIMEOUT = 10.0  # [s] default of any single wait; normally milliseconds
#: [s] start-up of a node process and its DDS discovery on a slow, shared 2-core machine.
PROCESS_START_TIMEOUT = 60.0
_ids = itertools.count()


def spin_until(executor, condition: Callable[[], object], what: str, timeout: float = TIMEOUT,
               step: float = 0.01, process: subprocess.Popen | None = None,
               after_spin: Callable[[], None] | None = None) -> None:
    """Spin ``executor`` until ``condition()`` is true.

    The test fails, naming ``what``, at ``timeout`` [s], or as soon as ``process`` (if given) has
    exited.
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if process is not None and process.poll() is not None:
            output = process.stdout.read() if process.stdout is not None else ''
            pytest.fail(f'{process_name(process)} exited ({process.returncode}) while '
                        f'waiting for {what}:\n{output}')
        if time.monotonic() > deadline:
            pytest.fail(f'timeout ({timeout:g} s) waiting for {what}')
        executor.spin_once(timeout_sec=step)
        if after_spin is not None:
            after_spin()


def spin_for(executor, seconds: float, step: float = 0.01) -> None:
    """Spin ``executor`` for ``seconds`` [s] of wall time (what arrives meanwhile)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=step)


@contextlib.contextmanager
def spinning_in_background(executor, step: float = 0.05) -> Iterator[None]:
    """Spin ``executor`` in a daemon thread for the duration of the block; stop at its end.

    For a test that blocks on something else meanwhile: a subprocess, a WebSocket.
    """
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=step)
    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5)


class NodeHarness:
    """The nodes under test and a harness node ``io`` in one context.

    The nodes under test and a harness node ``io`` (their inputs and outputs) in one
    context, spun by one SingleThreadedExecutor.
    """

    def __init__(self, context, *nodes, name: str | None = None, timeout: float = TIMEOUT,
                 step: float = 0.01) -> None:
        self.context = context
        self.nodes = list(nodes)
        self.node = nodes[0] if nodes else None
        self.io = rclpy.create_node(name or f'harness_{next(_ids)}', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        for node in (*nodes, self.io):
            self.executor.add_node(node)
        self.timeout = timeout
        self.step = step
        self.publishers: dict[str, object] = {}
        self.outputs: dict[str, list] = {}
        self.after_spin: Callable[[], None] | None = None

    def add(self, *nodes) -> None:
        """More nodes under test, in the same executor (destroyed by :meth:`close`)."""
        for node in nodes:
            self.executor.add_node(node)
            self.nodes.append(node)

    def listen(self, msg_type, topic: str, qos=100) -> list:
        """Collect what arrives on ``topic``; the list it appends to."""
        received: list = []
        self.io.create_subscription(msg_type, topic, received.append, qos)
        self.outputs[topic] = received
        return received

    def publisher(self, msg_type, topic: str, qos=100):
        self.publishers[topic] = self.io.create_publisher(msg_type, topic, qos)
        return self.publishers[topic]

    def publish(self, topic: str, msg) -> None:
        self.publishers[topic].publish(msg)

    def wait_matched(self) -> None:
        """Until every publisher has a reader and every listened topic a writer."""
        for topic, pub in self.publishers.items():
            self.spin_until(lambda: pub.get_subscription_count() > 0, f'a reader of {topic}')
        for topic in self.outputs:
            self.spin_until(lambda: self.io.count_publishers(topic) > 0,
                            f'a writer of {topic}')

    def spin_until(self, condition, what: str = '', timeout: float | None = None,
                   process: subprocess.Popen | None = None) -> None:
        spin_until(self.executor, condition, what, self.timeout if timeout is None else timeout,
                   self.step, process=process, after_spin=self.after_spin)

    def spin_for(self, seconds: float) -> None:
        spin_for(self.executor, seconds, self.step)

    def close(self) -> None:
        self.executor.shutdown()
        for node in (*self.nodes, self.io):
            node.destroy_node()


def process_name(process: subprocess.Popen) -> str:
    """Return the module of ``python -m MODULE ...``, else the executable."""
    args = [str(a) for a in process.args]
    return args[2] if len(args) > 2 and args[1] == '-m' else os.path.basename(args[0])


def installed_executable(package: str, name: str) -> str:
    """``<prefix>/lib/<package>/<name>``: what ``ros2 run package name`` runs."""
    from ament_index_python.packages import get_package_prefix
    path = os.path.join(get_package_prefix(package), 'lib', package, name)
    assert os.access(path, os.X_OK), f'{path} is not an executable (scripts/setup builds it)'
    return path


def ros_child_environment(**extra: str) -> dict[str, str]:
    """Return the environment of a node process started by a test.

    It is this process's (its DDS domain), without the marker of the ROS wheels bootstrap
    (the child bootstraps itself), and with this process as its launcher: a node this test
    starts ends with it, even when the test run is killed (wip_runtime.launched).
    """
    env = dict(os.environ, **extra)
    env.pop('_ROS_WHEELS_BOOTSTRAP_COMPLETE', None)
    env[LAUNCHER_PID_VARIABLE] = str(os.getpid())
    return env


@contextlib.contextmanager
def node_process(command: list[str], **popen) -> Iterator[subprocess.Popen]:
    """Run a node process; killed at the end of the block if it still runs.

    A node process (text output on a pipe unless ``popen`` says otherwise); killed at
    the end of the block if it still runs, whatever happened in the block.
    """
    popen.setdefault('env', ros_child_environment())
    popen.setdefault('stdout', subprocess.PIPE)
    popen.setdefault('stderr', subprocess.PIPE)
    popen.setdefault('text', True)
    process = subprocess.Popen(command, **popen)
    try:
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()


def communicate(process: subprocess.Popen, timeout: float,
                what: str = 'exit') -> tuple[str | None, str | None]:
    """(stdout, stderr) of ``process`` once it has exited.

    The test fails (the process killed) if it did not within ``timeout`` [s].
    """
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        output, errors = stop_with_stacks(process)
        pytest.fail(f'{process.args} did not {what} within {timeout:g} s:\n{output}\n'
                    f'{errors or ""}')


def stop_with_stacks(process: subprocess.Popen,
                     grace: float = 5.0) -> tuple[str | None, str | None]:
    """End a process that hangs so that its output says where.

    SIGABRT first, on which a Python child with faulthandler enabled (tests/conftest.py sets
    PYTHONFAULTHANDLER for every child) prints every thread's stack, then SIGKILL after ``grace``
    [s].
    """
    with contextlib.suppress(ProcessLookupError):
        process.send_signal(signal.SIGABRT)
    try:
        return process.communicate(timeout=grace)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.communicate()
