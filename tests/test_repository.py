"""The repository stands on its own: nothing in it cites a file outside it."""

import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
#: How an outside document used to be cited (the design notes live in docs/ now).
OUTSIDE = re.compile(r'shared/spec|\.\./shared|\bthe spec\b|\bthe brief\b', re.IGNORECASE)


def tracked_text_files():
    try:
        listed = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True,
                                text=True, check=True, timeout=30).stdout.split()
    except (OSError, subprocess.SubprocessError):
        pytest.skip('not a git checkout')
    for name in listed:
        path = ROOT / name
        if path.suffix in {'.png', '.svg', '.mcap', '.npz'} or not path.is_file():
            continue
        try:
            yield name, path.read_text(encoding='utf-8')
        except UnicodeDecodeError:
            continue


def test_no_file_cites_a_document_outside_the_repository():
    this = pathlib.Path(__file__).relative_to(ROOT).as_posix()
    found = [f'{name}:{n}: {line.strip()[:80]}' for name, text in tracked_text_files()
             if name != this
             for n, line in enumerate(text.splitlines(), 1) if OUTSIDE.search(line)]
    assert not found, '\n'.join(found)


def test_the_design_notes_cited_by_the_code_exist():
    cited = {m.group(1) for _, text in tracked_text_files()
             for m in re.finditer(r'\bdocs/([a-z0-9_-]+\.md)', text)}
    assert cited, 'the code cites its design notes in docs/'
    missing = sorted(c for c in cited if not (ROOT / 'docs' / c).is_file())
    assert not missing, missing


#: The last commit before the rule of docs/contributing.md (subjects of at most 72
#: characters); every commit after it follows the rule.
RULE_SINCE = 'b7cc102107b38ea9a2b535553a2b4ef2aee63f19'


def test_commit_subjects_since_the_rule_are_at_most_72_characters():
    try:
        subprocess.run(['git', 'cat-file', '-e', f'{RULE_SINCE}^{{commit}}'], cwd=ROOT,
                       capture_output=True, check=True, timeout=30)
        log = subprocess.run(['git', 'log', '--format=%h %s', f'{RULE_SINCE}..HEAD'],
                             cwd=ROOT, capture_output=True, text=True, check=True,
                             timeout=30).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        pytest.skip('not a git checkout with the history (a shallow clone?)')
    long = [line for line in log if len(line.split(' ', 1)[1]) > 72]
    assert not long, f'commit subjects over 72 characters: {long}'
