"""Every parameter description is short: one sentence of at most 200 characters.

A description says what the parameter does, with its unit and the paper's equation; the
why and the measurements are in docs/ (a page under docs/decisions/, linked from the
description). The limit keeps ``--list-parameters`` and docs/parameters.md a table one
reads line by line, not a page of notes.
"""

from wip_tools.parameters import node_registry, node_rows, scenario_rows

MAX_LENGTH = 200

# Descriptions allowed over the limit, by parameter name (none: every one is short).
ALLOWED_LONG: set[str] = set()


def _rows():
    for executable in sorted(node_registry()):
        for row in node_rows(executable):
            yield f'{executable}: {row.name}', row
    for row in scenario_rows():
        yield f'scenario: {row.name}', row


def test_every_description_is_at_most_200_characters():
    long = [f'{label} ({len(row.description)} characters): {row.description!r}'
            for label, row in _rows()
            if len(row.description) > MAX_LENGTH and row.name not in ALLOWED_LONG]
    assert not long, (f'descriptions over {MAX_LENGTH} characters (the why goes to '
                      'docs/decisions/):\n' + '\n'.join(long))


def test_the_allow_list_holds_only_long_descriptions():
    # A name shortened elsewhere must leave the list, so that the list empties at merge.
    lengths: dict[str, int] = {}
    for _, row in _rows():
        lengths[row.name] = max(lengths.get(row.name, 0), len(row.description))
    stale = sorted(name for name in ALLOWED_LONG if lengths.get(name, 0) <= MAX_LENGTH)
    assert not stale, f'shortened or gone, remove from ALLOWED_LONG: {stale}'
