"""What the plant node reports: per-tick timings, the run's statistics, its diagnostics.

No publisher here: the node publishes :func:`diagnostic_status` on ``/diagnostics`` and
writes :func:`run_stats` to its ``stats_file``.
"""

from __future__ import annotations

import math
import time

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from wip_control.core.model import STATE_NAMES
from wip_runtime.cli import EXIT_OK


class TickTimer:
    """Per-tick durations [s] kept in a growing list; summary statistics at the end."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def add(self, seconds: float) -> None:
        self.values.append(seconds)

    def summary(self) -> dict[str, float | int | None]:
        values = sorted(self.values)
        n = len(values)
        if n == 0:
            return {'count': 0, 'mean_us': None, 'p50_us': None, 'p99_us': None,
                    'max_us': None}
        return {'count': n, 'mean_us': 1e6 * math.fsum(values) / n,
                'p50_us': 1e6 * values[n // 2], 'p99_us': 1e6 * values[min(n - 1,
                                                                          int(0.99 * n))],
                'max_us': 1e6 * values[-1]}


def format_timing(summary: dict) -> str:
    """Return the mean and p99 of a :meth:`TickTimer.summary` in µs, or 'n/a'."""
    if not summary['count']:
        return 'n/a'
    return f'mean {summary["mean_us"]:.0f} us / p99 {summary["p99_us"]:.0f} us'


def run_stats(node) -> dict:
    """Return a plant node's timings and counters of its run so far."""
    wall = node.wall_elapsed()
    t = node.k * node.dt_control
    return {
        'clock_mode': node.clock_mode,
        'scenario': node.scenario.name,
        'ticks': node.k,
        'sim_time_s': t,
        'wall_time_s': wall,
        'real_time_factor': t / wall if wall > 0 else None,
        # CPU time of this process (all threads, DDS included) from start to end [s].
        'cpu_s': ((node.cpu_end or time.process_time()) - node.cpu_start
                  if node.cpu_start is not None else None),
        'exit_code': (node.exit_code if node.exit_code is not None
                      else node.final_exit_code),
        'end_reason': node.end_reason,
        'publish_s': node.publish_time.summary(),
        'step_s': node.step_time.summary(),
        'wait_for_torques_s': node.wait_time.summary(),
        'clock_to_torques_s': node.loop_time.summary(),
        'stale_torque_messages': node.stale_torques,
        # Topics whose readers had not acknowledged every sample when the process
        # ended (wip_runtime.node_main.wait_for_acknowledgements).
        'unacknowledged_topics': node.unacknowledged_topics,
        'zeroed_torque_ticks': node.zeroed_torques,
        'zeroed_torque_ticks_before_first': node.zeroed_torques_before_first,
        # realtime: wall time [s] held at the initial state before the controllers
        # engaged (hold_until_engaged; not in wall_time_s).
        'held_s': node.held_s,
        # The true state at the last tick [SI, rad].
        'final_state': dict(zip(STATE_NAMES, node.state)),
    }


def diagnostic_status(node) -> DiagnosticStatus:
    """Return a plant node's status: waiting, held, running or ended, with its figures."""
    status = DiagnosticStatus(name=f'{node.get_fully_qualified_name()}: plant',
                              hardware_id='simulation')
    t = node.k * node.dt_control
    if node.exit_code is not None or node.ended:
        status.level = (DiagnosticStatus.OK if EXIT_OK in (node.exit_code,
                                                            node.final_exit_code)
                        else DiagnosticStatus.ERROR)
        status.message = node.end_reason
    elif not node.started:
        status.level = DiagnosticStatus.WARN
        missing = node.unmatched()
        status.message = ('waiting for the start' if not missing
                          else 'waiting for the graph: ' + '; '.join(missing))
    elif node.held:
        status.level = DiagnosticStatus.WARN
        status.message = (f'held at the initial state for '
                          f'{node.held_s:.1f} s: the controllers '
                          'have not engaged (no wheel torques that are not zeroed)')
    else:
        waiting = time.perf_counter() - node.published_at
        if node.clock_mode == 'lockstep' and waiting > 1.0:
            status.level = DiagnosticStatus.WARN
            status.message = (f'waiting {waiting:.1f} s for /wip/wheel_torques stamped '
                              f'{t:.3f} s')
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'running, t = {t:.2f} s'
    wall = node.wall_elapsed()
    wait = node.wait_time.values[-200:]
    values = {
        'clock_mode': node.clock_mode,
        'sim time [s]': f'{t:.3f}',
        'duration [s]': f'{node.scenario.duration:g}',
        'ticks': str(node.k),
        'real-time factor': f'{t / wall:.2f}' if wall > 0 else 'n/a',
        'mean wait for torques, last 200 ticks [us]':
            f'{1e6 * sum(wait) / len(wait):.0f}' if wait else 'n/a',
        'stale torque messages': str(node.stale_torques),
        'ticks with zero torques (stale or none)': str(node.zeroed_torques),
        'ended': 'yes' if node.ended or node.exit_code is not None else 'no',
    }
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status
