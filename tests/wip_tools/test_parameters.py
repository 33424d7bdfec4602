"""The parameter reference: generated from the declarations, complete, and not drifting.

- docs/parameters.md equals ``wip_tools.parameters.markdown()``;
- every parameter a node declares at run time is in the registry with a unit and a range
  (or choices, or 'any' for a string), and every registered one is declared;
- ``scripts/simulate --list-parameters`` lists node parameters and only real scenario keys.
"""

import pathlib
import sys

import pytest

from wip_tools import parameters as reference

REPO = pathlib.Path(__file__).resolve().parents[2]
#: Parameters rclpy declares on every node by itself.
ROS_OWN = {'use_sim_time', 'start_type_description_service'}


def test_committed_reference_equals_the_generated_one():
    committed = (REPO / 'docs' / 'parameters.md').read_text(encoding='utf-8')
    assert committed == reference.markdown(), (
        'docs/parameters.md is stale: regenerate it with '
        '`ros2 run wip_tools parameters --markdown > docs/parameters.md`')


def test_registry_is_importable_without_rclpy_and_every_row_is_documented():
    # A fresh interpreter: the reference must not need a ROS installation's rclpy.
    import subprocess
    code = ('import sys; import wip_tools.parameters as p; p.markdown(); '
            "print('rclpy' in sys.modules)")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == 'False'
    for executable in reference.node_registry():
        rows = reference.node_rows(executable)
        assert rows, executable
        names = [r.name for r in rows]
        assert len(names) == len(set(names)), f'{executable} declares a name twice'
        for row in rows:
            assert row.unit, f'{executable}: {row.name} has no unit'
            assert row.range, f'{executable}: {row.name} has no range'
            assert row.description, f'{executable}: {row.name} has no description'


def test_list_parameters_shows_nodes_and_real_scenario_keys(capsys):
    from wip_tools.simulate import main
    assert main(['--list-parameters']) == 0
    text = capsys.readouterr().out
    for node, name in (('torque_mixer', 'safety.bridge_time'), ('eso', 'left_wheel_sign'),
                       ('eso', 'imu_mounting_rpy'), ('eso', 'datum.latitude'),
                       ('eso', 'position_source'), ('plant', 'start.expected_clock_subscribers'),
                       ('recorder', 'compression'), ('replay', 'rate')):
        section = text.split(f'node {node} (')[1].split('\n\n')[0]
        assert f'  {name} ' in section, (node, name)
    scenario = text.split('scenario file keys')[1]
    assert 'plant.model.model' not in scenario
    assert '  plant.model ' in scenario
    assert 'DisturbanceComponent(' not in scenario  # no Python reprs
    assert 'sine(amplitude=1, frequency=0.5)' in scenario
    for key, unit in (('duration', 's'), ('seed', '1'), ('fall_threshold', 'rad')):
        line = next(row for row in scenario.splitlines() if row.split()[:1] == [key])
        assert line.split()[1] == unit, line


def test_unknown_node_is_a_one_line_usage_error(capsys):
    assert reference.main(['--node', 'nope']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "unknown node 'nope'" in err


# -- run time: what the nodes really declare ------------------------------------------------

rclpy = pytest.importorskip('rclpy')


def _node_classes():
    from wip_bag.recorder_node import RecorderNode
    from wip_bag.replayer_node import ReplayerNode
    from wip_control.nodes.arc_node import ArcNode
    from wip_control.nodes.eso_node import EsoNode
    from wip_control.nodes.mpc_node import MpcNode
    from wip_control.nodes.reference_node import ReferenceNode
    from wip_control.nodes.torque_mixer_node import TorqueMixerNode
    from wip_control.nodes.trajectory_generator_node import TrajectoryGeneratorNode
    from wip_sim.plant_node import PlantNode
    from wip_sim.standin_base import StandinBase
    from wip_viewer.viewer_node import ViewerNode
    classes = {'reference': ReferenceNode, 'eso': EsoNode,
               'trajectory_generator': TrajectoryGeneratorNode, 'arc': ArcNode,
               'mpc': MpcNode, 'torque_mixer': TorqueMixerNode, 'plant': PlantNode,
               'standin_base': StandinBase, 'recorder': RecorderNode,
               'replay': ReplayerNode, 'viewer': ViewerNode}
    try:
        from wip_viewer.foxglove_bridge import FoxgloveBridge
        classes['foxglove_bridge'] = FoxgloveBridge
    except ImportError:  # the foxglove SDK is optional
        pass
    return classes


def _declared(cls, context, overrides):
    """Names the node declares.

    A node that refuses its (absent) input after declaring, such as the replayer without a bag,
    still shows what it declared.
    """
    from rclpy.parameter import Parameter
    node = cls.__new__(cls)
    try:
        node.__init__(context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in overrides.items()])
    except ValueError as err:
        assert 'bag' in str(err), err  # only the replayer's missing bag is expected
    try:
        return {name for name in node._parameters if name not in ROS_OWN}
    finally:
        node.destroy_node()


def test_every_declared_parameter_is_registered_and_vice_versa(tmp_path):
    classes = _node_classes()
    registry = reference.node_registry()
    missing = set(registry) - set(classes)
    assert missing <= {'foxglove_bridge'}, missing
    overrides = {'recorder': {'output': str(tmp_path / 'bag')},
                 'foxglove_bridge': {'port': 0}}
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        for executable, cls in classes.items():
            declared = _declared(cls, context, overrides.get(executable, {}))
            registered = {row.name for row in reference.node_rows(executable)}
            assert declared == registered, (
                executable, 'declared, not registered:', sorted(declared - registered),
                'registered, not declared:', sorted(registered - declared))
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize('executable, overrides, message', [
    ('standin_base', {'sensor_bunch': 11}, 'sensor_bunch: must be <= 10, got 11'),
    ('replay', {'bag': 'x', 'rate': -1.0}, 'rate: must be > 0.0, got -1.0'),
    ('eso', {'left_wheel_sign': 2}, 'left_wheel_sign: must be 1 or -1, got 2'),
    ('reference', {'realtime_start': 'later'},
     "realtime_start: 'later' is not one of ['first_tick', 'engaged']"),
    ('recorder', {'compression': 'gzip'}, "compression: 'gzip' is not one of"),
])
def test_a_value_out_of_its_declared_range_is_refused_naming_the_parameter(
        executable, overrides, message, tmp_path):
    # The range checks come from the declarations, also where rclpy's descriptor range
    # would have refused the value first (integers: sensor_bunch).
    from rclpy.parameter import Parameter
    from wip_runtime.config import ParamError
    context = rclpy.Context()
    rclpy.init(context=context)
    cls = _node_classes()[executable]
    values = {'output': str(tmp_path / 'bag')} if executable == 'recorder' else {}
    try:
        with pytest.raises(ParamError) as caught:
            cls(context=context, parameter_overrides=[
                Parameter(k, value=v) for k, v in {**values, **overrides}.items()])
        assert str(caught.value).startswith(message), str(caught.value)
    finally:
        rclpy.shutdown(context=context)
