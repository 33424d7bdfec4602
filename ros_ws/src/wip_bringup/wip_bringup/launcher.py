"""Process machinery shared by the bring-up modes.

Simulation (:mod:`wip_bringup.graph`) and hardware mode (:mod:`wip_bringup.hardware`) start the
same executables the way ``ros2 run`` does, in a DDS domain of their own, watch them through a
probe node, and stop them the same way. Both modes import this module; neither imports the other's
internals.
"""

from __future__ import annotations

import argparse
import dataclasses
import fcntl
import os
import pathlib
import re
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from typing import Any

from wip_control.nodes.launched import LAUNCHER_PID_VARIABLE
from wip_control.tools.cli import check_output_directory
from wip_control.tools.cli import EXIT_DISK_FULL as CLI_EXIT_DISK_FULL
from wip_control.tools.cli import EXIT_NOT_ENGAGED as CLI_EXIT_NOT_ENGAGED
from wip_viewer.viewer_core import MODEL_TOPICS, VIEWER_TOPICS as VIEWER_TOPIC_TYPES

from .private_domain import reserve_private_domain
from .ros_env import (FASTDDS_PROFILE, FASTDDS_PROFILE_VARIABLES, GraphError,  # noqa: F401
                      parse_namespace, ROS_DEFAULTS_VARIABLE, ros_network, RosNetwork,
                      use_user_ros_environment)


# The exit-code table of every tool (wip_control.tools.cli): 0 ok, 1 the vehicle fell (or a
# safety fault while engaged), 2 usage or input error, 3 internal error (a node crashed, the
# graph stalled), 4 disk full, 5 the controllers never engaged, 130 Ctrl-C (143 SIGTERM,
# 129 SIGHUP: 128 + the signal, runner_base.STOP_SIGNALS).
EXIT_OK, EXIT_FELL, EXIT_USAGE, EXIT_FAILED = 0, 1, 2, 3
EXIT_TIMEOUT = EXIT_FAILED
EXIT_INTERRUPTED = 130
#: The disk (or a quota) filled up: recording stopped and what fit was finalised.
EXIT_DISK_FULL = CLI_EXIT_DISK_FULL
#: The controllers never engaged (hardware mode, a real-time simulation).
EXIT_NOT_ENGAGED = CLI_EXIT_NOT_ENGAGED
#: Published by the viewer node (standard messages for 3-D viewers; nothing in the
#: control loop subscribes to them).
VIEWER_TOPICS = tuple(VIEWER_TOPIC_TYPES) + tuple(MODEL_TOPICS)
#: Marker of a log directory written by run_graph: only such a directory is replaced.
LOGS_MARKER = '.written-by-run_graph'

#: Process layouts of the controller nodes: 'separate' (one process per node, as six
#: `ros2 run`), 'composed' (the six nodes in one process, `ros2 run wip_control
#: controllers`, one executor) or, in simulation only, 'single' (the plant too: `ros2 run
#: wip_sim simulation`). Same nodes, names, parameters and topics in every layout.
LAYOUTS = ('separate', 'composed', 'single')
#: The layouts with a process of their own for the plant, and so those of hardware mode.
CONTROLLER_LAYOUTS = ('separate', 'composed')
#: Processes that hold several nodes, each keeping its own name.
MULTI_NODE_PROCESSES = ('controllers', 'simulation')

#: Executable of each node: (package, executable).
EXECUTABLES = {
    'reference': ('wip_control', 'reference'),
    'eso': ('wip_control', 'eso'),
    'trajectory_generator': ('wip_control', 'trajectory_generator'),
    'arc': ('wip_control', 'arc'),
    'mpc': ('wip_control', 'mpc'),
    'torque_mixer': ('wip_control', 'torque_mixer'),
    'controllers': ('wip_control', 'controllers'),
    'simulation': ('wip_sim', 'simulation'),
    'plant': ('wip_sim', 'plant'),
    'recorder': ('wip_bag', 'recorder'),
    'viewer': ('wip_viewer', 'viewer'),
    'foxglove_bridge': ('wip_viewer', 'foxglove_bridge'),
}


#: Topics that stay global under a namespace: the diagnostic aggregator listens on
#: /diagnostics (statuses carry the node's full name, namespace included), and a
#: simulation's /clock is the time of every node of its ROS domain; /tf and /tf_static are
#: every robot's (tf's convention: the frames carry the robot's prefix).
GLOBAL_TOPICS = ('/diagnostics', '/clock', '/rosout', '/parameter_events', '/tf',
                 '/tf_static')
#: The run's inputs from outside the graph, recorded with --record: the references (a
#: teleop's /cmd_vel, a planner's /plan) and the e-stop (button, reset topic, the
#: supervisor's heartbeat). A reset through the mixer's service is no topic: the mixer's
#: /diagnostics (recorded) show its effect.
INPUT_TOPICS = ('/cmd_vel', '/plan', '/wip/estop', '/wip/estop_reset', '/wip/heartbeat')


def in_namespace(topic: str, namespace: str) -> str:
    """Return the name a node of ``namespace`` gives its topic ``topic``.

    The name a node of ``namespace`` gives its topic ``topic`` (written absolute, as
    in the graph's tables): the nodes use relative names, so it resolves under their
    namespace; :data:`GLOBAL_TOPICS` stay as they are.
    """
    if not namespace or topic in GLOBAL_TOPICS:
        return topic
    return namespace + '/' + topic.lstrip('/')


PROBE_PERIOD = 0.5  # [s] wall: process polling and probe spinning
PROBE_CLOSE_TIMEOUT = 10.0  # [s] wall: the probe node's destruction (Probe.close)
GRACE_PERIOD = 5.0  # [s] after SIGINT before SIGKILL (controllers)
RECORDER_GRACE_PERIOD = 60.0  # [s] the recorder writes the rest of its queue first
LOG_TAIL_LINES = 15


#: The kernel's PM QoS interface for the CPU wake-up latency (Documentation/power/pm_qos_interface
#: in the kernel sources): a request holds while the file stays open.
CPU_LATENCY_DEVICE = '/dev/cpu_dma_latency'
#: Largest --cpu-latency accepted [us]; larger is no request at all in practice.
MAX_CPU_LATENCY_US = 1_000_000


class CpuLatencyRequest:
    """A PM QoS request that idle CPUs wake up within ``microseconds`` [us].

    Held until :meth:`close` (or until this process ends: the kernel drops it with the file).

    0 keeps idle CPUs out of their sleep states: they poll. Why it matters here: on a
    machine whose idle CPUs halt (a VM's haltpoll, a deep C-state on bare metal), the
    controllers' Python runs 2-4x slower right after the CPU slept (cold caches), so their
    CPU share at 200 Hz is several times the cost of the same work back to back
    (docs/realtime.md §2). The price: an idle CPU stays busy polling (power, and the host's
    CPU in a VM); it runs any other task at once, so it takes nothing from them.
    GraphError (usage) with the reason when the device is missing or not writable.
    """

    def __init__(self, microseconds: int, device: str = CPU_LATENCY_DEVICE) -> None:
        self.microseconds = int(microseconds)
        try:
            self._fd: int | None = os.open(device, os.O_WRONLY)
        except OSError as err:
            raise GraphError(f'--cpu-latency {microseconds}: not possible here ({device}: '
                             f'{err.strerror}); it needs root or write access to {device}',
                             EXIT_USAGE) from None
        try:
            os.write(self._fd, struct.pack('i', self.microseconds))
        except OSError as err:
            self.close()
            raise GraphError(f'--cpu-latency {microseconds}: {device} refused it '
                             f'({err.strerror})', EXIT_USAGE) from None

    def close(self) -> None:
        """Drop the request (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


@dataclasses.dataclass(frozen=True)
class Scheduling:
    """Real-time scheduling of a process.

    SCHED_FIFO ``priority`` (1..99; 0: the normal policy), the CPUs it may run on (empty: all) and,
    while it runs, a CPU wake-up latency request (``cpu_latency``, held by the launcher).

    Applied by starting the program through util-linux's ``chrt`` and ``taskset``
    (:meth:`command_prefix`), not by Python code between fork and exec (``preexec_fn``):
    the launching process has DDS threads, and a child forked from a threaded process
    may deadlock before exec (the subprocess documentation warns of it; a run here hung
    in such a child). The policy is inherited by every thread the program starts.
    """

    priority: int = 0
    cpus: tuple[int, ...] = ()
    #: RLIMIT_RTTIME [s] (0: none): a thread at SCHED_FIFO that runs this long without
    #: sleeping is killed by the kernel, instead of starving everything below its priority.
    rt_cpu_limit: float = 0.0
    #: A CPU wake-up latency request [us] held while the controllers run
    #: (:class:`CpuLatencyRequest`, machine-wide); None: none.
    cpu_latency: int | None = None

    def check(self) -> None:
        """Check that the scheduling can be applied.

        GraphError (usage) naming the option if the values are absurd or this user may
        not apply them (tried on a throwaway ``true``).
        """
        if not 0 <= self.priority <= 99:
            raise GraphError(f'--rt-priority: must be in 0..99, got {self.priority}',
                             EXIT_USAGE)
        available = os.sched_getaffinity(0)
        if self.cpus and not set(self.cpus) <= available:
            raise GraphError(f'--cpu-affinity: CPUs {sorted(set(self.cpus) - available)} are '
                             f'not available (this process may use {sorted(available)})',
                             EXIT_USAGE)
        if self.cpu_latency is not None:
            if not 0 <= self.cpu_latency <= MAX_CPU_LATENCY_US:
                raise GraphError(f'--cpu-latency: must be in 0..{MAX_CPU_LATENCY_US} us, got '
                                 f'{self.cpu_latency}', EXIT_USAGE)
            CpuLatencyRequest(self.cpu_latency).close()   # GraphError if not permitted
        if not (self.priority or self.cpus):
            return
        try:
            done = subprocess.run(self.command_prefix() + ['true'], capture_output=True,
                                  text=True, timeout=60, check=False)
        except (subprocess.SubprocessError, OSError) as err:
            done, reason = None, str(err)
        else:
            reason = (done.stderr.strip().splitlines() or [f'exit code {done.returncode}'])[-1]
        if done is None or done.returncode != 0:
            raise GraphError(
                f'--rt-priority {self.priority}: not permitted here ({reason}); it needs '
                'root, CAP_SYS_NICE or an rtprio limit (/etc/security/limits.conf)',
                EXIT_USAGE)

    def at_start(self) -> 'Scheduling':
        """Return what a process gets at its start when its priority is raised later.

        The priority is raised only once the process is up
        (:meth:`NodeProcess.raise_priority`); until then it gets its CPUs and the normal
        policy.
        """
        return dataclasses.replace(self, priority=0, rt_cpu_limit=0.0)

    def command_prefix(self) -> list[str]:
        """``prlimit``/``chrt``/``taskset`` words to put before a program's command line.

        The list is [] if nothing is asked for. Each tool execs the next, so the pid
        is the program's.
        """
        words: list[str] = []
        limit = self.priority and self.rt_cpu_limit > 0.0
        for tool, wanted in (('prlimit', limit), ('chrt', self.priority),
                             ('taskset', self.cpus)):
            if wanted and shutil.which(tool) is None:
                raise GraphError(f'{tool} not found: --rt-priority and --cpu-affinity need '
                                 'util-linux (apt-get install util-linux)', EXIT_USAGE)
        if limit:
            words += ['prlimit', f'--rttime={round(self.rt_cpu_limit * 1e6)}']
        if self.priority:
            words += ['chrt', '--fifo', str(self.priority)]
        if self.cpus:
            words += ['taskset', '--cpu-list', ','.join(map(str, self.cpus))]
        return words


def parse_cpus(text: str) -> tuple[int, ...]:
    """'0,1' or '1' -> (0, 1); ValueError with the reason otherwise."""
    try:
        cpus = tuple(sorted({int(part) for part in text.split(',') if part.strip()}))
    except ValueError as err:
        raise ValueError(f'expected CPU numbers separated by commas, got {text!r}') from err
    if not cpus or min(cpus) < 0:
        raise ValueError(f'expected CPU numbers >= 0, got {text!r}')
    return cpus


def executable_path(package: str, executable: str) -> pathlib.Path:
    """``<prefix>/lib/<package>/<executable>``, what ``ros2 run package executable`` runs."""
    from ament_index_python.packages import get_package_prefix, PackageNotFoundError
    try:
        prefix = get_package_prefix(package)
    except PackageNotFoundError as err:
        raise GraphError(f'package {package!r} not found in the ament index '
                         '(AMENT_PREFIX_PATH): source ros_ws/install/setup.bash or use '
                         'scripts/run_graph', EXIT_USAGE) from err
    path = pathlib.Path(prefix) / 'lib' / package / executable
    if not os.access(path, os.X_OK):
        raise GraphError(f'{path} is not an executable: rebuild the workspace '
                         '(scripts/setup)', EXIT_USAGE)
    return path


def graph_environment(domain_id: int, private: bool = True) -> dict[str, str]:
    """Environment of the node processes.

    Our DDS domain, plain logs; with ``private`` (a simulation) localhost-only discovery unless the
    user chose a range, else (hardware mode) the user's discovery settings as they are.
    """
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    if private:
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['PYTHONUNBUFFERED'] = '1'
    env.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
    # The nodes stop when this process ends, even if it is killed (nodes/launched.py).
    env[LAUNCHER_PID_VARIABLE] = str(os.getpid())
    # One BLAS thread per node process: small matrices, where a thread pool only adds
    # wake-ups (docs/realtime.md).
    env.setdefault('OPENBLAS_NUM_THREADS', '1')
    if not any(env.get(name) for name in FASTDDS_PROFILE_VARIABLES):
        env[FASTDDS_PROFILE_VARIABLES[0]] = str(FASTDDS_PROFILE)
    return env


def choose_domain_id() -> int:
    """Return the DDS domain of a run.

    ``$ROS_DOMAIN_ID`` if the user (or a test harness) set it, else a private domain
    reserved on this host for the life of this process (wip_bringup.private_domain); the
    pid-derived default of scripts/_env.sh counts as unset, since two runs' pids can map to
    one domain.
    """
    value = os.environ.get('ROS_DOMAIN_ID', '').strip()
    defaulted = f'ROS_DOMAIN_ID={value}' in os.environ.get(ROS_DEFAULTS_VARIABLE, '').split()
    if value and not defaulted:
        try:
            return int(value)
        except ValueError as err:
            raise GraphError(f'ROS_DOMAIN_ID={value!r} is not an integer', EXIT_USAGE) from err
    domain_id, descriptor = reserve_private_domain()
    _RESERVED_DOMAINS.append(descriptor)
    return domain_id


#: Descriptors holding this process's domain reservations (released when it exits).
_RESERVED_DOMAINS: list[int] = []


class NodeProcess:
    """One node's process, its log file and how to stop it."""

    def __init__(self, name: str, command: list[str], log_path: pathlib.Path,
                 env: dict[str, str], scheduling: Scheduling | None = None,
                 pass_fds: tuple[int, ...] = (), own_group: bool = False,
                 stop_signal: int = signal.SIGINT) -> None:
        """Start ``command`` as the node process ``name``; its options below.

        ``pass_fds``: descriptors the process inherits (the run's output locks: it holds
        them until it exits, also when the launcher dies first); ``own_group``: a process
        group of its own, out of the reach of the terminal's Ctrl-C (sent to the
        foreground group): the process gets SIGINT only from the launcher, when the
        launcher chooses. Not a session of its own: with autogroup scheduling (Linux) that
        would also change how the CPU is shared between it and the other nodes.
        ``stop_signal``: what :meth:`interrupt` sends (SIGINT, as Ctrl-C).
        """
        self.name = name
        self.command = command
        self.log_path = log_path
        self._log = open(log_path, 'w', encoding='utf-8')  # noqa: SIM115 - closed at the stop
        prefix = scheduling.command_prefix() if scheduling else []
        self.process = subprocess.Popen(prefix + command, stdout=self._log,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        env=env, pass_fds=pass_fds,
                                        process_group=0 if own_group else None)
        self.pid = self.process.pid
        self.stop_signal = stop_signal
        self._interrupted = False
        self.killed = False

    def raise_priority(self, scheduling: Scheduling) -> None:
        """Put the running process and its threads at ``scheduling.priority``.

        The policy is SCHED_FIFO, with ``rt_cpu_limit``; every thread the process has now is
        moved, and threads it starts later inherit the priority. If that fails, raise
        GraphError with the tool's message.

        Why after the start rather than at exec: six node processes starting at once at
        SCHED_FIFO on a busy 2-core machine ran their imports at real-time priority; one
        node came up 38 s late (Fast DDS's port lock timed out while a FIFO process held
        the CPU) and one was killed by RLIMIT_RTTIME (docs/realtime.md §3). Start-up needs
        no real-time priority; the control loop does.
        """
        if not scheduling.priority:
            return
        commands = [['chrt', '--fifo', '--all-tasks', '--pid', str(scheduling.priority),
                     str(self.pid)]]
        if scheduling.rt_cpu_limit > 0.0:
            commands.insert(0, ['prlimit', f'--pid={self.pid}',
                                f'--rttime={round(scheduling.rt_cpu_limit * 1e6)}'])
        for command in commands:
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=60,
                                      check=False)
            except (subprocess.SubprocessError, OSError) as err:
                raise GraphError(f'{self.name}: {command[0]} failed: {err}') from None
            if done.returncode != 0:
                reason = (done.stderr.strip().splitlines() or
                          [f'exit code {done.returncode}'])[-1]
                raise GraphError(f'{self.name}: could not set --rt-priority '
                                 f'{scheduling.priority} ({command[0]}: {reason})')

    def poll(self) -> int | None:
        return self.process.poll()

    @property
    def returncode(self) -> int | None:
        return self.process.returncode

    def interrupt(self) -> None:
        """Send the stop signal (once) if the process is still running."""
        if self.process.poll() is None and not self._interrupted:
            self.process.send_signal(self.stop_signal)
            self._interrupted = True

    def stop(self, grace: float) -> int | None:
        """SIGINT (if not sent yet), then SIGKILL after ``grace`` [s]; the exit code."""
        self.interrupt()
        try:
            self.process.wait(timeout=max(grace, 0.0))
        except subprocess.TimeoutExpired:
            self.killed = True
            self.process.kill()
            self.process.wait()
        self._log.close()
        return self.process.returncode

    def cpu_seconds(self) -> float | None:
        """CPU time [s] used so far (user + system, all threads).

        From /proc; None if unavailable (not Linux, or the process has exited).
        """
        try:
            with open(f'/proc/{self.pid}/stat', encoding='ascii') as stream:
                fields = stream.read().rsplit(')', 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
        except (OSError, ValueError, IndexError):
            return None

    def log_tail(self, lines: int = LOG_TAIL_LINES) -> str:
        if not self._log.closed:   # closed once the process was stopped
            self._log.flush()
        try:
            text = self.log_path.read_text(encoding='utf-8', errors='replace')
        except OSError:
            return ''
        return '\n'.join(text.splitlines()[-lines:])


class Probe:
    """A node of this process that looks at the graph and reads /diagnostics."""

    def __init__(self, domain_id: int, namespace: str = '') -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile
        self._rclpy = rclpy
        from rclpy.signals import SignalHandlerOptions
        self.context = rclpy.Context()
        # No rclpy signal handlers: they would shut this context down at a SIGINT or
        # SIGTERM, and the launcher still needs the probe to drain the recorder while it
        # stops the run (runner_base.stop_signals raises in the main thread instead).
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

    def call_start(self, timeout: float):
        """Call /plant/start once; returns the response or None (no answer in time)."""
        if not self.start_client.service_is_ready():
            return None
        future = self.start_client.call_async(self._trigger.Request())
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
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


def viewer_wanted(options) -> bool:
    """Whether the viewer runs.

    ``options.viewer`` if set, else whether anyone will see its topics (a bag is
    recorded or the live view is served).
    """
    if options.viewer is not None:
        return bool(options.viewer)
    return options.record is not None or options.foxglove_port is not None


def live_view_line(bridge: NodeProcess, host: str, port: int | None) -> str:
    """Where the live view is: the URL the bridge printed (with port 0, the port it got)."""
    match = re.search(r'foxglove_bridge: serving (ws://\S+)', bridge.log_tail(200))
    url = match.group(1) if match else f'ws://{host}:{port}'
    return (f'live view: open {url} in Foxglove (Open connection, Foxglove WebSocket; '
            'layout foxglove/wip_live.json)')


#: Lock file of a run directory (fcntl.flock; it holds the pid of the run that took it).
LOCK_FILE = '.run_graph.lock'


def _lock_holder(path: pathlib.Path) -> str:
    """Return the pid holding a flock on ``path``, from /proc/locks (Linux), else 'unknown'."""
    try:
        info = path.stat()
        with open('/proc/locks', encoding='ascii') as stream:
            lines = stream.read().splitlines()
    except OSError:
        return 'unknown'
    wanted = f'{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}:{info.st_ino}'
    for line in lines:
        fields = line.split()
        if 'FLOCK' in fields and wanted in fields:
            return fields[fields.index(wanted) - 1]
    return 'unknown'


def lock_output(path: pathlib.Path, option: str, directory: bool = False) -> int:
    """Take the exclusive lock of one output.

    A run directory is locked through its :data:`LOCK_FILE`; a bag directory
    (``directory``) is locked itself, since it must stay empty for the recorder. Return the
    descriptor, to be held until the run and every process it started have ended (the
    kernel drops the lock then, whatever killed them).

    GraphError (usage) naming the holder's pid if another run holds it: two runs into one
    folder would mix their files.
    """
    if directory:
        target = path
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    else:
        target = path / LOCK_FILE
        fd = os.open(target, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = (os.pread(fd, 32, 0).decode('ascii', 'replace').strip() if not directory
                  else '') or _lock_holder(target)
        os.close(fd)
        raise GraphError(f'{option} {path}: another run (pid {holder}) is writing there; '
                         'refusing to mix two runs in one folder', EXIT_USAGE) from None
    if not directory:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f'{os.getpid()}\n'.encode('ascii'), 0)
    return fd


def prepare_run_directory(out: pathlib.Path, bag: pathlib.Path | None,
                          extra_logs: tuple[str, ...] = ()) -> list[int]:
    """Check, lock and create the outputs of a run.

    Check the outputs of a run (``--out`` directory, ``--record`` bag) before anything is
    written, lock them (:func:`lock_output`: one run per folder), then create ``OUT/logs``
    (with its marker), replacing only the logs of an earlier run of ours (``OUT/logs`` and
    the ``extra_logs`` glob patterns in OUT). Returns the lock descriptors.

    GraphError (usage) naming the option when an output is unusable, would replace what
    this tool did not write, or is another run's; nothing is written then (but the folders
    and the lock file, when another run holds them).
    """
    try:
        check_output_directory(out, '--out')
        if bag is not None:
            check_output_directory(bag, '--record')
    except ValueError as err:
        raise GraphError(str(err), EXIT_USAGE) from err
    if bag is not None and bag.exists() and any(bag.iterdir()):
        raise GraphError(f'--record: {bag} exists and is not empty; refusing to '
                         'overwrite a bag (nothing was written)', EXIT_USAGE)
    logs = out / 'logs'
    if bag is not None and (bag == out or bag == logs or logs in bag.parents):
        raise GraphError(f'--record {bag}: not the run directory or its logs', EXIT_USAGE)
    old_logs = [old for old in [logs, *(p for pattern in extra_logs
                                         for p in sorted(out.glob(pattern)))]
                if old.exists() or old.is_symlink()]
    for old in old_logs:
        foreign = foreign_log_content(old)
        if foreign:
            raise GraphError(
                f'--out {out}: {old} holds {foreign}, which run_graph did not write; '
                'refusing to replace it (move it away or choose another --out)', EXIT_USAGE)
    out.mkdir(parents=True, exist_ok=True)
    locks = [lock_output(out, '--out')]
    try:
        if bag is not None:
            bag.mkdir(parents=True, exist_ok=True)   # empty: the recorder takes it
            locks.append(lock_output(bag, '--record', directory=True))
            if any(bag.iterdir()):  # written by the run that held it a moment ago
                raise GraphError(f'--record: {bag} exists and is not empty; refusing to '
                                 'overwrite a bag (nothing was written)', EXIT_USAGE)
    except BaseException:
        for fd in locks:
            os.close(fd)
        raise
    for old in old_logs:  # Logs of an earlier run_graph run (checked above).
        shutil.rmtree(old)
    (logs / 'ros').mkdir(parents=True)
    (logs / LOGS_MARKER).write_text('run_graph writes this directory and replaces it on the '
                                    'next run into the same --out\n', encoding='utf-8')
    return locks


def foreign_log_content(directory: pathlib.Path) -> str:
    """'' if ``directory`` is a log directory run_graph wrote, else what is foreign in it.

    run_graph's own: a directory with its marker file whose entries are the marker, the
    ``ros`` folder and ``<node>.log`` files.
    """
    if directory.is_symlink():
        return 'a symbolic link'
    if not directory.is_dir():
        return 'a file'
    if not any(directory.iterdir()):
        return ''  # Empty: nothing to lose.
    if not (directory / LOGS_MARKER).is_file():
        return 'content without the run_graph marker'
    ours = {LOGS_MARKER, 'ros'} | {f'{name}.log' for name in EXECUTABLES}
    foreign = sorted(p.name for p in directory.iterdir() if p.name not in ours)
    return ', '.join(foreign[:3])


FOXGLOVE_PORT = 8765  # Foxglove's default WebSocket port


def foxglove_port(text: str) -> int:
    """Parse --foxglove (an argparse type): a TCP port, 0..65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a port number') from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f'{port} is not in 0..65535')
    return port


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """--foxglove [PORT], --foxglove-host, --viewer/--no-viewer (simulation and hardware mode)."""
    parser.add_argument('--foxglove', nargs='?', type=foxglove_port, const=FOXGLOVE_PORT,
                        default=None, metavar='PORT',
                        help="serve the graph's topics live over the Foxglove WebSocket "
                        f'protocol on PORT (default {FOXGLOVE_PORT}; 0 = any free port), '
                        'with the e-stop services /wip/estop/{engage,release,reset}')
    parser.add_argument('--foxglove-host', default='127.0.0.1', metavar='ADDRESS',
                        help='address of the Foxglove server (default 127.0.0.1: this '
                        'machine only; 0.0.0.0 serves the network)')
    parser.add_argument('--viewer', action=argparse.BooleanOptionalAction, default=None,
                        help='the viewer node (Odometry, Path, markers for 3-D viewers); '
                        'default: on with --record or --foxglove, else off')
