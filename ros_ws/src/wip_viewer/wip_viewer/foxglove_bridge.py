"""Foxglove bridge node: the graph's topics over the Foxglove WebSocket protocol, live.

``scripts/run_graph --foxglove [PORT]`` starts it (simulation and hardware mode); open
Foxglove (app or web), "Open connection", "Foxglove WebSocket", ``ws://localhost:8765``.
``ros2 run wip_viewer foxglove_bridge --ros-args -p port:=8765`` starts it alone.

It uses the foxglove-sdk server (PyPI ``foxglove-sdk``) and no ROS bridge package (none is
on PyPI). Every topic of the graph is advertised as a channel with message encoding
``cdr`` and its ``ros2msg`` schema (the full definition with its dependencies, as in the
bags' MCAP schemas), so Foxglove decodes every message, the project's own wip_msgs too.
A channel's ROS subscription exists only while a client subscribes to it: an unwatched
bridge costs the graph nothing but discovery, and a watched one copies serialized bytes
(no deserialization) from a raw subscription (best effort, keep-last 10: a slow client
loses its own messages and never makes a publisher wait).

E-stop from the viewer (no ros2cli needed)
------------------------------------------
- Services (Foxglove "Call Service" panel; std_srvs/srv/Trigger, empty request):
  ``/wip/estop/engage`` publishes ``/wip/estop`` = true (the mixer latches it),
  ``/wip/estop/release`` publishes ``/wip/estop`` = false (the button released),
  ``/wip/estop/reset`` publishes ``/wip/estop_reset`` (std_msgs/Empty: the mixer resets a
  latched e-stop unless ``/wip/estop`` still says true or said it within
  ``safety.estop_hold_time``; its /diagnostics say which).
- Client publish (Foxglove "Publish" panel): ``/wip/estop`` (std_msgs/msg/Bool) and
  ``/wip/estop_reset`` (std_msgs/msg/Empty), in ``json`` or ``cdr``; other topics are
  refused with a status message (a viewer must not drive the robot).

Parameters (read-only)
----------------------
host : str, default ``127.0.0.1`` (localhost only; ``0.0.0.0`` to serve other machines).
port : int, default 8765; 0 = any free port (printed at start).
topics : string array, default empty = every topic of the graph (polled every
    ``discovery_period`` [s], hidden topics excepted).
discovery_period : float [s], wall time, default 0.5.

At start it prints ``foxglove_bridge: serving ws://HOST:PORT`` on stdout.
"""

from __future__ import annotations

import json
import queue
import sys
import threading

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Bool, Empty
from std_srvs.srv import Trigger

from wip_runtime.config import ParamError
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from wip_runtime.diagnostics import NodeDiagnostics
from wip_runtime.parameters import RosParams

from wip_bag.bag_writer import BagWriterError
from wip_bag.message_definitions import message_definition
from wip_bag.recorder_node import import_message_class, is_hidden_topic

from .settings import FoxgloveParams

ESTOP_TOPIC = '/wip/estop'
ESTOP_RESET_TOPIC = '/wip/estop_reset'
#: Topics a client may publish, with their types.
CLIENT_TOPICS = {ESTOP_TOPIC: 'std_msgs/msg/Bool', ESTOP_RESET_TOPIC: 'std_msgs/msg/Empty'}
#: Foxglove service name -> what it does (see the module docstring).
SERVICES = ('/wip/estop/engage', '/wip/estop/release', '/wip/estop/reset')
_VIEW_QOS = QoSProfile(depth=10, history=QoSHistoryPolicy.KEEP_LAST,
                       reliability=QoSReliabilityPolicy.BEST_EFFORT)
_TRIGGER_RESPONSE_DEFINITION = b'bool success\nstring message\n'


def schema_of(type_name: str):
    """Return the foxglove Schema of a ROS type: ``ros2msg`` text with its dependencies."""
    import foxglove
    encoding, text = message_definition(type_name)
    return foxglove.Schema(name=type_name, encoding=encoding, data=text.encode('utf-8'))


def trigger_service_schema():
    import foxglove
    from foxglove import MessageSchema, ServiceSchema
    return ServiceSchema(
        'std_srvs/srv/Trigger',
        request=MessageSchema(encoding='cdr', schema=foxglove.Schema(
            name='std_srvs/srv/Trigger_Request', encoding='ros2msg', data=b'')),
        response=MessageSchema(encoding='cdr', schema=foxglove.Schema(
            name='std_srvs/srv/Trigger_Response', encoding='ros2msg',
            data=_TRIGGER_RESPONSE_DEFINITION)))


def encode_trigger_response(success: bool, message: str, encoding: str) -> bytes:
    """Return a Trigger response in the request's encoding (json or cdr)."""
    if encoding == 'json':
        return json.dumps({'success': success, 'message': message}).encode('utf-8')
    return serialize_message(Trigger.Response(success=success, message=message))


def decode_client_message(topic: str, encoding: str, data: bytes):
    """Return the ROS message a client sent on one of :data:`CLIENT_TOPICS`; ValueError if bad."""
    if encoding == 'json':
        try:
            fields = json.loads(bytes(data).decode('utf-8') or '{}')
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f'{topic}: not JSON: {err}') from err
        if not isinstance(fields, dict):
            raise ValueError(f'{topic}: expected a JSON object, got {fields!r}')
        if topic == ESTOP_TOPIC:
            if not isinstance(fields.get('data'), bool):
                raise ValueError(f'{topic}: expected {{"data": true|false}}, got {fields!r}')
            return Bool(data=fields['data'])
        return Empty()
    if encoding == 'cdr':
        try:
            return deserialize_message(bytes(data), Bool if topic == ESTOP_TOPIC else Empty)
        except Exception as err:  # noqa: BLE001 - rclpy raises several types on bad CDR
            raise ValueError(f'{topic}: bad CDR: {err}') from err
    raise ValueError(f'{topic}: encoding {encoding!r} is not json or cdr')


class _Listener:
    """foxglove ServerListener that only queues work for the node's executor thread.

    foxglove ServerListener: runs on the server's threads, so it only queues work for
    the node's executor thread (rclpy entities are created there).
    """

    def __init__(self, work: queue.SimpleQueue) -> None:
        self.work = work
        self.client_channels: dict[tuple[int, int], tuple[str, str]] = {}
        self.lock = threading.Lock()

    def on_subscribe(self, client, channel) -> None:
        self.work.put(('subscribe', channel.topic))

    def on_unsubscribe(self, client, channel) -> None:
        self.work.put(('unsubscribe', channel.topic))

    def on_client_advertise(self, client, channel) -> None:
        with self.lock:
            self.client_channels[(client.id, channel.id)] = (channel.topic, channel.encoding)

    def on_client_unadvertise(self, client, client_channel_id) -> None:
        with self.lock:
            self.client_channels.pop((client.id, client_channel_id), None)

    def on_message_data(self, client, client_channel_id, data) -> None:
        with self.lock:
            found = self.client_channels.get((client.id, client_channel_id))
        if found is not None:
            self.work.put(('client_message', found[0], found[1], bytes(data)))


class FoxgloveBridge(Node):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('foxglove_bridge', **kwargs)
        import foxglove
        from foxglove import Service
        from foxglove.websocket import Capability
        settings = RosParams(self, '', FoxgloveParams).config
        self.host, self.port = settings.host, settings.port
        self.requested = set(settings.topics)
        self.requested.discard('')
        period = settings.discovery_period
        self.diagnostics = NodeDiagnostics(self, 'foxglove bridge', ())
        self.channels: dict[str, object] = {}  # topic -> foxglove.Channel
        self.types: dict[str, str] = {}
        self.watchers: dict[str, int] = {}  # topic -> clients subscribed
        self.subscriptions_: dict[str, object] = {}
        self.forwarded = 0
        self.work: queue.SimpleQueue = queue.SimpleQueue()
        self.listener = _Listener(self.work)
        # Relative: under a vehicle's namespace the e-stop reaches that vehicle's mixer
        # (the client still names them by the table's names).
        self.estop_publisher = self.create_publisher(Bool, ESTOP_TOPIC.lstrip('/'),
                                                     RELIABLE_QOS)
        self.reset_publisher = self.create_publisher(Empty, ESTOP_RESET_TOPIC.lstrip('/'),
                                                     RELIABLE_QOS)
        schema = trigger_service_schema()
        services = [Service(name, schema=schema, handler=self._on_service)
                    for name in SERVICES]
        try:
            self.server = foxglove.start_server(
                name='wip-ros', host=self.host, port=self.port,
                capabilities=[Capability.ClientPublish, Capability.Services],
                supported_encodings=['json', 'cdr'], server_listener=self.listener,
                services=services)
        except Exception as err:  # noqa: BLE001 - the SDK raises its own types (port in use)
            raise ParamError(f'cannot serve on {self.host}:{self.port}: {err}') from err
        self.url = f'ws://{self.host}:{self.server.port}'
        print(f'foxglove_bridge: serving {self.url}', flush=True)
        self.get_logger().info(f'serving {self.url} (Foxglove: Open connection, '
                               'Foxglove WebSocket)')
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self.discover, clock=wall)
        self.create_timer(0.02, self.handle_work, clock=wall)
        self.diagnostics.state(DiagnosticStatus.OK, f'serving {self.url}')
        self.discover()

    # -- channels -------------------------------------------------------------------------
    def discover(self) -> None:
        """Advertise a channel for every new topic of the graph (timer callback)."""
        import foxglove
        for topic, types in self.get_topic_names_and_types():
            if topic in self.channels or is_hidden_topic(topic):
                continue
            if self.requested and topic not in self.requested:
                continue
            if len(types) != 1:
                continue
            try:
                schema = schema_of(types[0])
            except (BagWriterError, LookupError, OSError, ValueError) as err:
                self.get_logger().warning(f'not offering {topic}: {err}')
                self.channels[topic] = None
                continue
            self.types[topic] = types[0]
            self.channels[topic] = foxglove.Channel(topic, schema=schema,
                                                    message_encoding='cdr')
        self.diagnostics.values.update({
            'url': self.url, 'channels': str(sum(c is not None for c in self.channels.values())),
            'watched topics': ', '.join(sorted(self.subscriptions_)) or 'none',
            'messages forwarded': str(self.forwarded)})

    def handle_work(self) -> None:
        """Handle what the server's listener queued (timer callback on the executor's thread)."""
        while True:
            try:
                item = self.work.get_nowait()
            except queue.Empty:
                return
            kind = item[0]
            if kind == 'subscribe':
                self._watch(item[1], +1)
            elif kind == 'unsubscribe':
                self._watch(item[1], -1)
            elif kind == 'client_message':
                self._client_message(*item[1:])

    def _watch(self, topic: str, change: int) -> None:
        count = max(0, self.watchers.get(topic, 0) + change)
        self.watchers[topic] = count
        if count and topic not in self.subscriptions_ and self.channels.get(topic):
            channel = self.channels[topic]
            self.subscriptions_[topic] = self.create_subscription(
                import_message_class(self.types[topic]), topic,
                lambda data, channel=channel: self._forward(channel, data), _VIEW_QOS,
                raw=True)
        elif not count and topic in self.subscriptions_:
            self.destroy_subscription(self.subscriptions_.pop(topic))

    def _forward(self, channel, data: bytes) -> None:
        channel.log(data)
        self.forwarded += 1

    # -- e-stop -----------------------------------------------------------------------------
    def _client_message(self, topic: str, encoding: str, data: bytes) -> None:
        from foxglove import StatusLevel
        if topic not in CLIENT_TOPICS:
            self.server.publish_status(
                f'{topic}: not accepted; a client may publish only '
                f'{", ".join(CLIENT_TOPICS)}', StatusLevel.Warning)
            return
        try:
            message = decode_client_message(topic, encoding, data)
        except ValueError as err:
            self.server.publish_status(str(err), StatusLevel.Error)
            return
        (self.estop_publisher if topic == ESTOP_TOPIC else self.reset_publisher).publish(message)
        self.get_logger().warning(f'client published {topic}: {message}')

    def _on_service(self, request) -> bytes:
        # Runs on a server thread; rclpy publishers are thread-safe.
        name = request.service_name
        if name == '/wip/estop/engage':
            self.estop_publisher.publish(Bool(data=True))
            text = f'{ESTOP_TOPIC} = true published: the mixer latches the e-stop'
        elif name == '/wip/estop/release':
            self.estop_publisher.publish(Bool(data=False))
            text = f'{ESTOP_TOPIC} = false published (released; call /wip/estop/reset)'
        elif name == '/wip/estop/reset':
            self.reset_publisher.publish(Empty())
            text = (f'{ESTOP_RESET_TOPIC} published: the mixer resets unless {ESTOP_TOPIC} '
                    'still says true (see its /diagnostics)')
        else:
            return encode_trigger_response(False, f'unknown service {name}', request.encoding)
        self.get_logger().warning(f'{name}: {text}')
        return encode_trigger_response(True, text, request.encoding)

    def destroy_node(self) -> None:
        try:
            self.server.stop()
        except Exception:  # noqa: BLE001 - stopping anyway
            pass
        super().destroy_node()


def main(args=None) -> int:
    """Entry point ``foxglove_bridge``."""
    return run_node(FoxgloveBridge, 'foxglove_bridge', args)


if __name__ == '__main__':
    sys.exit(main())
