"""The result of a run of ``scripts/run_graph``, either mode: ``OUT/run.json`` and its end."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Any, Callable

from .launcher import EXIT_USAGE


@dataclasses.dataclass
class RunResult:
    """What both runners return and write to ``OUT/run.json`` (each adds its own fields)."""

    exit_code: int
    message: str
    out: pathlib.Path
    bag: pathlib.Path | None
    domain_id: int
    node_exit_codes: dict[str, int | None] = dataclasses.field(default_factory=dict)
    startup_s: float | None = None
    wall_time_s: float | None = None
    #: CPU time [s] of each node process during the run.
    cpu_s: dict[str, float] = dataclasses.field(default_factory=dict)
    #: Wall times [s] of the start-up steps, from the start of the run.
    timeline: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: Latest /diagnostics status of every node: name -> {'message': ..., key: value}.
    node_diagnostics: dict[str, dict[str, str]] = dataclasses.field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {'exit_code': self.exit_code, 'message': self.message,
                'out': str(self.out), 'bag': str(self.bag) if self.bag else None,
                'domain_id': self.domain_id, 'startup_s': self.startup_s,
                'wall_time_s': self.wall_time_s, 'node_exit_codes': self.node_exit_codes,
                'cpu_s': self.cpu_s, 'timeline': self.timeline,
                'node_diagnostics': self.node_diagnostics}


def print_result(result: RunResult, formatted: Callable[[RunResult], str]) -> int:
    """Print the result of ``scripts/run_graph`` and return its exit status.

    The end of ``scripts/run_graph`` in either mode: the result on stdout (a run refused
    before anything ran: only its error, on stderr); the exit status.
    """
    if result.exit_code == EXIT_USAGE:  # Refused before anything ran: nothing to show.
        print(f'run_graph: error: {result.message}', file=sys.stderr)
        return EXIT_USAGE
    print(formatted(result))
    return result.exit_code
