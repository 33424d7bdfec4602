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
        text).replace('max 6.07 N·m', 'max 6.08 N·m'))
    monkeypatch.setattr(results_table, 'run_design', lambda design: {})
    assert results_table.main(['--check', str(PAGE)]) == 1
    assert 'differs' in capsys.readouterr().err
    missing = tmp_path / 'page.md'
    missing.write_text('no markers\n')
    assert results_table.main(['--check', str(missing)]) == 2
