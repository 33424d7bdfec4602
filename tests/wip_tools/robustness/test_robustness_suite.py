"""The robustness suite: one scenario file per robustness class.

Each with its physical pass criterion beside it (``criteria:`` in the file, the why in its header
comment).

Each file is a campaign file of one run (docs/campaign.md), so that ``scripts/campaign
FILE`` runs it too, and a campaign over seeds or parameters starts from it. Here every
class runs once, in-process, and must meet its criterion.

Classes that fail on this branch are marked ``xfail(strict=True)`` with the failure
measured (a controller change it needs is made elsewhere): when a class
starts to pass, its strict xfail fails, and the mark is to be removed.
"""

import pathlib

import pytest

from wip_tools.analysis.criteria import Criteria, criteria_to_mapping
from wip_tools.campaign import run_one
from wip_tools.campaign_file import load_campaign, run_specs

SCENARIOS = pathlib.Path(__file__).parent / 'scenarios'
ACCEPTANCE = (pathlib.Path(__file__).parents[3] / 'campaigns'
              / 'robustness_acceptance_mpc.yaml')
NOISE_100 = pathlib.Path(__file__).parents[3] / 'campaigns' / 'noise_100_seeds.yaml'

#: Classes run by this suite -> measured failure on main (None: it passes). Pushes,
#: stop-and-hold, slope and the full plant standing pass since the per-step-slack,
#: offset-free MPC (docs/mpc.md).
SUITE = {
    # Pass since the gyro-aided estimator, robust adaptation, pole-placed heading loop and
    # time-scaled reference (docs/estimation.md); measured on main before them:
    # sensor_noise fell at 0.52 s; large_initial_error 6.9 m off the path after 25 s;
    # slow_gps RMS 0.39 m; trifolium_path RMS 0.33 m (limits 0.1 m).
    'sensor_noise': None,
    # Passes since the MPC's speed preview (docs/mpc.md): RMS 0.105 m before, 0.062 after.
    'full_plant_mismatch': None,
    'pushes': None,
    'stop_and_hold': None,
    # Passes since the MPC's speed-rise slack (docs/history/mpc.md §9): max speed 1.554 m/s at the
    # cold start before (limit 1.55), 1.542 after; 2.49 after the push (limit 2.5).
    'speed_limit': None,
    # Passes since the reference's speed lead (docs/history/mpc.md §8): 0.52 m off the path
    # before, 0.08 m after.
    'sharp_corners': None,
    'large_initial_error': None,
    'slope': None,
    'wheel_radius_mismatch': None,
    'slow_gps': None,
    'full_plant_standing': None,
    'trifolium_path': None,
    # Terrain on the MuJoCo plant (docs/mujoco-plant.md): a 5 % slope from mid-path and a
    # patch of half the friction with a push on it pass.
    'mujoco_slope': None,
    'mujoco_low_friction_patch': None,
    # Passes since the drive torque may rise at impact_delta_torque against an obstacle
    # (docs/history/mpc.md §26): it ended 0.17 m from the end of the reference before
    # (limit 0.15 m), 0.141 m after. Seeds 0-99: none fall, before or after.
    'mujoco_bump': None,
    'mujoco_bump_1cm': None,
    'mujoco_bump_1cm_slow': None,
    # Passes since the MPC re-solves on the tick it sees a push (docs/history/mpc.md §14):
    # 0.107 m off the path after the bump before (limit 0.1 m), 0.078 m after. Seeds 0-19
    # with refusal_passes (docs/history/mpc.md §19): 12 crossed (7 pass), 8 refused (all
    # pass), none fell. Since the solves' mean drift and λ3 0.85 (§27) it meets the bump at
    # 0.3 m/s, not the 0.51 m/s of the speed's wander, and is refused on this seed; seeds
    # 0-99: 100 up, 100 pass.
    'mujoco_bump_2cm_slow': None,
    # Pass since a solve takes the mean drift of its period and λ3 is 0.85 (docs/history/mpc.md
    # §27): they crossed without a fall but ended 0.46 m from the end of the reference (limit
    # 0.15 m) and 0.108 m from the path (limit 0.1 m). Seeds 0-99, up / pass: 0.5 m/s
    # 100/73 -> 100/94; 0.3 m/s 100/83 -> 100/100.
    'mujoco_bump_3cm': None,
    'mujoco_bump_3cm_slow': None,
    # Passes since the drive torque may rise at impact_delta_torque against an obstacle
    # (docs/history/mpc.md §26): it met the edge at 0.51 m/s and fell at 17.57 s before;
    # now refused balanced (tilt 0.106 rad, limit 0.15), holding 0.099 m from its point.
    # Seeds 0-99: 94 up without a runaway alarm (76 before); the 6 falls met the edge at
    # 0.40-0.59 m/s (the speed's wander about 0.3 m/s under the IMU noise). 100 up since
    # the solves' mean drift and λ3 0.85 narrowed that wander (docs/history/mpc.md §27).
    'mujoco_kerb': None,
    # Seeds 0-19: 20 refused, 19 hold within 0.2 m of the point (seed 7: 0.201 m).
    'mujoco_kerb_slow': None,
    'mujoco_one_wheel_patch': None,
}
#: Classes too long for the suite: run them with scripts/campaign.
CAMPAIGN_ONLY = {'long_run_300s'}


def _params():
    for name, failure in SUITE.items():
        marks = [pytest.mark.slow]
        if failure is not None:
            marks.append(pytest.mark.xfail(strict=True, reason=f'measured: {failure}'))
        yield pytest.param(name, marks=marks, id=name)


def test_every_scenario_file_is_in_the_suite_or_campaign_only():
    files = {p.stem for p in SCENARIOS.glob('*.yaml')}
    assert files == set(SUITE) | CAMPAIGN_ONLY
    assert not set(SUITE) & CAMPAIGN_ONLY


@pytest.mark.parametrize('name', sorted(set(SUITE) | CAMPAIGN_ONLY))
def test_scenario_file_is_one_run_with_its_criterion_beside_it(name):
    path = SCENARIOS / f'{name}.yaml'
    campaign = load_campaign(path)
    assert campaign.total_runs == 1 and not campaign.vary and not campaign.grid
    # A class-specific criterion, beyond the hard limits every run meets by default.
    defaults = Criteria()
    specific = [f for f in ('max_abs_theta_outside_pulses', 'max_speed_outside_pulses',
                            'max_speed', 'max_convergence_time',
                            'max_rms_path_error_after_settle', 'max_path_error_after_settle',
                            'max_final_position_error', 'max_final_path_error',
                            'max_final_oscillation', 'max_final_abs_theta')
                if getattr(campaign.criteria, f) != getattr(defaults, f)]
    assert specific, f'{name}: no criterion of its own'
    header = path.read_text(encoding='utf-8').split('\nname:')[0]
    assert 'Criterion' in header and 'Class' in header, f'{name}: no comment with the why'
    assert campaign.criteria.max_wheel_torque == 15.0
    assert campaign.criteria.max_delta_tau_v is None   # the controller's own limit (19)
    assert campaign.criteria.max_qp_failures == 0 and campaign.criteria.no_fall


@pytest.mark.parametrize('name', list(_params()))
def test_robustness_class_meets_its_criterion(name):
    campaign = load_campaign(SCENARIOS / f'{name}.yaml')
    row = run_one(run_specs(campaign)[0], campaign.base, criteria_to_mapping(campaign.criteria))
    assert not row['error'], row['error']
    assert row['success'], f'{name}: {row["reasons"]}'


@pytest.mark.slow
def test_the_kerb_that_stops_the_vehicle_is_refused_balanced_and_a_bump_crossed_is_not():
    """The kerb that stops the vehicle is refused balanced; a bump it crosses is not refused.

    mujoco_kerb_slow: the wheels stop against the 4 cm edge with their centre
    a = √(r² − (r − h)²) = 12 cm before it (docs/mujoco-plant.md); the obstacle monitor
    must date the stall within 0.1 s of the stop (the estimate's lag) and name it 0.3 s
    later (its stall time), with the 2.0 cm the torque climbs, and the generator refuse
    0.3 s after that (obstacle_refuse_delay). Refused balanced: the axle never passes the point
    where the wheel meets the edge (5 m − 12 cm, 1 cm for the contact's give), the
    generator then follows the point 0.2 m (obstacle_back_off) behind where it stopped,
    and the vehicle ends within 0.1 m of it, at rest (|υ| < 0.05 m/s on average over the
    last 2 s), the tilt within 0.15 rad throughout. mujoco_bump_1cm and mujoco_bump
    (2 cm at 0.5 m/s): climbed, nothing named or refused (the 2 cm bump at 0.3 m/s stops
    the wheels and is refused since the speed no longer wanders up to 0.5 m/s). The stall
    is dated from the stop when the drive torque is past the 10 N m stall torque as the
    wheels stop; met
    with less (the wheels meeting the edge gently: 4-10 N m while the reference runs on)
    it is dated when the torque passes 10 N m, up to 1.2 s later, as a slope's hold below
    it is never named (docs/decisions/obstacle-refusal.md): the later of the two, each
    read from the record (the applied torque, the true lean), within 0.1 s.
    """
    import numpy as np

    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import scenario_from_mapping
    from wip_tools.campaign_file import scenario_mapping

    def run(name):
        campaign = load_campaign(SCENARIOS / f'{name}.yaml')
        return run_scenario(scenario_from_mapping(scenario_mapping(
            campaign.base, run_specs(campaign)[0])))

    kerb = run('mujoco_kerb_slow')
    truth = kerb.record['truth']
    t, x, v, theta = (np.asarray(truth[key]) for key in ('t', 'x', 'v', 'theta'))
    stop = t[np.argmax((x > 4.8) & (np.abs(v) < 0.02))]
    edge = 5.0 - 0.12
    assert not kerb.fell and x.max() <= edge + 0.01 and np.abs(theta).max() <= 0.15
    assert kerb.obstacle is not None and '2.0 cm' in kerb.obstacle.reason
    # The last rise of the applied torque past the stall torque, leaning forward, before
    # the stall was named 0.3 s (eso.obstacle_stall_time) after its start.
    torque = np.asarray(truth['tau_left']) + np.asarray(truth['tau_right'])
    window = t <= kerb.obstacle.since + 0.3
    pushing = (torque >= 10.0) & (theta > 0.0)
    gaps = np.flatnonzero(window & ~pushing)
    rise = t[gaps[-1] + 1] if gaps.size else t[0]
    dated = max(stop, rise)
    assert dated - 0.1 <= kerb.obstacle.since <= dated + 0.1, (stop, rise)
    command = kerb.record['command']
    t_c, x_e = np.asarray(command['t']), np.asarray(command['x_e'])
    refused = t_c[np.argmax((t_c >= kerb.obstacle.since) & (x_e < -0.19))]
    # Blocked 0.3 s after the stall began, refused obstacle_refuse_delay (0.3 s) later.
    assert refused == pytest.approx(kerb.obstacle.since + 0.6, abs=0.006)   # one tick
    assert x[-1] == pytest.approx(x.max() - 0.2, abs=0.1)
    assert np.abs(v[t > t[-1] - 2.0]).mean() < 0.05
    for name in ('mujoco_bump_1cm', 'mujoco_bump'):
        assert run(name).obstacle is None, name


@pytest.mark.slow
@pytest.mark.parametrize('run, body_mass', [(78, 28.60), (84, 26.84), (255, 29.72)])
def test_a_push_above_the_speed_limit_on_a_heavy_tall_body_is_caught(run, body_mass):
    """A push above the speed limit on a heavy tall body is caught.

    Acceptance runs 78 (28.6 kg, CoM 0.69 m, +7.6 m/s² at 46.4 s), 84 (26.8 kg, CoM
    0.54 m, +8 m/s² at 29.2 s) and 255 (29.7 kg, CoM 0.63 m, -8.8 m/s² at 20.7 s),
    trifolium under noise, full plant. The MPC's rise slack would weigh the acceleration
    of the recovery: without its gates (docs/history/mpc.md §9) run 78 fell at 48.8 s, run 84 at
    30.3 s (speed_rise_penalty 1e5), run 255 at 22.5 s. They must stay up and within the
    hard limits.
    """
    campaign = load_campaign(ACCEPTANCE)
    spec = run_specs(campaign)[run]
    assert spec['values']['plant.parameters.body_mass'] == pytest.approx(body_mass, abs=0.01)
    row = run_one(spec, campaign.base, criteria_to_mapping(campaign.criteria))
    assert not row['error'], row['error']
    assert row['success'], row['reasons']


@pytest.mark.slow
@pytest.mark.parametrize('run', [25, 59, 76])
def test_the_pulse_on_the_paper_plant_under_noise_is_caught(run):
    """The pulse on the paper plant under noise is caught.

    Runs 25, 59 and 76 of campaigns/noise_100_seeds.yaml: the paper's Section V
    (its 10 m/s² pulse at 30 s) on the paper plant under IMU 0.002 rad and gyro 0.01 rad/s
    noise. With the drive torque held for the 0.1 s MPC period they fell 2.5 s after the
    pulse, the tilt swinging from -0.17 to +0.31 rad with the torque at its limits; the
    MPC re-solving every 50 ms after a push (mpc.fast_resolve_period, docs/history/mpc.md §10)
    keeps them within 0.1 rad outside the pulse.
    """
    campaign = load_campaign(NOISE_100)
    spec = run_specs(campaign)[run]
    assert spec['values']['plant.model'] == 'paper'
    row = run_one(spec, campaign.base, criteria_to_mapping(campaign.criteria))
    assert not row['error'], row['error']
    assert row['success'], row['reasons']


@pytest.mark.slow
def test_without_re_solving_after_a_push_noise_run_25_falls():
    """Without re-solving after a push, noise run 25 falls.

    The run above with the torque held for the whole MPC period (fast_resolve_period
    0, as before): it falls (so the test above tests the re-solving).
    """
    campaign = load_campaign(NOISE_100)
    spec = run_specs(campaign)[25]
    base = {**campaign.base, 'mpc': {**campaign.base.get('mpc', {}),
                                     'fast_resolve_period': 0.0}}
    row = run_one(spec, base, criteria_to_mapping(campaign.criteria))
    assert not row['error'], row['error']
    assert row['fell'], ('run 25 no longer falls without re-solving: revisit '
                         'docs/history/mpc.md §10')
