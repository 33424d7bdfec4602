"""One hardware-mode run: the controller nodes alone, against a real base's topics.

Start, arm (the /wip/heartbeat), watch and stop the controller processes, then send the
base zero commands; the steps: docs/run_graph.md.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import signal
import time
from typing import Any, Callable

import yaml

from .hardware_outcome import hardware_outcome, HardwareResult
from .heartbeat import Heartbeat
from .hardware_params import (hardware_parameters, load_params_file, node_parameters,
                              parse_remap, remapped)
from .launcher import (EXIT_FAILED, EXIT_OK, EXIT_USAGE, GraphError, in_namespace, INPUT_TOPICS,
                       use_user_ros_environment)
from .params_check import check_run_inputs
from .params_files import CONTROLLER_NODES, DEFAULT_JOINTS, _NoAliasDumper
from .probe import Probe
from .run_result import RunResult
from .run_stop import stop_signal_number
from .runner_base import RunnerBase
from .scheduling import Scheduling
from . import thread_usage

#: The nodes of hardware mode, in start order.
HARDWARE_NODES = CONTROLLER_NODES
#: The base's side of the graph: default topic names -> what the controllers do with them.
BASE_SENSOR_TOPICS = ('/joint_states', '/imu/data', '/gps/fix', '/odom')
DEFAULT_EFFORT_TOPIC = '/effort_controller/commands'
#: Longest wait [s] for the base's topics to be discovered before reporting them missing.
BASE_DISCOVERY_WAIT = 2.0
#: Topics of the controllers recorded with --record (plus the base's, remapped).
CONTROLLER_TOPICS = ('/wip/reference', '/wip/state_estimate', '/wip/velocity_command',
                     '/wip/yaw_torque', '/wip/drive_torque', '/wip/wheel_torques',
                     '/diagnostics')
#: The /wip/heartbeat period [s] (the mixer's maximum age: HEARTBEAT_MAX_AGE).
HEARTBEAT_PERIOD = 0.1
STATUS_PERIOD = 5.0  # [s] wall, progress lines
PROBE_PERIOD = 0.2  # [s] wall
#: Topics of every node, left out of the "the graph shows" list of the base's absence.
_OWN_TOPICS = ('/rosout', '/parameter_events')
#: Zero commands sent at the stop (a few, in case one is lost before the match settles).
ZERO_COMMANDS = 3


@dataclasses.dataclass
class HardwareOptions:
    """Arguments of :func:`run_hardware` (see ``scripts/run_graph --help``)."""

    scenario: str | None = None
    params_files: list[str] = dataclasses.field(default_factory=list)
    remaps: list[str] = dataclasses.field(default_factory=list)
    duration: float | None = None  # [s] wall; None: until SIGINT
    out: str = 'out/hardware'
    record: str | None = None
    discovery_timeout: float = 60.0  # [s] wall: processes started -> every node reporting
    quiet: bool = False
    arm_delay: float = 2.0  # [s] wall: every node up -> the e-stop heartbeat starts
    heartbeat: bool = True  # publish the /wip/heartbeat (docs/run_graph.md, arming)
    layout: str = 'composed'  # controller processes: see wip_bringup.launcher.LAYOUTS
    scheduling: Scheduling = Scheduling()  # of the controller processes
    #: Programmatic stop (tests): polled while running; a non-empty string ends the run
    #: (exit 0) with that message.
    stop_when: Callable[[], str | None] | None = None
    #: Programmatic hook (tests, benchmarks): called with the runner when the run starts,
    #: e.g. to reach its processes and safety events from another thread.
    on_start: Callable[[Any], None] | None = None
    #: The viewer node (Odometry, Path, markers of the estimate); None: with --record or
    #: --foxglove (see wip_bringup.view_options.viewer_wanted).
    viewer: bool | None = None
    foxglove_port: int | None = None  # serve the topics to Foxglove on this port
    foxglove_host: str = '127.0.0.1'
    #: A stand-in base that ends this long [s] after the controllers engage (its duration):
    #: a FAULT from then on is its end (its inputs stop), not a failure of the run.
    base_end_after: float | None = None
    #: ROS namespace of every node and topic of the run ('' none; e.g. 'robot1'): two
    #: vehicles in one domain (--namespace).
    namespace: str = ''


# ----------------------------------------------------------------------------- the runner

class HardwareRunner(RunnerBase):
    """One hardware-mode run: start, watch and stop the controller processes."""

    NOT_UP = 'the controller nodes did not come up in {timeout:g} s'
    PRIVATE_NETWORK = False

    def __init__(self, options: HardwareOptions) -> None:
        # Before the base class picks the domain: the base is on the user's domain and
        # network, not on a private default of scripts/_env.sh.
        self.network = use_user_ros_environment()
        super().__init__(options)
        self.domain_id = self.network.domain_id
        self.missing: list[str] = []
        self.remaps: list[tuple[str, str]] = []
        self.extra: list[dict[str, Any]] = []
        self.generated: dict[str, dict] = {}
        self.safety_events: list[dict[str, Any]] = []
        self._safety: tuple[str, str] | None = None
        self._counts: dict[str, list[tuple[float, int]]] = {}
        self.effort_publisher = None
        self.position_error = ''   # the eso's "position source refused: ..." if any
        self.zero_command: list[float] = [0.0, 0.0]
        self.zero_commands_sent = 0
        self.heartbeat: Heartbeat | None = None

    # -- set-up ---------------------------------------------------------------------------
    def prepare(self) -> pathlib.Path:
        options = self.options
        self.scenario = self.load_scenario(options.scenario)
        if options.duration is not None and not 0.0 < options.duration <= 1e6:
            raise GraphError(f'--duration: must be > 0 s, got {options.duration}', EXIT_USAGE)
        self.check_namespace()
        self.check_layout_and_scheduling()
        if not options.arm_delay >= 0.0:
            raise GraphError(f'--arm-delay: must be >= 0 s, got {options.arm_delay}',
                             EXIT_USAGE)
        self.remaps = [parse_remap(text, self.namespace) for text in options.remaps]
        for source, _ in self.remaps:
            if self.namespace and not source.startswith(self.namespace + '/'):
                self.say(f'warning: --remap {source}: an absolute name matches no topic of '
                         f'the nodes under {self.namespace}; write it relative (e.g. '
                         f'{source.lstrip("/")}:=...)')
        self.extra = [load_params_file(path) for path in options.params_files]
        # Before anything is written or started: the files against the nodes' declarations.
        run_topics = [in_namespace(topic, self.namespace) for topic in
                      (*BASE_SENSOR_TOPICS, DEFAULT_EFFORT_TOPIC, *CONTROLLER_TOPICS,
                       *INPUT_TOPICS)]
        for line in check_run_inputs(options.params_files, self.extra, self.node_names(),
                                     hardware_parameters(self.scenario), self.remaps,
                                     run_topics, self.namespace):
            self.say(f'warning: {line}')
        self.prepare_outputs()
        recorder = self.recorder_parameters(
            list(CONTROLLER_TOPICS) + list(INPUT_TOPICS) + list(BASE_SENSOR_TOPICS)
            + [DEFAULT_EFFORT_TOPIC],
            discovery_period=0.5)
        self.generated = hardware_parameters(self.scenario, recorder,
                                             heartbeat=options.heartbeat)
        mixer = node_parameters('torque_mixer', self.generated, self.extra, self.namespace)
        self.zero_command = [0.0] * len(mixer.get('joints', DEFAULT_JOINTS))
        # The mixer's name for it: relative (the default) resolves in the namespace. The
        # zero commands of the last resort go there, so it must be the mixer's topic.
        effort = str(mixer.get('effort_topic', DEFAULT_EFFORT_TOPIC.lstrip('/')))
        self.effort_topic = remapped(
            effort if effort.startswith('/') else in_namespace('/' + effort, self.namespace),
            self.remaps)
        path = self.out / 'params.yaml'
        header = ('# ROS parameters of a wip-ros hardware-mode run (controllers only, real '
                  f'time), scenario {self.scenario.name!r};\n# written by wip_bringup.hardware; '
                  'the --params-file files given come after it on each command line.\n')
        # The vehicle drawn with the controllers' nominal dimensions (no plant here).
        view = self.view_parameters(self.scenario.controller_model.parameters)
        path.write_text(header + yaml.dump({**self.generated, **view}, Dumper=_NoAliasDumper,
                                           sort_keys=False, width=99), encoding='utf-8')
        # What each node ran with, the --params-file files merged in: the bag keeps it,
        # so that offline tools read the robot's wiring (joints, signs, IMU mounting).
        effective = {node: {'ros__parameters': node_parameters(node, self.generated,
                                                               self.extra, self.namespace)}
                     for node in self.generated}
        self.run_parameters_text = (
            '# ROS parameters each controller node of this hardware-mode run had: the '
            'generated ones\n# with every --params-file merged in (written by '
            'wip_bringup.hardware).\n' + yaml.dump(effective, Dumper=_NoAliasDumper,
                                                  sort_keys=False, width=99))
        return path

    def finish(self, result: RunResult) -> None:
        super().finish(result)
        text = getattr(self, 'run_parameters_text', None)
        if text and self.bag_created and self.bag.is_dir():
            self.write_output(result, self.bag / 'params.yaml', text)

    def extra_arguments(self, name: str) -> tuple[list[str], list[str]]:
        """Every --params-file after the generated one, every --remap, for every node."""
        files = [str(pathlib.Path(p).resolve()) for p in self.options.params_files]
        remaps = []
        for source, target in self.remaps:
            remaps += ['-r', f'{source}:={target}']
        return files, remaps

    # -- probe ------------------------------------------------------------------------------
    def open_probe(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from std_msgs.msg import Float64MultiArray
        self.probe = Probe(self.domain_id, self.namespace)
        node = self.probe.node
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                 QoSProfile(depth=100))
        # The last resort on the base's command topic (docs/run_graph.md, step 5); created
        # now so that it is matched long before it is needed.
        self._float_array = Float64MultiArray
        self.effort_publisher = node.create_publisher(
            Float64MultiArray, self.effort_topic,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        if self.options.heartbeat:
            from std_msgs.msg import Empty
            publisher = node.create_publisher(
                Empty, remapped(in_namespace('/wip/heartbeat', self.namespace), self.remaps),
                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
            # Not a timer of the probe: that runs only when this loop spins (Heartbeat).
            self.heartbeat = Heartbeat(lambda: publisher.publish(Empty()), HEARTBEAT_PERIOD)

    def arm(self) -> None:
        """Wait ``arm_delay`` (nodes watched), then start the e-stop heartbeat."""
        if not self.options.heartbeat:
            return
        deadline = time.monotonic() + self.options.arm_delay
        while time.monotonic() < deadline:
            self.check_alive()
            self.probe.spin(min(PROBE_PERIOD, max(0.0, deadline - time.monotonic())))
        self.heartbeat.arm()
        self.timeline['armed'] = time.monotonic() - self.t0
        self.say('armed: /wip/heartbeat started; the safety layer engages once every '
                 'input is fresh and the ESO has settled')

    def _on_diagnostics(self, msg) -> None:
        now = time.monotonic() - self.t0
        for status in msg.status:
            own = self.probe.own_status_name(status.name)   # None: another vehicle's
            if own is None:
                continue
            name = own.split(':', 1)[0].lstrip('/')
            values = {kv.key: kv.value for kv in status.values}
            if (name == 'eso' and status.message.startswith('position source refused')
                    and status.message != self.position_error):
                # The cause of the mixer's "position source refused": said once, kept for
                # the outcome's message.
                self.position_error = status.message
                self.say(f'eso: {status.message}')
            if 'outputs' in values:
                try:
                    self._counts.setdefault(name, []).append((now, int(values['outputs'])))
                except ValueError:
                    pass
            if name == 'torque_mixer' and 'safety state' in values:
                state, reasons = values['safety state'], values.get('safety reasons', '')
                # A change of state or of the causes (numbers aside: ages grow).
                key = (state, re.sub(r'[-+]?\d+(\.\d+)?', '#', reasons))
                if key != self._safety:
                    self._safety = key
                    self.safety_events.append({'t': round(now, 4), 'state': state,
                                               'reasons': reasons})
                    self.say(f'safety: {state}' + (f' ({reasons})' if reasons not in (
                        '', 'none') else ''))

    def send_zero_commands(self) -> None:
        """Publish zero efforts on the base's command topic (docs/run_graph.md)."""
        if self.effort_publisher is None or self.probe is None:
            return
        for _ in range(ZERO_COMMANDS):
            self.effort_publisher.publish(self._float_array(data=list(self.zero_command)))
            self.zero_commands_sent += 1
            self.probe.spin(0.01)

    # -- watching ---------------------------------------------------------------------------
    def node_died(self, name: str) -> None:
        if name in ('torque_mixer', 'controllers'):
            self.send_zero_commands()

    def base_topics(self) -> dict[str, dict[str, int]]:
        """Publishers/subscriptions of the base's topics (remapped names)."""
        eso = node_parameters('eso', self.generated, self.extra, self.namespace)
        sensors = ['/joint_states', '/imu/data']
        source = eso.get('position_source')
        if source != 'wheels':   # dead reckoning needs no position topic
            sensors.append('/odom' if source == 'odometry' else '/gps/fix')
        names = [remapped(in_namespace(topic, self.namespace), self.remaps)
                 for topic in sensors]
        # The probe is new: DDS discovery of the base's endpoints can take it a moment
        # more than the controllers' own (seen: the base's subscription missing once).
        deadline = time.monotonic() + BASE_DISCOVERY_WAIT
        while time.monotonic() < deadline and not (
                all(self.probe.count(n)[0] for n in names)
                and self.probe.count(self.effort_topic)[1]):
            self.probe.spin(0.1)
        out = {}
        for topic, name in zip(sensors, names):
            publishers, _ = self.probe.count(name)
            out[name] = {'publishers': publishers}
            if not publishers:
                self.missing.append(name)
                self.say(f"warning: no publisher on {name} (the base's {topic}) yet: the "
                         'safety layer commands zero torque until every input arrives')
        _, subscribers = self.probe.count(self.effort_topic)
        out[self.effort_topic] = {'subscriptions': subscribers}
        if not subscribers:
            self.missing.append(self.effort_topic)
            self.say(f"warning: nothing subscribes to {self.effort_topic}: is the base's "
                     'effort controller running (and the topic remapped)?')
        if all(name in self.missing for name in names):   # no sensor of the base at all
            self.say(self.no_base_message(names))
        return out

    def no_base_message(self, names: list[str]) -> str:
        """Message for none of the base's topics in the graph.

        None of the base's topics: what was expected, what the graph shows, and the
        likely cause (the base on another domain or discovery range).
        """
        node = self.probe.node
        # Every topic of the controllers' own nodes (they subscribe to the base's topics
        # too) is left out: what is left is what other nodes, a base among them, offer.
        ours = set(HARDWARE_NODES) | set(self.processes) | {node.get_name()}
        shown = []
        for name, _ in sorted(node.get_topic_names_and_types()):
            endpoints = (node.get_publishers_info_by_topic(name)
                         + node.get_subscriptions_info_by_topic(name))
            if name not in _OWN_TOPICS and any(e.node_name not in ours for e in endpoints):
                shown.append(name)
        return (f'warning: no base topic after {BASE_DISCOVERY_WAIT:g} s: expected '
                f'publishers on {", ".join(names)} and a subscription on {self.effort_topic}'
                f'; the graph shows {", ".join(shown) if shown else "no topic"} of other '
                f'nodes; the base may be on another ROS_DOMAIN_ID or discovery range than '
                f"this run's ({self.network.describe()}), or its topics need --remap")

    def watch(self) -> str:
        """Until SIGINT or the duration: progress, node health. Returns why it ended."""
        duration = self.options.duration
        start = time.monotonic()
        next_status = start + STATUS_PERIOD
        while True:
            self.probe.spin(PROBE_PERIOD)
            self.check_alive()
            now = time.monotonic()
            if duration is not None and now - start >= duration:
                return f'the duration of {duration:g} s was reached'
            if self.options.stop_when is not None:
                reason = self.options.stop_when()
                if reason:
                    return reason
            if now >= next_status:
                next_status += STATUS_PERIOD
                self.say(self.status_line(now - start))

    def status_line(self, elapsed: float) -> str:
        rates = self.rates(window=STATUS_PERIOD)
        state = self._safety[0] if self._safety else 'unknown'
        return (f't {elapsed:6.1f} s  safety {state}  rates [1/s]: '
                + ', '.join(f'{n} {rates[n]:.0f}' for n in HARDWARE_NODES if n in rates))

    def rates(self, window: float | None = None) -> dict[str, float]:
        """Mean outputs per second of each node.

        From its /diagnostics output counts (over the last ``window`` seconds, or the whole run).
        """
        out = {}
        for name, samples in self._counts.items():
            if window is not None:
                last = samples[-1][0]
                samples = [s for s in samples if s[0] >= last - window - 1.0]
            # Over the span in which the node produced: before its inputs came and after
            # they stopped (the base's end, before the nodes are stopped) it outputs
            # nothing, and counting that time would report a slower node.
            grew = [i for i in range(1, len(samples)) if samples[i][1] > samples[i - 1][1]]
            if grew:
                samples = samples[grew[0] - 1:grew[-1] + 1]
            if len(samples) >= 2 and samples[-1][0] > samples[0][0]:
                out[name] = ((samples[-1][1] - samples[0][1])
                             / (samples[-1][0] - samples[0][0]))
        return out

    def nodes_stopped(self) -> None:
        self.send_zero_commands()

    def shut_down(self, result: HardwareResult) -> None:
        # Before the probe's node (the publisher's) is destroyed; the nodes are stopped next.
        if self.heartbeat is not None:
            self.heartbeat.stop()
        super().shut_down(result)

    def outcome(self, ended: str) -> tuple[int, str]:
        """Return the run's exit code and message from the safety events seen until now.

        The states the stop itself causes come later and are not judged.
        """
        code, message = hardware_outcome(list(self.safety_events), ended,
                                         self.options.base_end_after, self.missing)
        if self.position_error and code != EXIT_OK:
            message += f'; eso: {self.position_error}'
        return code, message

    def controller_pids(self) -> dict[str, int]:
        """Return the controller processes' pids (all but the recorder's) by name."""
        return {name: process.pid for name, process in self.processes.items()
                if name != 'recorder'}

    # -- the run ----------------------------------------------------------------------------
    def run(self) -> HardwareResult:
        result = HardwareResult(EXIT_FAILED, '', self.out, self.bag, self.domain_id)
        cpu_start: dict[str, float | None] = {}
        threads_start: dict = {}
        run_start = None
        if self.options.on_start is not None:
            self.options.on_start(self)
        try:
            params_file = self.prepare()
            self.say(f'hardware mode: controllers of scenario {self.scenario.name!r} in real '
                     f'time, outputs in {self.out}')
            self.say(f"ROS network: {self.network.describe()} (from the environment; ROS's "
                     'defaults where unset)')
            self.open_probe()
            self.launch(params_file)
            self.say_foxglove_url()
            result.base_topics = self.base_topics()
            self.arm()
            result.startup_s = time.monotonic() - self.t0
            self.say(f'{len(self.processes)} nodes up in {result.startup_s:.1f} s; running '
                     + (f'for {self.options.duration:g} s' if self.options.duration
                        else 'until Ctrl-C'))
            run_start = time.monotonic()
            cpu_start = self.cpu_snapshot()
            threads_start = thread_usage.snapshot(self.controller_pids())
            reason = self.watch()
            result.exit_code, result.message = self.outcome(reason)
        except GraphError as err:
            result.exit_code, result.message = err.exit_code, str(err)
        except KeyboardInterrupt as err:
            # The normal end of a run without --duration: a stop, whatever sent it; judged
            # by what the safety layer did before it (a fall, then Ctrl-C, is a fall).
            result.exit_code, result.message = self.outcome(
                f'stopped by {signal.Signals(stop_signal_number(err)).name}')
        finally:
            if run_start is not None:
                result.wall_time_s = time.monotonic() - run_start
                result.cpu_s.update(self.cpu_since(cpu_start))
                result.threads = thread_usage.usage_since(
                    threads_start, thread_usage.snapshot(self.controller_pids()),
                    result.wall_time_s)
            self.shut_down(result)
        result.rates = self.rates()
        result.safety_events = list(self.safety_events)
        result.zero_commands_sent = self.zero_commands_sent
        result.timeline = dict(self.timeline)
        self.finish(result)
        return result


def run_hardware(options: HardwareOptions) -> HardwareResult:
    """Run the controllers in hardware mode (docs/run_graph.md)."""
    return HardwareRunner(options).run()
