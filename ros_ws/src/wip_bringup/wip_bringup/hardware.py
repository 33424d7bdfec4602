r"""Hardware mode of ``scripts/run_graph``: the controller nodes alone, against a real base.

Examples
--------
    scripts/run_graph --mode hardware --params-file my_base.yaml
    scripts/run_graph --no-plant --scenario line.yaml --params-file my_base.yaml \
        --remap /joint_states:=/base/joint_states --remap /imu/data:=/base/imu \
        --remap /effort_controller/commands:=/base/wheel_effort_controller/commands \
        --record out/robot/bag --duration 60

What it does
------------
1. Loads the scenario (``--scenario``, default the paper's Section V) for the
   CONTROLLER sections only (reference, eso, position, trajectory_generator, arc, mpc,
   mixer, rates, controller_model; the plant, disturbances and initial state of a
   scenario describe a simulation and are ignored), writes ``OUT/scenario.yaml`` and
   ``OUT/params.yaml`` (clock_mode realtime, no use_sim_time; the reference node starts
   its path when the safety layer first engages: ``realtime_start: engaged``).
2. Starts reference, eso, trajectory_generator, arc, mpc and torque_mixer (and, with
   ``--record BAG``, the recorder of every controller topic, of the base's topics and of
   the run's inputs: /cmd_vel, /plan, /wip/estop, /wip/estop_reset, /wip/heartbeat),
   each as its own process running ``<prefix>/lib/<package>/<executable>`` (what ``ros2
   run`` runs) with ``--ros-args --params-file OUT/params.yaml`` followed by every
   ``--params-file`` given (a later file overrides an earlier one, as in ROS: use
   ``/**:`` sections for the base's joint names, wheel signs, IMU mounting, datum...),
   ``-r __node:=<name>`` and every ``--remap FROM:=TO``, applied to every node.
3. Waits until every node is up and has sent /diagnostics, then reports which of the
   base's topics (after the remaps) have a publisher (sensors) or a subscription (the
   effort command). A missing base is not an error: the safety layer commands zero
   torque until every input has arrived and the ESO has settled.
   **Arming**: the generated parameters make the mixer require a heartbeat
   (``safety.max_estop_age`` = 1 s): no torque before the first ``/wip/heartbeat``
   (or e-stop) message, zero torque (FAULT) when none came for 1 s. This process
   publishes ``/wip/heartbeat`` (std_msgs/Empty) at 10 Hz, starting ``--arm-delay``
   seconds (default 2) after every node is up: the
   controllers engage only once the start-up, and its DDS discovery, is over (measured:
   a process's publish() can stall for 0.33 s while the others start, which a robot
   released at that moment does not survive), and torque stops if this supervisor dies.
   The heartbeat is its own topic, never a release: an e-stop of your own (``/wip/estop``
   = true, from a joystick...) latches, and while it keeps saying true the reset is
   refused.
   ``--no-heartbeat``: no heartbeat, no arm delay (the mixer engages as soon as ready).
4. Runs until SIGINT (Ctrl-C) or ``--duration`` [s of wall time], printing the safety
   state and the node rates every few seconds and recording every change of the safety
   state (with its reasons, from the mixer's /diagnostics) in ``OUT/run.json``. A node
   that dies ends the run (exit 3).
5. Stops every node by its pid (SIGINT, SIGKILL after a grace period; the recorder last)
   and then publishes a zero effort command on the base's command topic: a
   ``JointGroupEffortController`` holds the last command forever, and the mixer does not
   send one when it is killed. The same zero command is sent at once if the mixer dies
   during the run. (Nothing can be sent if this process itself is killed with SIGKILL.)

Network: hardware mode uses the ROS environment as you have it (``ROS_DOMAIN_ID``,
``ROS_AUTOMATIC_DISCOVERY_RANGE``, ``ROS_STATIC_PEERS``), with ROS's defaults where unset
(domain 0, discovery range SUBNET), and prints them at the start: the private domain and
localhost-only discovery that scripts/_env.sh gives simulations are dropped. When the base's
topics do not appear within a few seconds, it says which topics it expected and which the
graph shows (a base on another domain or discovery range shows none of them).

Outputs in OUT: ``params.yaml``, ``scenario.yaml``, ``logs/``, ``run.json`` (exit status,
start-up timeline, safety events, node rates, CPU time and last /diagnostics of every
node). With ``--record BAG``, also ``BAG/scenario.yaml`` and ``BAG/params.yaml``: the
parameters each node had, every ``--params-file`` merged in (``scripts/identify`` reads
the robot's wiring from it).

Exit status (``wip_control.tools.cli``): 0 the controllers engaged and the run ended without
a safety fault, stopped by SIGINT, SIGTERM or SIGHUP (the end of a run without
``--duration``; the nodes stopped, zero commands sent, the bag closed, run.json written), by
an e-stop of yours, or at the end of ``--duration``; 1 the vehicle fell or the safety layer
went to FAULT after engaging (the message gives the mixer's reason, e.g. "fallen:
|theta_hat| ... rad"); 5 the controllers never engaged (no inputs from the base, or the
estimate never settled: the message gives the mixer's last reason); 2 bad arguments or
outputs (also: another run holds --out or the bag); 3 a node failed or the nodes did not
come up in time; 4 the disk filled up (an output could not be written).
"""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import pathlib
import re
import signal
import sys
import time
from typing import Any, Callable, Iterable, Mapping

import yaml

from wip_control.core.config import ConfigError, load_yaml_text
from wip_control.core.controller_settings import ControllerSettings
from wip_control.tools.cli import add_exit_codes, bounded
from wip_bringup.params_files import (CONTROLLER_NODES, DEFAULT_JOINTS, flatten,
                                      graph_parameters, _NoAliasDumper)

from .params_check import check_remap, check_run_inputs, ParamsError
from .launcher import (add_view_arguments, EXIT_FAILED, EXIT_FELL, EXIT_NOT_ENGAGED, EXIT_OK,
                       EXIT_USAGE, GraphError, in_namespace, INPUT_TOPICS, LAYOUTS,
                       parse_cpus, Probe, Scheduling, use_user_ros_environment)
from .runner_base import (options_from_args, print_result, RunnerBase, RunResult,
                          stop_signal_number, stop_signals)

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
#: The mixer's ``safety.max_estop_age`` in hardware mode [s] and the heartbeat period [s].
HEARTBEAT_MAX_AGE = 1.0
HEARTBEAT_PERIOD = 0.1
STATUS_PERIOD = 5.0  # [s] wall, progress lines
PROBE_PERIOD = 0.2  # [s] wall
#: Safety states in which the mixer commands torque: the controllers have engaged.
ENGAGED_STATES = ('ACTIVE', 'DEGRADED', 'SHADOW')
#: Latency [s] of the mixer's safety state through its /diagnostics (period 1 s), as a margin.
DIAGNOSTICS_LATENCY = 0.5
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
    heartbeat: bool = True  # publish the /wip/heartbeat (see the module docstring)
    layout: str = 'composed'  # controller processes: see wip_bringup.launcher.LAYOUTS
    scheduling: Scheduling = Scheduling()  # of the controller processes
    #: Programmatic stop (tests): polled while running; a non-empty string ends the run
    #: (exit 0) with that message.
    stop_when: Callable[[], str | None] | None = None
    #: Programmatic hook (tests, benchmarks): called with the runner when the run starts,
    #: e.g. to reach its processes and safety events from another thread.
    on_start: Callable[[Any], None] | None = None
    #: The viewer node (Odometry, Path, markers of the estimate); None: with --record or
    #: --foxglove (see wip_bringup.launcher.viewer_wanted).
    viewer: bool | None = None
    foxglove_port: int | None = None  # serve the topics to Foxglove on this port
    foxglove_host: str = '127.0.0.1'
    #: A stand-in base that ends this long [s] after the controllers engage (its duration):
    #: a FAULT from then on is its end (its inputs stop), not a failure of the run.
    base_end_after: float | None = None
    #: ROS namespace of every node and topic of the run ('' none; e.g. 'robot1'): two
    #: vehicles in one domain (--namespace).
    namespace: str = ''


@dataclasses.dataclass
class HardwareResult(RunResult):
    """What :func:`run_hardware` returns (also written to ``OUT/run.json``)."""

    #: Each change of the mixer's safety state: {'t': [s] since the run start, 'state',
    #: 'reasons'}.
    safety_events: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    #: Mean output rate [1/s] of each node over the run, from its /diagnostics counts.
    rates: dict[str, float] = dataclasses.field(default_factory=dict)
    #: Base topics (remapped) -> publisher / subscription counts seen at the start.
    base_topics: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    zero_commands_sent: int = 0

    def summary(self) -> dict[str, Any]:
        return {'mode': 'hardware', **super().summary(),
                'safety_events': self.safety_events, 'rates': self.rates,
                'base_topics': self.base_topics, 'zero_commands_sent': self.zero_commands_sent}


# ----------------------------------------------------------------------------- parameters

def parse_remap(text: str, namespace: str = '') -> tuple[str, str]:
    """Parse a ``--remap`` rule ``'FROM:=TO'`` into absolute topic names.

    ``'FROM:=TO'`` -> (FROM, TO) as absolute topic names; GraphError on bad syntax or a
    side that is not a valid ROS topic name. A relative name is the nodes' one under
    ``namespace`` (rcl resolves both sides of a rule in the node's namespace):
    'imu/data:=base/imu' follows a vehicle's namespace, '/imu/data:=...' matches only a
    node of the root namespace.
    """
    try:
        check_remap(text)   # FROM:=TO, both sides valid ROS topic names
    except ParamsError as err:
        raise GraphError(str(err), EXIT_USAGE) from None
    source, _, target = text.partition(':=')
    return tuple(name if name.startswith('/') else f'{namespace}/{name}'
                 for name in (source.strip(), target.strip()))


def remapped(topic: str, remaps: Iterable[tuple[str, str]]) -> str:
    """Return the name ``topic`` has after the remaps (the first rule that matches, as in ROS)."""
    for source, target in remaps:
        if source == topic:
            return target
    return topic


def load_params_file(path: str | pathlib.Path) -> dict[str, Any]:
    """Return a ROS params YAML ``{node: {ros__parameters: {...}}}``; GraphError if malformed."""
    path = pathlib.Path(path)
    try:
        data = load_yaml_text(path.read_bytes(), f'--params-file {path}')
    except OSError as err:
        raise GraphError(f'--params-file {path}: {err.strerror or err}', EXIT_USAGE) from err
    except ConfigError as err:
        raise GraphError(str(err), EXIT_USAGE) from err
    if not isinstance(data, Mapping):
        raise GraphError(f'--params-file {path}: expected a mapping of node names',
                         EXIT_USAGE)
    for node, section in data.items():
        if not (isinstance(section, Mapping) and isinstance(
                section.get('ros__parameters'), Mapping)):
            raise GraphError(f'--params-file {path}: {node!r} has no ros__parameters '
                             'mapping', EXIT_USAGE)
    return dict(data)


def _matches(pattern: str, node: str) -> bool:
    """Whether a params-file key applies to the node ``node``.

    The key is one such as ``/**``, ``eso``, ``/eso`` or ``/**/eso``. ``node`` is the node's
    full name without the leading slash, such as ``eso`` or ``robot1/eso``.
    """
    pattern = str(pattern).lstrip('/')
    return pattern == node or fnmatch.fnmatchcase(node, pattern.replace('**', '*'))


def node_parameters(node: str, generated: Mapping[str, Any],
                    params_files: Iterable[Mapping[str, Any]],
                    namespace: str = '') -> dict[str, Any]:
    """Return the parameters ``node`` gets from the params files, flattened.

    The parameters ``node`` (under ``namespace``) gets, flattened
    (``'model.wheel_radius'``): the generated params file's, then each extra file's
    matching sections in order (later wins).
    """
    flat = flatten(generated.get(node, {}).get('ros__parameters', {}))
    full_name = f'{namespace.strip("/")}/{node}'.lstrip('/')
    for data in params_files:
        for key, section in data.items():
            if _matches(key, full_name):
                flat.update(flatten(section['ros__parameters']))
    return flat


def hardware_parameters(scenario: ControllerSettings, recorder: Mapping[str, Any] | None = None,
                        joints: tuple[str, str] = DEFAULT_JOINTS,
                        heartbeat: bool = True) -> dict[str, dict]:
    """Return the generated params file of a hardware run.

    The generated params file of a hardware run: the controller nodes of
    :func:`~wip_bringup.params_files.graph_parameters` in real time, no plant (there the
    reference starts when the safety layer engages); with ``heartbeat``, the mixer requires
    /wip/heartbeat (``safety.max_estop_age``).
    """
    data = graph_parameters(scenario, 'realtime', None, joints, recorder=recorder,
                            plant=False)
    if heartbeat:
        mixer = data['torque_mixer']['ros__parameters']
        mixer.setdefault('safety', {})['max_estop_age'] = HEARTBEAT_MAX_AGE
    return data


# ---------------------------------------------------------------------------- the outcome

def hardware_outcome(events: list[dict[str, Any]], ended: str,
                     base_end_after: float | None = None,
                     missing: Iterable[str] = ()) -> tuple[int, str]:
    """Exit code and message of a run that ended normally.

    Both follow from the safety events seen until then (``ended`` says why the run ended):
    the code is 0 if the controllers engaged and no FAULT followed (an e-stop is the user's
    stop), 1 (EXIT_FELL) if one did, 5 (EXIT_NOT_ENGAGED) if they never engaged.
    ``missing`` lists the base topics without a publisher/subscription; the message names
    them when the controllers never engaged.
    """
    engaged = next((i for i, e in enumerate(events) if e['state'] in ENGAGED_STATES), None)
    if engaged is None:
        why = ''
        if events:
            last = events[-1]
            why = f'; the safety layer stayed {last["state"]}: {last["reasons"]}'
        else:
            why = '; no safety state came from the mixer'
        if missing:
            why += '; no inputs from the base: nothing on ' + ', '.join(missing)
        return EXIT_NOT_ENGAGED, f'the controllers never engaged ({ended}){why}'
    start = events[engaged]['t']
    for event in events[engaged + 1:]:
        if event['state'] != 'FAULT':
            continue
        if base_end_after is not None and (
                event['t'] >= start + base_end_after - DIAGNOSTICS_LATENCY):
            break
        return EXIT_FELL, (f'safety FAULT {event["t"] - start:.1f} s after the controllers '
                           f'engaged: {event["reasons"]} (then {ended})')
    return EXIT_OK, ended


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
        self.armed = False

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
                                     run_topics):
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
        # The last resort on the base's command topic (see the module docstring); created
        # now so that it is matched long before it is needed.
        self._float_array = Float64MultiArray
        self.effort_publisher = node.create_publisher(
            Float64MultiArray, self.effort_topic,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        if self.options.heartbeat:
            from std_msgs.msg import Empty
            self._empty = Empty
            self.heartbeat_publisher = node.create_publisher(
                Empty, remapped(in_namespace('/wip/heartbeat', self.namespace), self.remaps),
                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
            node.create_timer(HEARTBEAT_PERIOD, self._heartbeat)

    def _heartbeat(self) -> None:
        if self.armed:
            self.heartbeat_publisher.publish(self._empty())

    def arm(self) -> None:
        """Wait ``arm_delay`` (nodes watched), then start the e-stop heartbeat."""
        if not self.options.heartbeat:
            return
        deadline = time.monotonic() + self.options.arm_delay
        while time.monotonic() < deadline:
            self.check_alive()
            self.probe.spin(min(PROBE_PERIOD, max(0.0, deadline - time.monotonic())))
        self.armed = True
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
        """Publish zero efforts on the base's command topic (see the module docstring)."""
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

    def outcome(self, ended: str) -> tuple[int, str]:
        """Return the run's exit code and message from the safety events seen until now.

        The run's exit code and message from the safety events seen until now (the
        states the stop itself causes come later and are not judged).
        """
        code, message = hardware_outcome(list(self.safety_events), ended,
                                         self.options.base_end_after, self.missing)
        if self.position_error and code != EXIT_OK:
            message += f'; eso: {self.position_error}'
        return code, message

    # -- the run ----------------------------------------------------------------------------
    def run(self) -> HardwareResult:
        result = HardwareResult(EXIT_FAILED, '', self.out, self.bag, self.domain_id)
        cpu_start: dict[str, float | None] = {}
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
            self.shut_down(result)
        result.rates = self.rates()
        result.safety_events = list(self.safety_events)
        result.zero_commands_sent = self.zero_commands_sent
        result.timeline = dict(self.timeline)
        self.finish(result)
        return result


def run_hardware(options: HardwareOptions) -> HardwareResult:
    """Run the controllers in hardware mode; see the module docstring."""
    return HardwareRunner(options).run()


def format_result(result: HardwareResult) -> str:
    word = {EXIT_OK: 'OK', EXIT_FELL: 'FELL OR FAULT', EXIT_NOT_ENGAGED: 'NEVER ENGAGED'}
    lines = [f'{word.get(result.exit_code, "FAILED")}: {result.message}']
    if result.rates:
        lines.append('mean output rates [1/s]: ' + ', '.join(
            f'{n} {r:.1f}' for n, r in sorted(result.rates.items())))
    if result.safety_events:
        lines.append('safety states: ' + ' -> '.join(e['state'] for e in result.safety_events))
    if result.cpu_s and result.wall_time_s:
        lines.append('CPU [% of one core]: ' + ', '.join(
            f'{n} {100 * c / result.wall_time_s:.0f}' for n, c in sorted(
                result.cpu_s.items(), key=lambda item: -item[1])))
    lines.append(f'outputs: {result.out} (run.json, params.yaml, logs/)')
    if result.bag is not None:
        lines.append(f'bag: {result.bag}')
    return '\n'.join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the hardware-mode options of ``scripts/run_graph``."""
    parser.add_argument('--params-file', action='append', default=[], metavar='FILE',
                        dest='params_files',
                        help='hardware mode: extra ROS params file for every node, after the '
                             "scenario's (repeatable; later wins): the base's joint names, "
                             'wheel signs, IMU mounting, datum...')
    parser.add_argument('--remap', action='append', default=[], metavar='FROM:=TO',
                        dest='remaps',
                        help='hardware mode: topic remapping applied to every node '
                             '(repeatable), e.g. /imu/data:=/base/imu')
    parser.add_argument('--arm-delay', type=bounded(float, 0.0, 3600.0), default=2.0,
                        metavar='S',
                        help='hardware mode: seconds after every node is up before the '
                             '/wip/heartbeat starts and the controllers may engage')
    parser.add_argument('--layout', choices=LAYOUTS, default=None,
                        help='controller processes: separate (one per node, as six ros2 '
                        'run), composed (the six nodes in one process, one executor: '
                        'ros2 run wip_control controllers) or, simulation only, single '
                        '(the plant too: ros2 run wip_sim simulation); default: '
                        f'{HardwareOptions.layout}, and single for a recorded lockstep '
                        'simulation (the fastest with every topic; docs/realtime.md)')
    parser.add_argument('--rt-priority', type=bounded(int, 0, 99), default=0, metavar='N',
                        help='run the controller processes with SCHED_FIFO priority N '
                        '(1..99; default 0: the normal policy), set once every node is up; '
                        'needs root or CAP_SYS_NICE')
    parser.add_argument('--cpu-affinity', type=_cpus_argument, default=(), metavar='LIST',
                        help='pin the controller processes to these CPUs, e.g. 1 or 0,1')
    parser.add_argument('--cpu-latency', type=bounded(int, 0, 1_000_000), default=None,
                        metavar='US',
                        help='while the controllers run, ask the kernel (PM QoS, '
                        '/dev/cpu_dma_latency, machine-wide) that idle CPUs wake within US '
                        'microseconds; 0 keeps them polling instead of sleeping: less CPU '
                        'and latency for the controllers, more power (docs/realtime.md); '
                        'needs root')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run every node and topic under this ROS namespace (e.g. '
                        'robot1: /robot1/cmd_vel, frames robot1/odom, robot1/base_link); '
                        'two vehicles in one domain (docs/driving.md)')
    parser.add_argument('--no-heartbeat', action='store_true',
                        help='hardware mode: no /wip/heartbeat (and no arm delay): '
                             'the mixer engages as soon as its inputs are ready')


def _cpus_argument(text: str) -> tuple[int, ...]:
    try:
        return parse_cpus(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/run_graph --mode hardware', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', help='scenario YAML (its controller sections)')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='stop after this long [s of wall time] (default: Ctrl-C)')
    parser.add_argument('--out', default='out/hardware', metavar='DIR',
                        help='run directory (default out/hardware)')
    parser.add_argument('--record', metavar='DIR', help='record into this rosbag2 directory')
    parser.add_argument('--discovery-timeout', type=float, default=60.0, metavar='S')
    parser.add_argument('--quiet', action='store_true')
    add_view_arguments(parser)
    add_arguments(parser)
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    return run_from_args(args)


def run_from_args(args: argparse.Namespace) -> int:
    """Run hardware mode from parsed arguments (also used by ``wip_bringup.graph``)."""
    options = HardwareOptions(**options_from_args(
        args, params_files=list(args.params_files), remaps=list(args.remaps), out=args.out,
        arm_delay=args.arm_delay, heartbeat=not args.no_heartbeat,
        layout=args.layout or HardwareOptions.layout))
    with stop_signals():   # SIGTERM, SIGHUP stop the run as Ctrl-C does
        result = run_hardware(options)
    return print_result(result, format_result)


if __name__ == '__main__':
    sys.exit(main())
