"""Commands started all at once and collected: the tests that run many front doors.

Starting every command before waiting for the first overlaps their start-ups (Python and
rclpy imports), which on 2 cores is most of their time. No ROS import.
"""

from __future__ import annotations

import pathlib
import subprocess
from typing import Callable, Mapping


def run_at_once(runs: Mapping[str, list[str]], folder: Callable[[str], pathlib.Path],
                timeout: float, merge: bool = False) -> dict[str, tuple]:
    """Run every command of ``runs`` (key -> argv) at once, each in ``folder(key)``.

    key -> (status, stdout, stderr, the names in its folder after); with ``merge`` stderr goes
    into stdout (and the stderr slot is ''). A command still running after ``timeout`` [s] is
    killed and gives what it wrote, with its (negative) status; none outlives the call.
    """
    folders, processes, results = {}, {}, {}
    try:
        for key, command in runs.items():
            folders[key] = folder(key)
            processes[key] = subprocess.Popen(
                command, cwd=folders[key], text=True, stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT if merge else subprocess.PIPE,
                stdin=subprocess.DEVNULL)
        for key, process in processes.items():
            try:
                out, err = process.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                process.kill()
                out, err = process.communicate()
            results[key] = (process.returncode, out, err or '',
                            sorted(p.name for p in folders[key].iterdir()))
    finally:
        for process in processes.values():
            if process.poll() is None:
                process.kill()
                process.communicate()
    return results
