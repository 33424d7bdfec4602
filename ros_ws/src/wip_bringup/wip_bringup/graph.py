"""``scripts/run_graph``: run a scenario through the ROS 2 node graph.

Controllers composed in one process by default, or one process per node with ``--layout
separate``; a recorded lockstep run puts the plant with them (``--layout single``), the
fastest layout that records every topic.

Examples
--------
    scripts/run_graph                                   # paper scenario, lockstep
    scripts/run_graph --duration 10 --out /tmp/g10
    scripts/run_graph --scenario my.yaml --record out/my/bag --out out/my/run
    scripts/run_graph --clock realtime --duration 20
    scripts/run_graph --mode hardware --params-file my_base.yaml   # a real base, no plant
    scripts/run_graph --clock realtime --foxglove         # watch it live in Foxglove

``--mode hardware`` (alias ``--no-plant``) runs the controller nodes alone, in real time,
against a real base's topics: see ``wip_bringup.hardware`` (``--params-file``, ``--remap``).
The rest of this text is about the simulation mode.

What it does
------------
1. Loads and validates the scenario (``--scenario``, default the paper's Section V;
   ``--duration`` overrides its duration), writes it to ``OUT/scenario.yaml`` and the ROS
   parameters of every node to ``OUT/params.yaml``
   (:func:`wip_bringup.params_files.write_params_file`).
2. Starts the nodes, running the very executables ``ros2 run`` would run,
   ``<prefix>/lib/<package>/<executable>`` with the prefix from
   ``ament_index_python.get_package_prefix``, with ``--ros-args --params-file
   OUT/params.yaml`` (and ``-r __node:=<name>`` for a one-node process): the controllers
   reference, eso, trajectory_generator, arc, mpc, torque_mixer (wip_control) in one
   process (``--layout composed``, the default: ``controllers``) or one each
   (``--layout separate``), the plant (wip_sim; ``--layout single``, the default of a
   recorded lockstep run: in the controllers' process) and, with ``--record BAG``, the recorder
   (wip_bag) recording every topic of the graph into the rosbag2 directory BAG, the viewer
   (wip_viewer; with ``--record`` or ``--foxglove``, or ``--viewer``: nav_msgs/Odometry,
   nav_msgs/Path and visualization_msgs/MarkerArray for 3-D viewers, recorded too, see
   ``wip_viewer.viewer_node``) and, with ``--foxglove [PORT]``, the Foxglove bridge
   (``wip_viewer.foxglove_bridge``: every topic live on ws://127.0.0.1:PORT). Each
   process logs to ``OUT/logs/<name>.log`` (ROS log files in ``OUT/logs/ros``).
   The DDS domain is ``$ROS_DOMAIN_ID`` if set, else a free one in 1..101 reserved on this
   host (``wip_bringup.private_domain``: two runs never share one); discovery
   stays on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``).
3. Waits, with a timeout and without fixed sleeps, until a probe node of this process sees
   every node and, on every topic, at least the publishers and subscriptions of the
   design (:data:`PUBLISHERS`, :data:`SUBSCRIBERS`; the recorder adds one subscription
   per recorded topic), and then a /diagnostics message of every node sent after that
   moment (the probe's view of the graph can be complete before two *other* nodes have
   matched each other; their discovery exchange takes milliseconds; the nodes report every
   0.1 s while they start, so the wait is about 0.1 s).
   The controllers report the DDS match counts of their endpoints in /diagnostics
   (``matched subscriptions <topic>``, ``matched publishers <topic>``): both sides of
   every designed pair, and each controller's /clock subscription in lockstep, must
   count each other (:meth:`GraphRunner.unmatched_endpoints`).
4. Starts the plant with its ``/plant/start`` service (std_srvs/Trigger). The plant
   answers ``success: false`` until its own publishers and its wheel-torque subscription
   are matched at the DDS level (stricter than the graph view); the call is retried.
5. Shows progress (simulated time, real-time factor) from the plant's ``/diagnostics``
   (about 1 message/s: no per-tick traffic into this process), polls every process, and
   stops the run when a node dies (which it names, with the end of its log) or the
   simulation stalls (with every node's latest /diagnostics: inputs received and pending).
6. In real time with the plant in its own process, the plant holds its last sensors at
   the scenario's end (``hold_at_end``) and says so on /diagnostics: the other nodes but
   the recorder are stopped first, while their inputs still come (their end is then a
   stop, not a safety fault), then the plant.
   When the plant has exited: waits until the recorder has received what was published
   (lockstep: the counts implied by the plant's tick count; else stable counts), stops
   the other nodes with SIGINT (SIGKILL after a grace period), then the recorder (SIGINT:
   it writes the bag's summary and metadata.yaml), and copies the scenario into the bag
   directory (``BAG/scenario.yaml``, read by ``scripts/report``).

Start-up race: the graph view of step 3 does not prove that every publisher has matched
every subscription of another node (DDS matches pairwise, each side on its own, and the
nodes' reliable topics are volatile: a message sent before the reader has matched is lost
for it). In lockstep one lost message of the first tick stalls the run (about 1 start in
30 on a loaded 2-core machine before the match counts of both sides were checked). Should
it still happen, a stall on the first ticks is detected after
:data:`STARTUP_STALL_TIMEOUT` and the graph is started again (``--startup-retries``,
default 1; the first attempt's logs stay in ``OUT/logs_attempt_1``).

Outputs in OUT: ``params.yaml``, ``scenario.yaml``, ``logs/``, ``plant_stats.json``
(per-tick timings of the plant) and ``run.json`` (exit status, real-time factor, start-up
timeline, exit code, CPU time and last /diagnostics of every node).

Stopping and data safety
------------------------
SIGINT (Ctrl-C), SIGTERM (systemd, docker stop) and SIGHUP (a closed terminal) stop a run
the same way: the nodes are stopped (SIGINT), the recorder receives what was published up
to then and closes the bag, the scenario goes into the bag, ``run.json`` is written and
the result line printed; the exit status is then 130, 143 or 129 (128 + the signal).
Further signals during that stop are ignored. If run_graph itself is killed (SIGKILL),
its nodes get SIGINT from the kernel and the recorder still drains and closes the bag on
its own (``wip_bag.recorder_node``). One run per output folder: ``--out`` (its
``.run_graph.lock``) and the bag directory are locked (fcntl.flock) before anything is
written there; a second run into either is refused at once (exit 2, naming the holder's
pid). A full disk stops the run: what fit is finalised and the run says where it
happened, exit 4.

Exit status (``wip_control.tools.cli``): 0 the scenario ran to its end; 1 the vehicle
fell; 2 bad arguments, scenario or outputs (also: another run holds --out or the bag);
3 a node failed, or a timeout (discovery, start or stall); 4 the disk filled up; 5 (with
--clock realtime) the controllers never engaged; 130/143/129 stopped by
SIGINT/SIGTERM/SIGHUP. Hardware mode: 0 the controllers engaged and the run ended without a
safety fault (at the end of --duration, by Ctrl-C, SIGTERM, SIGHUP or your e-stop); 1 the
vehicle fell or the safety layer went to FAULT after engaging (the message gives the mixer's
reason); 5 the controllers never engaged (no inputs from the base, or the estimate never
settled: the message says which); 2, 3, 4 as above. It uses your ROS network settings
(ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS; ROS's defaults, domain 0
and SUBNET, where unset), while a simulation runs in a private domain on this host only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import random
import shlex
import shutil
import signal
import sys
import tempfile
import time
from typing import Any

import yaml

from wip_control.core.config import ConfigError
from wip_control.tools.cli import add_exit_codes, bounded, exit_with, write_atomic
from wip_sim.core.scenario import load_scenario, Scenario, scenario_to_mapping, with_duration
from wip_sim.settings import WITH_VIEWER
from wip_viewer.viewer_core import LATCHED_TOPICS

from .hardware import add_arguments, run_from_args
# LAYOUTS and viewer_wanted are imported from here by other modules and tests too.
from .launcher import (add_view_arguments, EXIT_DISK_FULL, EXIT_FAILED, EXIT_FELL, EXIT_OK,
                       EXIT_NOT_ENGAGED, EXIT_TIMEOUT, EXIT_USAGE, GRACE_PERIOD, GraphError,
                       in_namespace, INPUT_TOPICS, LAYOUTS, Probe, PROBE_PERIOD, Scheduling,
                       VIEWER_TOPICS, viewer_wanted)  # noqa: F401 - imported from here (the comment above)
from .runner_base import (DiskFull, is_disk_full, options_from_args, print_result,
                          RunnerBase, RunResult, STOP_EXIT_CODES, stop_signal_number,
                          stop_signals)
from .params_files import CONTROLLER_NODES, write_params_file


#: Publishers of each topic in the graph design.
PUBLISHERS = {
    '/joint_states': ('plant',),
    '/imu/data': ('plant',),
    '/gps/fix': ('plant',),
    '/wip/ground_truth': ('plant',),
    '/wip/reference': ('reference',),
    '/wip/state_estimate': ('eso',),
    '/wip/velocity_command': ('trajectory_generator',),
    '/wip/yaw_torque': ('arc',),
    '/wip/drive_torque': ('mpc',),
    '/wip/wheel_torques': ('torque_mixer',),
    '/effort_controller/commands': ('torque_mixer',),
}
#: Subscriptions of each topic in the graph design (without the recorder).
SUBSCRIBERS = {
    '/joint_states': ('eso',),
    '/imu/data': ('eso',),
    '/gps/fix': ('eso',),
    '/wip/ground_truth': (),
    '/wip/reference': ('trajectory_generator',),
    '/wip/state_estimate': ('trajectory_generator', 'arc', 'mpc'),
    '/wip/velocity_command': ('arc', 'mpc'),
    '/wip/yaw_torque': ('mpc', 'torque_mixer'),
    '/wip/drive_torque': ('torque_mixer',),
    '/wip/wheel_torques': ('plant', 'eso'),
    '/effort_controller/commands': (),
}
#: Lockstep: /clock is published by the plant; every controller node's time source
#: subscribes to it, except the reference node's, which its /clock ticker drives
#: (wip_control.nodes.common.ClockTicker). Composed, the nodes share the reference node's
#: time source (wip_control.nodes.common.share_sim_clock): one subscription.
CLOCK_SUBSCRIPTIONS = {'separate': len(CONTROLLER_NODES), 'composed': 1, 'single': 1}
#: Nodes with a /clock subscription of their own in lockstep, per layout.
CLOCK_NODES = {'separate': CONTROLLER_NODES, 'composed': ('reference',),
               'single': ('reference',)}
#: Topics recorded with --record: the graph's, its inputs (with /clock in lockstep; with the
#: viewer's topics, :data:`VIEWER_TOPICS`, when the viewer runs).
RECORDED_TOPICS = tuple(PUBLISHERS) + ('/diagnostics',) + INPUT_TOPICS

#: /diagnostics key prefixes of a node's DDS match counts of one topic, '<KEY> <topic>':
#: subscriptions matched by its publisher, publishers matched by its subscription (see
#: :meth:`GraphRunner.unmatched_endpoints`, ``wip_control.nodes.diagnostics``).
MATCHED_KEY = 'matched subscriptions'
MATCHED_PUBLISHERS_KEY = 'matched publishers'

#: A run whose plant has not passed its second tick this long [s] after its start has
#: stalled at start-up (the first ticks normally take milliseconds; 10 s covers the
#: slowest first MPC solve on a loaded machine many times over).
STARTUP_STALL_TIMEOUT = 10.0
#: [s] for the recorder to receive the last messages: the wait ends early when the counts
#: are complete, or when they have not changed for DRAIN_STALL (the recorder has nothing
#: left); it goes on while they grow (a recorder behind on a loaded machine catches up).
DRAIN_TIMEOUT = 120.0
DRAIN_STALL = 2.5


class StartupStall(GraphError):
    """The run stalled on its first ticks.

    A message published before its subscription was matched is lost (see :meth:`GraphRunner.run`).
    """

    def __init__(self, message: str) -> None:
        super().__init__(message, EXIT_TIMEOUT)


@dataclasses.dataclass
class GraphOptions:
    """Arguments of :func:`run_graph` (see ``scripts/run_graph --help``)."""

    scenario: str | None = None
    clock: str = 'lockstep'
    record: str | None = None
    duration: float | None = None
    out: str = 'out/graph'
    discovery_timeout: float = 60.0  # [s] wall: processes started -> graph complete
    stall_timeout: float = 30.0  # [s] wall without simulated-time progress
    startup_retries: int = 1  # new attempts after a stall on the first ticks
    quiet: bool = False
    layout: str = 'composed'  # see LAYOUTS
    scheduling: Scheduling = Scheduling()  # of the controller processes
    #: The viewer node (Odometry, Path, markers; recorded). None: when someone will look,
    #: i.e. with --record or --foxglove (it costs the lockstep run about a quarter of its
    #: speed on 2 cores: docs/viewing.md).
    viewer: bool | None = None
    foxglove_port: int | None = None  # serve the topics to Foxglove on this port
    foxglove_host: str = '127.0.0.1'
    #: ROS namespace of every node and topic of the run ('' none; e.g. 'robot1'): two
    #: vehicles in one domain (--namespace).
    namespace: str = ''


@dataclasses.dataclass
class GraphResult(RunResult):
    """What :func:`run_graph` returns (also written to ``OUT/run.json``).

    ``cpu_s`` of the plant from its own stats, ``timeline`` with the plant's refusals to start.
    """

    scenario: Scenario | None = None
    plant_stats: dict | None = None
    #: topic -> 'received/expected' when the recorder lacked messages at the end.
    recorder_shortfall: dict[str, str] = dataclasses.field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        stats = self.plant_stats or {}
        return {**super().summary(),
                'scenario': self.scenario.name if self.scenario else None,
                'sim_time_s': stats.get('sim_time_s'),
                'real_time_factor': stats.get('real_time_factor'),
                'recorder_shortfall': self.recorder_shortfall,
                'plant_stats': self.plant_stats}


def expected_endpoints(clock_mode: str, recording: bool, layout: str = 'separate',
                       viewer: bool = False) -> dict[str, tuple[int, int]]:
    """Minimum (publishers, subscriptions) of each topic before the plant may start."""
    extra = 1 if recording else 0
    expected = {topic: (len(PUBLISHERS[topic]), len(SUBSCRIBERS[topic]) + extra)
                for topic in PUBLISHERS}
    if viewer:
        # Its outputs must reach the recorder from the first message (the transient-local
        # ones reach a late reader too, and exist only with viewer.robot_model); its own
        # inputs are best effort and may miss the first ticks (nothing waits for it).
        expected.update({topic: (1, extra) for topic in VIEWER_TOPICS
                         if topic not in LATCHED_TOPICS})
    if clock_mode == 'lockstep':
        # The recorder runs on sim time too (its time source) and records /clock.
        expected['/clock'] = (1, CLOCK_SUBSCRIPTIONS[layout] + 2 * extra)
    return expected


def missing_endpoints(probe: Probe, expected: dict[str, tuple[int, int]],
                      nodes: list[str]) -> list[str]:
    """Return what the graph still lacks (empty when complete)."""
    missing = []
    present = probe.node_names()
    absent = [n for n in nodes if n not in present]
    if absent:
        missing.append('nodes ' + ', '.join(absent))
    for topic, (publishers, subscribers) in expected.items():
        have_pub, have_sub = probe.count(topic)
        if have_pub < publishers or have_sub < subscribers:
            missing.append(f'{topic} ({have_pub}/{publishers} publishers, '
                           f'{have_sub}/{subscribers} subscriptions)')
    return missing


class GraphRunner(RunnerBase):
    """One run: start, watch and stop the processes; see the module docstring."""

    EXTRA_PROCESSES = ('plant',)
    LAYOUTS = LAYOUTS
    read_settings = staticmethod(load_scenario)
    settings_to_mapping = staticmethod(scenario_to_mapping)
    UP_EVENT = 'graph complete'
    NOT_UP = 'the graph was not complete after {timeout:g} s'

    def __init__(self, options: GraphOptions) -> None:
        super().__init__(options)
        self.start_refusals: list[str] = []  # why /plant/start said no, with times
        #: The process that holds the plant (and, single, the controllers): the run ends
        #: with it.
        self.plant_process = 'simulation' if options.layout == 'single' else 'plant'
        #: Nodes stopped at the end of a real-time run before the plant (stop_held_plant).
        self.stopped_at_end: list[str] = []
        self.cpu_at_end: dict[str, float | None] = {}
        #: The run ends before the plant did (a stop signal, a failure): the recorder is
        #: drained once the nodes have stopped (nodes_stopped).
        self.drain_at_stop = False
        #: topic -> 'received/expected' of what the recorder lacked at the end (lockstep).
        self.recorder_shortfall: dict[str, str] = {}
        self.last_sim_time: float | None = None  # [s] the plant's latest progress report

    def stop_all(self) -> None:
        """Stop every process, in the order a run cut short needs.

        A run cut short in lockstep stops the controllers (and the viewer, the bridge)
        first: the plant then waits for torques and publishes nothing more, and stays up
        while the recorder takes what it published (a publisher that exits takes with it
        the samples a lagging reader has not received yet: about 90 ticks were lost so on
        a loaded machine); then the plant, then the recorder (the base class).
        """
        if (self.drain_at_stop and self.options.clock == 'lockstep'
                and 'recorder' in self.processes and self.plant_process == 'plant'
                and self.probe is not None):
            first = [p for n, p in self.processes.items() if n not in ('recorder', 'plant')]
            for process in first:
                process.interrupt()
            deadline = time.monotonic() + GRACE_PERIOD
            for process in first:
                process.stop(deadline - time.monotonic())
            self.drain_recorder(quiet=True)
            self.timeline['controllers stopped, recorder drained'] = (
                time.monotonic() - self.t0)
        super().stop_all()

    def stop_signal(self, name: str) -> int:
        """SIGTERM for the plant's process: rclpy's handler then only shuts its context down.

        At a SIGINT it also raises a KeyboardInterrupt, which can land in the plant's write of
        plant_stats.json after its spin loop ended, leaving the file empty (seen after a stop
        mid-run).
        """
        return signal.SIGTERM if name == self.plant_process else super().stop_signal(name)

    def nodes_stopped(self) -> None:
        if self.drain_at_stop and self.probe is not None:
            self.drain_recorder()
            self.timeline['recorder drained'] = time.monotonic() - self.t0

    def extra_processes(self) -> list[str]:
        return [self.plant_process]

    def view_processes(self) -> list[str]:
        """Leave the viewer out in the single layout: the simulation process holds it.

        (``--with-viewer``.) Its 200 Hz inputs then come from the intra-process bus
        instead of a process of its own taking them from DDS, which held a recorded run's
        second core (docs/decisions/recording-speed.md).
        """
        processes = super().view_processes()
        if self.options.layout == 'single':
            processes = [name for name in processes if name != 'viewer']
        return processes

    def process_environment(self, name: str, env: dict[str, str]) -> dict[str, str]:
        """Fast DDS's asynchronous publication in the single layout's simulation process.

        The lockstep loop closes inside that process, so its DDS writers feed observers only
        (the recorder, a user's tools); a sample handed to Fast DDS's own thread is sent on
        the other core while the loop goes on. Not where the loop itself crosses processes
        (composed, separate): the extra hand-off slows it. A setting of the user's stays.
        See docs/decisions/recording-speed.md.
        """
        if name == 'simulation' and PUBLICATION_MODE_VARIABLE not in env:
            return {**env, PUBLICATION_MODE_VARIABLE: 'ASYNCHRONOUS'}
        return env

    def program_arguments(self, name: str) -> list[str]:
        if name == 'simulation' and self.options.viewer:
            return [WITH_VIEWER]
        return []

    # -- set-up ---------------------------------------------------------------------------
    def prepare(self) -> pathlib.Path:
        """Scenario, run directory, params file; returns the params file."""
        options = self.options
        if options.clock not in ('lockstep', 'realtime'):
            raise GraphError(f'--clock: {options.clock!r} is not lockstep or realtime',
                             EXIT_USAGE)
        self.check_namespace()
        if (self.namespace and options.clock == 'lockstep'
                and os.environ.get('ROS_DOMAIN_ID', '').strip()):
            # /clock is global: a second lockstep simulation in this domain would step
            # this one's nodes (docs/driving.md, two robots in one domain).
            self.say('warning: lockstep in the shared ROS_DOMAIN_ID: /clock is global, so '
                     'no other simulation may run in this domain (two vehicles in one '
                     'domain: --clock realtime)')
        self.check_layout_and_scheduling()
        scenario = self.load_scenario(options.scenario)
        if options.duration is not None:
            try:   # the scenario's checks of a duration (range, control ticks, memory)
                scenario = with_duration(scenario, options.duration)
            except ConfigError as err:
                raise GraphError(f'--duration: {str(err).removeprefix("duration: ")}',
                                 EXIT_USAGE) from None
        self.scenario = scenario
        # Every output is checked before anything is written or started.
        scenario_path = self.prepare_outputs(stale=('plant_stats.json', 'run.json'),
                                             extra_logs=('logs_attempt_*',))
        recorder = self.recorder_parameters(
            (['/clock'] if options.clock == 'lockstep' else []) + list(RECORDED_TOPICS),
            discovery_period=0.2)
        plant_extra = {
            'autostart': False,
            'start.expected_sensor_subscribers': 1 + (recorder is not None),
            'start.expected_ground_truth_subscribers': int(recorder is not None),
            'start.expected_clock_subscribers': (
                CLOCK_SUBSCRIPTIONS[options.layout] + 2 * (recorder is not None)
                if options.clock == 'lockstep' else 0),
            'stats_file': str(self.out / 'plant_stats.json'),
            # Real time, the plant in its own process: the controllers are stopped at the
            # scenario's end while the plant still feeds them (see watch()).
            'hold_at_end': options.clock == 'realtime' and options.layout != 'single',
        }
        # The robot model hangs from base_link: with the viewer, the ESO's /odom and
        # odom -> base_link run in lockstep too (otherwise off there), so that a view or a
        # bag holds the whole chain map -> odom -> base_link -> wheels.
        params_file = write_params_file(scenario, self.out / 'params.yaml', options.clock,
                                        scenario_path, plant_extra=plant_extra,
                                        recorder=recorder, eso_extra=(
                                            {'odometry_output': 'always'} if options.viewer
                                            else None))
        # The vehicle drawn with the plant's true dimensions, the estimate's position
        # covariance from the GPS noise.
        view = self.view_parameters(scenario.plant.parameters, scenario.sensors.gps_noise_std,
                                    scenario.sensors.encoders_relative_to_body)
        if view:  # The whole file again, atomically, like every output of a run.
            write_atomic(params_file, params_file.read_text(encoding='utf-8')
                         + yaml.safe_dump(view, sort_keys=False))
        return params_file

    # -- watching ---------------------------------------------------------------------------
    def missing_from_view(self, nodes: list[str]) -> list[str]:
        expected = expected_endpoints(self.options.clock, self.bag is not None,
                                      self.options.layout, self.options.viewer)
        expected = {in_namespace(topic, self.namespace): counts
                    for topic, counts in expected.items()}
        return missing_endpoints(self.probe, expected, nodes)

    def unmatched_endpoints(self) -> list[str]:
        """Designed pairs whose DDS match is not yet seen by both sides.

        A pair counts as matched only when BOTH sides have seen the match, as the match
        counts in the controllers' /diagnostics report it (``matched subscriptions <topic>``
        of a publisher, ``matched publishers <topic>`` of a subscription; the plant checks
        its own endpoints before it starts). DDS matches each side on its own: a reliable
        volatile reader that has not matched the writer yet loses what it sends, and in
        lockstep one lost message of the first tick stalls the run. In lockstep every
        controller must also have matched the plant's /clock.
        """
        extra = 1 if self.bag is not None else 0
        # The nodes report their topics' full names (under the run's namespace).
        ns = self.namespace
        checks = []   # (node, key, wanted)
        for topic, publishers in PUBLISHERS.items():
            checks += [(name, f'{MATCHED_KEY} {in_namespace(topic, ns)}',
                        len(SUBSCRIBERS[topic]) + extra) for name in publishers]
        for topic, subscribers in SUBSCRIBERS.items():
            checks += [(name, f'{MATCHED_PUBLISHERS_KEY} {in_namespace(topic, ns)}',
                        len(PUBLISHERS[topic])) for name in subscribers]
        if self.options.clock == 'lockstep':
            checks += [(name, f'{MATCHED_PUBLISHERS_KEY} /clock', 1)
                       for name in CLOCK_NODES[self.options.layout]]
        missing = []
        for name, key, wanted in checks:
            if name == 'plant':
                continue  # Checked by the plant itself before it starts.
            found = self.probe.status_values(f'/{name}:', prefix=True)
            value = None if found is None else found[1].get(key)
            if value is not None and int(value) < wanted:
                missing.append(f'{name}: {key} {value}/{wanted}')
        return missing

    def start_plant(self) -> None:
        deadline = time.monotonic() + self.options.discovery_timeout
        last = f'the service {self.namespace}/plant/start did not answer'
        while time.monotonic() < deadline:
            self.check_alive()
            response = self.probe.call_start(timeout=2.0)
            if response is not None:
                if response.success:
                    self.timeline['plant started'] = time.monotonic() - self.t0
                    return
                last = response.message
                self.start_refusals.append(f'{time.monotonic() - self.t0:.3f}: {last}')
            self.probe.spin(0.1)
        raise GraphError(f'the plant did not start: {last}', EXIT_TIMEOUT)

    def cpu_snapshot(self) -> dict[str, float | None]:
        """CPU time [s] of each process; of one stopped at the end, as it ended."""
        snapshot = super().cpu_snapshot()
        for name, seconds in self.cpu_at_end.items():
            if snapshot.get(name) is None:
                snapshot[name] = seconds
        return snapshot

    def stop_held_plant(self, plant) -> int | None:
        """Stop every node, then the plant that holds its sensors at the scenario's end.

        The plant's ``hold_at_end``: every node but the recorder is stopped first, while
        its inputs still come, so that its end is a stop and not the loss of its inputs
        (which the safety layer would judge a fault); then the plant. Its exit code.
        """
        self.stopped_at_end = [n for n in self.processes
                               if n not in (self.plant_process, 'recorder')]
        # Their CPU time as they end (/proc forgets an exited process).
        self.cpu_at_end = {n: self.processes[n].cpu_seconds() for n in self.stopped_at_end}
        for name in self.stopped_at_end:
            self.processes[name].interrupt()
        deadline = time.monotonic() + GRACE_PERIOD
        for name in self.stopped_at_end:
            self.processes[name].stop(deadline - time.monotonic())
        return plant.stop(GRACE_PERIOD)

    def watch(self) -> int:
        """Until the plant exits: progress, node health, stall detection; its exit code."""
        plant = self.processes[self.plant_process]
        duration = self.scenario.duration
        started = time.monotonic()
        last_sim, last_progress = -1.0, started
        first_ticks = 2.5 * self.scenario.control_period
        while True:
            self.probe.spin(PROBE_PERIOD)
            code = plant.poll()
            if code is not None:
                return code
            self.check_alive()
            found = self.probe.status_values(': plant')
            if found is None:
                continue
            status, values = found
            if values.get('ended') == 'yes' and plant.poll() is None:
                return self.stop_held_plant(plant)
            try:
                sim = float(values.get('sim time [s]', 'nan'))
            except ValueError:
                sim = float('nan')
            if sim == sim:
                self.last_sim_time = sim
            self.check_recorder_space()
            now = time.monotonic()
            if sim > last_sim:
                last_sim, last_progress = sim, now
                self.progress(f'sim {sim:7.2f} / {duration:g} s   '
                              f'{values.get("real-time factor", "n/a")}x real time')
            elif last_sim < first_ticks and now - started > STARTUP_STALL_TIMEOUT:
                if self.options.clock == 'realtime':
                    # The plant holds the vehicle until the controllers engage
                    # (hold_until_engaged): starting again would not help; say why.
                    raise GraphError(
                        f'the controllers did not engage in {now - started:.0f} s: '
                        f'{status.message}\n{self.describe_nodes()}', EXIT_NOT_ENGAGED)
                raise StartupStall(
                    f'no progress for {now - started:.0f} s at t = {last_sim:g} s, the first '
                    f'ticks: {status.message}\n{self.describe_nodes()}')
            elif now - last_progress > self.options.stall_timeout:
                raise GraphError(
                    f'no progress for {self.options.stall_timeout:g} s at t = {last_sim:g} s: '
                    f'{status.message}\n{self.describe_nodes()}', EXIT_TIMEOUT)

    def plant_stats(self) -> dict | None:
        """``OUT/plant_stats.json``, or None when absent or unreadable.

        The plant could not write it whole: a full disk.
        """
        try:
            stats = json.loads((self.out / 'plant_stats.json').read_text(encoding='utf-8'))
        except (OSError, ValueError):
            return None
        return stats if isinstance(stats, dict) else None

    def where_stopped(self) -> str:
        """' at t = ... s' of simulated time, when the plant has reported progress."""
        t = (self.plant_stats() or {}).get('sim_time_s')
        t = t if isinstance(t, (int, float)) else self.last_sim_time
        return f' at t = {t:.3f} s' if t is not None else ''

    def check_recorder_space(self) -> None:
        """DiskFull if the recorder reports that the disk filled up.

        The run stops there (going on would record nothing more).
        """
        found = self.probe.status_values(': recorder') if self.bag is not None else None
        if found is None:
            return
        message = found[0].message
        if message.startswith('disk full'):   # the recorder finished the bag in time
            raise DiskFull(f'disk full{self.where_stopped()}: the recorder stopped and '
                           f'finished {self.bag} with what fit; the run was stopped there')
        if message.startswith('bag write failed') and ('No space left' in message
                                                       or 'quota' in message):
            raise DiskFull(f'disk full{self.where_stopped()}: the recorder could not write '
                           f'{self.bag} any more (scripts/bag_repair {self.bag} recovers '
                           'every complete chunk); the run was stopped there')

    def recorder_disk_full(self) -> bool:
        """Whether the recorder's log says a write failed for want of space."""
        recorder = self.processes.get('recorder')
        if recorder is None:
            return False
        tail = recorder.log_tail(400)
        return 'No space left on device' in tail or 'Disk quota exceeded' in tail

    def describe_nodes(self) -> str:
        """Latest /diagnostics message of every node (to explain a stall)."""
        lines = []
        for name, status in sorted(self.probe.diagnostics.items()):
            lines.append(f'  {name}: {status.message}')
            for kv in status.values:
                if kv.key.startswith(('received', 'dropped', 'pending', 'age')):
                    lines.append(f'      {kv.key}: {kv.value}')
        return '\n'.join(lines)

    def expected_recorded(self) -> dict[str, int]:
        """Messages a lockstep run published per topic, from the plant's tick count.

        Every control tick t_0 .. t_{k-1} produces one message of each topic (the MPC one
        every ``drive_decimation`` ticks, GPS every control_rate / gps_rate ticks), and the
        final ground truth at t_k has no tick after it.
        """
        if self.options.clock != 'lockstep':
            return {}
        ticks = (self.plant_stats() or {}).get('ticks')
        if not isinstance(ticks, int):
            return {}
        scenario = self.scenario
        gps_every = max(1, round(scenario.rates.control_rate / scenario.sensors.gps_rate))
        expected = {topic: ticks for topic in PUBLISHERS}
        expected['/clock'] = ticks
        expected['/wip/ground_truth'] = ticks + 1
        expected['/gps/fix'] = -(-ticks // gps_every)
        expected['/wip/drive_torque'] = -(-ticks // scenario.drive_decimation)
        return expected

    def drain_recorder(self, quiet: bool = False) -> None:
        """Wait until the recorder received everything the graph published.

        Lockstep: until its /diagnostics counts reach :meth:`expected_recorded`; otherwise
        (or if they never do) until the counts of the topics that end with the plant
        stopped changing over two of its /diagnostics messages.
        """
        if 'recorder' not in self.processes:
            return
        expected = self.expected_recorded()
        # Topics that stop when the plant does (in real time the controllers run on timers
        # too: the reference, the MPC, the mixer's watchdog).
        watched = set(expected) or {t for t, p in PUBLISHERS.items() if p == ('plant',)}
        deadline = time.monotonic() + DRAIN_TIMEOUT
        previous = None
        stable_since = None
        while time.monotonic() < deadline:
            if self.processes['recorder'].poll() is not None:
                return
            self.probe.spin(0.1)
            found = self.probe.status_values(': recorder')
            if found is None:
                continue
            _, values = found
            counts = {k[len('received '):]: int(v) for k, v in values.items()
                      if k.startswith('received /') and k[len('received '):] in watched}
            if expected and all(counts.get(t, 0) >= n for t, n in expected.items()):
                return
            if counts != previous:
                previous, stable_since = counts, time.monotonic()
            elif time.monotonic() - stable_since >= DRAIN_STALL:
                if expected and not quiet:
                    self.recorder_shortfall = {
                        t: f'{counts.get(t, 0)}/{n}' for t, n in expected.items()
                        if counts.get(t, 0) < n}
                    self.say(f'warning: the recorder missed messages: '
                             f'{self.recorder_shortfall}')
                return
        self.say(f'warning: the recorder was still receiving after {DRAIN_TIMEOUT:g} s')

    # -- the run ----------------------------------------------------------------------------
    def start_graph(self, params_file: pathlib.Path) -> None:
        """Start the processes, wait for the graph, start the plant."""
        if self.probe is None:
            self.probe = Probe(self.domain_id, self.namespace)
        self.launch(params_file)
        self.start_plant()

    def retry(self, attempt: int) -> None:
        """Stop the stalled attempt and clean up for a new one.

        A new domain when it is ours, so that nothing of the old processes can be discovered again.
        """
        self.stop_all()
        self.probe.close()
        self.probe = None
        logs = self.out / 'logs'
        logs.rename(self.out / f'logs_attempt_{attempt}')
        (logs / 'ros').mkdir(parents=True)
        if self.bag is not None and self.bag.exists():
            # Ours (prepare() checked it was absent or empty): emptied, not removed, so
            # that the lock on the directory stays this run's.
            for entry in self.bag.iterdir():
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry)
                else:
                    entry.unlink()
        (self.out / 'plant_stats.json').unlink(missing_ok=True)
        self.processes = {}
        self.timeline = {f'attempt {attempt} stalled': time.monotonic() - self.t0}
        self.start_refusals = []
        if not os.environ.get('ROS_DOMAIN_ID', '').strip():
            self.domain_id = random.choice([d for d in range(1, 102) if d != self.domain_id])

    def run(self) -> GraphResult:
        result = GraphResult(EXIT_FAILED, '', self.out, self.bag, self.domain_id)
        started = time.monotonic()
        stopped_by = ''
        try:
            params_file = self.prepare()
            result.scenario = self.scenario
            self.say(f'scenario {self.scenario.name!r} ({self.scenario.duration:g} s), clock '
                     f'{self.options.clock}, ROS_DOMAIN_ID={self.domain_id}, outputs in '
                     f'{self.out}')
            for attempt in range(self.options.startup_retries + 1):
                try:
                    self.start_graph(params_file)
                    result.startup_s = time.monotonic() - started
                    self.say(f'graph connected in {result.startup_s:.1f} s; plant started')
                    self.say_foxglove_url()
                    run_start = time.monotonic()
                    cpu_start = self.cpu_snapshot()
                    code = self.watch()
                    break
                except StartupStall as err:
                    if attempt == self.options.startup_retries:
                        raise
                    self.say(f'warning: {err}\nrun_graph: a message of the first tick was '
                             'lost (published before its subscription matched): '
                             f'starting the graph again (attempt {attempt + 2})')
                    self.retry(attempt + 1)
            result.wall_time_s = time.monotonic() - run_start
            result.cpu_s.update(self.cpu_since(cpu_start))
            if not self.options.quiet and self._interactive:
                sys.stderr.write('\n')
            self.timeline['plant ended'] = time.monotonic() - self.t0
            self.check_alive(exempt=(self.plant_process, *self.stopped_at_end))
            self.drain_recorder()
            self.timeline['recorder drained'] = time.monotonic() - self.t0
            if code == 0:
                result.exit_code, result.message = EXIT_OK, 'the scenario ran to its end'
            elif code == EXIT_FELL:     # the plant's fall: the table's 1, as the run's
                result.exit_code, result.message = EXIT_FELL, 'the vehicle fell'
            else:
                plant = self.processes[self.plant_process]
                raise GraphError(f"node 'plant' (pid {plant.pid}) exited with code {code}; "
                                 f'last lines of {plant.log_path}:\n{plant.log_tail()}')
        except GraphError as err:
            self.drain_at_stop = True
            result.exit_code, result.message = err.exit_code, str(err)
        except KeyboardInterrupt as err:
            self.drain_at_stop = True
            number = stop_signal_number(err)
            result.exit_code = 128 + number
            # The time is the plant's own once it has stopped (below).
            result.message = stopped_by = f'stopped by {signal.Signals(number).name}'
        except DiskFull as err:   # the recorder drops everything from then on: no drain
            result.exit_code, result.message = EXIT_DISK_FULL, str(err)
        except OSError as err:
            if not (self.prepared and is_disk_full(err)):
                raise
            self.drain_at_stop = True
            result.exit_code = EXIT_DISK_FULL
            result.message = (f'disk full{self.where_stopped()}: '
                              f'{err.filename or "an output"} not written ({err.strerror})')
        finally:
            self.shut_down(result)
        if stopped_by:
            result.message = stopped_by + self.where_stopped()
        if result.exit_code != EXIT_DISK_FULL and self.recorder_disk_full():
            result.exit_code = EXIT_DISK_FULL
            result.message = (f'disk full: the recorder stopped writing '
                              f'{self.bag}{self.where_stopped()}; the bag holds what fit. '
                              + result.message)
        result.timeline = dict(self.timeline, start_refusals=self.start_refusals)
        stats_path = self.out / 'plant_stats.json'
        result.plant_stats = self.plant_stats()
        if self.recorder_shortfall:
            # The run itself is sound; the bag is not whole, and the user must hear it even
            # with --quiet (received/expected per topic, as bag_info would count them).
            result.recorder_shortfall = self.recorder_shortfall
            result.message += (f'; but the bag lacks messages (received/expected): '
                               f'{self.recorder_shortfall}')
        if result.plant_stats is None and stats_path.is_file():
            # Cut short by a full disk (the plant writes it in place): no empty side file.
            self.say(f'warning: {stats_path} was not written whole (full disk?): removed')
            stats_path.unlink(missing_ok=True)
        if result.plant_stats is not None:
            # The plant's process CPU from its stats (process_time from the plant's start:
            # the process has ended, so it cannot be read now). Single, that process holds
            # the controllers too.
            if result.plant_stats.get('cpu_s') is not None:
                result.cpu_s[self.plant_process] = result.plant_stats['cpu_s']
        self.finish(result)
        return result


def run_graph(options: GraphOptions) -> GraphResult:
    """Run one scenario through the graph; see the module docstring."""
    return GraphRunner(options).run()


def run_graph_benchmark(scenario_path: str | None, layout: str = GraphOptions.layout,
                        record: bool = False) -> dict[str, Any]:
    """Run the whole scenario once through the lockstep graph, for ``scripts/bench``.

    In a temporary directory, recorded (every topic, as ``--record``) or not; returns its
    real-time factor, per-tick loop time and CPU, the final true state, and with
    ``record`` the bag's message count and check (``bag_info``).

    Returns ``{'failed': message, 'exit_code': code}`` if the run did not complete.
    """
    with tempfile.TemporaryDirectory(prefix='wip_bench_graph_') as out:
        bag = os.path.join(out, 'bag') if record else None
        result = run_graph(GraphOptions(scenario=scenario_path, clock='lockstep',
                                        out=os.path.join(out, 'run'), quiet=True,
                                        layout=layout, record=bag))
        checked = _bag_check(bag) if bag and result.exit_code == EXIT_OK else {}
    stats = result.plant_stats or {}
    if result.exit_code != EXIT_OK or not stats.get('real_time_factor'):
        return {'failed': result.message, 'exit_code': result.exit_code}
    ticks = stats['ticks']
    loop = stats.get('clock_to_torques_s') or {}
    return {'layout': layout, 'recorded': record, **checked,
            'final_state': stats.get('final_state'),
            'real_time_factor': stats['real_time_factor'], 'sim_time_s': stats['sim_time_s'],
            'wall_time_s': stats['wall_time_s'], 'ticks': ticks,
            'startup_s': result.startup_s,
            'clock_to_torques_us': {'mean': loop.get('mean_us'), 'p99': loop.get('p99_us')},
            'cpu_per_tick_us': {name: 1e6 * cpu / ticks for name, cpu in result.cpu_s.items()}}


def _bag_check(bag: str) -> dict[str, Any]:
    """Return the recorded bag's message count and ``bag_info``'s problems with it."""
    from wip_bag.bag_info import bag_information  # noqa: PLC0415 (only when recording)
    info = bag_information(bag)
    return {'bag_messages': info['message_count'], 'bag_problems': info['problems']}


def outcome_word(exit_code: int) -> str:
    """OK, STOPPED (by a signal: what ran is saved) or FAILED."""
    if exit_code == EXIT_OK:
        return 'OK'
    return 'STOPPED' if exit_code in STOP_EXIT_CODES else 'FAILED'


def format_result(result: GraphResult) -> str:
    """Human-readable summary of a run: outcome, timings, where the outputs are."""
    lines = [f'{outcome_word(result.exit_code)}: {result.message}']
    stats = result.plant_stats or {}
    if stats.get('real_time_factor'):
        lines.append(f'simulated {stats["sim_time_s"]:.2f} s in {stats["wall_time_s"]:.2f} s '
                     f'wall: {stats["real_time_factor"]:.2f}x real time '
                     f'({stats["ticks"]} ticks, start-up {result.startup_s or 0:.1f} s)')

        def fmt(key):
            entry = stats.get(key) or {}
            if not entry.get('count'):
                return 'n/a'
            return f'mean {entry["mean_us"]:.0f} us, p99 {entry["p99_us"]:.0f} us'
        lines.append(f'per tick: /clock published -> wheel torques received '
                     f'{fmt("clock_to_torques_s")} (plant publishing {fmt("publish_s")}, '
                     f'then the controllers {fmt("wait_for_torques_s")}); plant step '
                     f'{fmt("step_s")}')
    ticks = stats.get('ticks')
    if result.cpu_s and ticks:
        per_tick = {n: 1e6 * c / ticks for n, c in result.cpu_s.items()}
        lines.append(f'CPU per tick: {sum(per_tick.values()):.0f} us in all ('
                     + ', '.join(f'{n} {v:.0f}' for n, v in sorted(
                         per_tick.items(), key=lambda item: -item[1])) + ')')
    failed = {n: c for n, c in result.node_exit_codes.items()
              if c not in (0, None, EXIT_FELL)}
    if failed and result.exit_code != 0:
        lines.append('node exit codes: ' + ', '.join(f'{n}={c}' for n, c in failed.items()))
    lines.append(f'outputs: {result.out} (run.json, params.yaml, scenario.yaml, logs/)')
    if result.bag is not None:
        lines.append(f'bag: {result.bag}   report: scripts/report '
                     f'{shlex.quote(str(result.bag))} --out DIR')
    return '\n'.join(lines)


#: The layout of a recorded lockstep run: the plant and the controllers in one process,
#: whose own messages take the intra-process bus while DDS carries the recorder's copies;
#: the bag holds the same topics and counts as the composed layout's
#: (docs/decisions/recording-speed.md has the measurements).
RECORDED_LOCKSTEP_LAYOUT = 'single'
#: rmw_fastrtps's publication mode of every writer of a process (SYNCHRONOUS by default).
PUBLICATION_MODE_VARIABLE = 'RMW_FASTRTPS_PUBLICATION_MODE'


def default_layout(clock: str, record: str | None) -> str:
    """Return the layout when ``--layout`` is not given.

    A recorded lockstep run takes the fastest layout that records every topic; any other
    run the composed one, as on a robot.
    """
    return RECORDED_LOCKSTEP_LAYOUT if clock == 'lockstep' and record else GraphOptions.layout


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/run_graph', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--mode', choices=('simulation', 'hardware'), default='simulation',
                        help="simulation: the plant and the controllers; hardware: the "
                        "controllers alone against a real base's topics (real time)")
    parser.add_argument('--no-plant', action='store_true', help='same as --mode hardware')
    parser.add_argument('--scenario', help='scenario YAML file (default: paper Section V)')
    parser.add_argument('--clock', choices=('lockstep', 'realtime'), default=None,
                        help='lockstep (deterministic, faster than real time; the default) or '
                        'realtime; hardware mode is always realtime')
    parser.add_argument('--record', metavar='DIR',
                        help='record every graph topic into this rosbag2 directory')
    parser.add_argument('--duration', type=bounded(float, 0.0, 1e6, True), metavar='S',
                        help='override the scenario duration [s]; hardware mode: stop after '
                        'this long [s of wall time] (default: at Ctrl-C)')
    parser.add_argument('--out', default=None, metavar='DIR',
                        help='run directory: params, logs, timings (default out/graph, '
                        'hardware mode out/hardware)')
    parser.add_argument('--discovery-timeout', type=bounded(float, 0.0, 3600.0, True),
                        default=60.0, metavar='S',
                        help='wall time allowed for the graph to connect [s]')
    parser.add_argument('--stall-timeout', type=bounded(float, 0.0, 3600.0, True),
                        default=30.0, metavar='S',
                        help='wall time without simulated progress before giving up [s]')
    parser.add_argument('--startup-retries', type=bounded(int, 0, 10), default=1,
                        metavar='N',
                        help='start the graph again after a stall on the first ticks '
                        '(a start-up message lost to DDS discovery), at most N times')
    parser.add_argument('--quiet', action='store_true', help='no progress output')
    add_view_arguments(parser)
    add_arguments(parser)
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    if args.no_plant or args.mode == 'hardware':
        if args.clock == 'lockstep':
            parser.error('--mode hardware runs in real time: --clock lockstep is not possible')
        args.out = args.out or 'out/hardware'
        return run_from_args(args)
    if args.params_files or args.remaps:
        parser.error('--params-file and --remap are options of --mode hardware')
    options = GraphOptions(**options_from_args(
        args, clock=args.clock or 'lockstep', out=args.out or 'out/graph',
        stall_timeout=args.stall_timeout, startup_retries=args.startup_retries,
        layout=args.layout or default_layout(args.clock or 'lockstep', args.record)))
    with stop_signals():   # SIGTERM, SIGHUP stop the run as Ctrl-C does
        result = run_graph(options)
    return print_result(result, format_result)


if __name__ == '__main__':
    exit_with(main, 'run_graph')
