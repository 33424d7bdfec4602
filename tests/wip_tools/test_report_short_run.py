"""A claim whose time window is longer than the run is "not tested (run too short)".

In the report it is neither passed nor failed; run_graph's hint to make the report is
shell-quoted.
"""

import json
import shlex

from wip_sim.core.scenario import load_scenario
from wip_tools import simulate
from wip_tools.analysis.report_page import claims, NOT_TESTED


def verdicts(metrics, scenario):
    return {quantity: verdict for quantity, _, _, verdict in claims(metrics, scenario)}


def test_a_window_longer_than_the_run_is_not_tested(tmp_path, monkeypatch, capsys):
    path = tmp_path / 'short.yaml'
    path.write_text('duration: 5\n', encoding='utf-8')
    out = tmp_path / 'out'
    assert simulate.main(['--scenario', str(path), '--out', str(out), '--quiet',
                          '--no-figures']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    scenario = load_scenario(path)
    short = verdicts(metrics, scenario)
    assert short['tracking error afterwards (t ≥ 10 s)'] == NOT_TESTED
    converged = metrics['convergence_time_s']
    assert short['initial errors rejected (position error ≤ 0.1 m)'] == (
        'yes' if converged is not None and converged <= 8.0 else NOT_TESTED)
    # scripts/report prints the same verdicts after its summary.
    from wip_tools import report
    monkeypatch.setattr(report, 'report', lambda *args, **kwargs: metrics)
    monkeypatch.setattr(report, 'scenario_for', lambda bag, path: (scenario, 'test'))
    assert report.main(['BAG', '--out', str(tmp_path / 'r')]) == 0
    printed = capsys.readouterr().out
    assert 'tracking error afterwards (t ≥ 10 s) [fluctuates in a small range]: ' \
           f'{NOT_TESTED}' in printed
    # The same numbers from a run that reached the windows are judged.
    long = verdicts(dict(metrics, duration_s=90.0, convergence_time_s=None), scenario)
    assert long['initial errors rejected (position error ≤ 0.1 m)'].startswith('no')
    assert long['tracking error afterwards (t ≥ 10 s)'] != NOT_TESTED


def test_the_report_hint_after_a_run_is_shell_quoted(tmp_path):
    from wip_bringup.graph import format_result, GraphResult
    bag = tmp_path / 'my runs' / 'bag'
    text = format_result(GraphResult(0, 'the scenario ran to its end', tmp_path, bag, 7))
    (line,) = [line for line in text.splitlines() if line.startswith('bag:')]
    command = line.split('report: ', 1)[1]
    assert shlex.split(command) == ['scripts/report', str(bag), '--out', 'DIR']
