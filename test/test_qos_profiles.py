"""The Fast DDS profile the node loads: request readers DYNAMIC, rmw's defaults elsewhere."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ElementTree

import pytest

from collision_node.ros.qos import (FASTDDS_PROFILES_XML, fastdds_profiles, MIDDLEWARE_SETTINGS,
                                    own_fastdds_profiles)

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

NS = {'dds': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}


def profiles() -> dict:
    """Return the default profile of each entity kind in the XML."""
    root = ElementTree.fromstring(FASTDDS_PROFILES_XML)
    found = {}
    for profile in root.find('dds:profiles', NS):
        assert profile.get('is_default_profile') == 'true'
        found[profile.tag.split('}')[1]] = profile
    return found


def test_readers_free_each_sample_and_writers_keep_rmws_defaults():
    found = profiles()
    assert set(found) == {'data_writer', 'data_reader'}      # no participant, no topic names
    reader, writer = found['data_reader'], found['data_writer']
    assert reader.findtext('dds:historyMemoryPolicy', namespaces=NS) == 'DYNAMIC'
    # What rmw_fastrtps sets itself when it is not told to read the XML:
    assert writer.findtext('dds:historyMemoryPolicy', namespaces=NS) == \
        'PREALLOCATED_WITH_REALLOC'
    assert writer.findtext('dds:qos/dds:publishMode/dds:kind', namespaces=NS) == 'SYNCHRONOUS'
    for profile in (reader, writer):
        assert profile.findtext('dds:qos/dds:data_sharing/dds:kind', namespaces=NS) == 'OFF'
        # History, depth, reliability and durability stay with the ROS QoS profiles.
        assert {child.tag.split('}')[1] for child in profile.find('dds:qos', NS)} <= {
            'publishMode', 'data_sharing'}


def test_a_users_own_middleware_configuration_is_left_alone():
    assert own_fastdds_profiles({})
    assert own_fastdds_profiles({'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'})
    assert not own_fastdds_profiles({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'})
    for name in ('RMW_FASTRTPS_USE_QOS_FROM_XML', 'FASTRTPS_DEFAULT_PROFILES_FILE',
                 'FASTDDS_DEFAULT_PROFILES_FILE'):
        assert not own_fastdds_profiles({name: '/somewhere/profiles.xml'})
    assert own_fastdds_profiles({'FASTRTPS_DEFAULT_PROFILES_FILE': ''})


def test_the_profile_is_offered_only_while_the_node_is_created(monkeypatch):
    for name in ('RMW_IMPLEMENTATION', *MIDDLEWARE_SETTINGS):
        monkeypatch.delenv(name, raising=False)
    with fastdds_profiles() as used:
        assert used and os.environ['RMW_FASTRTPS_USE_QOS_FROM_XML'] == '1'
        path = os.environ['FASTRTPS_DEFAULT_PROFILES_FILE']
        with open(path, encoding='utf-8') as profile:
            assert profile.read() == FASTDDS_PROFILES_XML
    assert not os.path.exists(path)
    assert not any(name in os.environ for name in MIDDLEWARE_SETTINGS)
    monkeypatch.setenv('FASTRTPS_DEFAULT_PROFILES_FILE', '/users/own.xml')
    with fastdds_profiles() as used:
        assert not used and 'RMW_FASTRTPS_USE_QOS_FROM_XML' not in os.environ
    assert os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] == '/users/own.xml'
