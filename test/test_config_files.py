"""The packaged files are found, and the discovery profile is offered without overriding a
user's own profile."""

import os
import xml.etree.ElementTree as ET

from anyscale_manager import config_files

NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


def test_discovery_profile_is_a_default_participant_profile_announcing_every_quarter_second():
    path = config_files.find(config_files.DISCOVERY_PROFILE)
    assert path is not None and os.path.isfile(path)
    root = ET.parse(path).getroot()
    participant = root.find(f'{NS}participant')
    assert participant is not None and participant.get('is_default_profile') == 'true'
    period = participant.find(f'{NS}rtps/{NS}builtin/{NS}discovery_config/{NS}leaseAnnouncement')
    seconds = int(period.find(f'{NS}sec').text) + int(period.find(f'{NS}nanosec').text) * 1e-9
    assert seconds == 0.25
    # Nothing else is changed: the lease itself stays Fast DDS's default.
    assert participant.find(f'{NS}rtps/{NS}builtin/{NS}discovery_config/'
                            f'{NS}leaseDuration') is None


def test_with_discovery_profile_names_the_packaged_file_unless_a_profile_is_named():
    env = config_files.with_discovery_profile({'PATH': '/bin'})
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == config_files.find('fastdds_discovery.xml')
    assert env['PATH'] == '/bin'
    for var in config_files.PROFILE_VARS:
        own = {var: '/etc/my_profile.xml'}
        assert config_files.with_discovery_profile(own) == own


def test_find_names_nothing_for_a_file_the_package_does_not_ship():
    assert config_files.find('no_such_file.yaml') is None
    assert all(p.endswith(os.path.join('config', 'no_such_file.yaml'))
               for p in config_files.candidates('no_such_file.yaml'))


def test_the_settings_table_in_the_docs_is_made_from_the_declarations():
    """docs/configuration.md holds exactly what model/types.py declares (one home per fact):
    after changing a setting, run python -m anyscale_manager.model.settings_doc --write."""
    from anyscale_manager.model import settings_doc
    assert settings_doc.current() == settings_doc.block(), \
        'docs/configuration.md is stale: python -m anyscale_manager.model.settings_doc --write'
