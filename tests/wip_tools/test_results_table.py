"""docs/paper.md's results table is what the paper scenario gives (wip_tools.results_table).

Both designs are run in-process (about 40 s on the 2-core machine, hence slow) and the
table they make must be, character for character, the text between the page's markers:
every figure matches to the precision printed.
"""

import pathlib

import pytest

from wip_tools import results_table

PAGE = pathlib.Path(__file__).resolve().parents[2] / 'docs' / 'paper.md'


def test_the_page_holds_one_generated_table():
    text = PAGE.read_text(encoding='utf-8')
    assert text.count(results_table.BEGIN) == 1 and text.count(results_table.END) == 1
    table = results_table.documented(text)
    assert table is not None and table.count('\n') == len(results_table.ROWS) + 1


@pytest.mark.slow
def test_the_results_table_matches_a_run_of_both_designs(capsys):
    assert results_table.main(['--check', str(PAGE)]) == 0, capsys.readouterr().err


def test_a_changed_figure_is_found(monkeypatch, tmp_path, capsys):
    # The check fails when one printed figure differs (runs replaced by the documented
    # ones, one altered: no simulation).
    text = PAGE.read_text(encoding='utf-8')
    monkeypatch.setattr(results_table, 'table', lambda _results: results_table.documented(
        text).replace('0 failures in 989 ticks', '0 failures in 990 ticks'))
    monkeypatch.setattr(results_table, 'run_design', lambda design: {})
    assert results_table.main(['--check', str(PAGE)]) == 1
    assert 'differs' in capsys.readouterr().err
    missing = tmp_path / 'page.md'
    missing.write_text('no markers\n')
    assert results_table.main(['--check', str(missing)]) == 2


def test_the_readme_paper_design_scenario_is_the_tables_paper_column():
    # scripts/demo --scenario scenarios/paper_design.yaml runs what the table's
    # `design: paper` column reports: the same scenario but for its name.
    import dataclasses
    from wip_sim.core.scenario import load_scenario, scenario_from_mapping
    path = pathlib.Path(__file__).resolve().parents[2] / 'scenarios' / 'paper_design.yaml'
    from_file = load_scenario(path)
    assert from_file.design == 'paper'
    assert dataclasses.replace(from_file, name='', description='') == dataclasses.replace(
        scenario_from_mapping({'design': 'paper'}), name='', description='')
