"""Recorder node: record topics to a rosbag2 bag (MCAP storage), like ``ros2 bag record``.

rosbag2 is not on PyPI, so this node records with :mod:`wip_bag.bag_writer`; its bags are
rosbag2 bags (``ros2 bag info/play`` on a full ROS 2 install, ``rosbags``, Foxglove, the
project's report read them).

Parameters (all read-only, read at start-up)
--------------------------------------------
:class:`wip_bag.settings.RecorderParams` (docs/parameters.md): the bag directory (never
overwritten), the topics (empty: every topic of the graph, also later ones, hidden topics
excepted) and those excluded, the chunk compression and size (a chunk is also closed at
each flush), the splits into ``<name>_0.mcap``, ``<name>_1.mcap`` ... by size or receive
time, the flush period (chunk closed and fsync'ed: what a crash loses, every flushed chunk
being recovered by ``scripts/bag_repair``), the close timeout (past it the recorder exits
anyway and says so) and the scenario file stored in ``custom_data['wip.scenario']`` for
``scripts/rerun``.

Behaviour
---------
- A topic is subscribed once the graph knows its type (a publisher exists), with a raw
  subscription (serialized CDR, no deserialization). Its QoS follows rosbag2's
  ``adapt_request_to_offers``: reliable if every publisher offers reliable, else best
  effort; transient local if every publisher offers it, else volatile; history keep-last
  with depth SUBSCRIPTION_DEPTH (a deep queue: the recorder must not drop a burst). The
  offered profiles and the publishers' RIHS01 type hash are stored in the bag.
- Each message is stamped with its receive time on the node's clock: simulation time when
  ``use_sim_time`` is true (lockstep runs then give bags in simulation time), else system
  time. rosbag2 also stores a send time from the middleware's message info, which this node
  cannot get with the EventsExecutor (its callbacks take one argument), so the receive time
  is used for both.
- Callbacks only queue ``(topic, bytes, time)``; a writer thread writes the bag, so a
  compressing chunk write never delays the executor. It writes what is queued in batches,
  resting :data:`WRITE_BATCH_PAUSE` between them. Nothing received is dropped.
- SIGINT, SIGTERM, SIGHUP (and the launcher's death, which the kernel turns into SIGINT:
  ``wip_runtime.launched``): at a SIGINT a recorder that a launcher started first
  takes what the graph already sent (:mod:`.recorder_stop`); a live launcher drains it
  itself and stops it with SIGTERM, and a recorder run by hand stops at once. Then the
  subscriptions stop, the queue is drained and the bag is closed (MCAP summary and
  ``metadata.yaml`` written). The signals only set a flag (rclpy's own handler is off): no
  KeyboardInterrupt can land inside the close and leave the bag unfinished, whatever arrives
  meanwhile. The main thread never blocks (it spins with a timeout), so a signal is served
  within 0.1 s even while the writer is busy.
- Failures. A bag that exists (never overwritten) or cannot be created (unwritable path):
  ERROR log and exit code 1 at once. A write that fails during the run (disk full, file size
  limit, I/O error): the recorder logs it at ERROR level, reports it on ``/diagnostics``
  (level ERROR, with the count of messages dropped since), stops writing (the file is closed
  as it is, without a summary: ``scripts/bag_repair`` recovers every complete chunk) and
  drops what it receives from then on, without buffering it; it stays up until it is stopped
  (exit code 1) so that nothing else of the graph is disturbed. A full disk is seen coming
  (less free space than twice the largest chunk plus :data:`SUMMARY_MARGIN`): the recorder
  finishes the bag with what it holds (valid, no repair needed), reports ``disk full`` on
  ``/diagnostics`` (level ERROR) and drops the rest. The nodes being recorded
  never wait for the recorder: it is a separate process and its subscriptions are keep-last,
  so a stalled recorder only loses its own messages.
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) once per second (wall time; every 0.1 s
  for its first 10 s, while a launcher waits for every node to report): the bag path, the
  file being written, the messages recorded in total and per topic, the write backlog, and
  any topic that could not be recorded.
"""

import datetime
import os
import queue
import signal
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
import rclpy.logging
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile,
                       QoSReliabilityPolicy)
from rclpy.signals import SignalHandlerOptions

from wip_runtime.launched import end_with_launcher
from wip_runtime.node_main import init_rclpy
from wip_runtime.diagnostics import create_diagnostics_timer
from wip_runtime.parameters import RosParams
from wip_runtime.cli import answer_node_help, EXIT_USAGE

from .bag_writer import BagExistsError, BagWriterError, Rosbag2McapWriter
from .message_definitions import message_definition, type_description_hash
from .message_types import message_class
from .recorder_stop import make_executor, spin, STOP_SIGNALS, StopSignals
from .settings import RecorderParams

#: Keep-last depth of the recording subscriptions [messages]. A lockstep graph publishes
#: each topic at 200 Hz times its real-time factor (1000-3000 messages/s of wall time): with
#: 1000 a recorder descheduled for about a second on a loaded machine lost the oldest
#: messages of its reader caches (seen: 1985 of 2000 per topic at load 11 on 2 cores).
#: The DDS layer fills the cache lazily, so the depth costs memory only when it is used.
SUBSCRIPTION_DEPTH = 20000
DIAGNOSTICS_PERIOD = 1.0  # [s], wall time
_STOP = object()  # Sentinel that ends the writer thread.
#: Free space [bytes] kept for the MCAP summary and metadata.yaml.
SUMMARY_MARGIN = 128 * 1024
#: Free space [bytes] kept for the run's files written after its bag (50-70 KiB: run.json...).
RUN_FILES_MARGIN = 128 * 1024
SPACE_CHECK_PERIOD = 0.25  # [s] between two looks at the free space (statvfs)
#: [s] the writer thread rests after writing what was queued (it writes in batches).
WRITE_BATCH_PAUSE = 0.005
SCENARIO_KEY = 'wip.scenario'  # custom_data key read by scripts/rerun


class RecorderStartError(Exception):
    """The bag cannot be created (unwritable path, ...)."""


def default_output_name(now=None):
    """rosbag2's default bag name: ``rosbag2_YYYY_MM_DD-HH_MM_SS``."""
    now = now or datetime.datetime.now()
    return now.strftime('rosbag2_%Y_%m_%d-%H_%M_%S')


def is_hidden_topic(name):
    """Return True for topics with a path segment starting with '_' (rcl's hidden topics)."""
    return any(part.startswith('_') for part in name.split('/') if part)


def import_message_class(type_name):
    """Return the Python class of a ROS message type 'pkg/msg/Type'; BagWriterError if unknown."""
    return message_class(type_name, BagWriterError)


def request_qos(offered_profiles):
    """QoS to subscribe with, given the publishers' offered profiles (rosbag2's rule)."""
    reliable = bool(offered_profiles) and all(
        p.reliability == QoSReliabilityPolicy.RELIABLE for p in offered_profiles)
    transient_local = bool(offered_profiles) and all(
        p.durability == QoSDurabilityPolicy.TRANSIENT_LOCAL for p in offered_profiles)
    return QoSProfile(
        history=QoSHistoryPolicy.KEEP_LAST, depth=SUBSCRIPTION_DEPTH,
        reliability=(QoSReliabilityPolicy.RELIABLE if reliable or not offered_profiles
                     else QoSReliabilityPolicy.BEST_EFFORT),
        durability=(QoSDurabilityPolicy.TRANSIENT_LOCAL if transient_local
                    else QoSDurabilityPolicy.VOLATILE))


class RecorderNode(Node):
    """Records topics to a rosbag2 MCAP bag; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('recorder', **kwargs)
        settings = RosParams(self, '', RecorderParams).config
        output = settings.output or default_output_name()
        self.output = os.path.abspath(os.path.expanduser(output))
        self.requested = [self.resolve_topic_name(t) for t in settings.topics]
        self.excluded = {self.resolve_topic_name(t) for t in settings.exclude}
        compression = settings.compression
        discovery_period = settings.discovery_period
        self.flush_period = settings.flush_period
        self.close_timeout = settings.close_timeout
        self.bag = self._open_bag(settings)
        self._dropped = 0  # messages received after a write failure
        self._disk_full = False  # recording stopped for want of space, the bag finished
        self._file_size = 0  # [bytes] of the bag file at the last look
        self._largest_write = 0  # [bytes] largest growth of the file between two looks
        self.last_received = time.monotonic()  # [s] of the last message (the stop's drain)
        self._closed = False
        self._closed_ok = False
        self._queue = queue.SimpleQueue()
        self._received = {}  # topic -> messages received (the writer thread counts writes)
        self._recorded = {}  # topic -> Subscription
        self._failed = {}  # topic -> reason it is not recorded
        self._writer_error = None
        self._writer = threading.Thread(target=self._write_loop, name='bag_writer',
                                        daemon=True)
        self._writer.start()
        try:
            # Wall-clock timers: with use_sim_time, a paused or absent /clock must not stop
            # the discovery of topics nor the diagnostics.
            wall = Clock(clock_type=ClockType.STEADY_TIME)
            self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
            self.create_timer(discovery_period, self.discover, clock=wall)
            # (It cannot tell when a run starts: every 0.1 s for the start-up time.)
            create_diagnostics_timer(self, self.publish_diagnostics, DIAGNOSTICS_PERIOD)
            self._last_diagnostics = (time.monotonic(), 0)
            self.get_logger().info(
                f'recording {"all topics" if not self.requested else self.requested} '
                f'to {self.output} ({compression})')
            self.discover()
        except BaseException:
            self.close()  # Leave a valid (maybe empty) bag, never a half-written one.
            raise

    def _open_bag(self, settings):
        """Create the bag with its custom data (the recorder, namespace and scenario)."""
        custom_data = {'recorder': self.get_fully_qualified_name()}
        # Under a namespace (one vehicle of several in a domain) the topics of that
        # namespace are stored without it: a vehicle's bag then reads the same whatever
        # namespace it ran under, and the bag tools, which know the graph's names
        # (/wip/state_estimate, ...), read it as it is. The namespace is kept here.
        self.namespace = self.get_namespace().rstrip('/')
        if self.namespace:
            custom_data['namespace'] = self.namespace
        scenario_file = settings.scenario_file
        if scenario_file:
            try:
                with open(scenario_file, encoding='utf-8') as stream:
                    custom_data[SCENARIO_KEY] = stream.read()
            except OSError as err:
                raise ValueError(f'scenario_file {scenario_file!r}: {err.strerror}') from err
        try:
            return Rosbag2McapWriter(
                self.output, compression=settings.compression, custom_data=custom_data,
                chunk_size=settings.chunk_size, max_bag_size=settings.max_bag_size,
                max_bag_duration=settings.max_bag_duration)
        except BagExistsError:
            raise
        except OSError as err:
            raise RecorderStartError(f'cannot create the bag {self.output}: '
                                     f'{err.strerror or err}') from err

    # -- topics ----------------------------------------------------------------------------
    def _wanted(self, topic):
        if topic in self.excluded or topic in self._recorded or topic in self._failed:
            return False
        if self.requested:
            return topic in self.requested
        return not is_hidden_topic(topic)

    def discover(self):
        """Subscribe to the wanted topics that the graph now knows (timer callback)."""
        if self._closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if not self._wanted(topic):
                continue
            if len(types) != 1:
                self._fail(topic, f'has several types {types}')
                continue
            try:
                self._subscribe(topic, types[0])
            except (BagWriterError, LookupError, ValueError) as err:
                self._fail(topic, str(err))

    def _fail(self, topic, reason):
        self._failed[topic] = reason
        self.get_logger().error(f'not recording {topic}: {reason}')

    def _subscribe(self, topic, type_name):
        publishers = self.get_publishers_info_by_topic(topic)
        if not publishers:
            # Known from a subscriber only: wait for a publisher, whose QoS decides ours
            # (a reliable request would never match a best-effort publisher).
            return
        message_class = import_message_class(type_name)
        offered = [info.qos_profile for info in publishers]
        hashes = {str(info.topic_type_hash) for info in publishers}
        hashes = {h for h in hashes if h.startswith('RIHS01_')}
        type_hash = hashes.pop() if len(hashes) == 1 else type_description_hash(type_name)
        encoding, definition = message_definition(type_name)
        stored = self.stored_name(topic)
        # Declared to the writer through the queue so that the writer thread alone touches
        # the bag; messages of this topic are queued after it.
        self._queue.put(('topic', stored, type_name, definition, offered, type_hash, encoding))
        self._received[stored] = 0
        self._recorded[topic] = self.create_subscription(
            message_class, topic, lambda data, stored=stored: self._on_message(stored, data),
            request_qos(offered), raw=True)
        self.get_logger().info(f'recording {topic} [{type_name}]'
                               + (f' as {stored}' if stored != topic else ''))

    def stored_name(self, topic):
        """Return the name ``topic`` has in the bag: without the recorder's namespace."""
        if self.namespace and topic.startswith(self.namespace + '/'):
            return topic[len(self.namespace):]
        return topic

    def _on_message(self, topic, data):
        # One-argument callback (the EventsExecutor does not support MessageInfo).
        if self._closed:
            return
        self.last_received = time.monotonic()
        self._received[topic] += 1
        if self._writer_error is not None:
            self._dropped += 1  # Recording stopped: nothing is buffered.
            return
        self._queue.put(('message', topic, data, self.get_clock().now().nanoseconds))

    # -- writer thread ---------------------------------------------------------------------
    def _space_left(self):
        """(free bytes on the bag's file system, the margin needed to finish the bag and run)."""
        try:
            size = os.path.getsize(self.bag.mcap_path)
            info = os.statvfs(self.output)
        except OSError:
            return None, 0
        grown = size - self._file_size
        if grown > self._largest_write:
            self._largest_write = grown
        self._file_size = size
        largest = self._largest_write or self.bag.chunk_size // 4
        return info.f_bavail * info.f_frsize, 2 * largest + SUMMARY_MARGIN + RUN_FILES_MARGIN

    def _check_space(self):
        """Finish the bag while it still fits (writer thread); True if recording stopped."""
        free, needed = self._space_left()
        if free is None or free >= needed:
            return False
        self._writer_error = (f'disk full: {free} bytes left on the disk of {self.output} '
                              f'(at least {needed} needed to go on); recording stopped, the '
                              'bag was finished with what fit')
        self._disk_full = True
        self.bag.close()   # Summary and metadata.yaml: the margin was kept for them.
        rclpy.logging.get_logger(self.get_name()).error(self._writer_error)
        return True

    def _write_loop(self):
        last_flush = time.monotonic()
        last_space_check = 0.0
        while True:
            try:
                items = [self._queue.get(timeout=0.2)]
            except queue.Empty:
                items = [None]
            # Then what came meanwhile, and a pause: a thread woken for every message (10
            # per control tick in lockstep) spent more on waking than on writing.
            while True:
                try:
                    items.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            for item in items:
                if item is _STOP:
                    return
                if self._writer_error is not None:
                    continue  # Failed: discard what was queued before the failure was seen.
                try:
                    if item is not None and item[0] == 'message':
                        _, topic, data, stamp = item
                        self.bag.write(topic, data, stamp)
                    elif item is not None:
                        _, topic, type_name, definition, offered, type_hash, encoding = item
                        self.bag.add_topic(topic, type_name, definition, offered, type_hash,
                                           definition_encoding=encoding)
                except Exception as err:  # noqa: BLE001 - reported, never silent
                    self._on_write_failure(err)
            try:
                now = time.monotonic()
                if (self._writer_error is None and self.flush_period > 0.0
                        and now - last_flush >= self.flush_period):
                    self.bag.flush(fsync=True)
                    last_flush = now
                if self._writer_error is None and now - last_space_check >= SPACE_CHECK_PERIOD:
                    last_space_check = now
                    self._check_space()
            except Exception as err:  # noqa: BLE001 - reported, never silent
                self._on_write_failure(err)
            time.sleep(WRITE_BATCH_PAUSE)

    def _on_write_failure(self, err):
        """Stop writing after a failed write; report it (called in the writer thread)."""
        reason = f'{type(err).__name__}: {err}'
        self._writer_error = reason
        self.bag.abandon()  # Finishing would write again; the repair recovers the chunks.
        rclpy.logging.get_logger(self.get_name()).error(
            f'bag write failed, recording stopped: {reason}; the bag {self.output} is left '
            f'unfinished: scripts/bag_repair {self.output} recovers every complete chunk')

    # -- diagnostics -----------------------------------------------------------------------
    def publish_diagnostics(self):
        """Publish the recording figures on /diagnostics (timer callback)."""
        total = sum(self._received.values())
        now = time.monotonic()
        then, total_then = self._last_diagnostics
        rate = (total - total_then) / max(now - then, 1e-9)
        self._last_diagnostics = (now, total)
        backlog = self._queue.qsize()
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: recorder',
                                  hardware_id='')
        if self._disk_full:
            status.level = DiagnosticStatus.ERROR
            status.message = f'{self._writer_error}; {self._dropped} message(s) dropped since'
        elif self._writer_error is not None:
            status.level = DiagnosticStatus.ERROR
            status.message = (f'bag write failed, recording stopped: {self._writer_error}; '
                              f'{self._dropped} message(s) dropped since; run '
                              'scripts/bag_repair on the bag')
        elif self._failed:
            status.level = DiagnosticStatus.WARN
            status.message = f'{len(self._failed)} topic(s) not recorded'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'recording {len(self._recorded)} topic(s)'
        status.values = [
            KeyValue(key='bag', value=self.output),
            KeyValue(key='messages received', value=str(total)),
            KeyValue(key='messages written', value=str(self.bag.message_count)),
            KeyValue(key='receive rate [1/s]', value=f'{rate:.1f}'),
            KeyValue(key='write backlog', value=str(backlog)),
            KeyValue(key='file', value=self.bag.file_name),
            KeyValue(key='messages dropped (write failure)', value=str(self._dropped)),
        ]
        status.values += [KeyValue(key=f'received {topic}', value=str(count))
                          for topic, count in sorted(self._received.items())]
        status.values += [KeyValue(key=f'not recorded {topic}', value=reason)
                          for topic, reason in sorted(self._failed.items())]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diagnostics_pub.publish(array)

    # -- shutdown --------------------------------------------------------------------------
    def close(self):
        """Stop recording, write what was received and close the bag; idempotent.

        Returns
        -------
        bool
            True if the bag was closed properly (summary and metadata.yaml written).
        """
        if self._closed:
            return self._closed_ok
        self._closed = True  # From now on callbacks queue nothing.
        self._closed_ok = False
        self._queue.put(_STOP)  # Last item: everything received before is written.
        self._writer.join(timeout=self.close_timeout)
        # After a SIGINT the context is shut down: log without the /rosout publisher (a
        # logger of another name than the node's, which rcl would route to /rosout).
        logger = (self.get_logger() if self.context.ok()
                  else rclpy.logging.get_logger(f'wip_bag.{self.get_name()}'))
        if self._disk_full and not self._writer.is_alive():
            self._closed_ok = True   # Finished when the space ran low (_check_space).
            logger.error(f'{self._writer_error}: {self.bag.message_count} messages')
        elif self._writer.is_alive():
            logger.error(
                f'the writer did not finish within close_timeout = {self.close_timeout:g} s '
                f'({self._queue.qsize()} item(s) left): bag {self.output} left unfinished; '
                f'scripts/bag_repair {self.output} recovers every complete chunk')
        elif self._writer_error is not None:
            logger.error(
                f'bag {self.output} not closed: {self._writer_error}; '
                f'scripts/bag_repair {self.output} recovers every complete chunk')
        else:
            try:
                self.bag.close()
                self._closed_ok = True
                logger.info(
                    f'closed {self.output}: {self.bag.message_count} messages on '
                    f'{len(self.bag.message_counts())} topic(s) in '
                    f'{len(self.bag.file_names)} file(s)')
            except OSError as err:
                self._writer_error = f'{type(err).__name__}: {err}'
                self.bag.abandon()
                logger.error(f'closing bag {self.output} failed: {err}; '
                             f'scripts/bag_repair {self.output} recovers every complete chunk')
        for subscription in self._recorded.values():
            self.destroy_subscription(subscription)
        return self._closed_ok

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    """Entry point ``recorder`` (``ros2 run wip_bag recorder --ros-args -p output:=...``)."""
    if answer_node_help('recorder', 'wip_bag', args):
        return 0
    launched = end_with_launcher()
    # Our own handlers (stop_signals): rclpy's would shut the context down and raise
    # KeyboardInterrupt wherever the main thread is, also inside the bag's close.
    if not init_rclpy('recorder', args, SignalHandlerOptions.NO):
        return EXIT_USAGE
    stop = StopSignals()
    node = None
    status = 0
    try:
        node = RecorderNode()
        executor = make_executor()
        node.get_logger().debug(f'executor: {type(executor).__name__}')
        spin(node, executor, stop, launched)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BagExistsError, RecorderStartError, ValueError) as err:
        rclpy.logging.get_logger('recorder').error(str(err))
        print(f'recorder: error: {err}', file=sys.stderr)
        status = EXIT_USAGE
    except Exception:  # noqa: BLE001
        # A signal shuts the context down at any point, also inside a ROS call (e.g. "failed
        # to initialize wait set: the given context is not valid"): that is a normal stop.
        if rclpy.ok() and not stop.count:
            raise
    finally:
        for number in STOP_SIGNALS:  # Nothing may cut the close short from here on.
            signal.signal(number, signal.SIG_IGN)
        if node is not None:
            if not node.close():
                status = 1
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
