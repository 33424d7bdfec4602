"""Hardware mode against the stand-in base, both in their own processes: one measured run.

The harness of the real-time tests (tests/wip_sim/test_standin_base.py, the fault
injection tests) and of ``scripts/bench``'s real-time part. The stand-in base
(:mod:`wip_sim.standin_base`: full plant, RK4 at 1 kHz, real time) speaks only the topics
of a ros2_control base under names of its own (``/base/...``) and conventions that differ
from the simulator's on purpose (joints ``wheel_l``/``wheel_r`` listed right first, the
left joint's sign −1, an IMU mounted upside down and turned a quarter turn); the
controllers run as ``scripts/run_graph --mode hardware`` with ``--remap`` and a
``--params-file`` of the base's conventions.

:func:`freeze_process` (SIGSTOP, sleep, SIGCONT) injects a stall of a controller process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import pathlib
import signal
import subprocess
import threading
import time
from typing import Any, Callable, Mapping

import yaml

from .hardware_outcome import HardwareResult
from .hardware_runner import HardwareOptions, run_hardware
from .launcher import GraphError, ROS_DEFAULTS_VARIABLE
from .processes import choose_domain_id, executable_path, graph_environment
from .scheduling import Scheduling

CONTROL_RATE = 200.0  # [Hz]
#: SCHED_FIFO priorities where permitted: the base above the controllers, as a base's
#: firmware would be, both above everything else on the machine (a robot's computer runs
#: its control at real-time priority; the tests then hold with other jobs running: at the
#: normal policy one busy process made 1 of 8 stand-in tests fall, bunched samples).
BASE_PRIORITY = 30
CONTROLLER_PRIORITY = 20
#: RLIMIT_RTTIME of those processes [s]: one that runs this long at SCHED_FIFO without
#: sleeping (a runaway, or a machine too slow for the layout) is killed by the kernel and
#: the run fails, rather than starve the test runner and everything else (seen: two
#: controller processes spinning at SCHED_FIFO 20 kept a 2-core machine unusable for
#: minutes). Start-up (imports) runs well under it on a slow machine.
RT_CPU_LIMIT = 30.0
#: The base's conventions (see the module docstring).
BASE = {
    'left_joint': 'wheel_l', 'right_joint': 'wheel_r', 'joints': ['wheel_r', 'wheel_l'],
    'left_wheel_sign': -1, 'right_wheel_sign': 1,
    'imu_mounting_rpy': [math.pi, 0.0, math.pi / 2],
}
#: [s] the arm delay of a run whose subject is not the arming (the tests' runs): the
#: release then comes at least this plus the safety layer's settle time (0.25 s) after
#: every node is up and reporting, later than a publish() stall of a DDS discovery still
#: under way lasts (about 0.33 s, docs/real-base.md). The user's default (2 s) covers a
#: start-up it does not watch: nodes started by hand, a robot on a slower computer.
SHORT_ARM_DELAY = 0.5
#: Relative rules: under a namespace (--namespace) they apply in it, to the base and the
#: controllers alike.
REMAPS = ['joint_states:=base/joint_states', 'imu/data:=base/imu', 'gps/fix:=base/fix',
          'effort_controller/commands:=base/effort_controller/commands']


def line_scenario(speed: float = 0.5, kind: str = 'line', **reference) -> dict[str, Any]:
    """Return a full-plant scenario on a line (or another reference kind), no disturbance."""
    return {
        'name': f'standin_{kind}',
        'description': f'hardware-mode run: {kind} at {speed} m/s, full plant model',
        'duration': 600.0,
        'reference': {'kind': kind, **({'line_speed': speed} if kind == 'line' else {}),
                      **reference},
        'plant': {'model': 'full'},
        'disturbances': {'yaw': [], 'longitudinal': []},
        'rates': {'control_rate': CONTROL_RATE},
        'eso': {'sample_period': 1.0 / CONTROL_RATE},
    }


def write_params(path: pathlib.Path, parameters: Mapping[str, Any]) -> pathlib.Path:
    """Return a params file applying ``parameters`` to every node."""
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': dict(parameters)}}))
    return path


@dataclasses.dataclass
class StandinRun:
    """What one run gives: the controllers' result, the base's statistics and exit code."""

    result: HardwareResult
    stats: dict[str, Any]
    base_code: int | None
    #: SCHED_FIFO priorities the base and the controllers ran at (0: normal policy).
    base_priority: int = 0
    controller_priority: int = 0
    #: CPUs the base and the controllers were pinned to (empty: any).
    base_cpus: tuple[int, ...] = ()
    controller_cpus: tuple[int, ...] = ()

    def summary(self) -> dict[str, Any]:
        """Return the measured numbers (also written to ``measured.json`` beside the run)."""
        stats, result = self.stats, self.result
        ticks = stats['ticks_checked']
        wall = result.wall_time_s or 0.0
        return {
            'control_rate_hz': CONTROL_RATE,
            'commands_received_rate_hz': stats['command_rate_hz'],
            'command_gap_ms': stats['command_gap'],
            'command_age_ms': stats['command_age'],
            'deadline_misses': stats['deadline_misses'],
            'deadline_miss_limit_ms': 1e3 * stats['deadline_miss_limit_s'],
            'base_ticks_checked': ticks,
            'deadline_miss_fraction': stats['deadline_misses'] / ticks if ticks else None,
            'base_tick_period_ms': stats['tick_period'],
            'base_stalls': stats['stalls'],
            'fell': stats['fell'],
            'node_rates_hz': result.rates,
            'controller_cpu_fraction': controller_cpu_fraction(result),
            'process_cpu_fraction': {n: c / wall for n, c in result.cpu_s.items()}
            if wall else {},
            'sensor_to_command_latency_ms': mixer_latency_ms(result),
            'controller_threads': result.threads,
            'safety_events': result.safety_events,
        }


def controller_cpu_fraction(result: HardwareResult) -> float | None:
    """CPU share of one core the controller processes used.

    CPU time of the controller processes (not the recorder) / wall time: the share of
    one core the controllers used.
    """
    if not result.wall_time_s:
        return None
    return sum(c for n, c in result.cpu_s.items() if n != 'recorder') / result.wall_time_s


def mixer_latency_ms(result: HardwareResult) -> dict[str, float] | None:
    """Sensor -> command latency percentiles [ms] from the mixer's last /diagnostics."""
    mixer = next((v for k, v in result.node_diagnostics.items()
                  if k.startswith('/torque_mixer')), {})
    text = mixer.get('sensor to command latency [ms] p50/p99/max')
    if not text:
        return None
    p50, p99, p100 = (float(v) for v in text.split()[0].split('/'))
    return {'p50': p50, 'p99': p99, 'max': p100}


def run_against_standin(directory: pathlib.Path, controller_conventions: Mapping[str, Any],
                        run_time: float, *, scenario: Mapping[str, Any] | None = None,
                        exit_after_fall: float = 1.0,
                        base_extra: Mapping[str, Any] | None = None,
                        layout: str = HardwareOptions.layout,
                        realtime_priority: bool = True,
                        pin_cpus: bool = False,
                        cpu_latency: int | None = None,
                        record: bool = False,
                        during: Callable[[HardwareResult | None, dict], None] | None = None,
                        end_after_during: float | None = None,
                        namespace: str = '',
                        stop_when: Callable[[Any], str | None] | None = None,
                        runner_duration: float | None = None,
                        arm_delay: float = HardwareOptions.arm_delay) -> StandinRun:
    """Start the stand-in base, run hardware mode until the base exits; both results.

    ``during(None, processes)``, if given, runs in a thread once the base has released the
    robot (its stats file is not needed: it waits for the first ACTIVE safety state seen
    by the runner), with the controller processes by name (to freeze one, say).
    ``end_after_during`` [s]: the run ends that long after ``during`` returns (the base is
    stopped with SIGINT, exit 0); ``run_time`` is then only a cap. A test whose injections
    must all happen within the run uses it: how soon the runner sees the engagement
    depends on the machine's load, the base's clock does not.
    ``realtime_priority``: run the base and the controllers at SCHED_FIFO priorities
    (:data:`BASE_PRIORITY`, :data:`CONTROLLER_PRIORITY`, limited to :data:`RT_CPU_LIMIT`
    without sleeping) if this user may; the run's ``measured.json`` says whether they
    were. ``pin_cpus``: the base on the first CPU this process may use, the controllers on
    the last (:func:`pinned_cpus`; nothing on a one-CPU machine), as a robot's computer
    would keep its control on a core of its own. ``cpu_latency`` [us]: the controllers'
    ``--cpu-latency`` (a PM QoS request held while they run; GraphError where not permitted).
    ``record``: the controllers' topics go to
    the bag ``directory/bag`` (costs CPU: for diagnosis, not for measuring).
    ``namespace``: the base and the controllers under this ROS namespace (one vehicle of
    several in a domain). ``stop_when(runner)``: also end the run when it returns a reason
    (the runner, once it started, or None). ``runner_duration`` [s]: the hardware run's
    own cap (default ``run_time`` + 40: a base that is never released runs until then).
    ``arm_delay`` [s]: the controllers' ``--arm-delay`` (default the user's).
    """
    base_scheduling, controller_scheduling = standin_scheduling(realtime_priority, pin_cpus,
                                                                cpu_latency)
    scenario_path, base_params, controller_params = _write_inputs(
        directory, controller_conventions, run_time, scenario, exit_after_fall, base_extra)
    domain = str(choose_domain_id())
    runner_holder: dict[str, Any] = {}
    injector = None
    with open(directory / 'base.log', 'w', encoding='utf-8') as log:
        base = _start_base(base_params, namespace, domain, base_scheduling, log)
        try:
            options = HardwareOptions(
                scenario=str(scenario_path), params_files=[str(controller_params)],
                remaps=REMAPS, out=str(directory / 'run'),
                duration=run_time + 40.0 if runner_duration is None else runner_duration,
                quiet=True, layout=layout, scheduling=controller_scheduling,
                namespace=namespace, arm_delay=arm_delay,
                record=str(directory / 'bag') if record else None,
                # The base ends run_time after its release (the engagement): a FAULT then
                # (its inputs stop) is the end of the run, not a failure.
                base_end_after=float(run_time),
                stop_when=lambda: (base.poll() is not None and f'base exited ({base.returncode})'
                                   or stop_when is not None
                                   and stop_when(runner_holder.get('runner'))))
            options.on_start = lambda runner: runner_holder.setdefault('runner', runner)
            if during is not None:
                injector = threading.Thread(
                    target=_when_engaged, daemon=True,
                    args=(runner_holder, during, base, end_after_during))
                injector.start()
            with _private_ros_environment(domain):
                result = run_hardware(options)
        finally:
            _stop_base(base)
            if injector is not None:
                injector.join(timeout=30)
    stats = json.loads((directory / 'base_stats.json').read_text(encoding='utf-8'))
    run = StandinRun(result, stats, base.returncode, base_scheduling.priority,
                     controller_scheduling.priority, base_scheduling.cpus,
                     controller_scheduling.cpus)
    _write_measured(directory, run, layout)
    return run


def standin_scheduling(realtime_priority: bool, pin_cpus: bool,
                       cpu_latency: int | None) -> tuple[Scheduling, Scheduling]:
    """Return the scheduling of the stand-in base and of the controllers.

    SCHED_FIFO priorities where this user may (the base above the controllers), the CPUs
    of :func:`pinned_cpus` with ``pin_cpus``, the controllers' ``--cpu-latency``.
    """
    base_scheduling = controller_scheduling = Scheduling()
    if realtime_priority and permitted(Scheduling(BASE_PRIORITY, rt_cpu_limit=RT_CPU_LIMIT)):
        base_scheduling = Scheduling(BASE_PRIORITY, rt_cpu_limit=RT_CPU_LIMIT)
        controller_scheduling = Scheduling(CONTROLLER_PRIORITY, rt_cpu_limit=RT_CPU_LIMIT)
    cpus = pinned_cpus() if pin_cpus else None
    if cpus is not None:
        base_scheduling = dataclasses.replace(base_scheduling, cpus=(cpus[0],))
        controller_scheduling = dataclasses.replace(controller_scheduling, cpus=(cpus[1],))
    if cpu_latency is not None:
        controller_scheduling = dataclasses.replace(controller_scheduling,
                                                    cpu_latency=cpu_latency)
    return base_scheduling, controller_scheduling


def _write_inputs(directory: pathlib.Path, controller_conventions: Mapping[str, Any],
                  run_time: float, scenario: Mapping[str, Any] | None,
                  exit_after_fall: float, base_extra: Mapping[str, Any] | None):
    """Write the scenario, the base's and the controllers' params files; their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    scenario_path = directory / 'scenario.yaml'
    scenario_path.write_text(yaml.safe_dump(dict(scenario or line_scenario())))
    base_params = write_params(directory / 'base.yaml', dict(
        BASE, **(base_extra or {}), duration=float(run_time),
        exit_after_fall=float(exit_after_fall),
        stats_file=str(directory / 'base_stats.json'), scenario_file=str(scenario_path)))
    controller_params = write_params(directory / 'controllers.yaml', controller_conventions)
    return scenario_path, base_params, controller_params


def _start_base(base_params: pathlib.Path, namespace: str, domain: str,
                scheduling: Scheduling, log) -> subprocess.Popen:
    """Start ``wip_sim standin_base`` in the run's domain, its output into ``log``."""
    # The controllers' environment (the base too ends with this process, same transport),
    # on localhost whatever the user's discovery range.
    env = dict(graph_environment(int(domain)), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    command = [str(executable_path('wip_sim', 'standin_base')), '--ros-args',
               '--params-file', str(base_params)]
    for remap in REMAPS:
        command += ['-r', remap]
    if namespace:
        command += ['-r', f'__ns:=/{namespace.lstrip("/")}']
    return subprocess.Popen(scheduling.command_prefix() + command, stdout=log,
                            stderr=subprocess.STDOUT, env=env)


@contextlib.contextmanager
def _private_ros_environment(domain: str):
    """Give hardware mode (in this process) the run's private domain, as the user's.

    Hardware mode uses the environment's ROS settings as the user's: this run's private
    domain and localhost-only discovery, with no record of scripts/_env.sh's defaults that
    would make it drop them; restored afterwards.
    """
    private = {'ROS_DOMAIN_ID': domain, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
               ROS_DEFAULTS_VARIABLE: None}
    previous = {name: os.environ.get(name) for name in private}
    try:
        for name, value in private.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        yield
    finally:
        for name, value in previous.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _stop_base(base: subprocess.Popen) -> None:
    """SIGINT to the base if it still runs; SIGKILL after 10 s."""
    if base.poll() is None:
        base.send_signal(signal.SIGINT)
    try:
        base.wait(timeout=10)
    except subprocess.TimeoutExpired:
        base.kill()
        base.wait()


def _write_measured(directory: pathlib.Path, run: StandinRun, layout: str) -> None:
    """``directory/measured.json``: the run's summary, with its priorities and CPUs."""
    measured = dict(run.summary(), base_priority=run.base_priority,
                    controller_priority=run.controller_priority,
                    base_cpus=list(run.base_cpus), controller_cpus=list(run.controller_cpus),
                    layout=layout)
    (directory / 'measured.json').write_text(json.dumps(measured, indent=2))


def pinned_cpus() -> tuple[int, int] | None:
    """Return (base CPU, controllers' CPU), or None with fewer than two CPUs.

    (base CPU, controllers' CPU): the first and the last CPU this process may use, or
    None with fewer than two.
    """
    available = sorted(os.sched_getaffinity(0))
    return (available[0], available[-1]) if len(available) >= 2 else None


def permitted(scheduling: Scheduling) -> bool:
    """Whether this user may apply ``scheduling`` (tried on a throwaway child)."""
    try:
        scheduling.check()
        return True
    except GraphError:
        return False


def engaged(result: HardwareResult | Any) -> bool:
    """Whether the controllers' safety layer reached ACTIVE in a run.

    A :class:`HardwareResult` or a running runner: both keep ``safety_events``.
    """
    return any(event['state'] == 'ACTIVE' for event in result.safety_events)


def _when_engaged(holder: dict, during: Callable, base: subprocess.Popen,
                  end_after: float | None) -> None:
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline:
        runner = holder.get('runner')
        if runner is not None and engaged(runner):
            try:
                during(runner, runner.processes)
            finally:
                if end_after is not None:
                    time.sleep(end_after)
                    if base.poll() is None:
                        _base_ends_now(runner)
                        base.send_signal(signal.SIGINT)
            return
        time.sleep(0.01)


def _base_ends_now(runner) -> None:
    """Stop the base now, before its run time.

    From here its inputs stop, and a FAULT is the end of the run, not a failure
    (``HardwareOptions.base_end_after``, counted from the engagement, which the outcome
    reads when the run is over).
    """
    start = next(e['t'] for e in runner.safety_events if e['state'] == 'ACTIVE')
    now = time.monotonic() - runner.t0
    current = runner.options.base_end_after
    runner.options.base_end_after = min(now - start, current if current is not None
                                        else float('inf'))


def freeze_process(pid: int, seconds: float) -> float:
    """SIGSTOP the process for ``seconds``, then SIGCONT it; the measured freeze [s]."""
    start = time.monotonic()
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)
    return time.monotonic() - start


def realtime_benchmark(directory: pathlib.Path, seconds: float = 20.0,
                       cases: tuple[tuple[str, bool, bool, int | None], ...] = (
                           ('separate', False, False, None), ('composed', False, False, None),
                           ('composed', True, False, None), ('composed', True, True, None),
                           ('composed', True, False, 0), ('composed', True, True, 0)),
                       arm_delay: float | None = None) -> list[dict[str, Any]]:
    """Measure the controllers at 200 Hz against the stand-in base, case by case.

    The controllers at 200 Hz against the stand-in base, one run per (layout, real-time
    priority, pinned CPUs, CPU wake-up latency request [us]) case, side by side: CPU share
    of one core, sensor -> command latency, the command age and gaps seen by the base.
    A case this user may not run (the latency request needs root) is a row with
    ``skipped`` and the reason. ``scripts/bench`` prints it. ``arm_delay`` [s]: each
    run's (None: hardware mode's default).
    """
    rows: list[dict[str, Any]] = []
    for layout, priority, pin, cpu_latency in cases:
        name = (f'{layout}{"_rt" if priority else ""}{"_pinned" if pin else ""}'
                f'{"" if cpu_latency is None else f"_latency{cpu_latency}"}')
        try:
            if cpu_latency is not None:
                Scheduling(cpu_latency=cpu_latency).check()
        except GraphError as err:
            rows.append({'layout': layout, 'cpu_latency': cpu_latency, 'skipped': str(err)})
            continue
        run = run_against_standin(directory / name, BASE, seconds, layout=layout,
                                  realtime_priority=priority, pin_cpus=pin,
                                  cpu_latency=cpu_latency,
                                  arm_delay=(HardwareOptions.arm_delay if arm_delay is None
                                             else arm_delay))
        summary = run.summary()
        rows.append({'layout': layout, 'rt_priority': run.base_priority > 0,
                     'pinned': bool(run.controller_cpus), 'cpu_latency': cpu_latency,
                     'command_age_ms': summary['command_age_ms'],
                     'fell': summary['fell'],
                     'controller_cpu_fraction': summary['controller_cpu_fraction'],
                     'latency_ms': summary['sensor_to_command_latency_ms'],
                     'command_gap_ms': summary['command_gap_ms'],
                     'deadline_misses': summary['deadline_misses'],
                     'threads': summary['controller_threads'],
                     'control_rate_hz': summary['control_rate_hz']})
    return rows
