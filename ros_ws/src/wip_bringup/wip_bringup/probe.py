"""The probe: a node of the launching process that looks at the graph and reads /diagnostics."""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

from .run_stop import stop_raised_in_native_code

PROBE_CLOSE_TIMEOUT = 10.0  # [s] wall: the probe node's destruction (Probe.close)


class Probe:
    """A node of this process that looks at the graph and reads /diagnostics."""

    def __init__(self, domain_id: int, namespace: str = '') -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile
        self._rclpy = rclpy
        from rclpy.signals import SignalHandlerOptions
        from wip_runtime.dds_profile import use_launcher_profile
        # Made before the nodes it starts, the probe must announce itself as often as they
        # do, or some of them see it (and it them) only seconds later (the profile says why).
        use_launcher_profile()
        self.context = rclpy.Context()
        # No rclpy signal handlers: they would shut this context down at a SIGINT or
        # SIGTERM, and the launcher still needs the probe to drain the recorder while it
        # stops the run (run_stop.stop_signals raises in the main thread instead).
        rclpy.init(context=self.context, domain_id=domain_id, args=[],
                   signal_handler_options=SignalHandlerOptions.NO)
        #: The run's namespace ('' or '/robot1'): the probe sits in it, so relative
        #: names (the plant's start service) resolve as the nodes' do.
        self.namespace = namespace
        self.node = rclpy.create_node('run_graph', context=self.context,
                                      namespace=namespace or '/',
                                      start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.diagnostics: dict[str, Any] = {}  # status name -> latest DiagnosticStatus
        self.received_at: dict[str, float] = {}  # status name -> time.monotonic() [s]
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                      QoSProfile(depth=100))
        from std_srvs.srv import Trigger
        self._trigger = Trigger
        self.start_client = self.node.create_client(Trigger, 'plant/start')

    def own_status_name(self, name: str) -> str | None:
        """Return a /diagnostics status name without the run's namespace.

        A /diagnostics status name ('/robot1/eso: role') without the run's namespace
        ('/eso: role'), or None for a node of another namespace (/diagnostics is global:
        another vehicle of the domain reports there too).
        """
        node, sep, rest = name.partition(':')
        parent = node.rpartition('/')[0]
        if parent != self.namespace:
            return None
        return node[len(self.namespace):] + sep + rest

    def _on_diagnostics(self, msg) -> None:
        now = time.monotonic()
        for status in msg.status:
            name = self.own_status_name(status.name)
            if name is None:
                continue
            self.diagnostics[name] = status
            self.received_at[name] = now

    def reporting_since(self, since: float) -> set[str]:
        """Names of the nodes with a /diagnostics status received after ``since``."""
        return {name.split(':', 1)[0].lstrip('/') for name, at in self.received_at.items()
                if at > since}

    def spin(self, duration: float) -> None:
        """Handle what arrived, for about ``duration`` [s]."""
        deadline = time.monotonic() + duration
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            with stop_raised_in_native_code():
                self.executor.spin_once(timeout_sec=left)

    def node_names(self) -> set[str]:
        return {name for name, namespace in self.node.get_node_names_and_namespaces()
                if namespace == (self.namespace or '/')}

    def count(self, topic: str) -> tuple[int, int]:
        return self.node.count_publishers(topic), self.node.count_subscribers(topic)

    def status_values(self, text: str,
                      prefix: bool = False) -> tuple[Any, dict[str, str]] | None:
        """Latest status whose name ends (or starts) with ``text``, with its values."""
        for name, status in self.diagnostics.items():
            if name.startswith(text) if prefix else name.endswith(text):
                return status, {kv.key: kv.value for kv in status.values}
        return None

    def describe_nodes(self) -> str:
        """Latest /diagnostics message of every node (to explain a stall)."""
        lines = []
        for name, status in sorted(self.diagnostics.items()):
            lines.append(f'  {name}: {status.message}')
            for kv in status.values:
                if kv.key.startswith(('received', 'dropped', 'pending', 'age')):
                    lines.append(f'      {kv.key}: {kv.value}')
        return '\n'.join(lines)

    def call_start(self, timeout: float):
        """Call /plant/start once; returns the response or None (no answer in time)."""
        if not self.start_client.service_is_ready():
            return None
        future = self.start_client.call_async(self._trigger.Request())
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            with stop_raised_in_native_code():
                self.executor.spin_once(timeout_sec=0.05)
        return future.result() if future.done() else None

    def close(self) -> None:
        self.executor.shutdown()
        # rclpy's destroy waits until no one uses an entity's handle, without a timeout;
        # once, after a stand-in run whose controllers had been frozen, on a loaded
        # machine, it waited forever (no other thread left; cause not found). The probe
        # is this process's last use of ROS: past PROBE_CLOSE_TIMEOUT it is left to the
        # process's exit rather than hang the run's end.
        closer = threading.Thread(target=self.node.destroy_node, name='probe_close',
                                  daemon=True)
        closer.start()
        closer.join(PROBE_CLOSE_TIMEOUT)
        if closer.is_alive():
            print(f'warning: the probe node did not close within {PROBE_CLOSE_TIMEOUT:g} s '
                  '(rclpy); going on', file=sys.stderr)
            return
        self._rclpy.try_shutdown(context=self.context)
