"""The node processes of a run: what ``ros2 run`` would start, their environment and domain.

:class:`NodeProcess` is one node's process, its log file and how to stop it.
"""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess

from wip_runtime.dds_profile import use_node_profile
from wip_runtime.launched import LAUNCHER_PID_VARIABLE

from .launcher import EXIT_USAGE, GraphError
from .private_domain import reserve_private_domain
from .ros_env import ROS_DEFAULTS_VARIABLE
from .scheduling import Scheduling
from .thread_usage import stat_name_and_cpu

LOG_TAIL_LINES = 15


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
    use_node_profile(env)
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
                return stat_name_and_cpu(stream.read())[1]
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
