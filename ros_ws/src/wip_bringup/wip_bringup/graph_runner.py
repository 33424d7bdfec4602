"""One simulation run of ``scripts/run_graph``: start, watch and stop the graph's processes.

The steps, the start-up race and the outputs: docs/run_graph.md.
"""

from __future__ import annotations

import os
import pathlib
import random
import shutil
import signal
import sys
import time

import yaml

from wip_runtime.config import ParamError
from wip_runtime.node_main import STOP_ACK_TIMEOUT
from wip_runtime.cli import write_atomic
from wip_sim.core.scenario import load_scenario, scenario_to_mapping, with_duration
from wip_sim.settings import ALREADY_STARTED, WITH_VIEWER

from .graph_options import GraphOptions, GraphResult, StartupStall
from .graph_design import (expected_endpoints, missing_endpoints, plant_parameters,
                           RECORDED_TOPICS, unmatched_pairs)
from .graph_recording import RecordingMixin
from .launcher import (EXIT_DISK_FULL, EXIT_FAILED, EXIT_FELL, EXIT_NOT_ENGAGED, EXIT_OK,
                       EXIT_TIMEOUT, EXIT_USAGE, GraphError, in_namespace, LAYOUTS, PROBE_PERIOD)
from .params_files import write_params_file
from .probe import Probe
from .run_stop import DiskFull, is_disk_full, stop_signal_number
from .runner_base import RunnerBase

#: A run whose plant has not passed its second tick this long [s] after its start has
#: stalled at start-up (the first ticks normally take milliseconds; 10 s covers the
#: slowest first MPC solve on a loaded machine many times over).
STARTUP_STALL_TIMEOUT = 10.0
#: rmw_fastrtps's publication mode of every writer of a process (SYNCHRONOUS by default).
PUBLICATION_MODE_VARIABLE = 'RMW_FASTRTPS_PUBLICATION_MODE'


class GraphRunner(RecordingMixin, RunnerBase):
    """One simulation run: start, watch and stop the processes (docs/run_graph.md)."""

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
            self.stop_processes([p for n, p in self.processes.items()
                                 if n not in ('recorder', 'plant')])
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

    def grace_period(self, name: str) -> float:
        """Add to the plant's grace its wait for its readers' acknowledgements.

        Stopped by a signal, a simulator waits up to ``STOP_ACK_TIMEOUT`` for them
        (``wip_sim.simulator_main``); a reader in a killed process never acknowledges
        (docs/decisions/stopping-and-data-safety.md).
        """
        grace = super().grace_period(name)
        return grace + STOP_ACK_TIMEOUT if name == self.plant_process else grace

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
            except ParamError as err:
                raise GraphError(f'--duration: {str(err).removeprefix("duration: ")}',
                                 EXIT_USAGE) from None
        self.scenario = scenario
        # Every output is checked before anything is written or started.
        scenario_path = self.prepare_outputs(stale=('plant_stats.json', 'run.json'),
                                             extra_logs=('logs_attempt_*',))
        recorder = self.recorder_parameters(
            (['/clock'] if options.clock == 'lockstep' else []) + list(RECORDED_TOPICS),
            discovery_period=0.2)
        plant_extra = plant_parameters(options.clock, options.layout, recorder is not None,
                                       self.out / 'plant_stats.json')
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
        """Designed pairs whose DDS match is not yet seen by both sides (unmatched_pairs)."""
        def values(name: str) -> dict[str, str] | None:
            found = self.probe.status_values(f'/{name}:', prefix=True)
            return None if found is None else found[1]
        return unmatched_pairs(values, self.namespace, self.bag is not None,
                               self.options.clock, self.options.layout)

    def start_plant(self) -> None:
        """Ask the plant to start until it has.

        An answer lost or later than the call's timeout on a loaded machine is not a
        failure: the plant then answers the next request 'already started', or has run a
        short scenario to its end before it (exit 0, or the fall's status, which
        :meth:`watch` takes at once); only the runner's stop could end it otherwise.
        """
        deadline = time.monotonic() + self.options.discovery_timeout
        last = f'the service {self.namespace}/plant/start did not answer'
        plant = self.processes[self.plant_process]
        while time.monotonic() < deadline:
            if plant.poll() in (EXIT_OK, EXIT_FELL):
                break
            self.check_alive()
            response = self.probe.call_start(timeout=2.0)
            if response is not None:
                if response.success or response.message == ALREADY_STARTED:
                    break
                last = response.message
                self.start_refusals.append(f'{time.monotonic() - self.t0:.3f}: {last}')
            self.probe.spin(0.1)
        else:
            raise GraphError(f'the plant did not start: {last}', EXIT_TIMEOUT)
        self.timeline['plant started'] = time.monotonic() - self.t0

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
        self.stop_processes([self.processes[name] for name in self.stopped_at_end])
        self.stop_processes([plant])
        return plant.returncode

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
            # The plant is the poll's above: ending after it (at the scenario's end) it is
            # taken at the next turn, not called a node that died.
            self.check_alive(exempt=(self.plant_process,))
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
                        f'{status.message}\n{self.probe.describe_nodes()}', EXIT_NOT_ENGAGED)
                raise StartupStall(
                    f'no progress for {now - started:.0f} s at t = {last_sim:g} s, the first '
                    f'ticks: {status.message}\n{self.probe.describe_nodes()}')
            elif now - last_progress > self.options.stall_timeout:
                raise GraphError(
                    f'no progress for {self.options.stall_timeout:g} s at t = {last_sim:g} s: '
                    f'{status.message}\n{self.probe.describe_nodes()}', EXIT_TIMEOUT)

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
        stopped_by = ''
        try:
            self.run_to_end(result)
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
        self.conclude(result, stopped_by)
        return result

    def run_to_end(self, result: GraphResult) -> None:
        """Prepare, start the graph (again after a stall at start-up), run it to its end."""
        started = time.monotonic()
        params_file = self.prepare()
        result.scenario = self.scenario
        self.say(f'scenario {self.scenario.name!r} ({self.scenario.duration:g} s), clock '
                 f'{self.options.clock}, ROS_DOMAIN_ID={self.domain_id}, outputs in '
                 f'{self.out}')
        code, run_start, cpu_start = self.start_and_watch(params_file, result, started)
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

    def start_and_watch(self, params_file: pathlib.Path, result: GraphResult, started: float):
        """Start the graph, retrying after a start-up stall, and watch it until the plant exits.

        Returns the plant's exit code, and the wall time and CPU times at the run's start.
        """
        attempt = 0
        while True:
            try:
                self.start_graph(params_file)
                result.startup_s = time.monotonic() - started
                self.say(f'graph connected in {result.startup_s:.1f} s; plant started')
                self.say_foxglove_url()
                run_start = time.monotonic()
                cpu_start = self.cpu_snapshot()
                return self.watch(), run_start, cpu_start
            except StartupStall as err:
                if attempt == self.options.startup_retries:
                    raise
                self.say(f'warning: {err}\nrun_graph: a message of the first tick was '
                         'lost (published before its subscription matched): '
                         f'starting the graph again (attempt {attempt + 2})')
                attempt += 1
                self.retry(attempt)

    def conclude(self, result: GraphResult, stopped_by: str) -> None:
        """Complete ``result`` once every process has stopped, and write ``OUT/run.json``."""
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


def run_graph(options: GraphOptions) -> GraphResult:
    """Run one scenario through the graph (docs/run_graph.md)."""
    return GraphRunner(options).run()
