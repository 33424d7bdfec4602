"""The controllers in hardware mode against a stand-in base in its own process.

The stand-in base (``wip_sim.standin_base``) simulates the robot (full model, RK4 at
1 kHz, in real time) and speaks only the topics of a ros2_control base, under names of
its own: ``/base/joint_states``, ``/base/imu``, ``/base/fix`` out and
``/base/effort_controller/commands`` (std_msgs/Float64MultiArray) in. Its conventions
differ from the simulator's on purpose: joints named ``wheel_l``/``wheel_r`` listed
right first, the left joint's positive direction rolling backwards (sign −1), an IMU
mounted upside down and turned a quarter turn. The controllers run as in
``scripts/run_graph --mode hardware`` (:func:`wip_bringup.hardware_runner.run_hardware`), in the
default (composed) layout unless a test says otherwise, with ``--remap`` for the topic
names and a ``--params-file`` with the base's conventions (the harness is
:mod:`wip_bringup.standin_run`).

1. Configured consistently, the controllers keep the robot up and on a straight line
   (0.5 m/s, the paper's initial errors: 0.5 m behind, 0.5 m aside, 0.1 rad, tilt
   0.05 rad) in real time, every command within the safety layer's bound and at the
   rate the control needs (measured by the base: the commands it receives), through
   the freezes of 3 within the bound (one run for both); the machine's own rates and
   latencies are scripts/bench's (docs/testing.md).
2. With the left wheel's sign wrong on the controllers' side, the robot cannot balance:
   the safety layer's wiring check sends zero torque and names ``left_wheel_sign``, and
   no node crashes (every wiring mistake: test_standin_wiring.py).
3. Fault injection: controller processes frozen (SIGSTOP/SIGCONT) for 20, 60 and 150 ms
   are ridden through (the composed ones in the run of 1); a 0.5 s freeze, past the
   safety layer's bound, zeroes the torque with the cause named.

Numbers measured on the 2-core development machine (200 Hz, 7 processes): see the
module's report in ``OUT/measured.json`` of each run and the assertions' comments.
"""

import time

import numpy as np
import pytest

pytest.importorskip('rclpy')

from wip_control.core.references import make_reference, ReferenceParams  # noqa: E402
from wip_control.core.safety_config import SafetyParams  # noqa: E402
from wip_bringup.standin_run import (BASE, CONTROL_RATE, engaged, freeze_process,  # noqa: E402
                                 run_against_standin, SHORT_ARM_DELAY)

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.wallclock]

RUN_TIME = 16.0  # [s] of simulated (= wall) time after the release


# ------------------------------------------------------------------ fault injection
# The controllers' processes are frozen (SIGSTOP ... SIGCONT) while they balance the base:
# a frozen process sends nothing, and the base (like a ros2_control effort controller)
# holds the last command. Within the safety layer's bound (age limit + bridge_time:
# 0.05 + 0.30 s for the estimate) the controllers ride through (DEGRADED, never FAULT)
# and the base stays up and on the line; past it they command zero torque and say why.
FREEZES = (0.02, 0.06, 0.15)   # [s] within the bound
FREEZE_SPACING = 3.0           # [s] between two freezes: the robot settles again


def _freezes(names, seconds, log, starts=None):
    """Freeze each named process for each duration, FREEZE_SPACING apart.

    The injector: each named process frozen for each duration, FREEZE_SPACING apart;
    ``log`` gets (name, measured freeze [s]), ``starts`` the time.monotonic() of each.
    """
    def inject(runner, processes):
        for name in names:
            for duration in seconds:
                time.sleep(FREEZE_SPACING)
                if processes[name].poll() is not None:   # the run has ended
                    return
                if starts is not None:
                    starts.append(time.monotonic())
                try:
                    log.append((name, freeze_process(processes[name].pid, duration)))
                except ProcessLookupError:      # the run has ended (the test says why)
                    return
    return inject


def _on_the_line(stats, after):
    truth = {k: np.asarray(v) for k, v in stats['truth'].items()}
    later = truth['t'] > after
    return np.abs(truth['theta']).max(), np.abs(truth['y'][later]).max()


@pytest.fixture(scope='module')
def consistent_run(tmp_path_factory):
    """Return (result, stats, base exit code, freeze log) of the consistent configuration.

    One run for the three tests that read it: the composed controllers are frozen for
    FREEZES, FREEZE_SPACING apart from the engagement, all within the safety layer's bound,
    so what the consistent configuration must hold (up, on the line after 10 s, every
    command within the bound, half the control rate over the run) holds through them with
    the same bounds, and the ride-through is judged on the same run.
    """
    directory = tmp_path_factory.mktemp('standin') / 'consistent'
    log = []
    run = run_against_standin(directory, BASE, RUN_TIME,
                              during=_freezes(['controllers'], FREEZES, log))
    return run.result, run.stats, run.base_code, log


def test_hardware_mode_keeps_the_standin_base_up_and_on_the_line(consistent_run):
    result, stats, code, _ = consistent_run
    assert result.exit_code == 0, result.message
    assert code == 0, stats['end_reason']         # the base ran its time, did not fall
    assert stats['released'] and not stats['fell']
    assert stats['sim_time_s'] == pytest.approx(RUN_TIME, abs=0.01)
    truth = {k: np.asarray(v) for k, v in stats['truth'].items()}
    # Tilt: the in-process run of the same scenario peaks at 0.073 rad, and so does this
    # graph (measured 0.063-0.078 rad over 16 runs since the runner arms the controllers
    # after the start-up). Before that, a process of the graph stalling for 0.33 s in
    # publish() while the others started (DDS discovery; seen in about 1 start in 4) could
    # hit the release: the robot then peaked at 0.14-0.23 rad, and fell once. With the
    # three freezes of this run: 0.100 rad, 3 runs of 3 (docs/history/testing.md).
    # Bound: 0.3 rad, below the safety layer's fall threshold (0.35 rad).
    assert np.abs(truth['theta']).max() < 0.3, stats['stalls']
    # The controllers engaged only after the runner armed them.
    assert result.timeline['armed'] < [e['t'] for e in result.safety_events
                                       if e['state'] == 'ACTIVE'][0]
    # On the path: the reference starts when the safety layer engages, which is the
    # base's release (its t = 0) within the chain's latency (< 0.05 s = 2.5 cm at
    # 0.5 m/s). With the FULL plant model the controllers' speed loop oscillates (their
    # nominal model is the paper's): the in-process runner of this scenario reaches a
    # position error of 0.85 m after 10 s (0.34 m across the line), and this real-time
    # graph, with one or two control periods of latency, 0.74-2.34 m (0.31-0.48 m across
    # the line) over 7 runs. With the paper's model the graph tracks like the runner
    # (0.21 vs 0.24 m). Bounds: 3 m along, 0.6 m across the line after 10 s.
    reference = make_reference(ReferenceParams(kind='line', line_speed=0.5))
    later = truth['t'] > 10.0
    ref = [reference.sample(t) for t in truth['t'][later]]
    error = np.hypot(truth['x'][later] - [r.x for r in ref],
                     truth['y'][later] - [r.y for r in ref])
    assert error.max() < 3.0
    assert np.abs(truth['y'][later]).max() < 0.6
    # It went somewhere: at least 60 % of the reference's 8 m in 16 s.
    assert truth['x'][-1] - truth['x'][0] > 0.6 * 0.5 * RUN_TIME


def test_hardware_mode_sustains_the_rate_the_control_needs_in_real_time(consistent_run):
    result, stats, _, _ = consistent_run
    # What the control needs, not what this machine gives (the machine's rates, latencies
    # and CPU share are scripts/bench's):
    # - Every command reached the base within the safety layer's bound: an input older
    #   than its age limit plus the ride-through (max_estimate_age 0.05 s + bridge_time
    #   0.3 s) is a fault, so a larger gap at the base would be one the controllers
    #   should have reported.
    bound_ms = 1e3 * (SafetyParams().max_estimate_age + SafetyParams().bridge_time)
    assert stats['command_age']['max_ms'] <= bound_ms, stats['command_age']
    assert stats['rejected_commands'] == 0
    # - Half the control rate at least, over the run: the ESO's discretisation requires
    #   h * (fastest observer pole, 60 rad/s) <= 1, i.e. >= 60 Hz, and the in-process runner
    #   of this scenario at 100 Hz tracks as at 200 Hz (max |theta| 0.099 rad, on the line
    #   after 10 s, both). The base measures the commands it receives; each node's mean
    #   output rate comes from its /diagnostics over the span in which it produced.
    needed = 0.5 * CONTROL_RATE
    assert stats['command_rate_hz'] >= needed, stats['command_gap']
    for name in ('eso', 'trajectory_generator', 'arc', 'torque_mixer', 'reference'):
        assert result.rates[name] >= needed, (name, result.rates)
    # The MPC's timer: its plan is followed for two periods at most before the safety
    # layer's drive-torque age limit (0.25 s = 2.5 periods of 0.1 s): half its rate too.
    assert result.rates['mpc'] >= 0.5 * 10.0, result.rates
    # The run engaged once, and the end (the base stopping) is a stale-input fault.
    states = [e['state'] for e in result.safety_events]
    assert 'ACTIVE' in states
    assert result.zero_commands_sent > 0
    print(f"command rate {stats['command_rate_hz']:.1f} Hz, age p99 "
          f"{stats['command_age']['p99_ms']:.1f} ms max {stats['command_age']['max_ms']:.1f} "
          f"ms, deadline misses {stats['deadline_misses']}/{stats['ticks_checked']}, "
          f"rates {result.rates}")


def test_a_wrong_wheel_sign_makes_the_safety_layer_zero_the_torque(tmp_path):
    wrong = dict(BASE, left_wheel_sign=1)
    run = run_against_standin(tmp_path / 'wrong_sign', wrong, 10.0, exit_after_fall=1.0,
                              arm_delay=SHORT_ARM_DELAY)
    result, stats, code = run.result, run.stats, run.base_code
    # A fall while engaged: exit 1, and the message names the mixer's reason.
    assert result.exit_code == 1, result.message
    assert result.message.startswith('safety FAULT '), result.message
    # The wiring check names the parameter (tests/wip_sim/test_standin_wiring.py).
    assert 'wiring: left_wheel_sign: ' in result.message, result.message
    # No node crashed: each was stopped by SIGINT at the end.
    assert all(c == 0 for c in result.node_exit_codes.values()), result.node_exit_codes
    assert stats['released']                         # the controllers did engage ...
    assert code == 1 and stats['fell']               # ... and could not balance it
    faults = [e for e in result.safety_events if e['state'] == 'FAULT']
    assert faults, result.safety_events
    # After engaging, the first reason is the wiring verdict, before the fall it causes.
    engaged_at = next(i for i, e in enumerate(result.safety_events) if e['state'] == 'ACTIVE')
    first = next(e for e in result.safety_events[engaged_at:] if e['state'] == 'FAULT')
    assert first['reasons'].startswith('wiring: left_wheel_sign: '), first
    # The base received only zero commands once it lay on the ground.
    assert stats['commands_after_fall'] > 0
    assert stats['nonzero_commands_after_fall'] == 0
    assert stats['last_command'] == [0.0, 0.0]
    mixer = next(v for k, v in result.node_diagnostics.items()
                 if k.startswith('/torque_mixer'))
    assert int(mixer['zeroed ticks']) > 0


def test_position_from_odometry_instead_of_gps_keeps_the_base_up_and_on_the_line(tmp_path):
    """Position from odometry instead of GPS keeps the base up and on the line.

    ``position_source: odometry``: the ESO takes x, y from nav_msgs/Odometry on /odom
    (here the base's true pose, as a localisation filter would give it) and ignores the
    GPS; the loop closes as with GPS (the bounds and windows of the GPS run above: with
    the full plant model the lateral error still swings to ~0.6 m before 10 s).
    """
    run_time = RUN_TIME
    run = run_against_standin(
        tmp_path / 'odometry', dict(BASE, position_source='odometry'), run_time,
        base_extra={'publish_odometry': True}, arm_delay=SHORT_ARM_DELAY)
    result, stats, code = run.result, run.stats, run.base_code
    assert result.exit_code == 0, result.message
    assert code == 0, stats['end_reason']
    assert stats['released'] and not stats['fell']
    truth = {k: np.asarray(v) for k, v in stats['truth'].items()}
    assert np.abs(truth['theta']).max() < 0.3
    later = truth['t'] > 10.0
    print(f'odometry source: max |theta| {np.abs(truth["theta"]).max():.3f} rad, max |y| '
          f'after 10 s {np.abs(truth["y"][later]).max():.2f} m')
    assert np.abs(truth['y'][later]).max() < 0.6
    assert truth['x'][-1] - truth['x'][0] > 0.6 * 0.5 * run_time
    # The ESO took its positions from /odom (the base publishes one with each IMU sample:
    # as many as IMU samples, but for those that best-effort delivery dropped, which hits
    # both topics alike) and has no GPS subscription at all.
    eso = next(v for k, v in result.node_diagnostics.items() if k.startswith('/eso:'))
    assert int(eso['received odom']) >= 0.9 * int(eso['received imu']) > 0, eso
    assert not any('gps' in key for key in eso if key.startswith(('received', 'age')))
    assert int(eso['odometry fixes accepted']) > 0 and eso['odometry fixes rejected'] == '0'


def test_freezes_of_the_composed_controllers_within_the_bound_are_ridden_through(
        consistent_run):
    result, stats, code, log = consistent_run
    run_time = RUN_TIME
    assert [name for name, _ in log] == ['controllers'] * len(FREEZES), log
    assert all(measured >= wanted for (_, measured), wanted in zip(log, FREEZES)), log
    assert code == 0 and not stats['fell'], stats['end_reason']
    states = [e['state'] for e in result.safety_events]
    engaged = states.index('ACTIVE')
    # Never zeroed once engaged, until the base stops at the end of its run_time after the
    # release (which is the engagement, within the diagnostics' latency: 0.5 s margin).
    end = result.safety_events[engaged]['t'] + run_time - 0.5
    faults = [e for e in result.safety_events[engaged:] if e['state'] == 'FAULT']
    assert all(e['t'] >= end for e in faults), result.safety_events
    theta_max, y_max = _on_the_line(stats, after=10.0)
    print(f'freezes {log}: max |theta| {theta_max:.3f} rad, max |y| after 10 s '
          f'{y_max:.2f} m, safety events {states}')
    assert theta_max < 0.3
    assert y_max < 0.6


def test_each_separate_controller_process_frozen_for_150_ms_is_ridden_through(tmp_path):
    names = ['reference', 'eso', 'trajectory_generator', 'arc', 'mpc', 'torque_mixer']
    # The run ends FREEZE_SPACING after the last freeze (the base's clock would not wait
    # for an injector that a loaded machine starts late: once no freeze happened at all);
    # run_time only caps it.
    run_time = 60.0 + FREEZE_SPACING * (len(names) + 1)
    for attempt in (1, 2):
        log, starts = [], []
        run = run_against_standin(tmp_path / f'freeze_each_{attempt}', BASE, run_time,
                                  layout='separate',
                                  during=_freezes(names, (0.15,), log, starts),
                                  end_after_during=FREEZE_SPACING, arm_delay=SHORT_ARM_DELAY)
        # Six processes starting at once at SCHED_FIFO on a busy 2-core machine: once a
        # node never came up (Fast DDS's shared-memory port lock timed out in one, another
        # ran 30 s without sleeping and RLIMIT_RTTIME killed it; docs/realtime.md). That is
        # the start-up, not the ride-through under test: one more attempt, said so.
        # (Nowadays the launcher raises the priority only once the nodes are up.)
        if attempt == 2 or engaged(run.result):
            break
        reason = (run.result.message or '-').splitlines()[0]
        print(f'attempt 1 never engaged: {reason}; node exits {run.result.node_exit_codes}; '
              'trying once more')
    stats = run.stats
    # The separate layout costs about three times the composed one (six processes, ~65 %
    # of a core here): a machine that cannot run it in real time drops the robot before
    # any freeze. That is a measured capacity, not the ride-through under test.
    if stats['fell'] and (not starts or stats['release_monotonic_s'] + stats['fall_time_s']
                          < starts[0]):
        pytest.skip(f'this machine cannot run the separate layout in real time: the robot '
                    f'fell {stats["fall_time_s"]:.2f} s after the release, before any '
                    f'freeze (command gaps p99 {stats["command_gap"]["p99_ms"]:.0f} ms, '
                    f'max {stats["command_gap"]["max_ms"]:.0f} ms)')
    assert [name for name, _ in log] == names, (
        f'frozen: {log}; base: {stats["end_reason"]}, exit {run.base_code}; safety events '
        f'{[e["state"] for e in run.result.safety_events][:10]}; controllers: '
        f'{run.result.message}; node exits {run.result.node_exit_codes}')
    assert run.base_code == 0 and not stats['fell'], stats['end_reason']
    theta_max, _ = _on_the_line(stats, after=0.0)
    print(f'freezes {log}: max |theta| {theta_max:.3f} rad')
    assert theta_max < 0.3


def test_a_freeze_past_the_bound_zeroes_the_torque_and_names_the_cause(tmp_path):
    log = []
    run = run_against_standin(tmp_path / 'long_freeze', BASE, 8.0, exit_after_fall=1.0,
                              during=_freezes(['controllers'], (0.5,), log),
                              arm_delay=SHORT_ARM_DELAY)
    result = run.result
    assert log and log[0][1] >= 0.5
    assert all(c == 0 for c in result.node_exit_codes.values()), result.node_exit_codes
    # The cause: the layer's own tick gap ('stalled', when it woke up to fresh inputs) or
    # an input older than age limit + bridge ('stale'), whichever it saw first.
    after = [e for e in result.safety_events if e['state'] == 'FAULT']
    assert any('bridge' in e['reasons'] and ('stale' in e['reasons']
                                             or 'stalled' in e['reasons'])
               for e in after), result.safety_events


def test_sensor_samples_delivered_late_in_bunches_are_ridden_through(tmp_path):
    """Sensor samples delivered late in bunches are ridden through.

    The base sends its encoder and IMU samples four at a time (every 20 ms the last 20 ms
    of samples, each with its own stamp), as a buffering USB/CAN bridge does: the ESO
    integrates each at its own sample time, so a bunch is neither a velocity spike nor a
    lost sample, and the robot balances as with a steady stream.
    """
    run = run_against_standin(tmp_path / 'bunched', BASE, RUN_TIME,
                              base_extra={'sensor_bunch': 4}, arm_delay=SHORT_ARM_DELAY)
    stats = run.stats
    assert run.base_code == 0 and not stats['fell'], stats['end_reason']
    theta_max, y_max = _on_the_line(stats, after=10.0)
    print(f'bunches of 4: max |theta| {theta_max:.3f} rad, max |y| after 10 s {y_max:.2f} m')
    assert theta_max < 0.3
    assert y_max < 0.6
    # Every estimate still comes from one sample: the ESO received the samples the base
    # published while balancing (counted by the base in the same run; 10 % for best-effort
    # delivery on a busy machine, and the last bunch held back at the base's end).
    eso = next(v for k, v in run.result.node_diagnostics.items() if k.startswith('/eso:'))
    assert int(eso['received imu']) >= 0.9 * stats['ticks_after_release'] > 0, (
        eso['received imu'], stats['ticks_after_release'])
