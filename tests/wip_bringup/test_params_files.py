"""The generated params file and the nodes' declared parameters stay in sync.

Each node of the graph is built in this process with the generated file as its
``--params-file`` (exactly how run_graph starts it, minus the process), then:

- every parameter of the file is declared by the node (ROS silently ignores an
  undeclared one, so a renamed parameter would otherwise fall back to its default), with
  the file's value and type (a float written as ``25`` would be refused as an integer);
- every parameter the node declares in a section the file writes (``eso.*``, ``model.*``
  ...) is in the file (a new config field gets its scenario value, not its default);
- each config section read back from the node's parameters equals the scenario's
  dataclass (non-default values, so a default could not pass by accident).
"""

import dataclasses

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.parameter import Parameter  # noqa: E402
import yaml  # noqa: E402

from wip_control.core.arc import ArcParams  # noqa: E402
from wip_runtime.config import from_mapping  # noqa: E402
from wip_control.core.eso import EsoParams  # noqa: E402
from wip_control.core.mixer import MixerParams  # noqa: E402
from wip_control.core.mpc_config import MpcParams  # noqa: E402
from wip_description.params import ModelParams  # noqa: E402
from wip_control.core.position import PositionParams  # noqa: E402
from wip_control.core.references import ReferenceParams  # noqa: E402
from wip_control.core.controller_settings import RatesParams  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping, scenario_to_mapping  # noqa: E402
from wip_control.core.trajectory_generator import TrajectoryGeneratorParams  # noqa: E402
from wip_control.nodes.settings import WheelTorqueLimit  # noqa: E402
from wip_bringup.params_files import (flatten, graph_parameters, section_applies,  # noqa: E402
                                            write_params_file)
from wip_bringup.private_domain import take_private_domain  # noqa: E402

pytestmark = pytest.mark.ros

# Every section changed from its default, so that reading the default back cannot pass.
SCENARIO = {
    'duration': 3.0,
    'rates': {'plant_rate': 900.0, 'control_rate': 100.0},
    'controller_model': {'parameters': {'body_mass': 27.5, 'wheel_radius': 0.21}},
    'reference': {'kind': 'circle', 'circle_radius': 2.5, 'circle_center': [1.0, -1.0]},
    'sensors': {'gps_rate': 5.0, 'encoders_relative_to_body': False,
                'gps_datum_latitude': 47.3769, 'gps_datum_longitude': 8.5417,
                'gps_datum_altitude': 408.0},
    'eso': {'epsilon': 0.02, 'sample_period': 0.01, 'tilt_gains': [5.0, 9.0, 5.0]},
    'position': {'gps_blend_gain': 0.5},
    'trajectory_generator': {'lambda1': 2.0, 'max_speed': 1.2},
    'arc': {'yaw_rate_gain': 15.0},
    'mpc': {'prediction_horizon': 15, 'control_horizon': 5, 'sampling_period': 0.2,
            'max_tilt': 0.12},
    'mixer': {'max_wheel_torque': 12.0},
}

#: node -> {parameter section: (config class, scenario value getter)}.
SECTIONS = {
    'reference': {'reference': (ReferenceParams, lambda s: s.reference),
                  'rates': (RatesParams, lambda s: s.rates)},
    'eso': {'eso': (EsoParams, lambda s: s.eso),
            'position': (PositionParams, lambda s: s.position),
            'model': (ModelParams, lambda s: s.controller_model.parameters)},
    'trajectory_generator': {'trajectory_generator': (TrajectoryGeneratorParams,
                                                      lambda s: s.trajectory_generator)},
    'arc': {'arc': (ArcParams, lambda s: s.arc), 'rates': (RatesParams, lambda s: s.rates)},
    'mpc': {'mpc': (MpcParams, lambda s: s.mpc),
            'model': (ModelParams, lambda s: s.controller_model.parameters),
            'mixer': (WheelTorqueLimit, lambda s: WheelTorqueLimit(s.mixer.max_wheel_torque)),
            'rates': (RatesParams, lambda s: s.rates)},
    'torque_mixer': {'mixer': (MixerParams, lambda s: s.mixer),
                     'rates': (RatesParams, lambda s: s.rates),
                     'model': (ModelParams, lambda s: s.controller_model.parameters)},
}


def node_class(name):
    if name == 'plant':
        from wip_sim.plant_node import PlantNode
        return PlantNode
    module = __import__(f'wip_control.nodes.{name}_node', fromlist=['x'])
    class_name = ''.join(part.capitalize() for part in name.split('_')) + 'Node'
    return getattr(module, class_name)


@pytest.fixture(scope='module')
def scenario():
    return scenario_from_mapping(SCENARIO)


@pytest.fixture(scope='module', params=['lockstep', 'realtime'])
def params_file(request, scenario, tmp_path_factory):
    directory = tmp_path_factory.mktemp(f'params_{request.param}')
    scenario_path = directory / 'scenario.yaml'
    scenario_path.write_text(yaml.safe_dump(scenario_to_mapping(scenario)))
    path = write_params_file(scenario, directory / 'params.yaml', request.param,
                             scenario_path, plant_extra={'autostart': False})
    return request.param, path


@pytest.fixture
def build_node(params_file):
    """Build a node in a private context whose arguments hold the params file."""
    built = []

    def build(name):
        _, path = params_file
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=take_private_domain(),
                   args=['--ros-args', '--params-file', str(path)])
        node = node_class(name)(context=context)
        built.append((node, context))
        return node
    yield build
    for node, context in built:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def _as_python(value):
    if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
        return list(value)
    return value


@pytest.mark.parametrize('name', ['reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                                  'torque_mixer', 'plant'])
def test_every_generated_parameter_is_declared_with_its_value_and_type(name, params_file,
                                                                      build_node):
    clock_mode, path = params_file
    written = flatten(yaml.safe_load(path.read_text())[name]['ros__parameters'])
    node = build_node(name)
    for key, value in written.items():
        assert node.has_parameter(key), f'{name}: {key} is in the params file but not declared'
        actual = node.get_parameter(key)
        assert _as_python(actual.value) == value, f'{name}.{key}'
        # The ROS type follows the written value: float stays double, int stays integer.
        expected_type = Parameter.Type.from_parameter_value(value)
        assert actual.type_ == expected_type, f'{name}.{key}: {actual.type_} != {expected_type}'
    assert node.get_parameter('use_sim_time').value == (clock_mode == 'lockstep'
                                                        and name != 'plant')


@pytest.mark.parametrize('name', list(SECTIONS))
def test_every_declared_section_parameter_gets_the_scenario_value(name, scenario, params_file,
                                                                   build_node):
    _, path = params_file
    written = flatten(yaml.safe_load(path.read_text())[name]['ros__parameters'])
    node = build_node(name)
    for section, (config_cls, getter) in SECTIONS[name].items():
        declared = [p for p in node._parameters if p.startswith(section + '.')]
        assert declared, f'{name} declares no {section}.* parameter'
        missing = sorted(set(declared) - set(written))
        assert not missing, f'{name}: declared but not in the params file: {missing}'
        values = {f.name: _as_python(node.get_parameter(f'{section}.{f.name}').value)
                  for f in dataclasses.fields(config_cls)}
        assert from_mapping(config_cls, values, section) == getter(scenario)


def test_plain_parameters_follow_the_scenario(scenario, params_file):
    clock_mode, path = params_file
    data = graph_parameters(scenario, clock_mode, path.parent / 'scenario.yaml')
    eso = flatten(data['eso']['ros__parameters'])
    assert eso['gps_period'] == pytest.approx(0.2, abs=1e-15)  # 1 / (5 Hz)
    assert eso['encoders_relative_to_body'] is False
    assert (eso['datum.latitude'], eso['datum.longitude'], eso['datum.altitude']) == \
        (47.3769, 8.5417, 408.0)
    plant = flatten(data['plant']['ros__parameters'])
    # The plant takes the datum from its scenario file only (one source).
    assert not any(key.startswith('datum.') for key in plant)
    # Derived values are computed in the node from the values they derive from: the ARC
    # gets the model and the ESO's yaw gain scale (not α̂(0)), the mixer the MPC's period.
    arc = data['arc']['ros__parameters']
    assert 'alpha_initial' not in arc
    assert arc['model'] == data['eso']['ros__parameters']['model']
    assert arc['eso'] == {'yaw_input_gain_scale': scenario.eso.yaw_input_gain_scale}
    assert data['torque_mixer']['ros__parameters']['mpc'] == {'sampling_period': 0.2,
                                                              'fast_resolve_period': 0.05,
                                                              'push_trigger': True}


def test_the_file_has_no_yaml_aliases_and_ints_stay_ints(scenario, params_file):
    # rcl's parser does not resolve YAML anchors/aliases (&id001 / *id001).
    _, path = params_file
    text = path.read_text()
    assert '&id' not in text and '*id' not in text
    mpc = yaml.safe_load(text)['mpc']['ros__parameters']['mpc']
    assert isinstance(mpc['prediction_horizon'], int)
    model = yaml.safe_load(text)['eso']['ros__parameters']['model']
    assert all(isinstance(v, float) for v in model.values())


def test_unknown_clock_mode_is_refused(scenario):
    with pytest.raises(ValueError, match='clock_mode'):
        graph_parameters(scenario, 'fast')


SECTION_KEYS = ('/**', 'eso', '/eso', '*', '/*', '/**/eso', '/*/eso', '/robot/eso',
                'robot/eso', '/robot/*', '/robot/**', '/**/robot/eso', '/a/b/eso', '/a/*/eso',
                '/a/**', 'mpc')


@pytest.mark.parametrize('namespace', ['', 'robot', '/a/b'])
def test_section_applies_as_rcl_gives_sections_to_a_real_node(tmp_path, namespace):
    # Each key sets a parameter of its own; a real node shows which sections rcl gave it.
    names = {key: f'p{index}' for index, key in enumerate(SECTION_KEYS)}
    path = tmp_path / 'sections.yaml'
    path.write_text(yaml.safe_dump({key: {'ros__parameters': {name: 1}}
                                    for key, name in names.items()}))
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=take_private_domain(),
               args=['--ros-args', '--params-file', str(path)])
    try:
        node = rclpy.node.Node('eso', namespace=namespace, context=context,
                               automatically_declare_parameters_from_overrides=True)
        given = {key for key, name in names.items() if node.has_parameter(name)}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert given == {key for key in SECTION_KEYS if section_applies(key, 'eso', namespace)}
    assert '/**' in given and 'mpc' not in given
