"""The MuJoCo plant (``plant: {model: mujoco}``, wip_sim.mujoco_plant) against the physics.

- where its physics and the 'full' plant's agree (flat ground, no slip, no rolling
  resistance) the closed loop gives the same motion over 10 s;
- the wheels slip where the friction cone says, and only there;
- at rest it stays at rest; a free fall keeps the full model's energy;
- the robust default controller balances it and follows the path for the whole paper
  scenario, up a 5 % slope and over a 2 cm bump.
"""

import math
import pathlib
import sys

import numpy as np
import pytest

pytest.importorskip('mujoco')

from wip_runtime.config import ParamError  # noqa: E402
from wip_sim.core.ground import ContactParams  # noqa: E402
from wip_tools.analysis.metrics import compute_metrics  # noqa: E402
from wip_description.params import ModelParams  # noqa: E402
from wip_sim.core.plant import (full_input_gains, Plant, scenario_plant,  # noqa: E402
                                simulate_hold)
from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.scenario import load_scenario, scenario_from_mapping, scenario_to_mapping
from wip_sim.mujoco_plant import MujocoPlant, body_inertias  # noqa: E402

PARAMS = ModelParams()
DT = 1e-3
LOSSLESS = ContactParams(rolling_resistance=0.0)
NO_DISTURBANCE = np.zeros((1, 3))


def _hold(plant, state, tau_left, tau_right, steps):
    return plant.hold_floats(tuple(state), tau_left, tau_right, np.zeros((steps, 3)), DT)


def test_scenario_builds_the_mujoco_plant_and_keeps_its_contact():
    scenario = scenario_from_mapping({'plant': {'model': 'mujoco',
                                                'contact': {'friction': 0.5}}})
    plant = scenario_plant(scenario)
    assert isinstance(plant, MujocoPlant)
    assert plant.contact == ContactParams(friction=0.5)
    assert plant.timestep == scenario.control_period / scenario.rates.substeps
    assert scenario_from_mapping(scenario_to_mapping(scenario)) == scenario
    # The equation plants roll without slip: a contact section there is a mistake.
    with pytest.raises(ParamError, match='plant.contact: only used by'):
        scenario_from_mapping({'plant': {'model': 'full', 'contact': {'friction': 0.5}}})
    with pytest.raises(ParamError, match='plant.contact.friction'):
        scenario_from_mapping({'plant': {'model': 'mujoco', 'contact': {'friction': -1.0}}})


def test_the_generated_bodies_have_the_full_models_masses_and_inertias():
    b = body_inertias(PARAMS)
    p = PARAMS
    # Pitch inertia about the axle of body + chassis: J_θ of the full model.
    assert b['base_pitch'] + b['base_mass'] * b['base_com'] ** 2 == pytest.approx(
        p.pitch_inertia)
    assert b['base_mass'] * b['base_com'] == pytest.approx(p.body_mass * p.com_height)
    # Yaw inertia at θ = 0 about the axle's centre, with the wheels' (J_ϕ of the model
    # but for the wheels' spin inertia, which the rolling contact adds as in J_ϕ).
    wheels = 2 * (b['wheel_diametral'] + p.wheel_mass * (p.track_width / 2) ** 2)
    assert b['base_yaw'] + wheels == pytest.approx(
        p.yaw_inertia + p.track_width ** 2 * p.wheel_mass / 2)
    # A physical body: the base's inertia satisfies the triangle inequality.
    assert b['base_roll'] + b['base_yaw'] >= b['base_pitch'] - 1e-12


@pytest.mark.parametrize('wheel_friction', [0.0, 0.5])
def test_closed_loop_motion_agrees_with_the_full_plant_over_10_s(wheel_friction):
    # Open-loop replay of recorded torques cannot be compared: the upright is unstable
    # (pole 4.6 rad/s, e^46 over 10 s), so any difference grows without bound. Closing
    # the loop with the same controller bounds the growth; what remains is what the
    # physics of the two plants does differently: the contact's compliance (0.04 mm of
    # compression, a rolling radius smaller by 2e-4, under 1 mm over the ~4 m driven),
    # MuJoCo's first-order step against RK4 at the same 1 ms, the roll inertia (+0.8 %
    # yaw inertia at 0.05 rad of tilt) and the creep of a soft friction contact (1e-4
    # m/s). Measured: 2 mm of position, 4e-4 rad of tilt, 2 mm/s; the bounds are 5x that.
    # With axle friction (the equation plant's torque term, MuJoCo's hinge damping; 0.5 N m
    # s/rad, ten times a real wheel's, so that it matters: it moves the run by 14 cm and
    # 0.025 rad of tilt) the two plants still agree within 2.8 mm and 6e-4 rad.
    records = {}
    for model in ('full', 'mujoco'):
        plant = {'model': model, 'wheel_friction': wheel_friction}
        if model == 'mujoco':
            plant['contact'] = {'rolling_resistance': 0.0}
        result = run_scenario(scenario_from_mapping({'duration': 10.0, 'plant': plant}))
        assert not result.fell
        records[model] = result.record['truth']
    full, mujoco = records['full'], records['mujoco']
    assert np.array_equal(full['t'], mujoco['t'])

    def error(name):
        return float(np.max(np.abs(full[name] - mujoco[name])))
    position = float(np.max(np.hypot(full['x'] - mujoco['x'], full['y'] - mujoco['y'])))
    assert position < 0.01
    assert error('x_v') < 0.01
    assert error('phi') < 0.01
    assert error('theta') < 0.002
    assert error('v') < 0.01
    assert error('theta_dot') < 0.003
    # The comparison is not trivial: the vehicle drove and turned.
    assert np.ptp(full['x_v']) > 1.0 and np.ptp(full['phi']) > 0.5


def _slip_threshold(params, friction):
    """Wheel torque [N m] (each wheel, both equal) at which the wheels start to slip.

    From rest upright. The ground force of a wheel is F = (τ − J_w φ̈)/r, its spin following
    the rolling υ̇ = g2 (2τ) of the full model: F = τ (1 − 2 J_w g2 / r)/r. It reaches
    the cone's μN, N = (m_p + m_c + 2 m_w) g / 2 (the centre of mass does not yet move
    vertically), at τ* = μ N r / (1 − 2 J_w g2 / r): above μ N r, because the motor also
    spins the wheel up.
    """
    p = params
    normal = (p.body_mass + p.chassis_mass + 2 * p.wheel_mass) * p.gravity / 2
    g2 = full_input_gains(p, 0.0)[1]
    return friction * normal * p.wheel_radius / (1 - 2 * p.wheel_inertia * g2 / p.wheel_radius)


@pytest.mark.parametrize('friction', [0.8, 0.4])
def test_the_wheels_slip_where_the_friction_cone_says(friction):
    threshold = _slip_threshold(PARAMS, friction)
    normal = (PARAMS.body_mass + PARAMS.chassis_mass + 2 * PARAMS.wheel_mass) * 9.81 / 2
    assert threshold > friction * normal * PARAMS.wheel_radius
    slips = {}
    for factor in (0.9, 1.1):
        plant = MujocoPlant(PARAMS, ContactParams(friction=friction, rolling_resistance=0.0))
        state = (0.0,) * 8
        peak = 0.0
        for _ in range(30):        # 30 ms of a torque step on both wheels, from rest
            state = _hold(plant, state, factor * threshold, factor * threshold, 1)
            peak = max(peak, *plant.wheel_slip())
        slips[factor] = peak
        assert state[6] > 0.1      # it drives forward either way
    # Below: the wheel rolls (a soft contact creeps by about 1e-4 m/s); above: it spins
    # faster than the ground moves under it by more than 0.05 m/s within 30 ms.
    assert slips[0.9] < 1e-3
    assert slips[1.1] > 0.05


def test_upright_at_rest_with_zero_torque_stays_at_rest():
    plant = MujocoPlant(PARAMS, ContactParams())
    start = (1.0, 2.0, 0.3, 0.5, 0.0, 0.0, 0.0, 0.0)
    state = start
    for _ in range(400):          # 2 s in control periods of 5 steps
        state = _hold(plant, state, 0.0, 0.0, 5)
    assert np.allclose(state, start, atol=1e-9)


def test_a_free_fall_keeps_the_full_models_energy_and_motion():
    # Zero torque from 0.05 rad of tilt until 0.4 rad, without rolling resistance: the
    # full model conserves E (RK4 to 1e-9 J); MuJoCo's soft contact and first-order step
    # may lose a little. Measured: 0.04 J of the 11.8 J turned into kinetic energy
    # (0.35 %), tilt within 1e-3 rad of the full model's at the end.
    full, mujoco = Plant(PARAMS, 'full'), MujocoPlant(PARAMS, LOSSLESS)
    start = (0.0, 0.0, 0.0, 0.0, 0.05, 0.0, 0.0, 0.0)
    state, reference = start, np.array(start)
    e0 = full.energy(start)
    while abs(state[4]) < 0.4:
        state = _hold(mujoco, state, 0.0, 0.0, 5)
        reference = simulate_hold(full, reference, 0.0, 0.0, None, 0.0, DT, 5)
    kinetic = e0 - PARAMS.body_mass * PARAMS.gravity * PARAMS.com_height * math.cos(state[4])
    assert kinetic > 10.0
    assert abs(full.energy(state) - e0) < 0.01 * kinetic
    assert abs(full.energy(reference) - e0) < 1e-6
    assert abs(state[4] - reference[4]) < 3e-3
    assert abs(state[3] - reference[3]) < 3e-3
    # With rolling resistance the fall loses energy, as it should.
    lossy = MujocoPlant(PARAMS, ContactParams(rolling_resistance=0.01))
    state = start
    while abs(state[4]) < 0.4:
        state = _hold(lossy, state, 0.0, 0.0, 5)
    assert full.energy(state) - e0 < -0.1


def test_robust_default_balances_the_mujoco_plant_on_the_paper_scenario():
    # The whole paper scenario (90 s, yaw disturbance, 10 m/s^2 collision pulse at 30 s)
    # with the default contact (rubber on concrete, rolling resistance 0.01): the
    # same bounds as the full plant's run in tests/test_paper_scenario.py.
    scenario = scenario_from_mapping({'plant': {'model': 'mujoco'}})
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell)
    assert not result.fell
    assert metrics['rms_position_error_m'] <= 0.7
    assert float(np.max(np.abs(result.record['truth']['theta']))) < 0.3


def test_a_state_set_from_outside_restarts_the_plant_there():
    plant = MujocoPlant(PARAMS, LOSSLESS)
    moving = _hold(plant, (0.0, 0.0, 0.0, 0.0, 0.02, 0.0, 0.3, 0.0), 1.0, 1.0, 5)
    other = (5.0, -1.0, 1.0, 2.0, 0.0, 0.1, 0.5, 0.0)
    fresh = MujocoPlant(PARAMS, LOSSLESS)
    assert _hold(plant, other, 0.0, 0.0, 5) == pytest.approx(
        _hold(fresh, other, 0.0, 0.0, 5), abs=1e-12)
    assert moving != other
    with pytest.raises(ValueError, match='built for steps of'):
        plant.hold_floats(other, 0.0, 0.0, NO_DISTURBANCE, 2e-3)


def test_disturbances_add_their_accelerations():
    # d = (d1, d2, d3) is defined as accelerations added to (ω̇, υ̇, θ̈): applied to the
    # MuJoCo plant over 20 ms from rest upright, the rates change as the full plant's do.
    d = np.tile((0.5, 1.0, -0.5), (20, 1))
    start = (0.0,) * 8
    full = simulate_hold(Plant(PARAMS, 'full'), start, 0.0, 0.0, lambda t: d[0], 0.0, DT, 20)
    mujoco = MujocoPlant(PARAMS, LOSSLESS).hold_floats(start, 0.0, 0.0, d, DT)
    for i in (5, 6, 7):            # ω, υ, θ̇
        assert mujoco[i] == pytest.approx(full[i], rel=0.02, abs=1e-4)


# ----------------------------------------------------------------------------- terrain

SCENARIOS = pathlib.Path(__file__).resolve().parents[2] / 'scenarios'


@pytest.mark.parametrize('name', ['mujoco_slope', 'mujoco_bump'])
def test_robust_default_stays_up_and_on_the_line_over_the_terrain(name):
    # A 5 % slope from x = 2 m, or a 2 cm bump at x = 5 m reached at the line's 0.5 m/s:
    # no fall, the tilt stays in the range of ordinary driving (the start-up from rest
    # takes 0.1 rad), and the vehicle ends within 5 cm of the reference's end point
    # (10 m / 12.5 m: it climbed, or crossed, and caught up).
    scenario = load_scenario(SCENARIOS / f'{name}.yaml')
    terrain = scenario.plant.terrain
    result = run_scenario(scenario)
    truth = result.record['truth']
    assert not result.fell
    assert float(np.max(np.abs(truth['theta']))) < 0.15
    end = scenario.reference.line_speed * scenario.duration
    assert abs(truth['x'][-1] - end) < 0.05
    assert float(np.max(np.abs(truth['y']))) < 0.01
    if terrain.slope_grade > 0.0:
        assert terrain.slope_grade == 0.05 and truth['x'][-1] > terrain.slope_start + 5.0
    else:
        assert terrain.bump_height == 0.02 and truth['x'][-1] > terrain.bump_position + 1.0


def test_the_slope_lifts_the_vehicle_by_its_grade():
    # Rolled 4 m up a 10 % slope, the axle is 0.4 m higher: the terrain is where the
    # scenario puts it (the height is read from the engine, not from the 8-state).
    from wip_sim.core.ground import TerrainParams
    plant = MujocoPlant(PARAMS, LOSSLESS, terrain=TerrainParams(slope_start=1.0,
                                                                slope_grade=0.1))
    state = (5.0, 0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 0.0)
    moved = _hold(plant, state, 0.0, 0.0, 50)     # 50 ms on the wheels (it rolls back)
    flat = MujocoPlant(PARAMS, LOSSLESS)
    _hold(flat, state, 0.0, 0.0, 50)
    # A wheel tangent to the slope has its centre r / cos(a) above the surface, which is
    # grade (x − start) above the plane.
    rise = plant._data.qpos[2] - flat._data.qpos[2]
    expected = 0.1 * (moved[0] - 1.0) + PARAMS.wheel_radius * (1 / math.cos(math.atan(0.1)) - 1)
    assert rise == pytest.approx(expected, abs=5e-4)
    assert expected > 0.39


def test_a_step_is_a_square_edge_of_its_height():
    # Beyond the edge the axle rests step_height higher; before it, on the plane; a wheel
    # rolled slowly into the edge (0.1 m/s, no torque) stops at it: its centre cannot come
    # nearer the edge than sqrt(r² − (r − h)²) horizontally.
    from wip_sim.core.ground import TerrainParams
    h, r = 0.04, PARAMS.wheel_radius
    terrain = TerrainParams(step_position=1.0, step_height=h)
    heights = {}
    for x in (0.5, 1.5):
        plant = MujocoPlant(PARAMS, LOSSLESS, terrain=terrain)
        _hold(plant, (x, 0.0, 0.0, x, 0.0, 0.0, 0.0, 0.0), 0.0, 0.0, 50)
        heights[x] = plant._data.qpos[2]
    assert heights[1.5] - heights[0.5] == pytest.approx(h, abs=2e-4)
    plant = MujocoPlant(PARAMS, LOSSLESS, terrain=terrain)
    state = (0.86, 0.0, 0.0, 0.86, 0.0, 0.0, 0.1, 0.0)
    farthest = 0.0
    for _ in range(30):                  # 0.3 s: it meets the edge after about 0.2 s
        state = _hold(plant, state, 0.0, 0.0, 10)
        farthest = max(farthest, state[0])
    reach = math.sqrt(r * r - (r - h) ** 2)
    assert farthest == pytest.approx(1.0 - reach, abs=2e-3)


def test_a_low_friction_patch_slips_where_the_ground_around_it_does_not():
    # μ = 0.3 on the patch (x in [−1, 1]), 0.8 around: a torque step between the two
    # thresholds (12.2 and 32.4 N m per wheel) slips on the patch only.
    from wip_sim.core.ground import TerrainParams
    terrain = TerrainParams(patch_start=-1.0, patch_end=1.0, patch_friction=0.3)
    tau = 1.2 * _slip_threshold(PARAMS, 0.3)
    assert tau < 0.9 * _slip_threshold(PARAMS, 0.8)
    peaks = {}
    for x in (0.0, 3.0):          # on the patch, beside it
        plant = MujocoPlant(PARAMS, LOSSLESS, terrain=terrain)
        state = (x, 0.0, 0.0, x, 0.0, 0.0, 0.0, 0.0)
        peak = 0.0
        for _ in range(30):
            state = _hold(plant, state, tau, tau, 1)
            peak = max(peak, *plant.wheel_slip())
        peaks[x] = peak
    assert peaks[0.0] > 0.05
    assert peaks[3.0] < 1e-3


def test_each_encoder_reads_its_own_wheel_so_one_wheel_slip_shows():
    # μ = 0.3 under the left wheel only (y > 0), 0.8 under the right: 15 N m on each
    # wheel (between the two slip thresholds, 12.2 and 32.4 N m) spins the left wheel
    # alone. Kinematics: the heading the wheels imply, ϕ_w = ϕ0 + r (φr − φl)/d, runs
    # from the true one by ∫ (s_r − s_l) dt / d (s_i: a wheel's slip speed).
    from wip_sim.core.ground import TerrainParams
    from wip_sim.core.sensor_models import Sensors
    terrain = TerrainParams(patch_start=-1.0, patch_end=1.0, patch_friction=0.3,
                            patch_y_min=0.0)
    assert 1.1 * _slip_threshold(PARAMS, 0.3) < 15.0 < 0.9 * _slip_threshold(PARAMS, 0.8)
    plant = MujocoPlant(PARAMS, LOSSLESS, terrain=terrain)
    sensors = Sensors(PARAMS)
    state = _hold(plant, (0.0,) * 8, 0.0, 0.0, 40)       # the right wheel drops 1 mm
    yaw0, _, _ = plant.wheel_readout(state)
    assert yaw0 == pytest.approx(state[2], abs=1e-6)
    slip_integral, slips = 0.0, []
    for _ in range(30):
        state = _hold(plant, state, 15.0, 15.0, 1)
        left, right = plant.wheel_slip()
        slips.append((left, right))
        slip_integral += (right - left) * DT
    assert max(s[0] for s in slips) > 1.0 and max(abs(s[1]) for s in slips) < 1e-3
    wheel_yaw, left_rate, right_rate = plant.wheel_readout(state)
    d, r = PARAMS.track_width, PARAMS.wheel_radius
    apart = d * (wheel_yaw - state[2])
    assert apart == pytest.approx(slip_integral, rel=0.1)
    assert abs(apart) > 0.02
    # The encoders: the left one ahead of the right by the slip (the true heading turned
    # the other way, left wheel held back), their rates the joints'.
    left, right = sensors.encoders(state, wheel_yaw)
    assert (left - right) * r == pytest.approx(-d * (wheel_yaw - yaw0), rel=1e-9)
    assert left - right > 0.1 and state[2] > 0.0
    assert sensors.wheel_rates(state, (left_rate, right_rate)) == (left_rate, right_rate)
    assert left_rate - right_rate > 5.0
    # A state it did not return has no readout (the sensors then use the rolling model).
    assert plant.wheel_readout((1.0,) * 8) is None


@pytest.mark.slow
def test_one_wheel_slip_shows_in_odometry_and_is_no_wiring_fault():
    # The robustness class with μ 0.2 under the left wheel (and a push on it): the
    # odometry's heading, r (φr − φl) / d, departs from the true one, and the wiring
    # check fed the run's sensors (wheel rates from the encoders, as a base's joint
    # velocities) finds nothing wrong.
    from wip_control.core.wiring_check import WiringCheck, WiringCheckParams
    from wip_tools.campaign_file import load_campaign
    campaign = load_campaign(pathlib.Path(__file__).parents[1] / 'wip_tools/robustness/'
                             'scenarios/mujoco_one_wheel_patch.yaml')
    mapping = dict(campaign.base, duration=13.0)
    result = run_scenario(scenario_from_mapping(mapping))
    assert not result.fell
    rec = result.record
    enc, imu, wheels, truth = rec['encoders'], rec['imu'], rec['wheels'], rec['truth']
    t = enc['t']
    d, r = PARAMS.track_width, PARAMS.wheel_radius
    odometry = r * (enc['right'] - enc['left']) / d
    true = np.interp(t, truth['t'], truth['phi']) - truth['phi'][0]
    assert np.max(np.abs(odometry - true)) > 0.02
    assert np.max(np.abs(odometry - true)[t < 5.0]) < 1e-3     # before the patch
    check = WiringCheck(WiringCheckParams(), PARAMS, t[1] - t[0])
    left_rate, right_rate = np.gradient(enc['left'], t), np.gradient(enc['right'], t)
    for i in range(len(t)):
        check.wheels(t[i], left_rate[i], right_rate[i])
        tau_l, tau_r = wheels['tau_left'][i], wheels['tau_right'][i]
        check.torque(t[i], tau_l + tau_r, True, tau_r - tau_l)
        verdict = check.imu(t[i], imu['pitch'][i], imu['pitch_rate'][i],
                            imu['yaw_rate'][i], None)
        assert verdict is None, verdict.reason


def test_the_plant_nodes_stepping_gives_the_runners_floats():
    # The plant node and the stand-in base step with simulate_hold (disturbance function,
    # a fresh tuple each tick), the in-process runner with hold_floats (disturbance rows,
    # its own tuple back): on the same torques and disturbances the two give the same
    # floats, so a lockstep graph run reproduces the in-process one on this plant too.
    from wip_sim.core.disturbances import Disturbances
    scenario = scenario_from_mapping({'plant': {'model': 'mujoco'}})
    disturbances = Disturbances(scenario.disturbances, seed=0)
    substeps, period = scenario.rates.substeps, scenario.control_period
    dt = period / substeps
    node, runner = scenario_plant(scenario), scenario_plant(scenario)
    start = (0.0, 0.0, 0.0, 0.0, 0.05, 0.0, 0.0, 0.0)
    node_state = runner_state = start
    for k in range(400):                  # 2 s
        t = k * period
        # Each wheel: a tilt PD (drive under the lean) and a varying turn.
        tau = 60.0 * node_state[4] + 10.0 * node_state[7] + math.sin(0.7 * t)
        node_state = tuple(simulate_hold(node, node_state, tau, tau + 0.5,
                                         disturbances.sample, t, dt, substeps).tolist())
        rows = disturbances.sample_many([t + j * dt for j in range(substeps)])
        runner_state = runner.hold_floats(runner_state, tau, tau + 0.5, rows, dt)
        assert node_state == runner_state
    # Not a trivial path: it stayed up, and turned by about 1 rad.
    assert abs(node_state[4]) < 0.1 and abs(node_state[2]) > 0.5


def test_without_mujoco_the_plant_says_what_to_install_in_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, 'mujoco', None)      # import mujoco fails
    scenario = scenario_from_mapping({'plant': {'model': 'mujoco'}})
    with pytest.raises(ImportError) as error:
        scenario_plant(scenario)
    message = str(error.value)
    assert "plant model 'mujoco' needs the mujoco package" in message
    assert 'pip install mujoco==' in message and '\n' not in message
    # The equation plants do not need it.
    assert scenario_plant(scenario_from_mapping({'plant': {'model': 'full'}})).model == 'full'
