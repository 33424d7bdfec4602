"""Modules that do one thing: no module over 500 lines, no function over 60.

Measured on every Python module of ros_ws/src (the source as written: docstrings and
comments count, they are what a reader scrolls through). A module or function over the
limit is allowed only with a reason on a line of docs/packages.md's section
"## Long modules and functions", which names it in backticks by its dotted name: a module
(`wip_tools.identify`) or a function (`wip_tools.identify.identify`,
`wip_bag.recorder_node.RecorderNode.__init__`).
"""

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent
SRC = ROOT / 'ros_ws' / 'src'
PACKAGES_DOC = ROOT / 'docs' / 'packages.md'
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60
SECTION = '## Long modules and functions'


def sources():
    """Dotted module name -> source text, every Python module of every package."""
    found = {}
    for package in sorted(p for p in SRC.iterdir() if (p / p.name / '__init__.py').is_file()):
        for path in sorted((package / package.name).rglob('*.py')):
            parts = list(path.relative_to(package).with_suffix('').parts)
            if parts[-1] == '__init__':
                parts.pop()
            found['.'.join(parts)] = path.read_text()
    return found


def functions(tree):
    """(qualified name, lines) of every function and method of a module's tree."""
    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                yield name, child.end_lineno - child.lineno + 1
                yield from walk(child, name + '.')
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, prefix + child.name + '.')
    yield from walk(tree, '')


def allowed():
    """Names given a reason in docs/packages.md's section (see the module docstring)."""
    text = PACKAGES_DOC.read_text()
    if SECTION not in text:
        return {}
    section = text.split(SECTION, 1)[1].split('\n## ', 1)[0]
    reasons = {}
    for line in section.splitlines():
        match = re.match(r'\s*[-*]\s+`([^`]+)`(.*)', line)
        if match:
            reasons[match.group(1)] = match.group(2).strip(' :—-')
    return reasons


def over_the_limits():
    """Dotted names over the limits (modules and functions) -> lines."""
    over = {}
    for module, text in sources().items():
        lines = text.count('\n') + (0 if text.endswith('\n') else 1)
        if lines > MAX_MODULE_LINES:
            over[module] = lines
        for name, length in functions(ast.parse(text)):
            if length > MAX_FUNCTION_LINES:
                over[f'{module}.{name}'] = length
    return over


def test_no_module_or_function_is_over_the_limits_without_a_reason():
    reasons = allowed()
    unexplained = {name: lines for name, lines in over_the_limits().items()
                   if not reasons.get(name)}
    assert not unexplained, (
        f'over {MAX_MODULE_LINES} lines per module or {MAX_FUNCTION_LINES} per function, '
        f'without a reason in {PACKAGES_DOC.name} "{SECTION}": {unexplained}')


def test_every_reason_names_something_still_over_the_limits():
    # A reason left behind after a split would allow the next long function unseen. (Lines
    # naming a test file give the reason a test module is long; they are not measured here.)
    sources_reasons = {name for name in allowed() if not name.startswith('tests/')}
    stale = sources_reasons - set(over_the_limits())
    assert not stale, f'{PACKAGES_DOC.name} "{SECTION}" names what is within the limits: {stale}'


def test_the_measure_counts_a_long_function_and_a_long_module():
    text = 'def f():\n' + '    x = 1\n' * 70 + '\n\nclass C:\n    def g(self):\n        pass\n'
    measured = dict(functions(ast.parse(text)))
    assert measured['f'] == 71 and measured['C.g'] == 2
