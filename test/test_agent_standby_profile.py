"""The master's standby copies announce a long DDS lease, so a thawed copy is heard at once."""

import copy
import xml.etree.ElementTree as ET

import yaml

from anyscale_manager.agent.catalogue import (FASTDDS_PROFILE_VARS, STANDBY_LEASE_S,
                                              build_catalogue, standby_profile_xml)
from anyscale_manager.model import load_mapping
from conftest import TESTBED


def load_testbed(change=None):
    with open(TESTBED, encoding='utf-8') as f:
        data = yaml.safe_load(f)
    data = copy.deepcopy(data)
    if change:
        change(data['/**']['ros__parameters'])
    return load_mapping(data, TESTBED)


def test_profile_is_valid_xml_with_the_lease():
    root = ET.fromstring(standby_profile_xml())
    lease = [e for e in root.iter() if e.tag.endswith('leaseDuration')]
    assert lease and lease[0][0].text == str(STANDBY_LEASE_S)


def test_only_the_masters_standby_copies_get_the_profile():
    d = load_testbed()
    robot = build_catalogue(d, 'robot', environ={'PATH': '/usr/bin'}, standby_profile='/p.xml')
    for name in ('amcl', 'ar'):
        assert all(robot[name].env[v] == '/p.xml' for v in FASTDDS_PROFILE_VARS)
    assert not any(v in robot['ekf'].env for v in FASTDDS_PROFILE_VARS)
    laptop = build_catalogue(d, 'laptop', environ={'PATH': '/usr/bin'}, standby_profile='/p.xml')
    assert not any(v in laptop['amcl'].env for v in FASTDDS_PROFILE_VARS)


def test_a_profile_of_the_users_own_is_kept():
    d = load_testbed(lambda p: p['nodes']['amcl']['launch'].update(
        env={'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}))
    robot = build_catalogue(d, 'robot', environ={'PATH': '/usr/bin'}, standby_profile='/p.xml')
    assert robot['amcl'].env['FASTRTPS_DEFAULT_PROFILES_FILE'] == '/mine.xml'
    assert 'FASTDDS_DEFAULT_PROFILES_FILE' not in robot['amcl'].env
