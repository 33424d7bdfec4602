"""Section 4 of ``scripts/bench``: the controllers in real time against the stand-in base.

Their CPU share and sensor -> command latency per layout, the nodes' own code fed directly
(:mod:`wip_tools.node_cost`), rclpy's floor (:mod:`wip_tools.rclpy_floor`) and the ratios
between them (docs/benchmarks.md).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time


def bench_realtime(seconds: float, arm_delay: float | None = None) -> list[dict]:
    """Real-time runs against the stand-in base (see ``wip_bringup.standin_run``).

    ``arm_delay`` [s]: hardware mode's ``--arm-delay`` in each (None: its default).
    """
    import tempfile
    try:
        from wip_bringup.standin_run import realtime_benchmark  # needs ROS
    except ImportError as err:
        return [{'skipped': f'node graph not available: {err}'}]
    with tempfile.TemporaryDirectory(prefix='wip_bench_rt_') as directory:
        import pathlib
        return realtime_benchmark(pathlib.Path(directory), seconds, arm_delay=arm_delay)


def bench_rclpy_floor(seconds: float) -> dict:
    """CPU of receiving the sensor streams alone (:mod:`wip_tools.rclpy_floor`).

    Taken as message objects, serialized (as the eso node takes them), and serialized with
    an effort command sent per tick (``loop``: the floor of a controller), one after the
    other.
    """
    try:
        from wip_tools.rclpy_floor import measure_floor  # needs ROS
    except ImportError as err:
        return {'skipped': f'rclpy not available: {err}'}
    return {'messages': measure_floor(seconds, raw=False),
            'serialized': measure_floor(seconds, raw=True),
            'loop': measure_floor(seconds, raw=True, reply=True)}


def bench_node_cost(seconds: float, pairs: int = 2) -> dict:
    """Return the controller nodes' own CPU per tick, fed directly (:mod:`wip_tools.node_cost`).

    Measured back to back and paced at 200 Hz, alternately, each in a process of its own;
    then once back to back by node (``split``: µs per tick inside each node's callbacks and
    the rest, node_cost's ``--split``).
    """
    runs: dict[str, list[dict]] = {'back_to_back': [], 'paced': [], 'split': []}
    for key, pace, *more in [*((('back_to_back', 0), ('paced', 1)) * pairs),
                             ('split', 0, '--split')]:
        done = subprocess.run([sys.executable, '-m', 'wip_tools.node_cost', '--seconds',
                               f'{seconds:g}', '--pace', str(pace), *more],
                              capture_output=True, text=True, timeout=600, check=False)
        lines = done.stdout.strip().splitlines()
        if done.returncode != 0 or not lines:
            tail = (done.stderr.strip().splitlines() or ['no output'])[-1]
            return {'failed': f'node_cost --pace {pace} {" ".join(more)}: exit '
                              f'{done.returncode}: {tail}'}
        runs[key].append(json.loads(lines[-1]))
    split = runs.pop('split')[0]['split_us']
    medians = {key: statistics.median(r['median_us'] for r in rows)
               for key, rows in runs.items()}
    return {**runs, 'median_us': medians, 'split_us': split,
            'paced_over_back_to_back': medians['paced'] / medians['back_to_back']}


#: Thread CPU [s] of :func:`calibration_loop` on a Raspberry Pi 4-class core (Cortex-A72 at
#: 1.5-1.8 GHz) with its distribution's CPython 3.11: an assumption, not measured on a Pi,
#: taken as 3x this project's 2-vCPU development machine with Debian 12's python3.11
#: (0.015 s there). A plain source build of CPython (no PGO/LTO, pyenv's default) slows
#: this loop far more than the nodes, and the estimate then reads low: measure with the
#: interpreter the robot uses (docs/realtime.md has the figures). Replace it
#: with a measurement on the target (``python -c 'from wip_tools.realtime_bench import
#: calibration_loop as c; print(c())'``) for a figure that is no longer an estimate.
PI_CLASS_CALIBRATION_S = 0.045


def calibration_loop(repeats: int = 5) -> float:
    """Return the least thread CPU [s] of a fixed pure-Python workload: this core's speed.

    Small-object work like the nodes' (dict and attribute access, float arithmetic, calls);
    the least of ``repeats`` so that a busy neighbour counts as little as possible.
    """
    def step(state: dict, k: int) -> float:
        x = state['x'] * 0.999 + 0.001 * k
        state['x'] = x
        return x

    best = float('inf')
    for _ in range(repeats):
        start = time.thread_time()
        state, total = {'x': 0.0}, 0.0
        for k in range(200_000):
            total += step(state, k)
        best = min(best, time.thread_time() - start)
    return best


def overhead_figures(rows: list[dict], floor: dict, cost: dict, per_tick_s: float,
                     calibration_s: float) -> dict:
    """Return the real-time section's ratios (the goals of the composed controllers' cost).

    - ``overhead_ratio``: (composed controllers at normal priority - rclpy's floor taken
      serialized) / the in-process loop, as CPU shares at 200 Hz;
    - ``overhead_ratio_loop``: the same against the ``loop`` floor (the sensors taken and
      one effort command sent per tick), which no controller process can go below;
    - ``paced_over_in_process``: the nodes' own code paced at 200 Hz / the in-process tick;
    - ``pi_class_share``: the composed share scaled by this core's speed against a Pi
      4-class core (:data:`PI_CLASS_CALIBRATION_S`): an estimate.
    A figure whose inputs are missing is None.
    """
    composed = next((r.get('controller_cpu_fraction') for r in rows
                     if r.get('layout') == 'composed' and not r.get('rt_priority')
                     and not r.get('pinned') and r.get('cpu_latency') is None), None)
    serialized = (floor.get('serialized') or {}).get('cpu_fraction')
    loop = (floor.get('loop') or {}).get('cpu_fraction')
    in_process = 200.0 * per_tick_s
    paced = (cost.get('median_us') or {}).get('paced')
    return {
        'composed_share': composed,
        'overhead_ratio': (None if composed is None or serialized is None
                           else (composed - serialized) / in_process),
        'overhead_ratio_loop': (None if composed is None or loop is None
                                else (composed - loop) / in_process),
        'paced_over_in_process': None if paced is None else 1e-6 * paced / per_tick_s,
        'calibration_s': calibration_s,
        'pi_class_share': (None if composed is None
                           else composed * PI_CLASS_CALIBRATION_S / calibration_s)}


def section_realtime(seconds: float, in_process: dict, report: dict,
                     arm_delay: float | None = None) -> None:
    """4. Real time against the stand-in base, the nodes' own cost, rclpy's floor."""
    print(f'\n== 4. Real time: controllers at 200 Hz against the stand-in base, '
          f'{seconds:g} s per layout')
    per_tick_s = 1.0 / (in_process['real_time_factor_median'] * 200.0)
    report['in_process_core_share_at_200hz'] = 200.0 * per_tick_s
    print(f'in-process, the same loop (plant included): {1e6 * per_tick_s:.0f} us per '
          f'tick = {100 * 200.0 * per_tick_s:.1f} % of a core at 200 Hz')
    rows = bench_realtime(seconds, arm_delay)
    report['realtime'] = rows
    for row in rows:
        _print_realtime_row(row)
    print('   (goals: <= 15 % of a core; latency p99 <= 2 ms, max <= 10 ms)')
    cost = bench_node_cost(min(10.0, max(3.0, seconds / 3.0)))
    report['node_cost'] = cost
    if 'failed' in cost:
        print(f'-> node cost: {cost}')
    else:
        print("the six nodes' own code, fed directly (no DDS take, no wake-up by a "
              'message), thread CPU per tick, medians: back to back '
              + ' / '.join(f'{r["median_us"]:.0f}' for r in cost['back_to_back'])
              + ' us; paced at 200 Hz '
              + ' / '.join(f'{r["median_us"]:.0f}' for r in cost['paced'])
              + f' us: {cost["paced_over_back_to_back"]:.1f}x (what running after an '
              'idle period costs on this machine)')
        split = cost['split_us']
        print('   by node, back to back, mean us per tick inside its callbacks: '
              + ', '.join(f'{name} {split[name]:.0f}' for name in split if name != 'tick')
              + f' (a tick {split["tick"]:.0f} us)')
    floor = bench_rclpy_floor(min(10.0, max(3.0, seconds / 2.0)))
    report['rclpy_floor'] = floor
    _print_floor(floor)
    figures = overhead_figures(rows, floor, cost, per_tick_s, calibration_loop())
    report['overhead'] = figures
    _print_overhead(figures)


def _print_realtime_row(row: dict) -> None:
    """Print one real-time run: CPU share, latency, the base's oldest command held.

    Then each controller process's threads by kind: CPU share, and per control tick how
    often they waited and were preempted (:mod:`wip_bringup.thread_usage`).
    """
    if 'skipped' in row:
        print(f'-> {row}')
        return
    lat = row['latency_ms'] or {}
    age = row['command_age_ms'] or {}
    latency_request = row.get('cpu_latency')
    case = (f'rt-priority {"yes" if row["rt_priority"] else "no"}'
            f'{", pinned" if row["pinned"] else ""}'
            + ('' if latency_request is None
               else f', cpu-latency {latency_request} us'))
    print(f'{row["layout"]:9s} {case:48s}: '
          f'controllers {100 * (row["controller_cpu_fraction"] or 0):.1f} % of a core; '
          f'sensor->command latency p50 {lat.get("p50", float("nan")):.2f} ms, p99 '
          f'{lat.get("p99", float("nan")):.2f} ms, max {lat.get("max", float("nan")):.2f}'
          f' ms; base: oldest command held {age.get("max_ms", float("nan")):.1f} ms, '
          f'{row["deadline_misses"]} deadline misses'
          f'{"; FELL" if row["fell"] else ""}')
    rate = row['control_rate_hz']
    for process, kinds in row['threads'].items():
        parts = ', '.join(
            f'{kind} {100 * used["cpu_fraction"]:.1f} % ({used["waits_per_s"] / rate:.1f} '
            f'waits, {used["preempted_per_s"] / rate:.1f} preempted a tick)'
            for kind, used in kinds.items() if used['cpu_fraction'] >= 0.001)
        print(f'{"":10s}{process} by thread: {parts}')


def _print_floor(floor: dict) -> None:
    for kind, measured in floor.items():
        if 'cpu_fraction' in measured:
            what = ('a process that receives the two sensor streams serialized and sends '
                    'one effort command per tick' if kind == 'loop' else
                    "a process that only receives the base's two sensor streams")
            print(f'rclpy floor, taken as {kind}: {what} '
                  f'({measured["messages_per_s"]:.0f} msg/s, empty '
                  f'callbacks, {measured["executor"]}): '
                  f'{100 * measured["cpu_fraction"]:.1f} % of a core, '
                  f'{measured["cpu_per_message_us"]:.0f} us per message, '
                  f'{measured["context_switches_per_s"]:.0f} context switches/s')
        else:
            print(f'-> rclpy floor ({kind}): {measured}')


def _print_overhead(figures: dict) -> None:
    def show(value, form):
        return 'n/a' if value is None else format(value, form)
    print(f"-> overhead ratio (composed - rclpy floor serialized) / in-process: "
          f"{show(figures['overhead_ratio'], '.1f')} (goal <= 3; against the loop floor "
          f"{show(figures.get('overhead_ratio_loop'), '.1f')}); the nodes' own code paced "
          f"/ in-process tick: {show(figures['paced_over_in_process'], '.1f')}x (goal <= 2)")
    share = figures['pi_class_share']
    print(f'-> Pi-class estimate: composed {show(share and 100 * share, ".0f")} % of a Raspberry '
          f'Pi 4-class core (this core {1e3 * figures["calibration_s"]:.0f} ms on the '
          f'calibration loop against an assumed {1e3 * PI_CLASS_CALIBRATION_S:.0f} ms there; '
          'an estimate, not a measurement)')
