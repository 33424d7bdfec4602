"""What the two runners of ``scripts/run_graph`` share.

:class:`RunnerBase`, the life of one run (output directory, node processes, probe, waiting for the
nodes, watching them, stopping them, ``OUT/run.json``); the part of its result both write is
:class:`wip_bringup.run_result.RunResult`.

The simulation runner (:class:`wip_bringup.graph_runner.GraphRunner`: the plant, a /clock in
lockstep, the ``/plant/start`` service) and the hardware runner
(:class:`wip_bringup.hardware_runner.HardwareRunner`: the e-stop heartbeat, the base's topics, zero
commands at the stop) subclass it and add only their own behaviour through the hooks named
below (``EXTRA_PROCESSES``, :meth:`RunnerBase.missing_from_view`,
:meth:`RunnerBase.unmatched_endpoints`, :meth:`RunnerBase.node_died`,
:meth:`RunnerBase.nodes_stopped`, :meth:`RunnerBase.extra_arguments`).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import signal
import sys
import threading
import time
from typing import Any, Iterable

import yaml

from wip_runtime.config import ParamError
from wip_control.core.controller_settings import (controller_settings_to_mapping,
                                                  ControllerParams, load_controller_settings)
from wip_runtime.cli import write_atomic

from .launcher import (CONTROLLER_LAYOUTS, EXECUTABLES, EXIT_DISK_FULL, EXIT_TIMEOUT,
                       EXIT_USAGE, GRACE_PERIOD, GraphError, in_namespace, LAYOUTS,
                       MULTI_NODE_PROCESSES, parse_namespace, RECORDER_GRACE_PERIOD,
                       VIEWER_TOPICS)
from .output_lock import prepare_run_directory
from .params_files import config_section, CONTROLLER_NODES, namespaced_params
from .probe import Probe
from .processes import choose_domain_id, executable_path, graph_environment, NodeProcess
from .run_result import RunResult
from .run_stop import is_disk_full, STOP_SIGNALS
from .scheduling import CpuLatencyRequest, Scheduling
from .view_options import live_view_line, viewer_wanted


class RunnerBase:
    """One run of controller processes (and what a subclass adds): see the module docstring.

    ``options`` is the runner's options dataclass; the fields read here are ``out``,
    ``record``, ``quiet``, ``layout``, ``scheduling``, ``viewer``, ``foxglove_port``,
    ``foxglove_host`` and ``discovery_timeout``.
    """

    #: Processes (each one node of the same name) besides the controllers, the recorder,
    #: the viewer and the Foxglove bridge.
    EXTRA_PROCESSES: tuple[str, ...] = ()
    #: The layouts this runner can start (``launcher.LAYOUTS``).
    LAYOUTS: tuple[str, ...] = CONTROLLER_LAYOUTS
    #: Timeline entry of the moment the probe saw every node (and what the subclass needs).
    UP_EVENT = 'nodes up'
    #: A simulation's nodes discover each other on this host only (unless the user chose a
    #: discovery range); hardware mode uses the user's network settings as they are.
    PRIVATE_NETWORK = True
    #: GraphError text when the nodes did not come up in time ({timeout} [s]).
    NOT_UP = 'the nodes did not come up in {timeout:g} s'

    def __init__(self, options) -> None:
        self.options = dataclasses.replace(options, viewer=viewer_wanted(options))
        self.out = pathlib.Path(options.out).resolve()
        self.bag = pathlib.Path(options.record).resolve() if options.record else None
        self.prepared = False  # True once prepare() set up the run directory
        self.bag_created = False  # True once this run's recorder may have written the bag
        self.processes: dict[str, NodeProcess] = {}
        #: Lock descriptors of --out and the bag (one run per folder), inherited by every
        #: node process: the folder stays locked until the last writer of this run ends.
        self.locks: list[int] = []
        self.probe: Probe | None = None
        #: The --cpu-latency request, held from the launch to the shut-down.
        self.cpu_latency_request: CpuLatencyRequest | None = None
        self.domain_id = choose_domain_id()
        #: The run's namespace ('' or '/robot1'), checked by :meth:`check_namespace`.
        self.namespace = ''
        self.scenario: ControllerParams | None = None
        self._interactive = sys.stderr.isatty()
        self.t0 = time.monotonic()
        #: Wall times [s] of the start-up steps, from the start of the run.
        self.timeline: dict[str, float] = {}

    # -- output -------------------------------------------------------------------------
    def say(self, text: str) -> None:
        if not self.options.quiet:
            if self._interactive:  # Clear a progress line first.
                sys.stderr.write('\r\033[K')
            print(f'run_graph: {text}', file=sys.stderr, flush=True)

    def progress(self, text: str) -> None:
        """Print a line that the next one replaces on a terminal."""
        if self.options.quiet:
            return
        if self._interactive:
            sys.stderr.write('\r\033[K  ' + text)
            sys.stderr.flush()
        else:
            print('  ' + text, file=sys.stderr, flush=True)

    def say_foxglove_url(self) -> None:
        if 'foxglove_bridge' in self.processes:
            self.say(live_view_line(self.processes['foxglove_bridge'],
                                    self.options.foxglove_host, self.options.foxglove_port))

    # -- set-up ---------------------------------------------------------------------------
    def check_namespace(self) -> None:
        self.namespace = parse_namespace(self.options.namespace)

    def namespaced_params_file(self, params_file: pathlib.Path) -> None:
        """Put the generated params file under the run's namespace (:func:`namespaced_params`)."""
        if not self.namespace:
            return
        write_atomic(params_file, namespaced_params(params_file.read_text(encoding='utf-8'),
                                                    self.namespace))

    def check_layout_and_scheduling(self) -> None:
        if self.options.layout not in self.LAYOUTS:
            raise GraphError(f'--layout: {self.options.layout!r} is not one of '
                             f'{list(self.LAYOUTS)}'
                             + (' (single holds the plant: simulation only)'
                                if self.options.layout in LAYOUTS else ''), EXIT_USAGE)
        self.options.scheduling.check()

    #: How the run reads its scenario file and writes it back: the controllers' sections
    #: here (hardware mode); the simulation reads the whole scenario (wip_sim).
    read_settings = staticmethod(load_controller_settings)
    settings_to_mapping = staticmethod(controller_settings_to_mapping)

    def load_scenario(self, path: str | None) -> ControllerParams:
        """Return the scenario file (None: the paper's); GraphError (usage) if it is invalid."""
        try:
            return self.read_settings(path)
        except ParamError as err:
            raise GraphError(str(err), EXIT_USAGE) from err

    def prepare_outputs(self, stale: Iterable[str] = ('run.json',),
                        extra_logs: tuple[str, ...] = ()) -> pathlib.Path:
        """Prepare the run directory.

        Check and create the run directory (nothing written before: see
        :func:`~wip_bringup.output_lock.prepare_run_directory`), remove the ``stale`` outputs
        of an earlier run, write ``OUT/scenario.yaml``; returns its path.
        """
        self.locks = prepare_run_directory(self.out, self.bag, extra_logs=extra_logs)
        self.prepared = True
        for name in stale:
            (self.out / name).unlink(missing_ok=True)
        path = self.out / 'scenario.yaml'
        write_atomic(path, yaml.safe_dump(self.settings_to_mapping(self.scenario),
                                         sort_keys=False))
        return path

    def recorder_parameters(self, topics: list[str],
                            discovery_period: float) -> dict[str, Any] | None:
        """Return the recorder's parameters (None without --record).

        They are ``topics`` and, when the viewer runs, its topics.
        """
        if self.bag is None:
            return None
        topics = list(topics) + (list(VIEWER_TOPICS) if self.options.viewer else [])
        # The nodes' names under the run's namespace (the recorder stores them without).
        topics = [in_namespace(topic, self.namespace) for topic in topics]
        return {'output': str(self.bag), 'topics': topics,
                'discovery_period': discovery_period}

    def view_parameters(self, model, position_std: float | None = None,
                        encoders_relative_to_body: bool | None = None) -> dict[str, dict]:
        """Params-file sections of the viewer and of the Foxglove bridge.

        Only those that run get a section. The viewer draws the vehicle, and builds its
        robot model, with ``model``'s dimensions (the wheel joints, signs and, unless given,
        the encoders' mounting from the params files' ``/**`` section).
        """
        options = self.options
        view: dict[str, dict] = {}
        if options.viewer:
            viewer = {'wheel_radius': float(model.wheel_radius),
                      'track_width': float(model.track_width),
                      'com_height': float(model.com_height)}
            if position_std is not None:
                viewer['position_std'] = float(position_std)
            parameters = {'viewer': viewer, 'model': config_section(model)}
            if encoders_relative_to_body is not None:
                parameters['encoders_relative_to_body'] = bool(encoders_relative_to_body)
            view['viewer'] = {'ros__parameters': parameters}
        if options.foxglove_port is not None:
            view['foxglove_bridge'] = {'ros__parameters': {
                'host': options.foxglove_host, 'port': int(options.foxglove_port)}}
        return view

    def controller_processes(self) -> list[str]:
        """Return the processes of the controllers.

        'controllers' (composed: the six nodes in one process), one per node (separate),
        or none of their own (single: they are in the simulation process).
        """
        layout = self.options.layout
        if layout == 'single':
            return []
        return ['controllers'] if layout == 'composed' else list(CONTROLLER_NODES)

    def extra_processes(self) -> list[str]:
        """Return the processes of :attr:`EXTRA_PROCESSES` (a runner may hold them otherwise)."""
        return list(self.EXTRA_PROCESSES)

    def view_nodes(self) -> list[str]:
        return ((['viewer'] if self.options.viewer else [])
                + (['foxglove_bridge'] if self.options.foxglove_port is not None else []))

    def view_processes(self) -> list[str]:
        """Return the processes of :meth:`view_nodes` (hook: a runner may compose one)."""
        return self.view_nodes()

    def program_arguments(self, name: str) -> list[str]:
        """Return arguments of the process ``name`` before ``--ros-args`` (hook)."""
        return []

    def node_names(self) -> list[str]:
        """Return the ROS nodes of the run (whatever the processes that hold them)."""
        return (list(CONTROLLER_NODES) + list(self.EXTRA_PROCESSES)
                + (['recorder'] if self.bag is not None else []) + self.view_nodes())

    def extra_arguments(self, name: str) -> tuple[list[str], list[str]]:
        """Return extra arguments of the process ``name`` (hook).

        Hook: (params files after the generated one, ROS arguments after the node name)
        of the process ``name``.
        """
        return [], []

    def commands(self, params_file: pathlib.Path) -> dict[str, list[str]]:
        """Return the command line of every process, in start order.

        The recorder comes first: it must not miss the start.
        """
        names = ((['recorder'] if self.bag is not None else []) + self.controller_processes()
                 + self.extra_processes() + self.view_processes())
        out = {}
        for name in names:
            package, executable = EXECUTABLES[name]
            files, arguments = self.extra_arguments(name)
            command = [str(executable_path(package, executable)),
                       *self.program_arguments(name), '--ros-args',
                       '--params-file', str(params_file)]
            for extra in files:
                command += ['--params-file', extra]
            if name not in MULTI_NODE_PROCESSES:   # there each node keeps its own name
                command += ['-r', f'__node:={name}']
            if self.namespace:   # every node of the process (a global rule)
                command += ['-r', f'__ns:={self.namespace}']
            out[name] = command + arguments
        return out

    def scheduled(self, name: str) -> bool:
        """Whether the process ``name`` gets ``options.scheduling``.

        The controllers only (single: the simulation process holds them, and the plant with them).
        Nothing else (the plant, the recorder, the viewer, the bridge) may take the CPU from them.
        """
        return name in self.controller_processes() or name == 'simulation'

    def stop_signal(self, name: str) -> int:
        """Return the signal that stops the process ``name`` (hook; SIGINT, as Ctrl-C).

        SIGTERM for the recorder: it stops at once, since this launcher has drained it. At
        a SIGINT, which is what the kernel sends at this launcher's death, a launched
        recorder first takes what is still coming (``wip_bag.recorder_node``).
        """
        return signal.SIGTERM if name == 'recorder' else signal.SIGINT

    def process_environment(self, name: str, env: dict[str, str]) -> dict[str, str]:
        """Return the environment of the process ``name`` (hook; the graph's, as is)."""
        return env

    def start_processes(self, params_file: pathlib.Path) -> None:
        env = graph_environment(self.domain_id, private=self.PRIVATE_NETWORK)
        env['ROS_LOG_DIR'] = str(self.out / 'logs' / 'ros')
        for name, command in self.commands(params_file).items():
            # Their CPUs at once, their priority once every node is up (launch; see
            # NodeProcess.raise_priority: start-up at SCHED_FIFO can starve the others).
            scheduling = self.options.scheduling.at_start() if self.scheduled(name) else None
            # The recorder in a process group of its own: a Ctrl-C in the terminal reaches
            # it only through this launcher, after the other nodes stopped and it drained.
            self.processes[name] = NodeProcess(name, command,
                                               self.out / 'logs' / f'{name}.log',
                                               self.process_environment(name, env),
                                               scheduling, pass_fds=tuple(self.locks),
                                               own_group=name == 'recorder',
                                               stop_signal=self.stop_signal(name))

    def launch(self, params_file: pathlib.Path) -> None:
        """Start the processes and wait until every node is up (:meth:`wait_for_nodes`)."""
        if self.options.scheduling.cpu_latency is not None:
            self.cpu_latency_request = CpuLatencyRequest(self.options.scheduling.cpu_latency)
        self.namespaced_params_file(params_file)
        self.start_processes(params_file)
        self.bag_created = self.bag is not None  # prepare() checked it was absent or empty
        self.timeline['processes started'] = time.monotonic() - self.t0
        self.say(f'started {len(self.processes)} processes in ROS_DOMAIN_ID='
                 f'{self.domain_id}; waiting for the graph')
        self.wait_for_nodes()
        if self.options.scheduling.priority:
            for name, process in self.processes.items():
                if self.scheduled(name):
                    process.raise_priority(self.options.scheduling)
            self.timeline['real-time priority set'] = time.monotonic() - self.t0

    # -- watching ---------------------------------------------------------------------------
    def node_died(self, name: str) -> None:
        """Handle the process ``name`` found dead, before the error (hook)."""

    def check_alive(self, exempt: Iterable[str] = ()) -> None:
        """Raise GraphError naming a node that exited (other than the ``exempt`` ones)."""
        for name, process in self.processes.items():
            code = process.poll()
            if code is None or name in exempt:
                continue
            self.node_died(name)
            raise GraphError(f'node {name!r} (pid {process.pid}) exited with code {code}; '
                             f'last lines of {process.log_path}:\n{process.log_tail()}')

    def missing_from_view(self, nodes: list[str]) -> list[str]:
        """Return what the probe's graph view still lacks (hook; default: absent nodes)."""
        present = self.probe.node_names()
        absent = [n for n in nodes if n not in present]
        return ['nodes ' + ', '.join(absent)] if absent else []

    def unmatched_endpoints(self) -> list[str]:
        """Return endpoints not yet matched although the graph view is complete (hook)."""
        return []

    def wait_for_nodes(self) -> None:
        """Wait until every node is seen and has matched its peers.

        Until the probe sees every node (:meth:`missing_from_view`), then a /diagnostics
        message of every node sent after that moment (the probe's view can be complete
        before two *other* nodes have matched each other; their exchange takes
        milliseconds; the nodes report every 0.1 s while they start, so the wait is short,
        ``wip_runtime.diagnostics.STARTUP_PERIOD``) and no :meth:`unmatched_endpoints`.
        """
        nodes = self.node_names()
        deadline = time.monotonic() + self.options.discovery_timeout
        missing = ['(not checked yet)']
        complete_since = None
        while time.monotonic() < deadline:
            self.check_alive()
            missing = self.missing_from_view(nodes)
            if missing:
                complete_since = None
            else:
                if complete_since is None:
                    complete_since = time.monotonic()
                silent = set(nodes) - self.probe.reporting_since(complete_since)
                unmatched = self.unmatched_endpoints()
                if not silent and not unmatched:
                    self.timeline[self.UP_EVENT] = complete_since - self.t0
                    self.timeline['diagnostics from every node'] = time.monotonic() - self.t0
                    return
                missing = (['/diagnostics from ' + ', '.join(sorted(silent))] if silent
                           else []) + unmatched
            self.probe.spin(0.1)
        raise GraphError(self.NOT_UP.format(timeout=self.options.discovery_timeout)
                         + f'; missing: {"; ".join(missing)}', EXIT_TIMEOUT)

    # -- stopping -------------------------------------------------------------------------
    def nodes_stopped(self) -> None:
        """Handle the stop of every process but the recorder (hook)."""

    def grace_period(self, name: str) -> float:
        """Return how long [s] the process ``name`` may take to end after its stop signal (hook).

        :data:`~.launcher.GRACE_PERIOD`, a node's clean-up, on top of any bounded wait that
        its stop makes by design (the plant's: :class:`~.graph_runner.GraphRunner`); then
        SIGKILL.
        """
        return GRACE_PERIOD

    def stop_processes(self, processes: list[NodeProcess]) -> None:
        """Send each its stop signal at once (they end in parallel); SIGKILL after its grace."""
        for process in processes:
            process.interrupt()
        signalled = time.monotonic()
        # The shortest grace first, so that each process is killed at its own deadline.
        for process in sorted(processes, key=lambda p: self.grace_period(p.name)):
            grace = self.grace_period(process.name)
            process.stop(signalled + grace - time.monotonic())
            if process.killed:
                self.say(f'warning: {process.name} (pid {process.pid}) ignored '
                         f'{signal.Signals(process.stop_signal).name} for {grace:g} s: killed')

    def stop_all(self) -> None:
        """Stop every process (:meth:`stop_signal`; the recorder last), SIGKILL after a grace."""
        self.stop_processes([p for n, p in self.processes.items() if n != 'recorder'])
        self.timeline['nodes stopped'] = time.monotonic() - self.t0
        self.nodes_stopped()
        if 'recorder' in self.processes:
            recorder = self.processes['recorder']
            code = recorder.stop(RECORDER_GRACE_PERIOD)
            self.timeline['recorder stopped'] = time.monotonic() - self.t0
            if code not in (0, None):
                self.say(f'warning: the recorder exited with code {code}; see '
                         f'{recorder.log_path}; if the bag was not closed, '
                         f'scripts/bag_repair {self.bag} recovers every complete chunk')

    # -- the result -----------------------------------------------------------------------
    def cpu_snapshot(self) -> dict[str, float | None]:
        """CPU time [s] used so far by each process."""
        return {name: process.cpu_seconds() for name, process in self.processes.items()}

    def cpu_since(self, start: dict[str, float | None]) -> dict[str, float]:
        """CPU time [s] of each process since the :meth:`cpu_snapshot` ``start``."""
        used = {}
        for name, now in self.cpu_snapshot().items():
            if now is not None and start.get(name) is not None:
                used[name] = now - start[name]
        return used

    def shut_down(self, result: RunResult) -> None:
        """End the run, whatever happened.

        The end of every run, whatever happened: the nodes' last /diagnostics into
        ``result``, every process stopped, the probe closed.
        """
        if self.probe is not None:
            self.probe.spin(0.05)
            result.node_diagnostics = {
                name: {'message': status.message,
                       **{kv.key: kv.value for kv in status.values}}
                for name, status in sorted(self.probe.diagnostics.items())}
        # A second Ctrl-C (or SIGTERM, SIGHUP) must not leave the nodes running nor the bag
        # unfinished (signal handlers can only be set from the main thread; a runner in
        # another thread is stopped by its caller).
        shield = threading.current_thread() is threading.main_thread()
        previous = ({n: signal.signal(n, signal.SIG_IGN) for n in STOP_SIGNALS}
                    if shield else {})
        try:
            self.stop_all()
        finally:
            for number, handler in previous.items():
                signal.signal(number, handler)
            if self.cpu_latency_request is not None:
                self.cpu_latency_request.close()
        if self.probe is not None:
            self.probe.close()

    def finish(self, result: RunResult) -> None:
        """Exit codes into ``result``, the scenario into the bag, ``OUT/run.json``."""
        result.domain_id = self.domain_id
        result.node_exit_codes = {n: p.returncode for n, p in self.processes.items()}
        scenario = self.out / 'scenario.yaml'
        if self.bag_created and self.bag.is_dir() and scenario.is_file():
            # Only into a bag this run recorded (never into one it refused); whole or not
            # at all (a full disk must not leave an empty scenario.yaml that a reader would
            # take for the default scenario).
            self.write_output(result, self.bag / 'scenario.yaml', scenario.read_bytes())
        if self.prepared and self.out.is_dir():  # A refused run leaves --out untouched.
            self.write_output(result, self.out / 'run.json',
                              json.dumps(result.summary(), indent=2) + '\n')

    def write_output(self, result: RunResult, path: pathlib.Path, data: bytes | str) -> None:
        """Write one output atomically.

        A full disk is said in ``result`` (and on stderr), not raised: the run's other outputs are
        still written where they fit.
        """
        try:
            write_atomic(path, data)
        except OSError as err:
            if not is_disk_full(err):
                raise
            self.say(f'disk full: {path} not written ({err.strerror})')
            if result.exit_code != EXIT_DISK_FULL:
                result.exit_code = EXIT_DISK_FULL
                result.message = (f'disk full: {path} not written; '
                                  + (result.message or ''))
            else:   # already a disk-full run: the file it lacks is said too (even --quiet)
                result.message = f'{result.message or "disk full"}; {path} not written'


def options_from_args(args, **own) -> dict[str, Any]:
    """Keyword arguments of either mode's options.

    They are taken from ``scripts/run_graph``'s parsed arguments: first those both modes
    have, then the mode's ``own``.
    """
    return dict(scenario=args.scenario, record=args.record, duration=args.duration,
                discovery_timeout=args.discovery_timeout, quiet=args.quiet,
                scheduling=Scheduling(priority=args.rt_priority, cpus=tuple(args.cpu_affinity),
                                      cpu_latency=args.cpu_latency),
                viewer=args.viewer, foxglove_port=args.foxglove,
                foxglove_host=args.foxglove_host, namespace=args.namespace, **own)
