"""run_graph's end-of-run check of the recorder's counts (GraphRunner.drain_recorder).

A scripted probe plays the recorder's /diagnostics: a recorder that stops short of what
the plant's ticks imply makes the run's result name each short topic (received/expected),
even with --quiet; one that catches up leaves it empty.
"""

from __future__ import annotations

import pytest

pytest.importorskip('rclpy')
from wip_bringup import graph_recording  # noqa: E402
from wip_bringup.graph_runner import GraphOptions, GraphRunner  # noqa: E402

EXPECTED = {'/imu/data': 2000, '/wip/ground_truth': 2001}


class ScriptedProbe:
    """The recorder's 'received /topic' values, one dict per spin, the last one repeated."""

    def __init__(self, script):
        self.script, self.spins = list(script), 0

    def spin(self, timeout: float) -> None:
        self.spins += 1

    def status_values(self, name: str):
        counts = self.script[min(self.spins, len(self.script)) - 1]
        return name, {f'received {topic}': str(n) for topic, n in counts.items()}


class LiveProcess:
    def poll(self):
        return None


class CheckedRunner(GraphRunner):
    def expected_recorded(self) -> dict[str, int]:
        return dict(EXPECTED)


def drained(tmp_path, monkeypatch, script) -> CheckedRunner:
    monkeypatch.setattr(graph_recording, 'DRAIN_STALL', 0.0)
    runner = CheckedRunner(GraphOptions(out=str(tmp_path / 'run'), quiet=True))
    runner.processes = {'recorder': LiveProcess()}
    runner.probe = ScriptedProbe(script)
    runner.drain_recorder()
    return runner


def test_a_recorder_that_stops_short_is_named_topic_by_topic(tmp_path, monkeypatch):
    runner = drained(tmp_path, monkeypatch, [{'/imu/data': 1, '/wip/ground_truth': 1},
                                             {'/imu/data': 2000, '/wip/ground_truth': 1}])
    assert runner.recorder_shortfall == {'/wip/ground_truth': '1/2001'}


def test_a_recorder_that_catches_up_leaves_no_shortfall(tmp_path, monkeypatch):
    runner = drained(tmp_path, monkeypatch, [{'/imu/data': 10, '/wip/ground_truth': 10},
                                             {'/imu/data': 2000, '/wip/ground_truth': 2001}])
    assert runner.recorder_shortfall == {}
    assert runner.probe.spins == 2
