"""The Fast DDS profile the launcher gives its node processes where the user has none."""

import xml.etree.ElementTree as ET

import pytest

from wip_bringup.launcher import (FASTDDS_PROFILE, FASTDDS_PROFILE_VARIABLES,
                                  graph_environment)

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
