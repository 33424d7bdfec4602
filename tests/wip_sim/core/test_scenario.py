"""Scenario files: defaults are the paper's Section V; typos fail naming the key."""

import math

import pytest
import yaml

from wip_runtime.config import ParamError
from wip_control.core.references import make_reference
from wip_sim.core.simulation import initial_state
from wip_sim.core.scenario import (load_scenario, Scenario, scenario_from_mapping,
                                   scenario_to_mapping)


def test_default_scenario_is_the_paper_section_v():
    scenario = load_scenario(None)
    assert scenario.duration == 90.0
    assert scenario.initial_state.pose == (0.5, 0.5, 0.1)
    assert (scenario.initial_state.x_v, scenario.initial_state.theta) == (0.1, 0.05)
    assert scenario.mpc.sampling_period == pytest.approx(0.1)
    assert scenario.mpc_decimation == 20  # 0.1 s MPC period / 5 ms control period


def test_initial_pose_has_the_requested_body_frame_errors():
    # The body-frame errors of eq. (9) recomputed from the constructed initial pose
    # must give back (0.5, 0.5, 0.1) up to rounding.
    scenario = Scenario()
    ref = make_reference(scenario.reference).sample(0.0)
    x, y, phi = initial_state(scenario, ref)[:3]
    dx, dy = ref.x - x, ref.y - y
    x_e = math.cos(phi) * dx + math.sin(phi) * dy
    y_e = -math.sin(phi) * dx + math.cos(phi) * dy
    assert (x_e, y_e, ref.phi - phi) == pytest.approx((0.5, 0.5, 0.1), abs=1e-12)


def test_round_trip_through_yaml(tmp_path):
    original = Scenario()
    path = tmp_path / 'scenario.yaml'
    path.write_text(yaml.safe_dump(scenario_to_mapping(original)))
    assert load_scenario(path) == original


@pytest.mark.parametrize('document, key', [
    ({'mpc': {'max_tilt_angle': 0.1}}, 'mpc.max_tilt_angle'),
    ({'duraton': 10.0}, 'duraton'),
    ({'plant': {'parameters': {'body_mas': 25.0}}}, 'plant.parameters.body_mas'),
    ({'eso': {'epsilon': -0.01}}, 'eso.epsilon'),
    ({'mpc': {'max_tilt': 'small'}}, 'mpc.max_tilt'),
    ({'plant': {'model': 'fancy'}}, 'plant.model'),
    ({'rates': {'plant_rate': 1000.0, 'control_rate': 300.0}}, 'rates.plant_rate'),
])
def test_bad_keys_and_values_name_the_key(document, key):
    with pytest.raises(ParamError) as info:
        scenario_from_mapping(document)
    assert str(info.value).startswith(key), str(info.value)


def test_typo_in_a_file_names_the_file_and_key(tmp_path):
    path = tmp_path / 'typo.yaml'
    path.write_text('duration: 5.0\narc:\n  yaw_gian: 10.0\n')
    with pytest.raises(ParamError, match=r'typo\.yaml: arc\.yaw_gian: unknown key'):
        load_scenario(path)


def test_missing_file_and_invalid_yaml_are_clear_errors(tmp_path):
    with pytest.raises(ParamError, match='No such file'):
        load_scenario(tmp_path / 'absent.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('mpc: [unclosed\n')
    with pytest.raises(ParamError, match='not valid YAML'):
        load_scenario(bad)


def test_a_scenario_file_without_a_name_is_named_after_the_file(tmp_path):
    path = tmp_path / 'my_slope.yaml'
    path.write_text('duration: 5.0\n', encoding='utf-8')
    assert load_scenario(path).name == 'my_slope'
    named = tmp_path / 'other.yaml'
    named.write_text('name: hill climb\nduration: 5.0\n', encoding='utf-8')
    assert load_scenario(named).name == 'hill climb'
    empty = tmp_path / 'empty.yaml'
    empty.write_text('', encoding='utf-8')
    assert load_scenario(empty).name == 'empty'
