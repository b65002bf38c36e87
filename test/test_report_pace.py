"""A link's status goes out at once on a change the decider acts on, else once a period
(runtime/report_pace.py)."""

import dataclasses

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.runtime.report_pace import link_status_due, link_status_period_s

UP = p.LinkStatus(master='robot', remote='laptop', stamp=1.0, up=True, rtt_ms=0.4, loss=0.0,
                  bandwidth_available_kbps=50000.0, bandwidth_available_age_s=3.0,
                  bandwidth_used_kbps=900.0, peer_agent='alive', peer_agent_for_s=10.0)


def test_the_first_report_goes_out_and_an_unchanged_link_once_a_period():
    assert link_status_due(None, UP, 0.0, 1.0)
    later = dataclasses.replace(UP, stamp=1.25, rtt_ms=0.6, loss=0.1, bandwidth_used_kbps=950.0)
    assert not link_status_due(UP, later, 0.25, 1.0)     # readings move; nothing acted on
    assert link_status_due(UP, later, 1.0, 1.0)


@pytest.mark.parametrize('change', [{'up': False, 'peer_agent': None}, {'congested': True},
                                    {'bandwidth_available_kbps': 4000.0},
                                    {'peer_agent': 'restarting'}])
def test_what_the_decider_acts_on_goes_out_at_once(change):
    assert link_status_due(UP, dataclasses.replace(UP, **change), 0.01, 1.0)


def test_the_period_stays_under_a_third_of_the_deciders_observation_age():
    assert link_status_period_s(3.0) == 1.0
    assert link_status_period_s(1.5) == 0.5
