"""One run per output folder.

run_graph locks ``--out`` (its lock file) and the bag directory before it writes there; a second
run into either is refused at once (exit 2), with one line naming the holder's pid, and writes
nothing.
"""

import os
import subprocess
import sys
import textwrap

import pytest

from wip_bringup.launcher import EXIT_USAGE, GraphError
from wip_bringup.output_lock import LOCK_FILE, lock_output, prepare_run_directory


def _release(fds):
    for fd in fds:
        os.close(fd)


def test_a_second_run_into_a_locked_run_directory_is_refused_naming_the_pid(tmp_path):
    first = prepare_run_directory(tmp_path / 'run', tmp_path / 'bag')
    try:
        with pytest.raises(GraphError) as refused:
            prepare_run_directory(tmp_path / 'run', None)
        assert refused.value.exit_code == EXIT_USAGE
        assert f'pid {os.getpid()}' in str(refused.value)
        assert '\n' not in str(refused.value)
        # Another run directory, the same bag: refused too, the bag left empty.
        with pytest.raises(GraphError) as refused:
            prepare_run_directory(tmp_path / 'other', tmp_path / 'bag')
        assert refused.value.exit_code == EXIT_USAGE
        assert '--record' in str(refused.value) and f'pid {os.getpid()}' in str(refused.value)
        assert list((tmp_path / 'bag').iterdir()) == []
        assert not (tmp_path / 'other' / 'logs').exists()
    finally:
        _release(first)
    # Released: the next run may use both.
    _release(prepare_run_directory(tmp_path / 'run', tmp_path / 'bag'))


def _lock_holder(folder):
    """Another process holding ``folder``'s output lock (it has it once this returns)."""
    holder = subprocess.Popen(
        [sys.executable, '-c', textwrap.dedent(f"""
            import pathlib, time
            from wip_bringup.output_lock import lock_output
            lock_output(pathlib.Path({str(folder)!r}), '--out')
            print('locked', flush=True)
            time.sleep(600)
        """)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == 'locked'
    return holder


def test_the_lock_is_dropped_when_its_holder_dies(tmp_path):
    holder = _lock_holder(tmp_path)
    try:
        with pytest.raises(GraphError, match=f'pid {holder.pid}'):
            lock_output(tmp_path, '--out')
    finally:
        holder.kill()
        holder.wait()
    os.close(lock_output(tmp_path, '--out'))
    assert (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())


@pytest.mark.ros
def test_run_graph_into_a_folder_another_run_holds_exits_2_at_once(tmp_path):
    pytest.importorskip('rclpy')
    out = tmp_path / 'run'
    out.mkdir()
    holder = _lock_holder(out)
    try:
        done = subprocess.run([sys.executable, '-m', 'wip_bringup.graph', '--out', str(out),
                               '--duration', '1'],
                              capture_output=True, text=True, timeout=300, check=False)
    finally:
        holder.kill()
        holder.wait()
    assert done.returncode == EXIT_USAGE, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f'pid {holder.pid}' in lines[0], done.stderr
    assert lines[0].startswith('run_graph: error: --out ')
    assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]  # nothing of its own
