"""Replayer node: play a rosbag2 bag back, like ``ros2 bag play``.

rosbag2 is not on PyPI; this node plays the project's bags and any rosbag2 MCAP bag (a bag
directory with ``metadata.yaml``, split into several files or not, or a single ``.mcap``
file). The bag is checked first (every chunk's CRC, a proper end): a damaged or unfinished
bag is refused with what it lost, unless ``partial`` is set (then its intact chunks are
played, with a warning naming what is missing). The serialized messages are
republished as recorded (``publisher.publish(bytes)``: no decoding, no re-encoding), so
subscribers receive the recorded bytes exactly.

Run it as ``scripts/replay BAG [options]`` (``--help`` lists them; each sets the parameter
of the same name) or ``ros2 run wip_bag replay --ros-args -p bag:=BAG ...``.

Parameters (read-only, read at start-up)
----------------------------------------
:class:`wip_bag.settings.ReplayerParams` (docs/parameters.md): the bag (also the first
positional argument), rate, start offset, duration and loop, the topics played, excluded
and remapped (``from:=to``; ``--ros-args -r`` works too), ``/clock`` (the recorded time,
before each newer message and at ``clock_rate`` in between; a recorded ``/clock`` is then
not played), a paused start, the wait for subscribers (how many, on which played topics,
for how long before playing anyway), a delay, the publishers' history depth, a partial
bag's intact part (``partial``) and whether to exit at the end (``exit_when_done``: false
stays up, paused at the end, e.g. for transient-local topics).

QoS
---
Each topic is published with the QoS its publishers offered when it was recorded (the
``offered_qos_profiles`` of the bag), as rosbag2's player does
(``Rosbag2QoS::adapt_offer_to_recorded_offers``): the recorded profile if all recorded
publishers offered the same reliability, durability, deadline and liveliness, else the
default (reliable, volatile). The history is keep-last ``qos_depth`` (rosbag2 uses 10).
A reliable keep-last writer overwrites samples that a slow reader has not acknowledged
yet once its history is full, so the depth is the slack a subscriber has: 1000 (the
recorder's subscription depth) is 0.5 s of a 200 Hz topic played 10 times faster
(measured: a 90 s graph bag, 182k messages, played at rate 10 into the recorder lost 2
messages with depth 100, none with 1000).

Timing
------
Messages are sent at their recorded receive times (MCAP log times, the order of the bag),
spaced by (recorded spacing) / ``rate``, measured on the steady wall clock from the start
of playback; the time spent paused is added. A message late on its schedule (slow
subscriber, loaded machine) is sent at once and the schedule is kept, so lateness does not
accumulate.

Services
--------
``~/pause`` (std_srvs/SetBool): ``data: true`` pauses, ``false`` resumes; the response
tells the new state and the bag time reached. ``~/toggle_pause`` (std_srvs/Trigger).

``/diagnostics`` (diagnostic_msgs/DiagnosticArray) once a second: bag time reached,
messages published, state.

Exit codes: 0 end of the bag (or SIGINT/SIGTERM), 1 the bag cannot be read, 2 invalid
parameters.
"""

import argparse
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock as ClockMsg
from std_srvs.srv import SetBool, Trigger

from wip_runtime.node_main import init_rclpy
from wip_runtime.launched import end_with_launcher
from wip_runtime.parameters import RosParams
from wip_runtime.cli import (add_exit_codes, EXIT_INTERNAL, EXIT_USAGE, log_trace, one_line,
                             split_ros_args)

from .bag_reader import bag_summary, BagReadError, iter_raw_messages, read_topics
from .message_types import message_class
from .playback import parse_remaps, playback_qos, PlaybackClock
from .settings import ReplayerParams

# The exit-code table of every tool (wip_runtime.cli).
EXIT_OK = 0
EXIT_BAG_ERROR = EXIT_USAGE  # the bag cannot be played: an input error
EXIT_BAD_PARAMETERS = EXIT_USAGE

CLOCK_TOPIC = '/clock'
#: Topics played under their own name whatever the replayer's namespace (the recorder
#: stores them so: one /clock and one /diagnostics per domain).
GLOBAL_TOPICS = (CLOCK_TOPIC, '/diagnostics', '/rosout', '/parameter_events', '/tf',
                 '/tf_static')
DIAGNOSTICS_PERIOD = 1.0  # [s], wall time
SPIN_SLICE = 0.05  # [s]: longest spin_once while waiting; bounds the reaction time
FINE_WAIT = 0.002  # [s]: the last part of a wait is a plain sleep, more precise than spinning
FLUSH_TIMEOUT = 5.0  # [s] to wait for the acknowledgements of the last messages


class ReplayError(Exception):
    """The bag cannot be played as asked."""


class ReplayerNode(Node):
    """Plays a bag back; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('replayer', **kwargs)
        settings = RosParams(self, '', ReplayerParams).config
        self.bag = settings.bag
        self.rate = settings.rate
        self.start_offset = settings.start_offset
        self.duration = settings.duration
        self.loop = settings.loop
        self.allow_partial = settings.partial
        self.clock_enabled = settings.clock
        self.clock_rate = settings.clock_rate
        self.wait_for = settings.wait_for_subscribers
        self.wait_timeout = settings.wait_timeout
        self.delay = settings.delay
        self.qos_depth = settings.qos_depth
        self.exit_when_done = settings.exit_when_done
        if not self.bag:
            raise ValueError('parameter bag: no bag given')
        remaps = parse_remaps(list(settings.remap))

        self._create_publishers(settings, remaps)
        self._set_time_window()
        self._start(settings)

    def _create_publishers(self, settings, remaps):
        """Create a publisher per recorded topic played (and /clock); note those skipped."""
        try:
            recorded = read_topics(self.bag, self.allow_partial)
            lost = bag_summary(self.bag)['problems'] if self.allow_partial else []
        except (BagReadError, OSError) as err:
            raise ReplayError(f'cannot read bag {self.bag}: {err}') from err
        for line in lost:
            self.get_logger().warning(f'playing a partial bag: {line}')
        wanted = list(settings.topics)
        excluded = set(settings.exclude)
        missing = [t for t in wanted if t not in recorded]
        if missing:
            self.get_logger().warning(f'topics not in the bag: {missing}')
        if self.clock_enabled and CLOCK_TOPIC in recorded and CLOCK_TOPIC not in excluded:
            self.get_logger().warning(f'the bag holds {CLOCK_TOPIC}: not played, the replayer '
                                      'publishes its own clock')
            excluded.add(CLOCK_TOPIC)
        self.publishers_by_topic = {}  # recorded topic -> publisher
        self.skipped = {}  # recorded topic -> reason
        for topic, meta in recorded.items():
            if (wanted and topic not in wanted) or topic in excluded:
                continue
            if meta.serialization_format != 'cdr':
                self.skipped[topic] = f'serialization {meta.serialization_format!r}'
                continue
            try:
                msg_class = message_class(meta.type_name, ReplayError)
                qos = playback_qos(meta.offered_qos_profiles, self.qos_depth)
            except (ReplayError, ValueError) as err:
                self.skipped[topic] = str(err)
                continue
            name = remaps.get(topic, topic)
            if name == topic and self.get_namespace() != '/' and topic not in GLOBAL_TOPICS:
                # Played into the node's namespace: a vehicle's bag (stored without its
                # namespace by the recorder) replayed to one vehicle of several.
                name = topic.lstrip('/')
            self.publishers_by_topic[topic] = self.create_publisher(msg_class, name, qos)
        for topic, reason in self.skipped.items():
            self.get_logger().error(f'not playing {topic}: {reason}')
        if not self.publishers_by_topic:
            raise ReplayError(f'{self.bag}: no topic to play')
        self.clock_pub = (self.create_publisher(ClockMsg, CLOCK_TOPIC, QoSProfile(depth=10))
                          if self.clock_enabled else None)
        wait_topics = list(settings.wait_topics)
        self.wait_publishers = [p for p in self.publishers_by_topic.values()
                                if not wait_topics or p.topic_name in wait_topics]

    def _set_time_window(self):
        """Set the bag time [ns] played from (``start_offset``) and to (``duration``)."""
        starts = []
        for file_start in self._first_times():
            starts.append(file_start)
        if not starts:
            raise ReplayError(f'{self.bag}: no message on the played topics')
        self.bag_start_ns = min(starts)
        self.start_ns = self.bag_start_ns + int(round(self.start_offset * 1e9))
        self.end_ns = (self.start_ns + int(round(self.duration * 1e9))
                       if self.duration > 0.0 else None)

    def _start(self, settings):
        """Set the playback state up; start the pause services and the diagnostics."""
        self.clock = PlaybackClock(self.rate, self.start_ns, time.monotonic())
        self.clock.paused = settings.start_paused
        self.published = 0
        self.loops = 0
        self.last_clock_ns = None
        self.last_bag_ns = self.start_ns
        self.state = 'starting'
        self.create_service(SetBool, '~/pause', self._on_pause)
        self.create_service(Trigger, '~/toggle_pause', self._on_toggle)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD, self.publish_diagnostics, clock=wall)
        self.get_logger().info(
            f'playing {len(self.publishers_by_topic)} topic(s) of {self.bag} at rate '
            f'{self.rate:g}' + (' with /clock' if self.clock_enabled else '')
            + (f', from +{self.start_offset:g} s' if self.start_offset else '')
            + (f' for {self.duration:g} s' if self.duration else '')
            + (', looping' if self.loop else ''))

    # -- parameters ------------------------------------------------------------------------
    def _first_times(self):
        for message in iter_raw_messages(self.bag, topics=list(self.publishers_by_topic),
                                         allow_partial=self.allow_partial):
            yield message.log_time_ns
            return

    # -- services --------------------------------------------------------------------------
    def set_paused(self, paused):
        now = time.monotonic()
        if paused:
            self.clock.pause(now)
        else:
            self.clock.resume(now)
        self.get_logger().info(f'{"paused" if paused else "resumed"} at bag time '
                               f'{self.clock.bag_time_ns(now) * 1e-9:.3f} s')

    def _on_pause(self, request, response):
        self.set_paused(bool(request.data))
        response.success = True
        response.message = (f'{"paused" if self.clock.paused else "playing"} at bag time '
                             f'{self.clock.bag_time_ns(time.monotonic()) * 1e-9:.9f} s')
        return response

    def _on_toggle(self, request, response):
        self.set_paused(not self.clock.paused)
        response.success = True
        response.message = 'paused' if self.clock.paused else 'playing'
        return response

    # -- playback --------------------------------------------------------------------------
    def wait_for_subscribers(self, executor):
        """Wait (spinning) until the awaited topics have enough subscriptions, or time out."""
        if self.wait_for <= 0:
            return True
        deadline = time.monotonic() + self.wait_timeout
        self.state = 'waiting for subscribers'
        while rclpy.ok(context=self.context):
            short = [p.topic_name for p in self.wait_publishers
                     if p.get_subscription_count() < self.wait_for]
            if not short:
                return True
            if time.monotonic() >= deadline:
                self.get_logger().warning(
                    f'playing without {self.wait_for} subscription(s) on {short} after '
                    f'{self.wait_timeout:g} s')
                return False
            executor.spin_once(timeout_sec=SPIN_SLICE)
        return False

    def _publish_clock(self, bag_ns):
        if self.clock_pub is None or (self.last_clock_ns is not None
                                      and bag_ns <= self.last_clock_ns):
            return
        msg = ClockMsg()
        msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
        self.clock_pub.publish(msg)
        self.last_clock_ns = bag_ns

    def _wait_until(self, bag_ns, executor):
        """Wait (spinning, publishing /clock) until the playback reaches ``bag_ns``."""
        clock_period = 1.0 / self.clock_rate if (self.clock_pub and self.clock_rate) else None
        next_clock = time.monotonic()
        while rclpy.ok(context=self.context):
            now = time.monotonic()
            target = self.clock.wall_time(bag_ns)
            remaining = target - now
            if clock_period is not None and not self.clock.paused and now >= next_clock:
                self._publish_clock(min(self.clock.bag_time_ns(now), bag_ns))
                next_clock = now + clock_period
            if remaining <= 0.0:
                return True
            if remaining <= FINE_WAIT:
                time.sleep(remaining)
                return rclpy.ok(context=self.context)
            slice_ = min(remaining - FINE_WAIT, SPIN_SLICE)
            if clock_period is not None and not self.clock.paused:
                slice_ = min(slice_, max(0.0, next_clock - now))
            executor.spin_once(timeout_sec=slice_)
        return False

    def play(self, executor):
        """Play the bag (looping if asked); returns when done or shut down."""
        self.wait_for_subscribers(executor)
        if self.delay > 0.0:
            end = time.monotonic() + self.delay
            while rclpy.ok(context=self.context) and time.monotonic() < end:
                executor.spin_once(timeout_sec=min(SPIN_SLICE, end - time.monotonic()))
        topics = list(self.publishers_by_topic)
        self.clock.restart(self.start_ns, time.monotonic())
        while rclpy.ok(context=self.context):
            self.state = 'playing'
            last_spin = time.monotonic()
            for message in iter_raw_messages(self.bag, topics=topics, start_ns=self.start_ns,
                                             end_ns=self.end_ns,
                                             allow_partial=self.allow_partial):
                if not self._wait_until(message.log_time_ns, executor):
                    return
                self._publish_clock(message.log_time_ns)
                self.publishers_by_topic[message.topic].publish(message.data)
                self.published += 1
                self.last_bag_ns = message.log_time_ns
                now = time.monotonic()
                if now - last_spin > SPIN_SLICE:  # Late messages never wait: serve the rest.
                    executor.spin_once(timeout_sec=0.0)
                    last_spin = now
            if not self.loop:
                break
            self.loops += 1
            self.last_clock_ns = None  # The clock jumps back to the start point.
            self.clock.restart(self.start_ns, time.monotonic())
        self.state = 'done'
        self.get_logger().info(f'done: {self.published} messages published')

    def flush(self, timeout=FLUSH_TIMEOUT):
        """Wait until the reliable subscribers acknowledged everything published."""
        deadline = time.monotonic() + timeout
        for publisher in list(self.publishers_by_topic.values()) + [self.clock_pub]:
            if publisher is None:
                continue
            left = max(0.0, deadline - time.monotonic())
            publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))

    def publish_diagnostics(self):
        """Playback progress on /diagnostics (timer callback, wall clock)."""
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: replayer',
                                  hardware_id='')
        status.level = DiagnosticStatus.WARN if self.skipped else DiagnosticStatus.OK
        state = 'paused' if self.clock.paused and self.state == 'playing' else self.state
        status.message = state + (f'; {len(self.skipped)} topic(s) not played'
                                  if self.skipped else '')
        status.values = [
            KeyValue(key='bag', value=str(self.bag)),
            KeyValue(key='rate', value=f'{self.rate:g}'),
            KeyValue(key='bag time [s]', value=f'{self.last_bag_ns * 1e-9:.3f}'),
            KeyValue(key='from start [s]',
                     value=f'{(self.last_bag_ns - self.bag_start_ns) * 1e-9:.3f}'),
            KeyValue(key='messages published', value=str(self.published)),
            KeyValue(key='loops completed', value=str(self.loops)),
        ] + [KeyValue(key=f'not played {t}', value=r) for t, r in sorted(self.skipped.items())]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diagnostics_pub.publish(array)


# -- command line --------------------------------------------------------------------------
_OPTIONS = (
    # (option, parameter, type, help)
    ('--rate', 'rate', float, 'playback speed factor (default 1)'),
    ('--start-offset', 'start_offset', float, 'start this many seconds into the bag'),
    ('--duration', 'duration', float, 'play this many seconds of the bag'),
    ('--clock-rate', 'clock_rate', float, '/clock rate between messages [Hz] (default 100)'),
    ('--wait-for-subscribers', 'wait_for_subscribers', int,
     'subscriptions each played topic needs before playing'),
    ('--wait-timeout', 'wait_timeout', float, 'longest wait for subscribers [s]'),
    ('--delay', 'delay', float, 'wall-clock delay before playing [s]'),
    ('--qos-depth', 'qos_depth', int, 'keep-last depth of the publishers (default 1000)'),
)
_FLAGS = (
    ('--loop', 'loop', 'play in a loop'),
    ('--clock', 'clock', 'publish /clock from the recorded times'),
    ('--start-paused', 'start_paused', 'start paused (resume: ~/pause service)'),
    ('--stay', 'exit_when_done', 'stay up at the end of the bag (default: exit)'),
    ('--partial', 'partial', 'play the intact part of a damaged or unfinished bag'),
)
_LISTS = (
    ('--topics', 'topics', 'topics to play (default: all)'),
    ('--exclude', 'exclude', 'topics not played'),
    ('--remap', 'remap', 'topic renames from:=to'),
    ('--wait-topics', 'wait_topics', 'topics whose subscribers are awaited'),
)


def parse_command_line(argv):
    """Split ``argv`` into (parameter overrides, ROS arguments).

    Everything from ``--ros-args`` on is left to rclpy; the options before it are this
    tool's (see ``--help``).
    """
    argv, ros_args = split_ros_args(argv)
    parser = argparse.ArgumentParser(
        prog='scripts/replay', formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Play a rosbag2 MCAP bag (directory or .mcap file) like `ros2 bag play`; options set the
replayer node parameters of the same name.

Examples
--------
    scripts/replay out/demo/bag                      # at recorded speed
    scripts/replay out/demo/bag --rate 10 --clock    # 10x, publishing /clock
    scripts/replay out/demo/bag --topics /imu/data /joint_states --loop
    scripts/replay out/demo/bag --partial            # the intact part of a damaged bag""",
        epilog='Anything after --ros-args goes to ROS (e.g. -r /imu/data:=/replay/imu).')
    parser.add_argument('bag', nargs='?', help='bag directory or .mcap file')
    for option, _, kind, text in _OPTIONS:
        parser.add_argument(option, type=kind, help=text)
    for option, _, text in _FLAGS:
        parser.add_argument(option, action='store_true', help=text)
    for option, _, text in _LISTS:
        parser.add_argument(option, nargs='+', help=text,
                            metavar='FROM:=TO' if option == '--remap' else 'TOPIC')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    try:   # before anything starts
        parse_remaps(args.remap or [])
    except ValueError as err:
        parser.error(str(err))
    overrides = []
    if args.bag:
        overrides.append(Parameter('bag', value=args.bag))
    for option, name, _, _ in _OPTIONS:
        value = getattr(args, option[2:].replace('-', '_'))
        if value is not None:
            overrides.append(Parameter(name, value=value))
    for option, name, _ in _FLAGS:
        if getattr(args, option[2:].replace('-', '_')):
            overrides.append(Parameter(name, value=(name != 'exit_when_done')))
    for option, name, _ in _LISTS:
        value = getattr(args, option[2:].replace('-', '_'))
        if value:
            overrides.append(Parameter(name, Parameter.Type.STRING_ARRAY, list(value)))
    return overrides, ros_args


def main(args=None):
    """Entry point ``replayer`` and ``scripts/replay``; returns the exit code."""
    argv = sys.argv[1:] if args is None else list(args)
    overrides, ros_args = parse_command_line(argv)
    end_with_launcher()
    if not init_rclpy('replay', [sys.argv[0]] + ros_args, SignalHandlerOptions.ALL):
        return EXIT_BAD_PARAMETERS
    node = None
    status = EXIT_OK
    try:
        node = ReplayerNode(parameter_overrides=overrides)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.play(executor)
        if rclpy.ok():
            node.flush()
            while not node.exit_when_done and rclpy.ok():
                executor.spin_once(timeout_sec=SPIN_SLICE)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ReplayError as err:
        print(f'replayer: error: {err}', file=sys.stderr)
        status = EXIT_BAG_ERROR
    except ValueError as err:
        print(f'replayer: error: {err}', file=sys.stderr)
        status = EXIT_BAD_PARAMETERS
    except Exception as err:  # noqa: BLE001
        # A signal shuts the context down at any point, also inside a ROS call (e.g. "failed
        # to initialize wait set: the given context is not valid"): that is a normal stop.
        if rclpy.ok():
            where = log_trace('replayer', err)
            print(f'replayer: internal error: {one_line(err)} (full trace in {where})',
                  file=sys.stderr)
            status = EXIT_INTERNAL
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
