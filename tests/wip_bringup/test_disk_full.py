"""A full disk is a stated outcome of run_graph.

On a 1 MiB tmpfs as --out and --record the recorder stops in time and finishes the bag with what
fit (bag_info OK), the run says "disk full at t = ..." and exits 4, and no side file is left empty.

Needs root (mount); skipped with the reason otherwise.
"""

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip('rclpy')

from wip_bag.bag_info import main as bag_info_main  # noqa: E402
from wip_bringup.launcher import EXIT_DISK_FULL  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture
def small_disk(tmp_path):
    disk = tmp_path / 'disk'
    disk.mkdir()
    done = subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=1m', 'tmpfs', str(disk)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f'cannot mount a tmpfs here: {done.stderr.strip() or done.returncode}')
    try:
        yield disk
    finally:
        subprocess.run(['umount', '-l', str(disk)], check=False)


def test_a_full_disk_stops_the_run_with_the_bag_finished_and_says_so(small_disk, capsys):
    run, bag = small_disk / 'run', small_disk / 'bag'
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()))
    # 60 s of the paper scenario record far more than 1 MiB: the disk fills up mid-run.
    done = subprocess.run([sys.executable, '-m', 'wip_bringup.graph', '--duration', '60',
                           '--record', str(bag), '--out', str(run), '--quiet'],
                          capture_output=True, text=True, timeout=600, env=env, check=False)
    assert done.returncode == EXIT_DISK_FULL, done.stdout + done.stderr
    first = done.stdout.splitlines()[0]
    assert first.startswith('FAILED: disk full at t = '), done.stdout
    assert 'Traceback' not in done.stderr
    assert bag_info_main([str(bag)]) == 0, capsys.readouterr().out
    for path in [*run.iterdir(), *bag.iterdir()]:   # no empty side file
        if path.is_file():
            assert path.stat().st_size > 0, path
    # The recorder keeps room for the run's own files (RUN_FILES_MARGIN): run.json is
    # written whole, with the reason.
    summary = json.loads((run / 'run.json').read_text(encoding='utf-8'))
    assert summary['exit_code'] == EXIT_DISK_FULL
    assert summary['message'].startswith('disk full')
    # bag_repair into the full disk names where it failed and the way out, in one line. The
    # recorder stops with a margin free (it may hold a copy of the bag): fill it first.
    filler = os.open(small_disk / 'filler', os.O_WRONLY | os.O_CREAT)
    try:
        while os.write(filler, b'\0' * 4096):
            pass
    except OSError:
        pass
    finally:
        os.close(filler)
    from wip_bag.bag_repair import main as bag_repair_main
    capsys.readouterr()
    assert bag_repair_main([str(bag), '--out', str(small_disk / 'copy')]) == EXIT_DISK_FULL
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(small_disk / 'copy') in err[0] and '--out' in err[0], err
    assert not (small_disk / 'copy').exists()
