"""The documentation holds together: links resolve, and each page opens with its reference.

Rules of docs/contributing.md ("Documentation"):

- every relative link of README.md and docs/ (``[text](path)``, ``[text](path#anchor)``,
  ``[text](#anchor)``) names a file of the repository, and its anchor a heading of that
  file as GitHub slugs it;
- a reference page (docs/*.md; not docs/decisions/ nor docs/history/) opens with its
  reference: no heading of it names history (a date, "history", "what changed", "what was
  cut", "session", "issue", "before → after"), and its first section (the first ``##``
  heading) is not a measurement or a rationale ("measured", "results", "why", "not done",
  "limits", "design notes"), nor is its title;
- every reference and history page is listed in docs/index.md.
"""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCS = ROOT / 'docs'
#: Pages rewritten by their owners in the same pass; they follow the rule once that lands.
NOT_YET_REFERENCE_FIRST: set[str] = set()
LINK = re.compile(r'(?<!!)\[[^\]]*\]\(([^)\s]+)\)')
HISTORY = re.compile(r'\b20\d\d-\d\d-\d\d\b|history|what changed|what was cut|session|'
                     r'\bissue\b|before\s*(→|->)\s*after', re.IGNORECASE)
NOT_REFERENCE = re.compile(r'measured|results|\bwhy\b|not done|limits|design notes',
                           re.IGNORECASE)


def markdown_files():
    return [ROOT / 'README.md', *sorted(DOCS.rglob('*.md'))]


def reference_pages():
    return sorted(DOCS.glob('*.md'))


def test_the_readme_opens_with_its_reference():
    found = list(headings((ROOT / 'README.md').read_text(encoding='utf-8')))
    history = [title for _, title in found if HISTORY.search(title)]
    assert not history, f'README.md: history belongs in docs/history/: {history}'
    sections = [title for level, title in found if level == 2]
    assert sections[0] == 'Two commands', 'README.md: the demo and the tests come first'


def prose(text: str) -> str:
    """Drop the fenced code blocks (a ``# comment`` there is no heading)."""
    return re.sub(r'^```.*?^```', '', text, flags=re.MULTILINE | re.DOTALL)


def headings(text: str):
    """Yield (level, title) of each Markdown heading outside code blocks."""
    for match in re.finditer(r'^(#{1,6})\s+(.*?)\s*$', prose(text), re.MULTILINE):
        yield len(match.group(1)), match.group(2)


def slug(title: str) -> str:
    """Return the anchor GitHub gives a heading: lower case, no punctuation, '-' for spaces."""
    title = re.sub(r'`|\*\*|\[([^\]]*)\]\([^)]*\)', r'\1', title).lower()
    return re.sub(r'[^\w\- ]', '', title).replace(' ', '-')


def anchors(path: pathlib.Path) -> set:
    seen, out = {}, set()
    for _, title in headings(path.read_text(encoding='utf-8')):
        base = slug(title)
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f'{base}-{count}')
    return out


def test_the_slug_is_githubs():
    assert slug('2. What the graph costs, and the composed layout') == \
        '2-what-the-graph-costs-and-the-composed-layout'
    assert slug('`cmd_vel`: velocity commands (teleop)') == 'cmd_vel-velocity-commands-teleop'
    assert slug('Two robots in one domain: namespaces') == 'two-robots-in-one-domain-namespaces'


@pytest.mark.parametrize('path', markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(path):
    broken = []
    for target in LINK.findall(prose(path.read_text(encoding='utf-8'))):
        if re.match(r'[a-z]+:', target):
            continue    # https:, mailto:
        file, _, anchor = target.partition('#')
        linked = (path.parent / file).resolve() if file else path
        if not linked.exists():
            broken.append(f'{target}: no such file')
        elif anchor and linked.suffix == '.md' and anchor not in anchors(linked):
            broken.append(f'{target}: no heading #{anchor} in {linked.relative_to(ROOT)}')
    assert not broken, '\n'.join(broken)


@pytest.mark.parametrize('path', reference_pages(), ids=lambda p: p.name)
def test_each_page_opens_with_its_reference(path):
    if path.name in NOT_YET_REFERENCE_FIRST:
        pytest.skip(f'{path.name}: being rewritten reference-first')
    found = list(headings(path.read_text(encoding='utf-8')))
    assert found and found[0][0] == 1, f'{path.name}: opens with its # title'
    history = [title for _, title in found if HISTORY.search(title)]
    assert not history, (f'{path.name}: history belongs in docs/history/ or docs/decisions/, '
                         f'linked from the page: {history}')
    assert not NOT_REFERENCE.search(found[0][1]), \
        f'{path.name}: the title names the reference, not a rationale'
    sections = [title for level, title in found if level == 2]
    assert not sections or not NOT_REFERENCE.search(sections[0]), \
        f'{path.name}: the first section is reference, not "{sections[0]}"'


def test_every_page_is_in_the_index():
    index = (DOCS / 'index.md').read_text(encoding='utf-8')
    listed = {(DOCS / target.partition('#')[0]).resolve() for target in LINK.findall(index)}
    pages = [*DOCS.glob('*.md'), *DOCS.glob('history/*.md')]
    missing = [p.relative_to(DOCS).as_posix() for p in pages
               if p.name != 'index.md' and p.resolve() not in listed]
    assert not missing, f'docs/index.md: add a line for {missing}'
