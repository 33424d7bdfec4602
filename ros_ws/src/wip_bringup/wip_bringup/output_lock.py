"""The outputs of a run: checked before anything is written, and locked (one run per folder)."""

from __future__ import annotations

import fcntl
import os
import pathlib
import shutil

from wip_runtime.cli import check_output_directory

from .launcher import EXECUTABLES, EXIT_USAGE, GraphError

#: Marker of a log directory written by run_graph: only such a directory is replaced.
LOGS_MARKER = '.written-by-run_graph'

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
