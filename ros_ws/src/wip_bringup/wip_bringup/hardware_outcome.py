"""The outcome of a hardware-mode run: its result, exit code and summary line."""

from __future__ import annotations

import dataclasses
from typing import Any, Iterable

from .launcher import EXIT_FELL, EXIT_NOT_ENGAGED, EXIT_OK
from .run_result import RunResult

#: Safety states in which the mixer commands torque: the controllers have engaged.
ENGAGED_STATES = ('ACTIVE', 'DEGRADED', 'SHADOW')
#: Latency [s] of the mixer's safety state through its /diagnostics (period 1 s), as a margin.
DIAGNOSTICS_LATENCY = 0.5


@dataclasses.dataclass
class HardwareResult(RunResult):
    """What ``hardware_runner.run_hardware`` returns (also written to ``OUT/run.json``)."""

    #: Each change of the mixer's safety state: {'t': [s] since the run start, 'state',
    #: 'reasons'}.
    safety_events: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    #: Mean output rate [1/s] of each node over the run, from its /diagnostics counts.
    rates: dict[str, float] = dataclasses.field(default_factory=dict)
    #: Base topics (remapped) -> publisher / subscription counts seen at the start.
    base_topics: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    zero_commands_sent: int = 0
    #: What the controller processes' threads did during the run, by kind
    #: (:func:`.thread_usage.usage_since`).
    threads: dict[str, dict[str, dict[str, float]]] = dataclasses.field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {'mode': 'hardware', **super().summary(),
                'safety_events': self.safety_events, 'rates': self.rates,
                'base_topics': self.base_topics, 'zero_commands_sent': self.zero_commands_sent,
                'threads': self.threads}


def hardware_outcome(events: list[dict[str, Any]], ended: str,
                     base_end_after: float | None = None,
                     missing: Iterable[str] = ()) -> tuple[int, str]:
    """Exit code and message of a run that ended normally.

    Both follow from the safety events seen until then (``ended`` says why the run ended):
    the code is 0 if the controllers engaged and no FAULT followed (an e-stop is the user's
    stop), 1 (EXIT_FELL) if one did, 5 (EXIT_NOT_ENGAGED) if they never engaged.
    ``missing`` lists the base topics without a publisher/subscription; the message names
    them when the controllers never engaged.
    """
    engaged = next((i for i, e in enumerate(events) if e['state'] in ENGAGED_STATES), None)
    if engaged is None:
        why = ''
        if events:
            last = events[-1]
            why = f'; the safety layer stayed {last["state"]}: {last["reasons"]}'
        else:
            why = '; no safety state came from the mixer'
        if missing:
            why += '; no inputs from the base: nothing on ' + ', '.join(missing)
        return EXIT_NOT_ENGAGED, f'the controllers never engaged ({ended}){why}'
    start = events[engaged]['t']
    for event in events[engaged + 1:]:
        if event['state'] != 'FAULT':
            continue
        if base_end_after is not None and (
                event['t'] >= start + base_end_after - DIAGNOSTICS_LATENCY):
            break
        return EXIT_FELL, (f'safety FAULT {event["t"] - start:.1f} s after the controllers '
                           f'engaged: {event["reasons"]} (then {ended})')
    return EXIT_OK, ended


def format_result(result: HardwareResult) -> str:
    word = {EXIT_OK: 'OK', EXIT_FELL: 'FELL OR FAULT', EXIT_NOT_ENGAGED: 'NEVER ENGAGED'}
    lines = [f'{word.get(result.exit_code, "FAILED")}: {result.message}']
    if result.rates:
        lines.append('mean output rates [1/s]: ' + ', '.join(
            f'{n} {r:.1f}' for n, r in sorted(result.rates.items())))
    if result.safety_events:
        lines.append('safety states: ' + ' -> '.join(e['state'] for e in result.safety_events))
    if result.cpu_s and result.wall_time_s:
        lines.append('CPU [% of one core]: ' + ', '.join(
            f'{n} {100 * c / result.wall_time_s:.0f}' for n, c in sorted(
                result.cpu_s.items(), key=lambda item: -item[1])))
    lines.append(f'outputs: {result.out} (run.json, params.yaml, logs/)')
    if result.bag is not None:
        lines.append(f'bag: {result.bag}')
    return '\n'.join(lines)
