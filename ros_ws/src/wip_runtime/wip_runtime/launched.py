"""A node started by a wip launcher ends with it.

run_graph, hardware mode and the stand-in harness start each node as a child process
and set ``WIP_LAUNCHER_PID`` in its environment. If the launcher dies without stopping
its children (SIGKILL, a crash, a timeout of the shell around it), a controller left
running on its own would keep commanding the robot, and at real-time priority it can
take every CPU from the rest of the machine (seen here: two orphaned controllers at
SCHED_FIFO starved a 2-core machine for minutes). :func:`end_with_launcher` asks the
kernel (prctl PR_SET_PDEATHSIG, Linux) for SIGINT when the launcher goes: the node
stops as on Ctrl-C (the mixer's last command is zero torque).
"""

from __future__ import annotations

import ctypes
import os
import signal

#: Environment variable holding the launcher's pid.
LAUNCHER_PID_VARIABLE = 'WIP_LAUNCHER_PID'
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def end_with_launcher(environ=os.environ) -> bool:
    """Arrange SIGINT for this process when its launcher ends; True if arranged.

    Nothing happens without ``WIP_LAUNCHER_PID``, or when this process is not the
    launcher's child (the variable was inherited by a grandchild: ``ros2 run`` from a
    shell that a launcher started). SystemExit (with the reason) if the launcher is
    already gone: call it first thing in ``main``.
    """
    value = environ.get(LAUNCHER_PID_VARIABLE, '')
    try:
        launcher = int(value)
    except ValueError:
        return False
    if launcher <= 1:
        return False
    if os.getppid() != launcher:
        if not _alive(launcher):
            raise SystemExit(f'launcher (pid {launcher}) is gone: not starting')
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGINT), 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):   # not Linux
        return False
    if os.getppid() != launcher:          # the launcher died in between
        raise SystemExit(f'launcher (pid {launcher}) is gone: not starting')
    return True


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs.

    A zombie does not: a launcher killed during this node's start-up stays a zombie until its own
    parent reaps it, and signal 0 still reaches it (a node that took it for alive would believe it
    was a grandchild and run on).
    """
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii', errors='replace') as stream:
            return stream.read().rsplit(')', 1)[1].split()[0] not in ('Z', 'X')
    except FileNotFoundError:
        return False
    except (OSError, IndexError):
        pass                              # no procfs: signal 0
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
