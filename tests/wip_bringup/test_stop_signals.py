"""Every way a run_graph run ends finalises its bag.

SIGINT, SIGTERM and SIGHUP to run_graph, and SIGKILL of run_graph (its nodes then get SIGINT from
the kernel, once or more, and the recorder drains and finishes on its own).

Each test runs ``python -m wip_bringup.graph`` (what ``scripts/run_graph`` execs) on a minute
of the paper scenario in lockstep with ``--record``, sends the signal mid-run (or
right after the plant started), and checks that ``bag_info`` says OK and that the bag
holds the ground truth up to the stop: its last stamp is the plant's last tick
(``plant_stats.json``), one control period allowed for a sample published while the stop
was under way. No wall-clock thresholds: every wait polls a condition with a generous
timeout.
"""

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip('rclpy')

from wip_bag.bag_info import main as bag_info_main  # noqa: E402
from wip_bag.bag_reader import read_bag  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402

# serial: each stop is judged by the nodes' clean exits within their grace periods, which
# the other tests on a second worker once made them miss (docs/testing.md).
pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.serial]

TIMEOUT = 240.0  # [s] for any one step on a loaded 2-core machine
# [s] simulated. The signal follows 0.5 s of it; the fastest recorded layout runs about
# 7x real time, so 60 s still take 8 s or more of wall time after the signal is due: a
# stop after 0.5 s is mid-run on any machine (and costs no more: the run is stopped).
DURATION = 60.0
CONTROL_PERIOD = 0.005  # [s] of the paper scenario (200 Hz)


def _wait_for(predicate, what: str, timeout: float = TIMEOUT):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.1)


def _sim_progress(err_path: pathlib.Path) -> float:
    """Return the latest simulated time run_graph's progress lines show (-1 before the start)."""
    latest = -1.0
    text = err_path.read_text(encoding='utf-8', errors='replace')
    if 'plant started' in text:
        latest = 0.0
    for line in text.splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == 'sim':
            try:
                latest = max(latest, float(words[1]))
            except ValueError:
                pass
    return latest


def _processes_of(run: pathlib.Path) -> list[int]:
    """Pids of the node processes of the run in ``run`` (their params file is in it)."""
    needle = str(run / 'params.yaml').encode()
    pids = []
    for entry in pathlib.Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                if needle in (entry / 'cmdline').read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


def _last_ground_truth_stamp(bag: pathlib.Path) -> float:
    stamps = [m.message.header.stamp.sec + 1e-9 * m.message.header.stamp.nanosec
              for m in read_bag(str(bag), topics=['/wip/ground_truth'])]
    assert stamps, 'no ground truth in the bag'
    return max(stamps)


@pytest.mark.parametrize('number, when', [
    (signal.SIGINT, 'mid-run'),
    (signal.SIGTERM, 'mid-run'),
    (signal.SIGHUP, 'mid-run'),
    (signal.SIGKILL, 'mid-run'),
    (signal.SIGTERM, 'at the start'),
    (signal.SIGINT, 'to the group'),
], ids=['SIGINT', 'SIGTERM', 'SIGHUP', 'SIGKILL', 'SIGTERM-at-start', 'Ctrl-C'])
def test_a_stopped_run_finishes_its_bag(tmp_path, capsys, number, when):
    run, bag = tmp_path / 'run', tmp_path / 'bag'
    err_path = tmp_path / 'stderr.txt'
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()))
    with open(err_path, 'w', encoding='utf-8') as err:
        process = subprocess.Popen(
            [sys.executable, '-m', 'wip_bringup.graph', '--duration', str(DURATION),
             '--record', str(bag), '--out', str(run), '--no-viewer'],
            stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL, env=env, text=True,
            start_new_session=True)   # a group of its own, as a terminal's foreground job
        try:
            at_least = 0.0 if when == 'at the start' else 0.5
            _wait_for(lambda: _sim_progress(err_path) >= at_least or process.poll() is not None,
                      f'simulated time {at_least} s')
            assert process.poll() is None, err_path.read_text()
            if when == 'to the group':   # a Ctrl-C in a terminal: run_graph and its nodes
                os.killpg(process.pid, number)
            else:
                process.send_signal(number)
            out, _ = process.communicate(timeout=TIMEOUT)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    stderr = err_path.read_text(encoding='utf-8', errors='replace')
    name = signal.Signals(number).name
    if number == signal.SIGKILL:
        assert process.returncode == -signal.SIGKILL
        # The nodes stop on their own (parent-death signal); the recorder closes the bag.
        _wait_for(lambda: not _processes_of(run), 'the orphaned nodes to end')
        assert not (run / 'run.json').exists()
        # The recorder's drain ended because nothing more came: not at the kernel's
        # repeated death signal (one per thread of the dying launcher that held it), which
        # once cut it short before the plant's last ticks (wip_bag.recorder_stop.drain).
        log = (run / 'logs' / 'recorder.log').read_text(encoding='utf-8', errors='replace')
        assert 'ended by nothing for 0.5 s' in log, log[-1500:]
    else:
        assert process.returncode == 128 + number, stderr
        summary = json.loads((run / 'run.json').read_text(encoding='utf-8'))
        assert summary['exit_code'] == 128 + number
        assert summary['message'].startswith(f'stopped by {name}')
        assert out.splitlines()[0].startswith(f'STOPPED: stopped by {name}'), out
        assert (bag / 'scenario.yaml').read_text(encoding='utf-8').strip()
        assert 'Traceback' not in stderr
    assert bag_info_main([str(bag)]) == 0, capsys.readouterr().out
    last = _last_ground_truth_stamp(bag)
    try:
        stats = json.loads((run / 'plant_stats.json').read_text(encoding='utf-8'))
    except (OSError, ValueError):
        # Only when the plant got a SIGINT of its own (the kernel's after SIGKILL, the
        # terminal's at Ctrl-C): rclpy's late KeyboardInterrupt can cut its write of the
        # stats (wip_control.nodes.common's run_simulator_node; run_graph itself stops the
        # plant with SIGTERM, and removes a stats file left empty). The bag's own /clock
        # then says where the plant was: the ground truth must reach its last tick.
        assert number == signal.SIGKILL or when == 'to the group'
        clocks = [m.message.clock.sec + 1e-9 * m.message.clock.nanosec
                  for m in read_bag(str(bag), topics=['/clock'])]
        stats = {'ticks': round(max(clocks) / CONTROL_PERIOD), 'sim_time_s': max(clocks)}
    last_tick = stats['ticks'] * CONTROL_PERIOD
    assert stats['sim_time_s'] < DURATION, 'the run ended before the signal'
    assert last_tick - CONTROL_PERIOD - 1e-9 <= last <= last_tick + 1e-9, (last, stats)
