"""run_graph's watch loop: how the end of the plant's process is taken."""

import pytest

pytest.importorskip('rclpy')

from wip_bringup.graph_runner import GraphOptions, GraphRunner  # noqa: E402
from wip_bringup.launcher import GraphError  # noqa: E402
from wip_sim.core.scenario import Scenario  # noqa: E402

pytestmark = pytest.mark.ros


class Process:
    """A node process whose poll() answers from a list (its last answer then on)."""

    def __init__(self, *answers):
        self.answers, self.pid, self.log_path = list(answers), 4242, 'node.log'

    def poll(self):
        return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]

    def log_tail(self):
        return ''


class Probe:
    def spin(self, _seconds):
        pass

    def status_values(self, _name):
        return None


def test_a_plant_that_ends_between_two_polls_ends_the_run_with_its_code(tmp_path):
    # The plant's exit (code 0 at the scenario's end) came after the loop's poll of the
    # plant and before its check of every node: that check must leave the plant to the
    # next poll, not call its normal end a node that exited (seen at load 20).
    runner = GraphRunner(GraphOptions(out=str(tmp_path / 'run'), quiet=True))
    runner.scenario, runner.probe = Scenario(), Probe()
    runner.processes = {'plant': Process(None, 0), 'eso': Process(None)}
    assert runner.watch() == 0


def test_another_node_that_exits_while_the_plant_runs_ends_the_run_naming_it(tmp_path):
    runner = GraphRunner(GraphOptions(out=str(tmp_path / 'run'), quiet=True))
    runner.scenario, runner.probe = Scenario(), Probe()
    runner.processes = {'plant': Process(None), 'eso': Process(None, 1)}
    runner.node_died = lambda name: None
    with pytest.raises(GraphError, match="node 'eso' .* exited with code 1"):
        runner.watch()
