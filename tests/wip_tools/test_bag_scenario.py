"""One scenario-lookup rule for the tools that read bags (wip_tools.bag_scenario).

The bag's own scenario, found from the bag directory or any file in it, with ``--scenario`` applied
over it key by key.
"""

import pytest
import yaml

pytest.importorskip('rclpy')

from wip_runtime.config import ParamError  # noqa: E402
from wip_sim.core.scenario import Scenario  # noqa: E402
from wip_tools.bag_scenario import merged, scenario_for_bag  # noqa: E402

#: A run on a circle with a faster yaw-rate limit than the default trifolium's 0.3 rad/s.
CIRCLE = {'name': 'circle_run', 'reference': {'kind': 'circle', 'circle_radius': 3.0},
          'trajectory_generator': {'max_yaw_rate': 0.5}}


def bag_with(tmp_path, scenario=None, custom=None):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'bag_0.mcap').write_bytes(b'')     # the lookup reads no message
    if scenario is not None:
        (bag / 'scenario.yaml').write_text(yaml.safe_dump(scenario))
    if custom is not None:
        (bag / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': {
            'version': 9, 'custom_data': {'wip.scenario': yaml.safe_dump(custom)}}}))
    return bag


def test_a_partial_scenario_changes_only_its_keys_of_the_bags_own(tmp_path):
    """A partial --scenario changes only its keys of the bag's own.

    The defect: a partial --scenario was filled from the paper's defaults, so a re-run
    of a circle bag followed a trifolium at 0.3 rad/s and blamed the tuned weight.
    """
    bag = bag_with(tmp_path, CIRCLE)
    tuned = tmp_path / 'tuned.yaml'
    tuned.write_text('mpc: {input_weight: 0.25}\n')
    scenario, where = scenario_for_bag(bag, tuned)
    assert scenario.mpc.input_weight == 0.25                       # the override
    assert scenario.reference.kind == 'circle'                     # the bag's own
    assert scenario.reference.circle_radius == 3.0
    assert scenario.trajectory_generator.max_yaw_rate == 0.5
    assert scenario.name == 'circle_run'
    assert str(tuned) in where and 'scenario.yaml' in where


def test_the_mcap_file_and_the_directory_find_the_same_scenario(tmp_path):
    bag = bag_with(tmp_path, CIRCLE)
    assert scenario_for_bag(bag / 'bag_0.mcap') == scenario_for_bag(bag)
    assert scenario_for_bag(bag)[0].reference.kind == 'circle'


def test_the_metadata_scenario_comes_before_the_file_and_nothing_outside_counts(tmp_path):
    bag = bag_with(tmp_path, {'name': 'from_file'}, custom={'name': 'from_metadata'})
    assert scenario_for_bag(bag)[0].name == 'from_metadata'
    # A scenario.yaml beside the bag directory belongs to something else: not used.
    lone = tmp_path / 'lone'
    lone.mkdir()
    (tmp_path / 'scenario.yaml').write_text(yaml.safe_dump({'name': 'beside'}))
    scenario, where = scenario_for_bag(lone)
    assert scenario == Scenario() and 'defaults' in where


def test_bad_scenarios_are_one_clear_error(tmp_path):
    bag = bag_with(tmp_path, {'mpc': {'input_weight': -1.0}})
    with pytest.raises(ParamError, match=r'mpc\.input_weight'):
        scenario_for_bag(bag)
    bag2 = tmp_path / 'b2'
    bag2.mkdir()
    (bag2 / 'scenario.yaml').write_text('- a list\n')
    with pytest.raises(ParamError, match='a scenario is a mapping'):
        scenario_for_bag(bag2)
    with pytest.raises(ParamError, match='No such file'):
        scenario_for_bag(tmp_path / 'lone_bag', tmp_path / 'missing.yaml')


def test_merge_is_by_section_and_replaces_lists_and_values():
    base = {'a': {'x': 1, 'y': [1, 2]}, 'b': 2}
    assert merged(base, {'a': {'y': [3]}, 'c': 4}) == {'a': {'x': 1, 'y': [3]}, 'b': 2,
                                                        'c': 4}
    assert base == {'a': {'x': 1, 'y': [1, 2]}, 'b': 2}           # not modified


@pytest.mark.parametrize('content', ['', '\n  \n', '# only a comment\n'])
def test_an_empty_scenario_file_in_the_bag_is_refused_not_taken_for_the_defaults(tmp_path,
                                                                                  content):
    """An empty scenario file in the bag is refused, not taken for the defaults.

    A run cut short by a full disk left an empty BAG/scenario.yaml; it was read as the
    paper's default scenario and gave metrics of another run.
    """
    bag = bag_with(tmp_path)
    (bag / 'scenario.yaml').write_text(content)
    with pytest.raises(ParamError, match='empty scenario file'):
        scenario_for_bag(bag)
    with pytest.raises(ParamError, match='empty scenario file'):
        scenario_for_bag(bag, bag / 'scenario.yaml')


@pytest.mark.parametrize('content', [b'', b'reference: {kind: [circle\n', b'\xff\xfe'],
                         ids=['empty', 'broken YAML', 'not UTF-8'])
def test_report_refuses_an_empty_or_unreadable_bag_scenario_in_one_line(tmp_path, capsys,
                                                                         content):
    from wip_tools.report import main as report_main
    bag = bag_with(tmp_path)
    (bag / 'scenario.yaml').write_bytes(content)
    assert report_main([str(bag), '--out', str(tmp_path / 'report'), '--partial']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('ERROR: ') and 'scenario.yaml' in err[0], err
    assert not (tmp_path / 'report').exists()
