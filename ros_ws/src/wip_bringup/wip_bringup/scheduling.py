"""Real-time scheduling of the controller processes: SCHED_FIFO, CPU affinity and PM QoS.

Applied to the processes :mod:`wip_bringup.processes` starts (``--rt-priority``,
``--cpu-affinity``, ``--cpu-latency``).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import struct
import subprocess

from .launcher import EXIT_USAGE, GraphError


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
        (:meth:`wip_bringup.processes.NodeProcess.raise_priority`); until then it gets its
        CPUs and the normal policy.
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
