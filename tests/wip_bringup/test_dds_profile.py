"""The Fast DDS profile the launcher gives its node processes where the user has none."""

import xml.etree.ElementTree as ET

import pytest

from wip_bringup.processes import graph_environment
from wip_runtime.dds_profile import (FASTDDS_PROFILE, LAUNCHER_PROFILE,
                                     process_ignores_local_endpoints,
                                     profile_ignores_local_endpoints, use_launcher_profile,
                                     PROFILE_VARIABLES as FASTDDS_PROFILE_VARIABLES)

NS = {'dds': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}


def test_the_profile_makes_reliable_writers_announce_their_samples_every_20_ms():
    root = ET.parse(FASTDDS_PROFILE).getroot()
    writer = root.find('dds:profiles/dds:data_writer', NS)
    assert writer.get('is_default_profile') == 'true'
    period = writer.find('dds:times/dds:heartbeatPeriod', NS)
    seconds = (int(period.find('dds:sec', NS).text)
               + 1e-9 * int(period.find('dds:nanosec', NS).text))
    assert seconds == pytest.approx(0.020)


def test_the_launcher_uses_it_only_where_the_user_has_no_profile(monkeypatch, tmp_path):
    for name in FASTDDS_PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    env = graph_environment(7)
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(FASTDDS_PROFILE)
    for name in FASTDDS_PROFILE_VARIABLES:
        own = tmp_path / 'mine.xml'
        monkeypatch.setenv(name, str(own))
        env = graph_environment(7)
        assert env[name] == str(own)
        assert all(env.get(other) in (None, '') for other in FASTDDS_PROFILE_VARIABLES
                   if other != name)
        monkeypatch.delenv(name)


def test_the_launchers_own_profile_is_set_where_the_user_has_none_and_never_reaches_a_node(
        monkeypatch, tmp_path):
    # Its participants announce every 0.1 s, as the nodes' do; they match their own endpoints.
    root = ET.parse(LAUNCHER_PROFILE).getroot()
    participant = root.find('dds:profiles/dds:participant', NS)
    assert participant.get('is_default_profile') == 'true'
    period = participant.find('dds:rtps/dds:builtin/dds:discovery_config/'
                              'dds:leaseAnnouncement', NS)
    assert (int(period.find('dds:sec', NS).text), int(period.find('dds:nanosec', NS).text)) \
        == (0, 100_000_000)
    assert not profile_ignores_local_endpoints(LAUNCHER_PROFILE.read_text(encoding='utf-8'))
    environ = {}
    assert use_launcher_profile(environ)
    assert environ == {'FASTRTPS_DEFAULT_PROFILES_FILE': str(LAUNCHER_PROFILE)}
    assert not process_ignores_local_endpoints('rmw_fastrtps_cpp', environ)
    for name in FASTDDS_PROFILE_VARIABLES:     # the user's own, in either variable, stays
        own = {name: str(tmp_path / 'mine.xml')}
        assert not use_launcher_profile(own) and own == {name: str(tmp_path / 'mine.xml')}
    # A node process started from a launcher that set it for itself gets the nodes' profile.
    for name in FASTDDS_PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv('FASTRTPS_DEFAULT_PROFILES_FILE', str(LAUNCHER_PROFILE))
    env = graph_environment(7)
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(FASTDDS_PROFILE)
    assert not env.get('FASTDDS_DEFAULT_PROFILES_FILE')


def test_the_profile_keeps_a_process_from_matching_its_own_endpoints():
    text = FASTDDS_PROFILE.read_text(encoding='utf-8')
    assert profile_ignores_local_endpoints(text)
    assert process_ignores_local_endpoints(
        'rmw_fastrtps_cpp', {'FASTRTPS_DEFAULT_PROFILES_FILE': str(FASTDDS_PROFILE)})
    assert process_ignores_local_endpoints(
        'rmw_fastrtps_cpp', {'FASTDDS_DEFAULT_PROFILES_FILE': str(FASTDDS_PROFILE)})
    # Another RMW does not read the property; without a profile Fast DDS matches them.
    assert not process_ignores_local_endpoints(
        'rmw_cyclonedds_cpp', {'FASTRTPS_DEFAULT_PROFILES_FILE': str(FASTDDS_PROFILE)})
    assert not process_ignores_local_endpoints('rmw_fastrtps_cpp', {})
    assert not process_ignores_local_endpoints(
        'rmw_fastrtps_cpp', {'FASTRTPS_DEFAULT_PROFILES_FILE': '/nonexistent/profile.xml'})


@pytest.mark.parametrize('text, expected', [
    (FASTDDS_PROFILE.read_text(encoding='utf-8').replace(
        '<value>true</value>', '<value>false</value>'), False),
    (FASTDDS_PROFILE.read_text(encoding='utf-8').replace(
        'is_default_profile="true">\n      <rtps>', 'is_default_profile="false">\n      <rtps>'),
     False),                                  # not the default participant profile
    ('<dds><profiles><participant profile_name="p" is_default_profile="true"><rtps>'
     '<propertiesPolicy><properties><property><name>fastdds.ignore_local_endpoints</name>'
     '<value>true</value></property></properties></propertiesPolicy></rtps></participant>'
     '</profiles></dds>', True),              # without the namespace
    ('<dds><profiles><participant profile_name="p" is_default_profile="true"><rtps>'
     '<propertiesPolicy><properties><property><name>fastdds.ignore_local_endpoints</name>'
     '<value>TRUE</value></property></properties></propertiesPolicy></rtps></participant>'
     '</profiles></dds>', False),             # Fast DDS refuses the value: they match
    ('<dds><profiles', False),                # not XML
])
def test_only_a_default_participant_profile_that_sets_the_property_counts(text, expected):
    assert profile_ignores_local_endpoints(text) is expected


@pytest.mark.parametrize('layout', ['single', 'composed', 'separate'])
@pytest.mark.parametrize('user_mode', [None, 'SYNCHRONOUS'])
def test_only_the_single_layouts_simulation_publishes_asynchronously(monkeypatch, tmp_path,
                                                                      layout, user_mode):
    """Its writers feed observers only; where the loop crosses processes they stay as set."""
    pytest.importorskip('ament_index_python')
    from wip_bringup import graph_runner, runner_base
    if user_mode is None:
        monkeypatch.delenv(graph_runner.PUBLICATION_MODE_VARIABLE, raising=False)
    else:
        monkeypatch.setenv(graph_runner.PUBLICATION_MODE_VARIABLE, user_mode)
    started = {}

    class Started:
        def __init__(self, name, command, log_path, env, *args, **kwargs):
            started[name] = env

    monkeypatch.setattr(runner_base, 'NodeProcess', Started)
    runner = graph_runner.GraphRunner(graph_runner.GraphOptions(
        out=str(tmp_path / 'o'), layout=layout, record=str(tmp_path / 'bag'), quiet=True))
    runner.start_processes(tmp_path / 'params.yaml')
    assert 'recorder' in started and len(started) > 1
    for name, env in started.items():
        expected = ('ASYNCHRONOUS' if name == 'simulation' and user_mode is None
                    else user_mode)
        assert env.get(graph_runner.PUBLICATION_MODE_VARIABLE) == expected, name
    assert ('simulation' in started) == (layout == 'single')
