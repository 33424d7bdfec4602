"""Model identification (wip_tools.identify, docs/identification.md).

Tested on in-process runs of the excitation scenario: off-nominal paper plants are
recovered, a standing-still run determines nothing, the identified model as the
controllers' one, and the CLI.
"""

import pathlib

import numpy as np
import pytest
import yaml

from wip_tools.analysis.metrics import true_lumped_disturbances
from wip_sim.core.plant import Plant
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import scenario_from_mapping
from wip_runtime.cli import EXIT_OK, EXIT_USAGE
from wip_tools import identify, identify_record

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXCITATION = ROOT / 'scenarios' / 'identification_excitation.yaml'
#: The combinations the excitation run must determine (l and m_p l² need turning at a
#: large tilt, which a gentle run does not do: they must be reported not determined).
DETERMINED = ('effective_mass', 'mpl', 'pitch_inertia', 'yaw_inertia_total')
#: Off-nominal plants: body mass ±20 %, centre-of-mass height ±10 % (nominal 25 kg, 0.6 m).
PLANTS = {'heavy_high': {'body_mass': 30.0, 'com_height': 0.66},
          'light_low': {'body_mass': 20.0, 'com_height': 0.54},
          'heavy_low': {'body_mass': 30.0, 'com_height': 0.54}}

_RUNS = {}


def _scenario(plant, model='paper', **changes):
    data = yaml.safe_load(EXCITATION.read_text())
    data['plant'] = {'model': model, 'parameters': dict(plant)}
    data.update(changes)
    return scenario_from_mapping(data)


def _run(key, plant, **changes):
    """One run per (key, plant) in the session: several tests share the same runs."""
    if key not in _RUNS:
        scenario = _scenario(plant, **changes)
        _RUNS[key] = (scenario, run_scenario(scenario))
    return _RUNS[key]


@pytest.mark.parametrize('name', sorted(PLANTS))
def test_excitation_run_recovers_every_combination_within_5_percent(name):
    # Noise-free sensors (the scenario's defaults); the fit uses the truth. What a robot
    # gives, noisy sensors, is the next test.
    scenario, result = _run(name, PLANTS[name])
    assert not result.fell
    fit = identify.identify(result.record, scenario.controller_model.parameters)
    true = identify.true_values(scenario.plant.parameters)
    for key in DETERMINED:
        estimate = fit.estimates[key]
        assert estimate.value is not None, (key, estimate.reason)
        assert estimate.value == pytest.approx(true[key], rel=0.05), key
        assert estimate.half_width < 0.05 * estimate.value
    for key in ('mpl2', 'com_height'):
        assert fit.estimates[key].value is None
        assert fit.estimates[key].reason
    assert fit.condition < identify.MAX_CONDITION


#: An IMU's noise (pitch 0.002 rad, gyro 0.01 rad/s: the robustness campaigns' values) and
#: a GPS's; the controllers run on these sensors, and the fit uses what they said.
IMU_NOISE = {'imu_pitch_noise_std': 0.002, 'imu_yaw_noise_std': 0.002,
             'gyro_noise_std': 0.01, 'gps_noise_std': 0.02}


@pytest.mark.parametrize('model', ['paper', 'full'])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_the_sensors_of_a_noisy_run_recover_every_combination_within_5_percent(model, seed):
    # A robot's bag has no ground truth: the fit takes the IMU's pitch and rates and the
    # wheel joint angles (auto picks them without truth). Measured worst: 3.6 % (J_θ, full
    # plant, seed 3; three laps at 0.8 Hz); at the former 4 Hz cut-off m_v came out 10 % low,
    # and two laps at 1 Hz left m_p l 6.8 % low under the quieter MPC (errors in variables).
    plant = PLANTS['heavy_high'] if seed != 2 else PLANTS['light_low']
    scenario, result = _run(f'noisy_{model}_{seed}', plant, model=model, seed=seed,
                            sensors=IMU_NOISE)
    assert not result.fell
    record = {g: result.record[g] for g in ('wheels', 'encoders', 'imu')}
    fit = identify.identify(record, scenario.controller_model.parameters, model=model)
    assert fit.source == 'sensors'
    true = identify.true_values(scenario.plant.parameters)
    for key in DETERMINED:
        assert fit.value(key) == pytest.approx(true[key], rel=0.05), key


def test_stamps_of_publishing_not_of_reading_are_noted_as_irregular():
    # A sample stamped late by 0.3-0.9 period puts its two intervals a quarter or more off
    # the period: with 10 % of them late, about 2 p (1 - p) = 18 % of the intervals.
    scenario, result = _run('noisy_paper_1', PLANTS['heavy_high'], model='paper', seed=1,
                            sensors=IMU_NOISE)
    record = {g: dict(result.record[g]) for g in ('wheels', 'encoders', 'imu')}
    assert identify.irregular_stamps(record) == 0.0
    t = np.asarray(record['encoders']['t'], dtype=float)
    period = float(np.median(np.diff(t)))
    rng = np.random.default_rng(0)
    late = rng.random(len(t)) < 0.1
    record['encoders']['t'] = t + np.where(late, rng.uniform(0.3, 0.9, len(t)) * period, 0.0)
    assert identify.irregular_stamps(record) == pytest.approx(2 * 0.1 * 0.9, abs=0.02)
    assert identify.irregular_stamps({}) == 0.0


def test_the_gyros_white_noise_is_measured_from_its_second_differences():
    # A body swaying at 1 Hz by 0.2 rad/s, sampled at 200 Hz with white noise of std σ, and
    # a burst of 20 samples 1 rad/s off (a bump): σ within 5 %.
    t = np.arange(0.0, 40.0, 0.005)
    rng = np.random.default_rng(1)
    for sigma in (0.0025, 0.01):
        rate = 0.2 * np.sin(2.0 * np.pi * t) + sigma * rng.standard_normal(len(t))
        rate[1000:1020] += 1.0
        record = {'imu': {'t': t, 'pitch_rate': rate}}
        assert identify.gyro_white_noise(record) == pytest.approx(sigma, rel=0.05)
    assert identify.gyro_white_noise({}) == 0.0
    unreadable = {'imu': {'t': t, 'pitch_rate': np.full(len(t), np.nan)}}
    assert identify.gyro_white_noise(unreadable) == 0.0


@pytest.mark.parametrize('model', ['paper', 'full'])
def test_axle_friction_is_identified_with_the_others_from_noisy_sensors(model):
    # A plant whose wheels have viscous axle friction b = 0.05 N m s/rad (plant
    # wheel_friction), noisy sensors, the fit from the sensors with --friction: b and every
    # combination within 5 % (measured: b within 0.5 %, the others within 1.5 %). Not
    # fitting b biases the others (m_v −4.5 %, m_p l and J_θ not determined, paper rows).
    b = 0.05
    data = yaml.safe_load(EXCITATION.read_text())
    data['plant'] = {'model': model, 'wheel_friction': b,
                     'parameters': dict(PLANTS['heavy_high'])}
    data.update(seed=1, sensors=IMU_NOISE)
    scenario = scenario_from_mapping(data)
    result = run_scenario(scenario)
    assert scenario.plant.model.wheel_friction == b and not result.fell
    record = {g: result.record[g] for g in ('wheels', 'encoders', 'imu')}
    fit = identify.identify(record, scenario.controller_model.parameters, model=model,
                            friction=True)
    true = identify.true_values(scenario.plant.parameters)
    for key in DETERMINED:
        assert fit.value(key) == pytest.approx(true[key], rel=0.05), key
    assert fit.value('friction') == pytest.approx(b, rel=0.05)


def test_state_estimate_alone_also_recovers_them_within_5_percent():
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    fit = identify.identify(result.record, scenario.controller_model.parameters,
                            source='estimate')
    true = identify.true_values(scenario.plant.parameters)
    for key in DETERMINED:
        assert fit.value(key) == pytest.approx(true[key], rel=0.05), key


@pytest.mark.parametrize('source', ['truth', 'estimate'])
def test_full_plant_is_recovered_with_the_full_rows_and_not_with_eq_1(source):
    """The full plant is recovered with the full rows and not with eq. (1).

    A real robot has the motor reaction torque: (1) does not fit it (values not
    determined or off), the full plant's rows do (docs/identification.md §7).
    """
    scenario, result = _run('full_heavy_high', PLANTS['heavy_high'], model='full')
    nominal = scenario.controller_model.parameters
    true = identify.true_values(scenario.plant.parameters)
    fit = identify.identify(result.record, nominal, source=source, model='full')
    for key in DETERMINED:
        assert fit.value(key) == pytest.approx(true[key], rel=0.05), key
    paper = identify.identify(result.record, nominal, source='truth')
    assert any(paper.value(k) is None or abs(paper.value(k) / true[k] - 1.0) > 0.05
               for k in DETERMINED)


def test_standing_still_determines_nothing():
    scenario, result = _run('hold', {}, reference={'kind': 'hold'}, duration=8.0)
    fit = identify.identify(result.record, scenario.controller_model.parameters)
    assert all(e.value is None and e.half_width is None for e in fit.estimates.values())
    text = identify.table(fit)
    assert text.count('not determined') == len(fit.estimates)
    for line in text.splitlines()[2:]:
        assert 'not determined' in line
    overrides, notes = identify.to_parameters(fit, scenario.controller_model.parameters)
    nominal = scenario.controller_model.parameters
    assert overrides['body_mass'] == pytest.approx(nominal.body_mass)
    assert any('not determined' in n for n in notes)


def test_identified_model_maps_back_to_the_plant_combinations():
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    nominal = scenario.controller_model.parameters
    overrides, _ = identify.to_parameters(identify.identify(result.record, nominal), nominal)
    model = nominal.replace(**overrides)
    truth = scenario.plant.parameters
    assert model.effective_mass == pytest.approx(truth.effective_mass, rel=0.01)
    assert model.body_mass * model.com_height == pytest.approx(
        truth.body_mass * truth.com_height, rel=0.01)
    assert model.pitch_inertia == pytest.approx(truth.pitch_inertia, rel=0.01)
    assert model.yaw_inertia_total == pytest.approx(truth.yaw_inertia_total, rel=0.01)


def _eso_error_and_tracking(scenario, record):
    """RMS of the forward/tilt ESO errors f̂ − f [m/s², rad/s²] and of the path error [m]."""
    lumped = true_lumped_disturbances(record, Plant(scenario.plant.parameters, 'paper'),
                                      scenario.controller_model.parameters)
    est, truth, ref = record['estimate'], record['truth'], record['reference']
    n = min(len(est['t']), len(truth['t']), len(ref['t']))
    keep = truth['t'][:n] >= 5.0
    rms = lambda x: float(np.sqrt(np.mean(np.square(x[:n][keep]))))  # noqa: E731
    path = np.hypot(truth['x'][:n] - ref['x'][:n], truth['y'][:n] - ref['y'][:n])
    return (rms(est['f2'][:n] - lumped['f2'][:n]), rms(est['f3'][:n] - lumped['f3'][:n]),
            rms(path))


def test_identified_model_as_the_controllers_model_is_no_worse():
    """The issue asked for a lower RMS tracking error with the identified model.

    Measured (docs/identification.md §6), it is not: the ESOs absorb the model error, and the path
    error and the ESO errors f̂ − f change by about ±1 % either way (here 0.0283 m nominal,
    0.0285 m identified). What is checked is what holds: the identified model balances and tracks
    as well as the nominal one, within 5 %.
    """
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    nominal = scenario.controller_model.parameters
    overrides, _ = identify.to_parameters(identify.identify(result.record, nominal), nominal)
    tuned = _scenario(PLANTS['heavy_high'], controller_model={'parameters': overrides})
    tuned_result = run_scenario(tuned)
    assert not tuned_result.fell
    f2_nom, f3_nom, path_nom = _eso_error_and_tracking(scenario, result.record)
    f2_id, f3_id, path_id = _eso_error_and_tracking(tuned, tuned_result.record)
    assert path_id < 1.05 * path_nom, (path_nom, path_id)
    assert f2_id < 1.1 * f2_nom and f3_id < 1.1 * f3_nom, (f2_nom, f2_id, f3_nom, f3_id)


def test_cli_on_a_saved_record(tmp_path, capsys):
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    npz = tmp_path / 'timeseries.npz'
    result.record.save_npz(npz)
    out = tmp_path / 'model.yaml'
    assert identify.main([str(tmp_path), '--out', str(out)]) == EXIT_OK
    printed = capsys.readouterr().out
    assert 'J_theta' in printed and 'not determined' in printed
    section = yaml.safe_load(out.read_text())['controller_model']['parameters']
    assert scenario_from_mapping({'controller_model': {'parameters': section}})
    params = tmp_path / 'model_params.yaml'
    assert identify.main([str(npz), '--out', str(params), '--write-params']) == EXIT_OK
    ros = yaml.safe_load(params.read_text())['/**']['ros__parameters']
    assert ros['model.body_mass'] == pytest.approx(section['body_mass'])


@pytest.mark.parametrize('case', ['missing', 'short', 'no_truth_no_wheels', 'not_npz'])
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys, case):
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    path = tmp_path / 'timeseries.npz'
    if case == 'short':
        groups = {g: {c: v[:200] for c, v in cols.items()}
                  for g, cols in result.record.groups.items()}
        type(result.record)(groups).save_npz(path)
    elif case == 'no_truth_no_wheels':
        groups = {g: cols for g, cols in result.record.groups.items()
                  if g not in ('truth', 'wheels')}
        type(result.record)(groups).save_npz(path)
    elif case == 'not_npz':
        path.write_text('not a record')
    elif case == 'missing':
        path = tmp_path / 'absent'
    assert identify.main([str(path)]) == EXIT_USAGE
    err = capsys.readouterr().err.strip()
    assert err.startswith('ERROR: ') and '\n' not in err, err


def _write_bag(directory, record, groups=('truth',)):
    """Write the record's truth as /wip/ground_truth messages in a rosbag2 MCAP bag.

    They are what the plant node publishes; stamps are the simulated times.
    """
    serialization = pytest.importorskip('rclpy.serialization')
    from wip_bag.bag_writer import Rosbag2McapWriter
    from wip_msgs.msg import GroundTruth
    truth = record['truth']
    with Rosbag2McapWriter(directory) as bag:
        if 'truth' in groups:
            bag.add_topic('/wip/ground_truth', 'wip_msgs/msg/GroundTruth')
        for k, t in enumerate(truth['t'].tolist()):
            stamp = int(round(t * 1e9))
            if 'truth' in groups:
                m = GroundTruth()
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
                for name in ('x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot',
                             'tau_left', 'tau_right'):
                    setattr(m, name, float(truth[name][k]))
                bag.write('/wip/ground_truth', serialization.serialize_message(m), stamp)


@pytest.mark.ros  # wip_msgs and rclpy: the colcon-built workspace
def test_cli_on_a_bag(tmp_path, capsys):
    scenario, result = _run('heavy_high', PLANTS['heavy_high'])
    _write_bag(tmp_path / 'bag', result.record)
    assert identify.main([str(tmp_path / 'bag')]) == EXIT_OK
    printed = capsys.readouterr().out
    assert 'J_theta' in printed and 'model.' not in printed and 'controller_model:' in printed
    # The bag's record gives the same fit as the in-process one.
    fit = identify.identify(identify_record.load_record(tmp_path / 'bag'),
                            scenario.controller_model.parameters)
    true = identify.true_values(scenario.plant.parameters)
    for key in DETERMINED:
        assert fit.value(key) == pytest.approx(true[key], rel=0.05), key


@pytest.mark.ros  # wip_msgs and rclpy: the colcon-built workspace
def test_cli_on_a_bag_without_the_needed_topics(tmp_path, capsys):
    serialization = pytest.importorskip('rclpy.serialization')
    from std_msgs.msg import String
    from wip_bag.bag_writer import Rosbag2McapWriter
    with Rosbag2McapWriter(tmp_path / 'bag') as bag:
        bag.add_topic('/chatter', 'std_msgs/msg/String')
        bag.write('/chatter', serialization.serialize_message(String(data='hi')), 1)
    assert identify.main([str(tmp_path / 'bag')]) == EXIT_USAGE
    err = capsys.readouterr().err.strip()
    assert err.startswith('ERROR: ') and '\n' not in err, err
