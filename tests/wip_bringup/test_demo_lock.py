"""``scripts/demo`` (the front door): one demo per output folder.

Two demos into one folder: the second is refused (exit 2) before it moves or removes
anything, and the first finishes with its outputs intact.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import time

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DEMO = pathlib.Path(__file__).resolve().parents[2] / 'scripts' / 'demo'


def test_a_second_demo_into_the_same_folder_is_refused_and_the_first_is_intact(tmp_path):
    out = tmp_path / 'demo'
    env = dict(os.environ, WIP_DEMO_OUT=str(out))
    first = subprocess.Popen([str(DEMO), '--duration', '2'], env=env, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        # The first holds the lock once its pid is in the lock file and its run has begun.
        deadline = time.monotonic() + 120
        lock = out / '.run_graph.lock'
        while time.monotonic() < deadline and not (
                lock.exists() and lock.read_text().strip() == str(first.pid)
                and (out / 'run' / 'logs').exists()):
            assert first.poll() is None, first.communicate()
            time.sleep(0.05)
        second = subprocess.run([str(DEMO), '--duration', '2'], env=env, text=True,
                                capture_output=True, timeout=120)
        assert second.returncode == 2, second.stderr
        assert f'another run (pid {first.pid}) is writing there' in second.stderr
        assert 'Traceback' not in second.stderr
        stdout, stderr = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == ['.run_graph.lock', 'bag', 'report', 'run']
    assert (out / 'bag' / 'metadata.yaml').exists() and (out / 'bag' / 'scenario.yaml').exists()
    assert (out / 'report' / 'metrics.json').exists()
    # Run again: the lock was released with the first's processes, and it replaces them.
    again = subprocess.run([str(DEMO), '--duration', '1'], env=env, text=True,
                           capture_output=True, timeout=600)
    assert again.returncode == 0, again.stderr
