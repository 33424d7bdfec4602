"""No docstring repeats its summary line in its body.

A docstring's first line is its summary; a body that opens by saying it again ("Return the
plant of X. / The plant of X (called by ...)") makes the reader read it twice. Found from
the source with ast: the body's first words equal the summary's words (case, punctuation
and markup aside), optionally without the summary's first word (its verb, "Return") and
after up to two words of the body ("The", "A ...").
"""

import ast
import pathlib
import re

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
#: Where the docstrings are: the packages' sources (not their build trees) and the tests.
ROOTS = (REPO_ROOT / 'ros_ws' / 'src', REPO_ROOT / 'tests')
#: Summaries shorter than this many words are not matched (too common to be a repeat).
MIN_WORDS = 3
#: Words of the body that may come before the repeated summary.
LEAD_WORDS = 2

#: Docstrings that may repeat their summary, each an exception with a reason given here, as
#: (path from the repository root, qualified name); '<module>' is the module docstring.
ALLOWED: set[tuple[str, str]] = set()


def words(text):
    """Lower-case words of ``text``, without punctuation and reST markup."""
    return re.sub(r'[^\w\s]', ' ', re.sub(r'[`*:]', '', text.lower())).split()


def repeats_summary(docstring):
    """Return True if the body of ``docstring`` opens with its summary line again."""
    summary, _, body = docstring.strip().partition('\n\n')
    summary, body = words(summary), words(body)
    for wanted in (summary, summary[1:]):
        if len(wanted) >= MIN_WORDS and any(
                body[lead:lead + len(wanted)] == wanted for lead in range(LEAD_WORDS + 1)):
            return True
    return False


def documented(tree):
    """Yield (qualified name, docstring) of a module, its classes and functions."""
    yield '<module>', ast.get_docstring(tree)

    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                yield name, ast.get_docstring(child)
                yield from walk(child, name + '.')

    yield from walk(tree, '')


def source_files():
    for root in ROOTS:
        for path in sorted(root.rglob('*.py')):
            relative = path.relative_to(REPO_ROOT)
            # ros_ws/src/<package>/... only: never a build or install tree.
            if 'build' not in relative.parts and 'install' not in relative.parts:
                yield relative


def repeated():
    for relative in source_files():
        tree = ast.parse((REPO_ROOT / relative).read_text(encoding='utf-8'))
        for name, docstring in documented(tree):
            if docstring and repeats_summary(docstring):
                yield relative.as_posix(), name


def test_no_docstring_repeats_its_summary():
    found = [item for item in repeated() if item not in ALLOWED]
    assert not found, ('docstrings whose body repeats the summary line (say it once): '
                       + ', '.join(f'{path}: {name}' for path, name in found))


def test_the_check_finds_a_repeat_and_passes_a_plain_docstring():
    # The pattern this test exists for, and two docstrings that only share words.
    assert repeats_summary('Return the plant of ``plant: mujoco``.\n\n'
                           'The plant of ``plant: mujoco`` (called by scenario_plant).')
    assert repeats_summary('Wheel torque [N m] at which the wheels slip.\n\n'
                           'Wheel torque [N m] at which the wheels slip from rest.')
    assert not repeats_summary('Return the plant of a scenario.\n\n'
                               'The model decides which plant: an equation or an engine.')
    assert not repeats_summary('One line only.')
