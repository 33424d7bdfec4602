"""The node graph in real time: the plant keeps the wall clock and the loop is closed.

One 4 s run of the paper scenario with ``--clock realtime`` (no /clock, every node on the
wall clock, latest-input synchronisation), recorded.

Whether the vehicle stays up in real time depends on every controller keeping up with
200 Hz on the machine, which a loaded 2-core CI host does not guarantee (measured: the
ESO node takes 1-1.5 ms per update in real time there; the vehicle fell after 2.7 s in one
of three runs with other jobs running). So a fall (exit code 3) is accepted here and the
tests check what the graph runner and the plant promise: wall-clock pacing, wall-clock
stamps, torques that arrive in time.
"""


import numpy as np
import pytest

pytest.importorskip('rclpy')

from wip_bag.bag_reader import bag_summary  # noqa: E402
from wip_bringup import graph_runner  # noqa: E402
from wip_bringup.graph_runner import GraphOptions, run_graph  # noqa: E402
from wip_bringup.launcher import EXIT_FELL, EXIT_NOT_ENGAGED  # noqa: E402
from wip_sim.settings import PlantNodeParams  # noqa: E402
from wip_tools.report import record_from_bag  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.wallclock]

DURATION = 4.0  # [s]
CONTROL_PERIOD = 0.005  # [s], 200 Hz
MAX_TORQUE_AGE = PlantNodeParams().max_torque_age  # [s], 0.05


@pytest.fixture(scope='module')
def realtime_run(tmp_path_factory):
    directory = tmp_path_factory.mktemp('realtime')
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setenv('ROS_DOMAIN_ID', str(take_private_domain()))
    try:
        # The single layout (plant and controllers in one process, the cheapest per tick):
        # on a 2-core machine (a third of its CPU taken by the hypervisor) with one
        # busy process, the composed layout's controllers needed 2.1-2.8 ms of CPU per
        # 5 ms tick in real time, the ESO ran at 90-130 Hz and every run fell within 1.5 s
        # with 15-20 % of the plant's ticks lacking a fresh torque; single: 1.8 ms per
        # tick for everything, no stale tick. The composed layout in real time is tested
        # against the stand-in base (tests/wip_sim/test_standin_base.py), at the
        # scheduling priority a robot would give it.
        result = run_graph(GraphOptions(clock='realtime', duration=DURATION,
                                        out=str(directory / 'run'), layout='single',
                                        record=str(directory / 'bag'), quiet=True))
    finally:
        monkeypatch.undo()
    if result.exit_code not in (0, EXIT_FELL) or result.plant_stats is None:
        pytest.fail(f'run_graph failed ({result.exit_code}): {result.message}')
    return result


def test_realtime_plant_runs_at_the_wall_clock_rate(realtime_run):
    assert realtime_run.exit_code in (0, EXIT_FELL), realtime_run.message
    stats = realtime_run.plant_stats
    if realtime_run.exit_code == 0:
        assert stats['ticks'] == round(DURATION / CONTROL_PERIOD)
    # A wall timer at 200 Hz: one step per tick, and the simulated time never runs ahead
    # of the wall clock (2 % for the timer's jitter at the end of the run). How far behind
    # it falls is the machine's capacity (a late timer tick does not catch up here), which
    # scripts/bench measures; the stamps spanning the wall time are checked below.
    assert stats['ticks'] * CONTROL_PERIOD == pytest.approx(stats['sim_time_s'])
    assert 0.0 < stats['real_time_factor'] <= 1.02


def test_realtime_plant_applies_the_latest_fresh_torques(realtime_run):
    stats = realtime_run.plant_stats
    # Ticks that ran with zero torque because none newer than max_torque_age (50 ms)
    # had arrived: before the first command, and after it where a command came late (how
    # many is the machine's speed). Every torque applied was fresh (checked below).
    before = stats['zeroed_torque_ticks_before_first']
    assert before < stats['ticks']
    record = record_from_bag(realtime_run.bag)
    truth = record['truth']
    # Wall-clock stamps shifted to the first sample, in order, spanning the plant's wall
    # time (not its simulated time). Not the gaps one by one: on a loaded machine the
    # recorder misses samples (median gap of two periods seen) and a late timer tick is
    # followed by one on time (two stamps < 1 ms apart).
    # The span also holds the time the vehicle was held before the controllers engaged.
    assert truth['t'][0] == 0.0
    assert np.all(np.diff(truth['t']) > 0.0)
    assert truth['t'][-1] == pytest.approx(stats['wall_time_s'] + stats['held_s'],
                                           abs=4 * CONTROL_PERIOD, rel=0.05)
    # What the plant applied is what the mixer sent last (zero when its safety layer
    # zeroes it): every applied pair is one of the commanded pairs.
    wheels = record['wheels']
    commanded = set(zip(wheels['tau_left'], wheels['tau_right'])) | {(0.0, 0.0)}
    assert set(zip(truth['tau_left'], truth['tau_right'])) <= commanded
    # ... and fresh: a non-zero pair was commanded (stamped) at most max_torque_age before
    # the tick that applied it (the tick's stamp is taken after its step: one period more,
    # and one for a preempted tick).
    stamped = {}
    for t, pair in zip(wheels['t'], zip(wheels['tau_left'], wheels['tau_right'])):
        stamped.setdefault(pair, []).append(t)
    for t, pair in zip(truth['t'], zip(truth['tau_left'], truth['tau_right'])):
        if pair == (0.0, 0.0):
            continue
        newest = max((s for s in stamped[pair] if s <= t), default=None)
        assert newest is not None and t - newest <= MAX_TORQUE_AGE + 2 * CONTROL_PERIOD, (
            t, pair, stamped[pair])
    assert '/clock' not in bag_summary(realtime_run.bag)['topics']


def test_realtime_plant_holds_the_vehicle_until_the_controllers_engage(realtime_run):
    # hold_until_engaged: while the safety layer settles (its wheel torques are zeroed)
    # the plant publishes its initial state and its time stays at 0; the first torques
    # not zeroed release it, and its ticks count from there. Before this, the vehicle fell
    # freely for the 0.3-0.5 s the layer needs and the composed graph fell within 2 s.
    stats = realtime_run.plant_stats
    assert 0.0 < stats['held_s'] < DURATION
    truth = record_from_bag(realtime_run.bag)['truth']
    held = truth['t'] < stats['held_s'] - 2 * CONTROL_PERIOD
    assert held.sum() >= 2
    for name in ('theta', 'x_v', 'v'):
        assert np.all(truth[name][held] == truth[name][0]), name
    assert np.all(truth['tau_left'][held] == 0.0)


def test_realtime_run_whose_controllers_never_engage_ends_with_the_reason(tmp_path,
                                                                          monkeypatch):
    # Held until the controllers engage: a vehicle that starts beyond the safety layer's
    # fall threshold (0.4 > 0.35 rad) is never released. The run ends (no retry: starting
    # again would not help) and says why, with the mixer's own reason.
    monkeypatch.setenv('ROS_DOMAIN_ID', str(take_private_domain()))
    # run_graph's start-up wait (10 s, for the slowest first MPC solve) cut to 4 s: what
    # is asserted (the plant held, the mixer's fall verdict) is there once the safety
    # layer has settled, 0.3-0.5 s after the plant starts (its /diagnostics go out at
    # once on the change). A verdict not seen by then fails the test, never passes it.
    monkeypatch.setattr(graph_runner, 'STARTUP_STALL_TIMEOUT', 4.0)
    scenario = tmp_path / 'tilted.yaml'
    scenario.write_text('name: tilted\nduration: 2.0\ninitial_state:\n  theta: 0.4\n')
    result = run_graph(GraphOptions(clock='realtime', scenario=str(scenario),
                                    out=str(tmp_path / 'run'), quiet=True))
    assert result.exit_code == EXIT_NOT_ENGAGED == 5, result.message
    assert 'the controllers did not engage' in result.message
    assert 'held at the initial state' in result.message
    assert 'fallen' in result.message        # the mixer's FAULT, from its /diagnostics


def test_a_normal_end_of_a_realtime_run_logs_no_error(tmp_path, domain):
    # The plant in its own process (composed layout): it holds its last sensors at the
    # scenario's end until run_graph has stopped the controllers, so that they end by a
    # stop and not by the loss of their inputs (before: "FAULT: MPC failed: status
    # INPUT_INVALID" at every end, then the estimates' staleness).
    result = run_graph(GraphOptions(clock='realtime', duration=DURATION,
                                    out=str(tmp_path / 'run'), layout='composed',
                                    quiet=True))
    if result.exit_code == EXIT_FELL:
        pytest.skip('the vehicle fell (a machine too loaded for the composed layout in '
                    'real time): a fall ends a run with an error, rightly')
    assert result.exit_code == 0, result.message
    assert result.plant_stats['exit_code'] == 0
    assert 'sensors held until the stop' in result.plant_stats['end_reason']
    errors = [line for log in sorted((tmp_path / 'run' / 'logs').glob('*.log'))
              for line in log.read_text(encoding='utf-8').splitlines()
              if '[ERROR]' in line or 'FAULT' in line]
    assert errors == []
    controllers = (tmp_path / 'run' / 'logs' / 'controllers.log').read_text(encoding='utf-8')
    assert 'stopping: zero effort command sent' in controllers
