"""``scripts/bench`` end to end on a short scenario.

Every part runs and reports (the numbers are benchmarks, not pass/fail; only their presence and
sanity are checked). The real-time section runs in a test of its own (``--realtime-only``,
marked wallclock); the others are in-process and lockstep runs (docs/testing.md).
"""

import contextlib
import io
import json
import os
import subprocess
import sys

import pytest
import yaml

pytest.importorskip('rclpy')

from wip_bringup.standin_run import pinned_cpus  # noqa: E402
from wip_tools import bench  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope='module')
def push_only(tmp_path_factory):
    """``scripts/bench --push-only`` once for the module: (its JSON report, what it printed).

    The push section is 12 in-process runs (four noisy cases of two seeds, four clean),
    deterministic bit for bit; the whole bench's run takes its rows from here instead of
    running them again (its own checks are about the other sections).
    """
    out = tmp_path_factory.mktemp('bench_push') / 'bench.json'
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = bench.main(['--push-only', '--push-seeds', '2', '--json', str(out)])
    assert status == 0
    return json.loads(out.read_text()), printed.getvalue()


def _short_scenario(tmp_path):
    scenario = tmp_path / 'short.yaml'
    scenario.write_text(yaml.safe_dump({'name': 'bench_short', 'duration': 2.0}))
    return scenario


def test_bench_reports_the_mpc_ratio_and_both_real_time_factors(tmp_path, capsys, push_only,
                                                                monkeypatch):
    # Sections 1-3 and 5: in-process and lockstep runs, none on the wall clock (section 4,
    # the real-time runs, is the next test's, marked wallclock).
    from wip_tools.analysis import push_recovery
    # Section 5 is the push-only run's (test_bench_push_only_...), printed again here.
    monkeypatch.setattr(push_recovery, 'push_recovery_rows',
                        lambda **_: push_only[0]['push_recovery'])
    out = tmp_path / 'bench.json'
    assert bench.main(['--scenario', str(_short_scenario(tmp_path)), '--repeats', '1',
                       '--json', str(out), '--no-realtime']) == 0
    report = json.loads(out.read_text())
    assert 'realtime' not in report and 'rclpy_floor' not in report     # --no-realtime
    # The interpreter the figures were measured on, as the first line printed says.
    assert report['environment']['python_executable'] == os.path.realpath(sys.executable)
    assert report['mpc']['ratio_tick'] > 0.0
    assert report['in_process']['real_time_factor_median'] > 0.0
    graph = report['graph']
    assert 'failed' not in graph and 'skipped' not in graph, graph
    assert graph['sim_time_s'] == pytest.approx(2.0)
    assert graph['ticks'] == 400                          # 2 s at 200 Hz
    assert graph['real_time_factor'] > 0.0
    assert set(graph['cpu_per_tick_us']) == {'plant', 'controllers'}     # composed
    single = report['graph_single']                  # plant and controllers, one process
    assert single['ticks'] == 400 and set(single['cpu_per_tick_us']) == {'simulation'}
    separate = report['graph_separate']
    assert separate['ticks'] == 400
    assert set(separate['cpu_per_tick_us']) >= {'plant', 'eso', 'mpc', 'torque_mixer'}
    # Recorded runs: every layout, its bag checked; lockstep ends where in-process does.
    for key in ('graph', 'graph_single', 'graph_separate'):
        recorded = report[f'{key}_recorded']
        assert recorded['recorded'] and recorded['ticks'] == 400, recorded
        assert recorded['bag_problems'] == [] and recorded['bag_messages'] > 400 * 5
        # The graph carries the IMU rates through a quaternion and body rates, which round:
        # within 2e-6 (test_lockstep's VALUE_ATOL) of in-process; recorded or not the same.
        assert 0.0 <= report[f'{key}_recorded_final_state_difference'] < 2e-6
        assert recorded['final_state'] == report[key]['final_state']
    repro = report['reproducibility']
    assert repro['processes'] == 3 and repro['identical'], repro
    assert repro['samples'] == 401 and repro['channels'] > 50
    assert report['in_process_over_graph'] == pytest.approx(
        report['in_process']['real_time_factor_median'] / graph['real_time_factor'])
    printed = capsys.readouterr().out
    assert printed.startswith('bench: commit ') and os.path.realpath(sys.executable) in printed
    assert 'in-process / graph' in printed and 'CPU' in printed
    assert 'composed, recorded' in printed and 'bit-identical' in printed
    assert report['push_recovery'] == push_only[0]['push_recovery']
    assert printed.count('0.700 m') == push_only[1].count('0.700 m') > 0


@pytest.mark.wallclock
def test_bench_reports_each_real_time_case_beside_the_rclpy_floor_and_the_nodes_cost(
        tmp_path, capsys):
    # Section 4 alone (--realtime-only: with the in-process run it is compared with). Each
    # real-time run is 3 s: the mixer's latency percentiles come from its /diagnostics,
    # which a 1 s run on a slow machine may end before. The nodes' cost and the floor take
    # the bench's least, 3 s each: a paced node_cost run of 1 s on a loaded machine had not
    # engaged by its end (the safety layer's settle time is wall time). The arming is not
    # under test here (tests/wip_sim/test_standin_base.py): each run arms after the short
    # delay of the tests' stand-in runs; the figures are measured from the arming on.
    from wip_bringup.standin_run import SHORT_ARM_DELAY
    out = tmp_path / 'bench.json'
    assert bench.main(['--scenario', str(_short_scenario(tmp_path)), '--repeats', '1',
                       '--json', str(out), '--realtime-seconds', '3',
                       '--arm-delay', str(SHORT_ARM_DELAY), '--realtime-only']) == 0
    report = json.loads(out.read_text())
    assert 'mpc' not in report and 'graph' not in report and 'push_recovery' not in report
    assert report['in_process']['real_time_factor_median'] > 0.0
    assert report['in_process_core_share_at_200hz'] > 0.0
    # Real time: one row per (layout, priority), each with a CPU share and latencies
    # measured by the mixer (the robot may fall in 3 s on a loaded machine: not checked).
    rows = report['realtime']
    assert [r['layout'] for r in rows] == ['separate'] + ['composed'] * 5
    assert [r['cpu_latency'] for r in rows] == [None] * 4 + [0, 0]
    pinned = pinned_cpus() is not None                  # pinned where there are two CPUs
    assert [r['pinned'] for r in rows[:4]] == [False, False, False, pinned]
    if 'skipped' in rows[4]:     # the PM QoS request needs root: says why, in both cases
        for row in rows[4:]:
            assert '--cpu-latency 0' in row['skipped'], row
        rows = rows[:4]
    else:
        assert [r['pinned'] for r in rows[4:]] == [False, pinned]
    for row in rows:
        assert 0.0 < row['controller_cpu_fraction'] < 2.0          # 2 cores at most
        # By thread: each controller process's first thread spun the nodes (it ran and
        # waited for its inputs), and the threads' shares add up to the process's.
        threads = row['threads']
        assert set(threads) == ({'controllers'} if row['layout'] == 'composed' else
                                {'reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                                 'torque_mixer'}), threads
        for kinds in threads.values():
            assert kinds['spinning']['cpu_fraction'] > 0.0 < kinds['spinning']['waits_per_s']
        assert sum(used['cpu_fraction'] for kinds in threads.values()
                   for used in kinds.values()) == pytest.approx(
                       row['controller_cpu_fraction'], abs=0.05)
        assert 0.0 < row['latency_ms']['p50'] <= row['latency_ms']['p99'] \
            <= row['latency_ms']['max']
    # The floor: the receiver got the two 200 Hz streams and spent CPU on them, taken
    # as message objects, serialized, and serialized with a command sent per tick.
    for kind, raw, reply in (('messages', False, False), ('serialized', True, False),
                             ('loop', True, True)):
        floor = report['rclpy_floor'][kind]
        assert floor['raw'] is raw and floor['reply'] is reply
        assert floor['messages_per_s'] > 100.0 and floor['cpu_fraction'] > 0.0, floor
    # The nodes fed directly: every run engaged, wrote each effort command to DDS but the
    # first, and reported a cost; both ways measured.
    cost = report['node_cost']
    assert 'failed' not in cost, cost
    for key in ('back_to_back', 'paced'):
        assert len(cost[key]) == 2
        for run in cost[key]:
            assert run['safety_state'].endswith('ACTIVE'), run
            assert run['effort_commands_to_dds'] >= run['ticks'] // 2, run
            assert 0.0 < run['median_us'] <= run['p90_us'], run
    assert cost['paced_over_back_to_back'] > 0.0
    # By node: each of the six ran every tick (its callbacks took time), the executor
    # turned for the timers; the rest of the tick (the bus's deliveries, the harness) is a
    # part of it; the parts make the tick.
    split = cost['split_us']
    nodes = ('arc', 'eso', 'mpc', 'reference', 'torque_mixer', 'trajectory_generator',
             'executor turns (timers)')
    assert set(split) == {*nodes, 'the rest (bus, harness)', 'tick'}, split
    assert all(split[name] > 0.0 for name in nodes), split
    assert split['tick'] > 0.0 and split['tick'] > split['the rest (bus, harness)']
    assert sum(split.values()) - split['tick'] == pytest.approx(split['tick'])
    # The mixer's wiring checks are served by the ESO's sensor subscriptions (one take).
    assert all(run['other_sensor_subscriptions'] == 0
               for key in ('back_to_back', 'paced') for run in cost[key])
    figures = report['overhead']
    assert figures['overhead_ratio'] is not None and figures['pi_class_share'] > 0.0
    assert figures['overhead_ratio_loop'] is not None
    assert figures['paced_over_in_process'] > 0.0
    printed = capsys.readouterr().out
    assert 'rclpy floor, taken as messages' in printed
    assert 'rclpy floor, taken as serialized' in printed
    assert 'rclpy floor, taken as loop' in printed and 'against the loop floor' in printed
    assert 'sensor->command latency' in printed and 'controllers by thread: spinning' in printed
    assert 'fed directly' in printed and 'by node, back to back' in printed
    assert 'overhead ratio' in printed and 'Pi-class estimate' in printed


def test_bench_options_that_contradict_each_other_are_refused_in_one_line(capsys):
    for argv, said in ((['--realtime-only', '--no-realtime'], 'not with --no-graph'),
                       (['--realtime-only', '--push-only'], 'not allowed with argument')):
        with pytest.raises(SystemExit) as refused:
            bench.main(argv)
        assert refused.value.code == 2
        assert said in capsys.readouterr().err, argv


def test_bench_refuses_a_negative_arm_delay_in_one_line(capsys):
    with pytest.raises(SystemExit) as refused:
        bench.main(['--arm-delay', '-1'])
    assert refused.value.code == 2
    assert '--arm-delay: must be >= 0' in capsys.readouterr().err


def test_node_cost_refuses_absurd_durations_in_one_line(capsys):
    from wip_tools import node_cost
    with pytest.raises(SystemExit) as refused:
        node_cost.main(['--seconds', 'nan'])
    assert refused.value.code == 2
    assert '--seconds: must be in (0, 3600]' in capsys.readouterr().err


def test_bench_push_only_prints_each_case_against_its_bound(push_only):
    report, printed = push_only
    rows = report['push_recovery']
    assert len(rows) == 8 and all(row['ratio'] > 1.0 for row in rows)
    assert 'mpc' not in report
    assert sum(line.endswith('met') or line.endswith('NOT MET')
               for line in printed.splitlines()) == 8 and '0.700 m' in printed
    # A noisy case is the median of its seeds, within their range; a clean one runs once.
    for row in rows:
        assert row['runs'] == (2 if row['noise'] else 1)
        assert row['ratio_min'] <= row['ratio'] <= row['ratio_max']
    assert printed.count('2: 0-0') == 4


def test_the_commit_is_the_checkouts_wherever_the_bench_is_started(tmp_path, monkeypatch):
    # scripts/bench writes into the working directory, which may be outside the checkout:
    # the commit recorded is still the one of the code that ran.
    root = os.path.dirname(os.path.realpath(bench.__file__))
    expected = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True,
                              text=True, check=False, cwd=root).stdout.strip()
    monkeypatch.chdir(tmp_path)
    assert bench._environment()['commit'] == expected
