"""The fleet run's record (testbed/fleet_record.py), without ROS: observer lines in, samples and
marks in, the questions the fleet's tests and a demo ask of them out."""

import json

import pytest

from anyscale_manager.testbed.fleet_netns import link_name
from anyscale_manager.testbed.fleet_record import FleetRecord, FleetSample
from anyscale_manager.testbed.record import HEARD_LAG_S


def sample(t, a=('home', 1), b=('home', 1), up=True, claims=None):
    workers = {r: {role: n} for r, (role, n) in (('robot_a', a), ('robot_b', b))}
    return FleetSample(t, workers, {'robot_a': up, 'robot_b': True}, claims or {})


def test_a_robots_observer_lines_are_its_arrivals_and_say_up_to_when_they_are_complete():
    rec = FleetRecord(0.0)
    assert not rec.ready('robot_a')
    rec.ingest_line('robot_a', json.dumps({'t': 1.0, 'ready': True}))
    rec.ingest_line('robot_a', json.dumps({'t': 2.0, 'arrivals': {'/robot_a/w': [1.9, 1.5]}}))
    rec.ingest_line('robot_a', 'not json')
    rec.ingest_line('robot_a', json.dumps({'t': 2.2, 'topic': '/anyscale/layout', 'data': '{}'}))
    assert rec.ready('robot_a') and not rec.ready('robot_b')
    assert rec.heard('robot_a') == [1.5, 1.9] and rec.heard('robot_b') == []
    assert rec.judged_until('robot_a') == pytest.approx(2.2 - HEARD_LAG_S)


@pytest.mark.parametrize('workers, where', [
    ({'home': 1, 'away': 0}, 'home'), ({'home': 0, 'away': 1}, 'away'),
    ({'home': 1, 'away': 1}, 'both'), ({'home': 0, 'away': 0}, 'none'), ({}, 'none')])
def test_where_a_robots_worker_runs(workers, where):
    assert FleetSample(0.0, {'robot_a': workers}, {}, {}).where('robot_a') == where


def test_the_server_is_judged_over_every_sample_and_the_first_that_holds_is_found():
    rec = FleetRecord(0.0)
    rec.add(sample(1.0, a=('away', 1), claims={'robot_a': 60.0}))
    rec.add(sample(2.0, a=('away', 1), b=('away', 1), claims={'robot_a': 60.0,
                                                              'robot_b': 60.0}))
    rec.add(sample(3.0, b=('away', 1), up=False, claims={'robot_b': 60.0}))
    assert rec.most_on_server() == 2 and rec.most_claimed() == 120.0
    assert rec.most_on_server(start=2.5) == 1 and rec.most_claimed(end=1.5) == 60.0
    assert rec.first(lambda s: s.where('robot_b') == 'away') == 2.0
    assert rec.first(lambda s: s.where('robot_b') == 'away', since=2.5) == 3.0
    assert rec.first(lambda s: s.on_server == 0) is None


def test_the_timeline_has_a_row_per_period_and_every_mark():
    rec = FleetRecord(10.0)
    for i in range(5):
        rec.add(sample(10.0 + 0.5 * i, a=('away', 1), up=i < 2, claims={'robot_a': 60.0}))
    rec.mark(11.1, 'link_a cut')
    rows = rec.timeline(('robot_a', 'robot_b'), every_s=1.0)
    assert len(rows) == 4 and rows[2].endswith('-- link_a cut'), rows
    assert 'robot_a: away link up  claim  60' in rows[0] and 'robot_b: home' in rows[0]
    assert 'robot_a: away link CUT' in rows[3], rows


def test_each_robot_has_its_link():
    assert link_name('robot_a') == 'link_a' and link_name('scout') == 'link_scout'


def test_a_hand_over_after_a_cut_is_read_from_the_samples():
    """robot_a's link cut at 10 s: home at 11, its server copy gone at 12, its claim released
    at 13 (the room freed then), robot_b started there at 14 and serving alone at 15."""
    rec = FleetRecord(0.0)
    rows = [(9.0, {'away': 1}, {'home': 1}, {'robot_a': 60.0}),
            (11.0, {'away': 1, 'home': 1}, {'home': 1}, {'robot_a': 60.0}),
            (12.0, {'home': 1}, {'home': 1}, {'robot_a': 60.0}),
            (13.0, {'home': 1}, {'home': 1}, {}),
            (14.0, {'home': 1}, {'home': 1, 'away': 1}, {'robot_b': 60.0}),
            (15.0, {'home': 1}, {'away': 1}, {'robot_b': 60.0})]
    for t, a, b, claims in rows:
        rec.add(FleetSample(t, {'robot_a': {'home': a.get('home', 0), 'away': a.get('away', 0)},
                                'robot_b': {'home': b.get('home', 0), 'away': b.get('away', 0)}},
                            {'robot_a': t < 10.0, 'robot_b': True}, claims))
    h = rec.hand_over('robot_a', 'robot_b', 10.0)
    assert (h.home, h.fenced, h.released, h.started, h.serving, h.freed) == \
        (11.0, 12.0, 13.0, 14.0, 15.0, 13.0)
    with pytest.raises(ValueError, match='not sampled'):
        rec.hand_over('robot_b', 'robot_a', 10.0)


def test_a_sample_says_whether_all_or_none_of_a_robots_nodes_serve_on_the_server():
    s = FleetSample(0.0, {}, {}, {}, {'robot_a': ('amcl', 'ar'), 'robot_b': ()})
    assert s.all_away('robot_a', ('ar', 'amcl')) and not s.none_away('robot_a')
    assert s.none_away('robot_b') and not s.all_away('robot_b', ('amcl', 'ar'))
    assert not s.none_away('robot_c')         # not started: neither
