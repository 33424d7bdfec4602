"""A table of every scenario key: dotted name, unit, default, range, description."""

from __future__ import annotations

import dataclasses
import typing

from wip_control.core.config import describe
from wip_control.core.scenario import Scenario


def _rows(cls: type, prefix: str) -> list[tuple[str, str, str, str, str]]:
    rows = []
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        field_type = hints[field.name]
        name = f'{prefix}{field.name}'
        if dataclasses.is_dataclass(field_type):
            rows += _rows(field_type, name + '.')
            continue
        meta = field.metadata
        low, high = meta.get('minimum'), meta.get('maximum')
        span = ''
        if meta.get('choices'):
            span = '|'.join(meta['choices'])
        elif low is not None or high is not None:
            span = f'[{low if low is not None else "-inf"}, {high if high is not None else "inf"}]'
        default = field.default if field.default is not dataclasses.MISSING else ''
        rows.append((name, meta.get('unit', ''), repr(default), span,
                     meta.get('description', '')))
    return rows


def parameter_table() -> str:
    rows = _rows(Scenario, '')
    width = max(len(r[0]) for r in rows)
    return '\n'.join(f'{r[0]:<{width}}  {r[1]:<10} {r[2]:<14} {r[3]:<22} {r[4]}' for r in rows)


__all__ = ['parameter_table', 'describe']
