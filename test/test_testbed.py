"""Test-bed pieces: link schedules, the run record and its reports, the demo's checks, and the
network namespaces with their shaped link and CPU quotas (those skip, saying why, without root).
"""

import json
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime.delta import STALL_ALLOWANCE_S
from anyscale_manager.testbed import harness, links, netns
from anyscale_manager.testbed import schedule as sched
from anyscale_manager.testbed.record import HEARD_LAG_S, DeltaBreach, Record
from anyscale_manager.testbed.report import (
    category, connection_dips, cpu_series, cut_off_spans, dips, draw_timeline, event_line,
    event_log, fold_notes, location, loss_text, loss_window_s, machine_note, serving, spans,
    split_readings, status_table, with_own_reports, wrap_lines, write_event_log)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TESTBED = os.path.join(REPO, 'config', 'icar2015_testbed.yaml')
NETNS_OK, NETNS_WHY = netns.available()


# --- schedules ----------------------------------------------------------------------------------

def test_paper_schedule_keeps_the_link_up_about_half_the_run():
    steps = sched.paper_schedule(60.0)
    assert 0.45 <= sched.up_fraction(steps, 60.0) <= 0.65
    assert [s.action for s in steps].count('cut') == 2
    throttle = next(s for s in steps if s.action == 'throttle')
    assert throttle.rate_kbps < 6000      # below AR's need
    assert all(0 <= s.at_s <= 60 for s in steps)


@pytest.mark.parametrize('text, message', [
    ('10:explode', 'unknown action'),
    ('10:throttle', 'throttle needs a rate'),
    ('10:cut=5', 'only throttle takes a rate'),
    ('-1:cut', '>= 0'),
    ('cut', 'SECONDS:ACTION'),
    ('x:cut', 'not a number'),
])
def test_bad_schedules_are_refused_with_the_item_named(text, message):
    with pytest.raises(ValueError, match=message):
        sched.parse(text)


def test_schedule_parse_sorts_and_round_trips():
    steps = sched.parse('30:restore, 10:cut,20:throttle=4000')
    assert [str(s) for s in steps] == ['10:cut', '20:throttle=4000', '30:restore']
    assert sched.up_fraction(steps, 40.0) == pytest.approx(0.5)


# --- the record ---------------------------------------------------------------------------------

def _state(scale, nodes, gen=1):
    return p.AgentState(scale=scale, generation=gen, stamp=0.0, nodes={
        n: p.NodeReport(state='running', pid=100 + i, since=0.0, restarts=0, ready=True,
                        exit_reason='') for i, n in enumerate(nodes)})


def _line(t, topic, message):
    return json.dumps({'t': t, 'topic': topic, 'data': message.to_json()})


@pytest.fixture
def record():
    return Record(load_deployment(TESTBED))


def test_record_placement_follows_agent_reports_and_forgets_stale_ones(record):
    record.ingest_line(_line(1.0, p.TOPIC_AGENT_STATE, _state('robot', ['laser', 'amcl', 'ar'])))
    record.ingest_line(_line(5.0, p.TOPIC_AGENT_STATE, _state('robot', ['laser', 'ar'])))
    record.ingest_line(_line(5.0, p.TOPIC_AGENT_STATE, _state('laptop', ['amcl'])))
    assert record.where('amcl', 2.0) == ('robot',)
    assert record.where('amcl', 6.0) == ('laptop',)
    assert category(record, 6.0)[0] == 'only AMCL on the laptop'
    assert category(record, 2.0)[0] == 'AMCL and AR on the robot'
    # No laptop report for longer than the agent timeout: nothing is known to run there.
    assert record.where('amcl', 5.0 + record.deployment.decider.agent_timeout_s + 1) == ()


def test_record_serving_since_is_the_first_report_of_every_node_running_there(record):
    record.ingest_line(_line(1.0, p.TOPIC_AGENT_STATE, _state('robot', ['laser', 'amcl'])))
    record.ingest_line(_line(2.0, p.TOPIC_AGENT_STATE, _state('robot', ['laser', 'amcl', 'ar'])))
    record.ingest_line(_line(3.0, p.TOPIC_AGENT_STATE, _state('laptop', ['ar'])))
    assert record.serving_since('robot', ('amcl',), 0.5) == 1.0
    assert record.serving_since('robot', ('amcl', 'ar'), 0.5) == 2.0
    assert record.serving_since('robot', ('amcl', 'ar'), 2.5) is None
    assert record.serving_since('laptop', ('amcl',), 0.0) is None


def test_record_keeps_malformed_observer_lines_as_problems(record):
    record.ingest_line('not json at all')
    record.ingest_line(json.dumps({'t': 1.0, 'topic': p.TOPIC_LAYOUT, 'data': '{"x": 1}'}))
    record.ingest_line(json.dumps([1, 2]))
    assert len(record.problems) == 3
    assert record.layouts == []


def test_observed_violations_use_the_delta_rule(record):
    conn = record.deployment.connection('amcl_ekf')      # freq_min 2 Hz, Δ 2 s
    times = [i * 0.2 for i in range(50)]                  # 5 Hz until t = 9.8
    times += [14.0 + i * 0.2 for i in range(50)]          # silent 9.8 .. 14.0, then 5 Hz
    record.arrivals['/amcl_pose'] = times
    record.heard_until = 25.0
    found = record.observed_violations(conn, 0.0, 24.0)
    assert len(found) == 1
    v = found[0]
    assert 9.8 < v.start < 12.0 and 14.0 <= v.end < 14.6
    assert v.excess_s > 0
    # A short gap (1 s) is within Δ: no violation.
    record.arrivals['/amcl_pose'] = [i * 0.2 for i in range(50)] + \
        [10.8 + i * 0.2 for i in range(50)]
    assert record.observed_violations(conn, 0.0, 20.0) == []


def test_congestion_onsets_count_each_congested_spell_once(record):
    def link(t, up, congested):
        record.ingest_line(_line(t, p.TOPIC_LINK_STATUS, p.LinkStatus(
            master='robot', remote='laptop', stamp=t, up=up, rtt_ms=1.0, loss=0.0,
            bandwidth_available_kbps=5000.0, bandwidth_available_age_s=0.0,
            bandwidth_used_kbps=4000.0, queueing_delay_ms=90.0 if congested else 1.0,
            congested=congested)))
    for t, up, congested in [(1.0, True, False), (2.0, True, True), (2.25, True, True),
                             (3.0, True, False), (4.0, True, True), (5.0, False, False),
                             (6.0, True, True)]:
        link(t, up, congested)
    assert record.congestion_onsets(0.0, 10.0) == [2.0, 4.0, 6.0]
    assert record.congestion_onsets(2.1, 5.0) == [4.0]       # a spell begun before t0 is not
    spans_ = record.timeline(1.5, 6.5)['link']
    assert [(t, state, c) for t, state, c, *_ in spans_][:3] == [
        (-0.5, 'up', ''), (0.5, 'up', 'congested'), (1.5, 'up', '')]


def test_handovers_read_the_moved_nodes_outputs_at_the_scale_it_left(record):
    def event(t, kind, node, src, dst):
        record.ingest_line(_line(t, p.TOPIC_EVENTS, p.Event(
            stamp=t, kind=kind, node=node, from_scale=src, to_scale=dst, reason='test',
            generation=1)))

    def reading(t, scale, rate):
        record.readings.setdefault('amcl_ekf', []).append((t, scale, p.ConnectionReading(
            rate_hz=rate, bytes_per_s=0.0, below_for_s=0.0, level=p.OK)))
    event(10.0, 'migrate', 'amcl', 'robot', 'laptop')
    event(30.0, 'migrate_back', 'amcl', 'laptop', 'robot')     # not a move out of the robot
    event(40.0, 'migrate', 'amcl', 'robot', 'laptop')
    # After the first move the robot hears AMCL throughout; after the second, it reads below
    # freq_min from 41.0 s until the reading at 43.0 s.
    for k in range(13):
        reading(10.0 + 0.5 * k, 'robot', 3.0)
        reading(40.0 + 0.5 * k, 'robot', 0.5 if 2 <= k <= 5 else 3.0)
        reading(40.0 + 0.5 * k, 'laptop', 0.0)                # another scale's reading
    record.readings['amcl_ekf'].sort(key=lambda x: x[0])
    # The agents' reports after the second move: ready on the laptop at 40.4 s, the robot's
    # copy frozen at 41.2 s.
    for t, scale, state in [(40.2, 'laptop', 'starting'), (40.4, 'laptop', 'running'),
                            (40.5, 'robot', 'running'), (41.2, 'robot', 'standby')]:
        report = _state(scale, ['amcl'])
        report.nodes['amcl'].state = state
        report.nodes['amcl'].ready = state == 'running'
        record.agent_states.setdefault(scale, []).append((t, report))
    rows = record.handovers(0.0, 60.0, 'robot')
    amcl = [(r['t'], r['min_rate_hz'], r['below_s'], r['ready_s'], r['left_s']) for r in rows
            if r['node'] == 'amcl' and r['connection'] == 'amcl_ekf']
    assert amcl == [(10.0, 3.0, 0.0, None, None), (40.0, 0.5, 2.0, 0.4, 1.2)]
    assert record.handovers(0.0, 60.0, 'laptop') == []


def test_reported_violations_close_when_the_probe_goes_quiet_or_recovers(record):
    def reading(level, below):
        return p.ConnectionReading(rate_hz=0.0, bytes_per_s=0.0, below_for_s=below, level=level)
    for t, scale, level, below in [(10.0, 'laptop', p.ERROR, 2.5), (10.5, 'laptop', p.ERROR, 3.0),
                                   (30.0, 'laptop', p.ERROR, 23.0),      # after a long silence
                                   (11.0, 'robot', p.ERROR, 1.2), (11.5, 'robot', p.OK, 0.0)]:
        record.readings.setdefault('camera_ar', []).append((t, scale, reading(level, below)))
    record.readings['camera_ar'].sort(key=lambda x: x[0])
    found = record.reported_violations(0.0, 40.0)
    spans_ = sorted((v.source, v.start, v.end) for v in found)
    assert ('robot', 9.8, 11.5) == (spans_[-1][0], round(spans_[-1][1], 2), spans_[-1][2])
    laptop = [v for v in found if v.source == 'laptop']
    assert sorted(round(v.end, 1) for v in laptop) == [10.5, 30.0]


def test_serving_only_drops_the_reports_of_a_cut_off_copy(record):
    """AMCL ran on the laptop until the cut at 10 s; the layout put it back on the robot at
    10.8 s. The laptop's copy, cut off, reported laser_amcl past Δ (its input starved) once the
    link returned: it served nobody, so only the robot's own report counts."""
    def layout(t, where, gen):
        assignments = {n: 'robot' for n in ('laser', 'amcl', 'ar')}
        assignments['amcl'] = where
        record.layouts.append((t, p.Layout(generation=gen, deployment='icar2015_testbed',
                                           assignments=assignments, reason='test', stamp=t)))
    layout(0.0, 'laptop', 1)
    layout(10.8, 'robot', 2)

    def reading(level, below):
        return p.ConnectionReading(rate_hz=0.0, bytes_per_s=0.0, below_for_s=below, level=level)
    record.readings['laser_amcl'] = [(25.0, 'laptop', reading(p.ERROR, 15.0)),
                                     (25.5, 'laptop', reading(p.ERROR, 15.5))]
    record.readings['amcl_ekf'] = [(13.5, 'robot', reading(p.ERROR, 3.5)),
                                   (14.0, 'robot', reading(p.OK, 0.0))]
    every = record.reported_violations(0.0, 40.0)
    assert sorted(v.source for v in every) == ['laptop', 'robot']
    serving = record.reported_violations(0.0, 40.0, serving_only=True)
    assert [(v.connection, v.source) for v in serving] == [('amcl_ekf', 'robot')]


# --- reports ------------------------------------------------------------------------------------

def _busy_record(record):
    record.link_set(0.0, True, 54000.0)
    record.link_set(10.0, False, 54000.0)
    for t in range(0, 20):
        robot = ['laser', 'camera', 'ar'] + (['amcl'] if t >= 10 else [])
        record.ingest_line(_line(t, p.TOPIC_AGENT_STATE, _state('robot', robot)))
        if t < 10:
            record.ingest_line(_line(t, p.TOPIC_AGENT_STATE, _state('laptop', ['amcl'])))
        status = p.ConnectionStatus(scale='robot', stamp=0.0, connections={
            'amcl_ekf': p.ConnectionReading(rate_hz=5.0 if t < 10 else 2.5, bytes_per_s=1.0,
                                            below_for_s=0.0, level=p.OK)})
        record.ingest_line(_line(t + 0.1, p.TOPIC_CONNECTION_STATUS, status))
    record.ingest_line(_line(10.5, p.TOPIC_EVENTS, p.Event(
        stamp=0.0, kind='migrate_back', node='amcl', from_scale='laptop', to_scale='robot',
        reason='link down', generation=3)))
    record.mark(10.0, 'link cut')
    return record


def test_spans_follow_the_paper_colours(record):
    _busy_record(record)
    labels = [label for _, _, label, _ in spans(record, 0.0, 19.0)]
    assert labels[0] == 'only AMCL on the laptop'
    assert labels[-1] == 'AMCL and AR on the robot'


def test_status_table_shows_link_scales_connections_and_placement(record):
    _busy_record(record)
    text = status_table(record, 15.0, 0.0, 'netns')
    assert 'CUT' in text and 'robot' in text and 'amcl_ekf' in text
    assert 'AMCL: robot' in text
    assert 'migrate_back amcl' in text


def test_timeline_png_and_event_log_are_written(record, tmp_path):
    _busy_record(record)
    png = draw_timeline(record, str(tmp_path / 'timeline.png'), 0.0, 19.0, 'test')
    with open(png, 'rb') as f:
        assert f.read(8) == b'\x89PNG\r\n\x1a\n'
    jsonl, text = write_event_log(record, str(tmp_path), 0.0)
    rows = [json.loads(line) for line in open(jsonl)]
    assert [r['kind'] for r in rows] == ['action', 'migrate_back']
    assert 'migrate_back amcl laptop -> robot' in open(text).read()
    assert event_log(record, 0.0) == rows


# --- reading the demo at a glance ---------------------------------------------------------------

def _report(scale, t, serving_nodes, standby=()):
    """An agent's report at t: ``serving_nodes`` active and ready, ``standby`` inactive."""
    state = _state(scale, list(serving_nodes) + list(standby))
    for n in standby:
        state.nodes[n] = p.NodeReport(state='standby', pid=500, since=0.0, restarts=0,
                                      ready=False, exit_reason='', lifecycle='inactive')
    return t, state


def _cut_at_10(record, laptop_stands_down_at=None):
    """AMCL and AR serve on the laptop; the link is cut at 10 s. The robot's agent activates
    its standby copies, ready from 10.4 s. The robot's observer last hears the laptop's agent
    at 9.9 s; the laptop's own observer (a view of its own) hears it until the end, standing
    its copies down at ``laptop_stands_down_at``. Returns the laptop's view."""
    record.link_set(0.0, True, 54000.0)
    record.link_set(10.0, False, 54000.0)
    laptop_view = Record(record.deployment)
    for k in range(0, 41):
        t = k * 0.5 - 0.1
        pinned = ['laser', 'camera', 'ekf', 'navigation']
        robot = _report('robot', t, pinned + (['amcl', 'ar'] if t >= 10.4 else []),
                        standby=() if t >= 10.4 else ('amcl', 'ar'))
        record.agent_states.setdefault('robot', []).append(robot)
        down = laptop_stands_down_at is not None and t >= laptop_stands_down_at
        laptop = _report('laptop', t, [] if down else ['amcl', 'ar'],
                         standby=('amcl', 'ar') if down else ())
        laptop_view.agent_states.setdefault('laptop', []).append(laptop)
        if t < 10.0:
            record.agent_states.setdefault('laptop', []).append(laptop)
    return laptop_view


def test_the_layout_band_shows_where_a_node_serves_not_a_cut_off_report(record):
    """The laptop's last report (9.9 s) says AMCL and AR run there for agent_timeout_s more,
    but the link is cut at 10 s: what the robot's consumers hear from 10.4 s is the robot's
    copies. The band says so, and draws the cut-off copies apart."""
    laptop_view = _cut_at_10(record, laptop_stands_down_at=11.5)
    assert record.deployment.decider.agent_timeout_s > 2.0
    assert 'laptop' in record.where('amcl', 12.0)            # the reports alone still say it
    assert serving(record, 'amcl', 12.0) == (('robot',), ('laptop',))
    assert location(record, 'amcl', 9.0) == 'laptop'
    assert location(record, 'amcl', 10.2) == ''              # between the cut and the robot
    assert location(record, 'amcl', 10.5) == 'robot'
    assert category(record, 10.5)[0] == 'AMCL and AR on the robot'
    band = spans(record, 0.0, 19.0)
    red = next(start for start, _, label, _ in band if label == 'AMCL and AR on the robot')
    assert 10.0 <= red <= 10.75
    # The cut-off copies, as far as the robot heard (until that report aged out) ...
    stale = 9.9 + record.deployment.decider.agent_timeout_s
    [(a, b, text)] = cut_off_spans(record, 0.0, 19.0)
    assert (a, text) == (10.0, 'AMCL, AR on laptop') and stale <= b <= stale + 0.25
    # ... and as the laptop's own observer heard them: active until its agent stood them down.
    seen = with_own_reports(record, {'robot': record, 'laptop': laptop_view})
    found = cut_off_spans(seen, 0.0, 19.0)
    assert [(a, text) for a, _, text in found] == [(10.0, 'AMCL, AR on laptop')]
    assert 11.9 <= found[0][1] <= 12.25
    assert seen.agent_states['robot'] is record.agent_states['robot']


def _reading(rate, level=p.OK, below=0.0, ended=None):
    return p.ConnectionReading(rate_hz=rate, bytes_per_s=0.0, below_for_s=below, level=level,
                               ended_below_s=ended)


def test_a_dip_within_delta_is_allowed_and_one_past_delta_is_not():
    points = [(1.0, _reading(10.0)), (1.5, _reading(0.0, p.WARN, 0.3)),
              (2.0, _reading(0.0, p.WARN, 0.8)), (2.5, _reading(9.0, ended=1.1)),
              (3.0, _reading(10.0)),
              (5.0, _reading(3.0, p.WARN, 1.5)), (6.0, _reading(0.0, p.ERROR, 2.5)),
              (6.5, _reading(10.0, ended=2.9)),
              (8.0, _reading(4.0, p.OK))]                     # below, still open at the end
    found = dips('laser_amcl', points, 5.0)
    assert [(round(x.start, 2), x.end, x.min_rate_hz, x.below_s, x.allowed) for x in found] == [
        (1.2, 2.5, 0.0, 1.1, True), (3.5, 6.5, 0.0, 2.9, False), (8.0, 8.0, 4.0, 0.0, True)]
    # A stretch never starts before the reading above it.
    assert dips('x', [(1.0, _reading(10.0)), (1.5, _reading(0.0, p.WARN, 5.0))],
                5.0)[0].start == 1.0


def test_dips_are_read_at_the_serving_subscriber_not_at_a_copy_standing_by(record):
    """laser_amcl is probed where AMCL serves: the laptop's probe until the cut, the robot's
    after. The cut-off laptop's probe reading 0 Hz is another scale's, not a dip; the robot's
    first readings at 0 Hz (within Δ 2 s) are one allowed dip."""
    _cut_at_10(record)
    rows = []
    for k in range(40):
        t = k * 0.5
        if t < 10.0:
            rows.append((t, 'laptop', _reading(10.0)))
        else:
            rows.append((t, 'laptop', _reading(0.0, p.ERROR if t > 12.0 else p.WARN, t - 10.0)))
        if 10.5 <= t < 11.5:
            rows.append((t, 'robot', _reading(0.0, p.WARN, t - 10.4)))
        elif t >= 11.5:
            rows.append((t, 'robot', _reading(10.0, ended=1.2 if t == 11.5 else None)))
    record.readings['laser_amcl'] = rows
    conn = record.deployment.connection('laser_amcl')
    served, others = split_readings(record, conn, 0.0, 19.5)
    assert {s for _, s, _ in others} == {'laptop'} and all(t >= 10.0 for t, _, _ in others)
    assert [t for t, _ in served] == [k * 0.5 for k in range(20)] + [
        10.5 + k * 0.5 for k in range(19)]
    found = connection_dips(record, 0.0, 19.5)
    assert [(x.connection, x.allowed, round(x.start, 2), x.end, x.below_s) for x in found] == [
        ('laser_amcl', True, 10.4, 11.5, 1.2)]


def test_the_cpu_panel_plots_each_scale_against_its_capacity(record):
    def status(t, scale, cpu, capacity, cores):
        record.ingest_line(_line(t, p.TOPIC_SCALE_STATUS, p.ScaleStatus(
            scale=scale, stamp=t, cpu_total=cpu, capacity_cpu=capacity, cpu_by_node={},
            mem_percent=1.0, load_1m=0.1, cpu_source='cgroup', cores=cores)))
    for k in range(21):
        t = k * 0.5
        status(t, 'robot', 150.0 + k, 200.0, 0.6)
        if not 4.0 < t < 8.0:                       # not heard while the link was cut
            status(t + 0.1, 'laptop', 90.0, 700.0, 2.1)
    robot, laptop = cpu_series(record, 2.0, 10.0)
    assert (robot.scale, robot.capacity_cpu, robot.source, robot.cores) == (
        'robot', 200.0, 'cgroup', 0.6)
    assert robot.times[0] == 0.0 and robot.cpu[0] == 154.0 and len(robot.times) == 17
    assert laptop.capacity_cpu == 700.0
    gap = [i for i, x in enumerate(laptop.times) if x != x]      # NaN: the line breaks
    assert len(gap) == 1 and laptop.times[gap[0] - 1] == pytest.approx(2.1)
    assert laptop.times[gap[0] + 1] == pytest.approx(6.1)
    assert cpu_series(record, 20.0, 30.0)[0].times == ()


def _link_report(t, up, loss, rtt=0.3):
    return t, p.LinkStatus(master='robot', remote='laptop', stamp=t, up=up, rtt_ms=rtt,
                           loss=loss, bandwidth_available_kbps=None,
                           bandwidth_available_age_s=None, bandwidth_used_kbps=0.0)


def test_a_loss_counted_over_a_cut_is_not_shown_as_the_links_loss(record):
    window = loss_window_s(record.deployment)
    assert 10.0 <= window <= 12.0        # 40 beats at 4 Hz and the 3 periods a beat may wait
    reports = [_link_report(t * 0.25, not 5.0 <= t * 0.25 < 12.0,
                            0.0 if t * 0.25 < 5.0 else 0.73) for t in range(80)]
    assert loss_text(reports[:10], window) == 'loss 0%'
    assert loss_text(reports[:30], window) == ''                 # down: no loss figure
    up_again = reports[:52]                                      # 13 s: up 1 s, 73 % counted
    assert up_again[-1][1].up and up_again[-1][1].loss == 0.73
    assert loss_text(up_again, window) == \
        f'loss - (its last {window:.0f} s of beats hold the cut)'
    later = reports + [_link_report(12.0 + window + 0.5, True, 0.05)]
    assert loss_text(later, window) == 'loss 5%'


def test_the_demo_table_says_no_loss_figure_right_after_a_cut(record):
    for t, s in [_link_report(1.0, True, 0.0), _link_report(2.0, False, 0.5),
                 _link_report(6.0, True, 0.73)]:
        record.link_status.append((t, s))
    record.link_set(0.0, True, 54000.0)
    monitor = status_table(record, 6.2, 0.0, 'netns').splitlines()[2]
    assert monitor.startswith('  monitor: up, rtt 0.3 ms, loss - (its last')
    assert '73' not in monitor
    assert status_table(record, 6.2, 0.0, 'netns').splitlines()[1] == \
        'link wifi: UP, shaped to 54.0 Mbit/s'
    assert 'emulated on loopback: not shaped' in status_table(record, 6.2, 0.0, 'loopback')


def test_long_lines_wrap_at_words_with_an_indent():
    line = '  migrate amcl robot -> laptop: ' + ' '.join(f'word{i}' for i in range(40))
    wrapped = wrap_lines('short\n' + line, 60).split('\n')
    assert wrapped[0] == 'short' and all(len(x) <= 60 for x in wrapped)
    assert wrapped[1].startswith('  migrate') and all(x.startswith('      ') for x in wrapped[2:])
    assert ' '.join(' '.join(wrapped[1:]).split()) == ' '.join(line.split())   # no word cut


def test_the_demo_table_wraps_an_events_reason_instead_of_cutting_it(record):
    _busy_record(record)
    reason = ('amcl: CPU 152, the most CPU-intensive migratable node that fits, to laptop '
              '(power 11.2): CPU 30 + 152 <= 630; link wifi 224/43200 kbit/s')
    record.events.append((12.0, p.Event(stamp=0.0, kind='migrate', node='amcl',
                                        from_scale='robot', to_scale='laptop', reason=reason,
                                        generation=4)))
    record.events.append((13.0, p.Event(stamp=0.0, kind='scale_lost', node='',
                                        from_scale='laptop', to_scale='',
                                        reason='scale laptop lost', generation=4)))
    lines = status_table(record, 15.0, 0.0, 'netns', width=80).splitlines()
    assert all(len(x) <= 80 for x in lines)
    assert lines[-1] == '  scale_lost laptop: scale laptop lost'      # no arrow to nowhere
    start = next(i for i, x in enumerate(lines) if x.startswith('  migrate amcl robot'))
    event = ' '.join(x.strip() for x in lines[start:start + 3])
    assert event.endswith('link wifi 224/43200 kbit/s') and lines[start + 1].startswith('      ')


def _note(t, reason, kind='note', node=''):
    return {'t': t, 'source': 'decider', 'kind': kind, 'node': node, 'from_scale': '',
            'to_scale': '', 'reason': reason, 'generation': 3}


def test_a_repeated_note_is_said_once_then_how_long_it_held():
    held = [_note(10.0 + 0.5 * k, f'amcl -> laptop: amcl migrated back from laptop '
                                  f'{0.5 * k:.1f} s ago, within T = 20 s') for k in range(41)]
    other = [_note(12.0 + 2.0 * k, f'scale robot at {97 + k}% of its CPU capacity: the plan '
                                   f'does not hold there ({"amcl, ar" if k else "ar"} below '
                                   'their expected rate)', kind='warning') for k in range(3)]
    flapping = [_note(11.0 + 3.0 * k, 'cpu: scale robot CPU 195 > usable 180', 'violation')
                for k in range(3)]
    harness_row = {'t': 15.0, 'source': 'harness', 'kind': 'action', 'reason': 'link cut'}
    again = _note(45.0, 'amcl -> laptop: amcl migrated back from laptop 1.0 s ago, within '
                        'T = 20 s')
    rows = sorted(held + other + flapping + [harness_row, again], key=lambda r: r['t'])
    assert len(rows) == 49
    folded = fold_notes(rows)
    assert [(r['t'], r['kind'], r.get('times')) for r in folded] == [
        (10.0, 'note', None), (11.0, 'violation', None), (12.0, 'warning', None),
        (15.0, 'action', None), (16.0, 'warning', 3), (17.0, 'violation', 3),
        (30.0, 'note', 41), (45.0, 'note', None)]
    text = [event_line(r) for r in folded]
    assert text[0] == ('    10.0  note         amcl -> laptop: amcl migrated back from laptop '
                       '0.0 s ago, within T = 20 s')
    assert text[6] == ('    30.0  note         (held 20.0 s, 41 times) amcl -> laptop: amcl '
                       'migrated back from laptop 20.0 s ago, within T = 20 s')
    assert text[4].startswith('    16.0  warning      (held 4.0 s, 3 times) scale robot at 99%')
    assert text[5] == ('    17.0  violation    (3 times in 6.0 s, the last:) cpu: scale robot '
                       'CPU 195 > usable 180')        # it came and went: it did not hold
    assert folded[3] == harness_row and folded[-1] == again


def test_a_move_ends_the_notes_that_name_the_node_it_moved():
    def notes(t, k):
        return [_note(t, f'amcl -> laptop: within T, {k} s'),
                _note(t, f'ar -> laptop: within T, {k + 5} s')]
    rows = [n for k in range(9) for n in notes(10.0 + 0.5 * k, k)]
    move = {'t': 14.2, 'source': 'decider', 'kind': 'migrate', 'node': 'amcl',
            'from_scale': 'robot', 'to_scale': 'laptop', 'reason': 'fits', 'generation': 4}
    rows += [dict(move, kind='layout', node='', from_scale='', to_scale=''), move]
    rows += [n for k in range(4) for n in notes(14.5 + 0.5 * k, k)]
    folded = fold_notes(rows)
    assert [(r['t'], r['kind'], r['reason'][:2], r.get('times')) for r in folded] == [
        (10.0, 'note', 'am', None), (10.0, 'note', 'ar', None), (14.0, 'note', 'am', 9),
        (14.2, 'layout', 'fi', None), (14.2, 'migrate', 'fi', None),
        (14.5, 'note', 'am', None), (16.0, 'note', 'ar', 13), (16.0, 'note', 'am', 4)]
    assert event_line(folded[4]) == '    14.2  migrate      amcl robot -> laptop: fits'


def test_the_event_log_folds_notes_and_says_what_single_machine_means_here(record, tmp_path):
    def event(t, kind, reason):
        record.events.append((t, p.Event(stamp=t, kind=kind, node='', from_scale='',
                                         to_scale='', reason=reason, generation=1)))
    event(1.0, 'single_machine', 'single-machine mode: scales robot, laptop on host vm share '
                                 'one machine: each scale that no cgroup quota confines ...')
    for k in range(130):
        event(2.0 + 0.25 * k, 'note', f'amcl -> laptop: amcl migrated back from laptop '
                                      f'{0.25 * k:.2f} s ago, within T = 40 s')
    for t, scale, cores in [(1.5, 'robot', 0.6), (1.6, 'laptop', 2.1)]:
        record.ingest_line(_line(t, p.TOPIC_SCALE_STATUS, p.ScaleStatus(
            scale=scale, stamp=t, cpu_total=10.0, capacity_cpu=100.0, cpu_by_node={},
            mem_percent=1.0, load_1m=0.1, cpu_source='cgroup', cores=cores)))
    jsonl, text = write_event_log(record, str(tmp_path), 0.0)
    lines = open(text).read().splitlines()
    assert len(open(jsonl).read().splitlines()) == 131          # the raw log keeps every row
    assert len(lines) == 4
    assert lines[1].startswith(' ' * 10 + 'here: ') and \
        "each of robot, laptop measures its CPU as its own cgroup's usage, against its " \
        'capacity spread over the CPUs its quota lets it use (robot 0.6, laptop 2.1)' in lines[1]
    assert '(held 32.2 s, 130 times)' in lines[3]
    assert machine_note(record, 0.5) == ''                        # not said yet
    assert "the scales share one machine (the decider's single-machine mode); each scale's CPU " \
        "is its own cgroup's (robot 0.6, laptop 2.1 CPUs)" in \
        status_table(record, 5.0, 0.0, 'netns', width=200).splitlines()
    event(40.0, 'single_machine', 'single-machine mode ended: scales robot, laptop no longer '
                                  'report one machine')
    assert machine_note(record, 41.0) == ''


# --- the demo command's checks (no test-bed started) --------------------------------------------

@pytest.mark.parametrize('args, message', [
    (['--duration', '0'], '--duration'),
    (['--schedule', '5:fly'], 'unknown action'),
    (['--config', '/nonexistent/deployment.yaml'], 'cannot read'),
    (['--domain-id', '999'], 'out of range'),
    (['--three-scales', '--config', 'x.yaml'], 'leave out --config'),
    (['--three-scales', '--mode', 'loopback'], 'loopback emulates one'),
    (['--three-scales', '--schedule', '5:cut'], 'name a link after @'),
    (['--three-scales', '--schedule', '5:cut@radio'], "unknown link 'radio'"),
])
def test_demo_refuses_bad_input_before_starting_anything(args, message, tmp_path, python,
                                                         ros_env):
    out = subprocess.run([python, '-m', 'anyscale_manager.cli', 'demo', '--out',
                          str(tmp_path / 'out')] + args, env=ros_env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2, out.stdout + out.stderr
    assert message in out.stderr


def test_demo_runs_on_loopback_writes_its_files_and_exits_0(tmp_path, python, ros_env):
    """The README's first command, short and on loopback (no root needed): the schedule is
    applied (a throttle skipped, said so), the files are written, the teardown is clean."""
    out_dir = tmp_path / 'demo'
    out = subprocess.run([python, '-m', 'anyscale_manager.cli', 'demo', '--mode', 'loopback',
                          '--duration', '8', '--schedule', '2:throttle=5000,4:cut,6:restore',
                          '--out', str(out_dir)], env=ros_env, capture_output=True, text=True,
                         timeout=240)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert 'mode: loopback' in out.stdout
    for name in ('timeline.png', 'events.txt', 'events.jsonl', 'summary.json'):
        assert (out_dir / name).stat().st_size > 0, name
    summary = json.loads((out_dir / 'summary.json').read_text())
    assert summary['mode'] == 'loopback' and summary['teardown_notes'] == []
    assert summary['schedule'] == ['2:throttle=5000', '4:cut', '6:restore']
    events = (out_dir / 'events.txt').read_text()
    assert 'throttle=5000 skipped' in events and 'link cut' in events


def test_demo_finds_the_packaged_deployment():
    from anyscale_manager.testbed.cli import default_config
    path = default_config()
    assert path and os.path.basename(path) == 'icar2015_testbed.yaml'
    load_deployment(path)


# --- each network mode's link control (no root, no ROS) ----------------------------------------

def test_the_mode_is_chosen_with_its_reason():
    def there():
        return True, 'namespaces here'

    def not_there():
        return False, 'not root'
    assert links.choose('loopback', there) == (links.LOOPBACK,
                                               'loopback asked for: the link is emulated')
    assert links.choose('auto', there) == (links.NETNS, 'namespaces here')
    assert links.choose('netns', there) == (links.NETNS, 'namespaces here')
    mode, why = links.choose('auto', not_there)
    assert mode == links.LOOPBACK and 'not root' in why and 'no bandwidth shaping' in why
    with pytest.raises(harness.HarnessError, match='not available: not root'):
        links.choose('netns', not_there)
    with pytest.raises(harness.HarnessError, match='unknown mode'):
        links.choose('wifi', there)


def test_nothing_built_cuts_nothing_and_starts_nothing(tmp_path):
    idle = links.LinkControl()
    idle.cut('wifi')
    idle.restore('wifi')
    idle.release()
    assert idle.teardown() == [] and idle.network is None and idle.cpu_group('robot') is None
    assert idle.discovery_peers('laptop') is None and idle.ros_parameters() == []
    with pytest.raises(harness.HarnessError):
        idle.throttle(5000.0, 'wifi')
    with pytest.raises(harness.HarnessError):
        idle.popen('robot', ['true'], {}, True, None, None)
    tb = harness.Testbed(harness.Options(TESTBED, 0, mode='loopback', run_dir=str(tmp_path)))
    assert tb.network is None and isinstance(tb.link_control, links.LinkControl)


def _all_stopped(pids, stopped=True, timeout_s=5.0):
    """Wait until every pid is stopped (or, ``stopped=False``, none is): a signal takes effect
    when the process is next scheduled. False if that is not so within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        if all((psutil.Process(pid).status() == psutil.STATUS_STOPPED) == stopped
               for pid in pids):
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)


def test_loopback_cuts_by_freezing_the_laptop_agent_and_what_it_started(tmp_path):
    """The harness drives the emulated link through its control: a cut stops the laptop agent
    and its children and is recorded, a throttle is refused and skipped in a schedule, a restore
    thaws them; the agents learn the scales' loopback hosts and the probes' port."""
    tb = harness.Testbed(harness.Options(TESTBED, 0, mode='loopback', run_dir=str(tmp_path)))
    control = links.LoopbackLinks(tb.deployment.scale_names, tb._laptop_agent_pid)
    control.setup()
    tb.link_control = control
    agent = control.popen('laptop', ['sh', '-c', 'sleep 30 & wait'], {'PATH': os.environ['PATH']},
                          True, subprocess.DEVNULL, subprocess.DEVNULL)
    try:
        assert os.getsid(agent.pid) == agent.pid                    # a session of its own
        tb.procs['agent_laptop'] = harness.Proc('agent_laptop', 'laptop', [], agent, '', 0.0)
        deadline = time.monotonic() + 5.0
        while not psutil.Process(agent.pid).children() and time.monotonic() < deadline:
            time.sleep(0.02)
        child = psutil.Process(agent.pid).children()[0].pid
        tb.cut()
        assert _all_stopped([agent.pid, child])
        assert tb.link == (False, netns.DEFAULT_RATE_KBPS)
        with pytest.raises(harness.HarnessError, match='cannot throttle on loopback'):
            tb.throttle(5000.0)
        tb.apply(sched.Step(1.0, 'throttle', 5000.0))
        assert tb.link == (False, netns.DEFAULT_RATE_KBPS)
        tb.restore()
        assert _all_stopped([agent.pid, child], stopped=False)
        assert [text for _, text in tb.record.marks] == [
            'link cut', '1:throttle=5000 skipped: cannot throttle on loopback: bandwidth '
            'shaping needs network namespaces (root)', 'link restored']
        args = tb._deployment_args()
        assert {'scales.robot.host:=127.0.0.1', 'scales.laptop.host:=127.0.0.1',
                f'monitoring.bandwidth_probe_port:={control.probe_port}'} <= set(args)
        assert control.probe_port > 0
        assert tb._env('laptop')['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
        assert tb.cpu_seconds().keys() <= {'agent_laptop'}
    finally:
        os.killpg(agent.pid, signal.SIGKILL)
        agent.wait()


class _Group:
    def __init__(self, used_s):
        self.used_s = used_s


class _Network:
    """What NamespaceLinks reads of a built netns.Network."""

    addresses = {'robot': '10.77.0.1', 'laptop': '10.77.0.2'}
    groups = {'robot': _Group(1.5)}

    def __init__(self):
        self.calls = []

    def peers(self, scale):
        return [a for s, a in self.addresses.items() if s != scale]

    def cut(self, link):
        self.calls.append(('cut', link))

    def restore(self, link):
        self.calls.append(('restore', link))

    def throttle(self, rate_kbps, link):
        self.calls.append(('throttle', rate_kbps, link))

    def cpu_usage_s(self, scale):
        group = self.groups.get(scale)
        return group.used_s if group else None

    def leftover_pids(self):
        return [77]

    def teardown(self):
        return ['cgroup busy']


def test_namespaces_act_on_the_network_and_keep_discovery_on_the_link(tmp_path):
    control = links.NamespaceLinks(('robot', 'laptop'), [('wifi', 'robot', 'laptop', 54000.0)],
                                   {'robot': 0.3})
    assert control.observer_per_scale and not control.cuts_processes
    control.network = net = _Network()
    tb = harness.Testbed(harness.Options(TESTBED, 0, mode='netns', run_dir=str(tmp_path)))
    tb.link_control = control
    assert tb.network is net
    tb.cut()
    tb.throttle(5000.0)
    tb.restore('wifi')
    assert net.calls == [('cut', 'wifi'), ('throttle', 5000.0, 'wifi'), ('restore', 'wifi')]
    assert tb.link == (True, 5000.0)
    env = tb._env('laptop')
    assert env['ROS_STATIC_PEERS'] == '10.77.0.1' and env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == \
        'SUBNET'
    args = tb._deployment_args()
    assert {'scales.robot.host:=10.77.0.1', 'scales.laptop.host:=10.77.0.2'} <= set(args)
    assert not any('bandwidth_probe_port' in a for a in args)
    assert control.cpu_group('robot') is net.groups['robot']
    assert control.cpu_group('laptop') is None
    assert tb.cpu_seconds() == {'scale_robot': 1.5}
    assert control.teardown() == ['processes left in the namespaces/cgroups: [77]',
                                  'cgroup busy']


# --- namespaces, link and quotas (root only) ----------------------------------------------------

def test_available_says_why_not_in_plain_words():
    ok, why = netns.available()
    assert isinstance(ok, bool) and why
    if os.geteuid() != 0:
        assert not ok and 'root' in why


def test_tbf_arguments_and_refusals():
    args = netns.tbf_arguments(54000)
    assert args[:3] == ['tbf', 'rate', '54000kbit']
    with pytest.raises(ValueError):
        netns.tbf_arguments(0)


needs_netns = pytest.mark.skipif(not NETNS_OK, reason=f'no namespaces here: {NETNS_WHY}')

TCP_SINK = '''
import socket, threading
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("0.0.0.0", 5301)); s.listen(4)
def drain(c):
    try:
        while c.recv(65536):
            pass
    except OSError:
        pass                 # the sender ends with a reset (SO_LINGER 0)
while True:
    c, _ = s.accept(); threading.Thread(target=drain, args=(c,), daemon=True).start()
'''
TCP_SEND = '''
import socket, struct, sys, time
s = socket.create_connection((sys.argv[1], 5301), timeout=float(sys.argv[2]))
s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 65536)
b = b"x" * 8192; t = time.time(); n = 0
while time.time() - t < 1.5:
    n += s.send(b)
print(n * 8 / 1000 / (time.time() - t))
# Reset instead of a graceful close: no orphaned send buffer keeps the link busy afterwards.
s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
s.close()
'''


def _throughput_kbps(net, connect_timeout_s=5.0, src='robot', dst='laptop'):
    out = net.run(src, [sys.executable, '-c', TCP_SEND, net.addresses[dst],
                        str(connect_timeout_s)], timeout=20)
    return float(out.strip())


@needs_netns
def test_network_shapes_cuts_throttles_and_leaves_nothing_behind():
    env = {'PATH': os.environ.get('PATH', '/usr/bin:/bin')}
    net = netns.Network(rate_kbps=20000, cpu_cores={'robot': 0.25, 'laptop': 0.9})
    with net:
        names = set(net.namespaces.values())
        assert names <= set(netns.list_namespaces())
        sink = net.popen('laptop', [sys.executable, '-c', TCP_SINK], env)
        deadline = time.monotonic() + 10
        while True:
            try:
                rate = _throughput_kbps(net, 1.0)
                break
            except netns.TestbedError:
                assert time.monotonic() < deadline, 'the sink never came up'
                time.sleep(0.2)
        assert 12000 <= rate <= 26000, rate
        net.throttle(4000)
        assert 2000 <= _throughput_kbps(net) <= 6000
        net.cut()
        assert 'blackhole' in net.qdisc('robot') and 'blackhole' in net.qdisc('laptop')
        with pytest.raises(netns.TestbedError):
            _throughput_kbps(net, 1.0)
        net.restore()
        assert 'tbf' in net.qdisc('laptop')
        assert 2000 <= _throughput_kbps(net) <= 6000      # the throttle survives the cut
        # The CPU quota: a busy loop in the robot's group gets about 0.25 of a core.
        busy = 'import time\nt = time.time()\nwhile time.time() - t < 2: pass'
        spin = net.popen('robot', [sys.executable, '-c', busy], env)
        used0, t0 = net.cpu_usage_s('robot'), time.monotonic()
        spin.wait(timeout=20)
        cores = (net.cpu_usage_s('robot') - used0) / (time.monotonic() - t0)
        assert 0.15 <= cores <= 0.32, cores
        assert sink.poll() is None
        groups = [g.path for g in net.groups.values()]
    assert sink.wait(timeout=10) is not None          # teardown killed what was left inside
    assert not names & set(netns.list_namespaces())
    assert not any(os.path.exists(g) for g in groups)


@needs_netns
def test_three_scale_network_shapes_and_cuts_each_link_alone_and_forwards_nothing():
    """Robot, laptop and server: each pair joined by its own link. Each scale has one address
    for all its links; a packet crosses only the link joining its two ends (a cut link is not
    bypassed through the third scale), and each link is throttled and cut on its own."""
    env = {'PATH': os.environ.get('PATH', '/usr/bin:/bin')}
    net = netns.Network(scales=('robot', 'laptop', 'server'),
                        links=[('ethernet', 'robot', 'laptop', 100000.0),
                               ('wifi', 'robot', 'server', 20000.0),
                               ('backhaul', 'laptop', 'server', 4000.0)])
    with net:
        neighbours = [net.addresses['robot'], net.addresses['laptop']]
        assert sorted(net.peers('server')) == sorted(neighbours)
        with pytest.raises(ValueError, match='name a link'):
            net.cut()
        sink = net.popen('server', [sys.executable, '-c', TCP_SINK], env)

        def rate(src):
            return _throughput_kbps(net, 1.0, src=src, dst='server')
        deadline = time.monotonic() + 10
        while True:
            try:
                wifi = rate('robot')
                break
            except netns.TestbedError:
                assert time.monotonic() < deadline, 'the sink never came up'
                time.sleep(0.2)
        assert 12000 <= wifi <= 26000, wifi
        assert 2000 <= rate('laptop') <= 6000                 # the backhaul's own rate
        net.cut('wifi')
        assert 'blackhole' in net.qdisc('server', 'wifi')
        assert 'tbf' in net.qdisc('server', 'backhaul')
        assert not net.link_state('wifi').up and net.link_state('backhaul').up
        with pytest.raises(netns.TestbedError):
            rate('robot')                                     # not through the laptop
        assert 2000 <= rate('laptop') <= 6000
        net.restore('wifi')
        net.throttle(8000.0, 'wifi')
        assert 5000 <= rate('robot') <= 10000
        assert sink.poll() is None


@needs_netns
def test_network_teardown_runs_on_an_exception():
    net = netns.Network()
    with pytest.raises(RuntimeError):
        with net:
            names = set(net.namespaces.values())
            raise RuntimeError('boom')
    assert not names & set(netns.list_namespaces())


@needs_netns
def test_remove_stale_cleans_what_a_dead_run_left():
    dead = 4194304 + 7      # above pid_max: no live process can have it
    tag = f'{netns.NAME_PREFIX}-{dead}-1'
    net = netns.Network(tag=tag, cpu_cores={'robot': 0.5}).setup()
    try:
        removed = netns.remove_stale()
        assert f'{tag}-robot' in removed and f'{tag}-laptop' in removed
        assert not any(n.startswith(tag) for n in netns.list_namespaces())
    finally:
        net.teardown()


def test_timeline_tells_a_thaw_from_a_cold_start(record):
    def state(t, pid, st='running'):
        s = _state('robot', ['amcl'])
        s.nodes['amcl'] = p.NodeReport(state=st, pid=pid, since=0.0, restarts=0, ready=True,
                                       exit_reason='')
        record.agent_states.setdefault('robot', []).append((t, s))
    state(9.0, 500, 'standby')
    state(10.5, 500)          # thawed: same pid
    state(11.0, 500)
    state(20.0, 777)          # a new process
    record.arrivals['/amcl_pose'] = [9.6, 10.8, 11.2]
    tl = record.timeline(10.0, 25.0, nodes=('amcl',))
    assert tl['reports'] == [(-1.0, 'amcl', 'standby', 500), (0.5, 'amcl', 'running', 500),
                             (10.0, 'amcl', 'running', 777)]
    assert tl['/amcl_pose'] == [-0.4, 0.8, 1.2]


def test_settled_needs_a_quiet_layout_and_the_probes_within_limits(record):
    ok = p.ConnectionReading(rate_hz=5.0, bytes_per_s=0.0, below_for_s=0.0, level=p.OK)
    low = p.ConnectionReading(rate_hz=0.0, bytes_per_s=0.0, below_for_s=1.0, level=p.WARN)
    record.readings['amcl_ekf'] = [(9.0, 'robot', low), (9.8, 'robot', ok), (9.9, 'laptop', low)]
    record.events.append((3.0, p.Event(kind='migrate', node='amcl', from_scale='robot',
                                       to_scale='laptop', reason='x', stamp=3.0, generation=2)))
    assert record.settled(10.0, ['amcl_ekf'], 'robot', 5.0)
    assert not record.settled(10.0, ['amcl_ekf'], 'robot', 8.0)      # a move 7 s ago
    assert not record.settled(11.5, ['amcl_ekf'], 'robot', 5.0)      # no fresh reading
    record.readings['amcl_ekf'].append((10.2, 'robot', low))
    assert not record.settled(10.3, ['amcl_ekf'], 'robot', 5.0)      # below its minimum


def test_a_standby_copy_is_live_but_never_where_its_node_runs(record):
    """A lifecycle node's inactive copy: a process its agent holds (copies, start counts) that
    serves nobody (not in where, running_on or placement)."""
    robot = _state('robot', ['laser', 'amcl'])
    robot.nodes['amcl'] = p.NodeReport(state='standby', pid=500, since=0.0, restarts=0,
                                       ready=False, exit_reason='', lifecycle='inactive')
    laptop = _state('laptop', ['amcl'])
    laptop.nodes['amcl'].lifecycle = 'active'
    record.ingest_line(_line(1.0, p.TOPIC_AGENT_STATE, robot))
    record.ingest_line(_line(1.0, p.TOPIC_AGENT_STATE, laptop))
    assert record.where('amcl', 1.5) == ('laptop',)
    assert 'amcl' not in record.running_on('robot', 1.5)
    assert set(record.copies('robot', 1.5)) == {'laser', 'amcl'}
    assert record.standby_on('robot', 1.5)['amcl'].pid == 500
    assert record.standby_on('laptop', 1.5) == {}
    assert 500 in record.start_counts('robot')['amcl']


def test_the_observers_lag_is_not_judged_as_silence(record):
    """The observer writes its arrivals every 0.2 s: judged up to "now", the messages it has
    not written yet would read as a silence of the 40 Hz odometer (Δ 0) at the span's end. The
    record judges only up to HEARD_LAG_S before the observer's latest line."""
    conn = record.deployment.connection('odometer_odometry')     # freq_min 10 Hz, Δ 0
    record.arrivals['/wheel_ticks'] = [i / 40 for i in range(400)]   # 40 Hz, 0 .. 9.975 s
    record.heard_until = 10.2          # its latest line; what came after is not written yet
    assert record.judged_until() == pytest.approx(10.2 - HEARD_LAG_S)
    assert record.observed_violations(conn, 0.0, 10.4) == []
    # Once the observer has written past the span with nothing more heard, the silence counts.
    record.heard_until = 11.0
    found = record.observed_violations(conn, 0.0, 10.4)
    assert [(round(v.start, 2), round(v.end, 2)) for v in found] == [
        (round(9.975 + 0.1 + STALL_ALLOWANCE_S, 2), 10.4)]


def test_a_silence_says_whether_its_sender_stalled_or_its_messages_were_lost(record):
    ticks = [i / 40 for i in range(100)] + [3.0]          # about 0.52 s silent from 2.475
    record.arrivals['/wheel_ticks'] = ticks
    v = DeltaBreach('odometer_odometry', 2.67, 3.0, 0.0, 'observer')
    record.arrival_seqs['/wheel_ticks'] = list(range(1, 102))
    assert record.silence(v) == 'silent 0.52 s from 2.475 s, lost 0'
    record.arrival_seqs['/wheel_ticks'] = list(range(1, 101)) + [121]
    assert record.silence(v) == 'silent 0.52 s from 2.475 s, lost 20'
    record.arrival_seqs['/wheel_ticks'] = list(range(1, 102))
    # Its writer's own stamps: it stalled (sent 0.52 s apart), or its messages were held on
    # the way or read late here (sent 50 ms apart, delivered late).
    record.arrival_sent['/wheel_ticks'] = list(ticks)
    assert record.silence(v) == 'silent 0.52 s from 2.475 s, lost 0, sent 0.52 s apart'
    record.arrival_sent['/wheel_ticks'] = ticks[:-1] + [2.525]
    assert record.silence(v) == 'silent 0.52 s from 2.475 s, lost 0, sent 0.05 s apart'
    assert record.silence(v, lambda t: t - 2.0) == \
        'silent 0.52 s from 0.475 s, lost 0, sent 0.05 s apart'      # the run's own seconds
    record.arrival_seqs['/wheel_ticks'] = [-1] * 101
    assert record.silence(v) is None


def test_delta_violations_judge_the_connections_into_the_scale(record):
    """The observer's Δ judgement: amcl_ekf (EKF is pinned to the robot) always counts;
    camera_ar only while the layout has AR on the robot; Δ = 0 tolerates no reading below."""
    def layout(t, ar, gen):
        record.layouts.append((t, p.Layout(generation=gen, deployment='icar2015_testbed',
                                           assignments={'ar': ar}, reason='test', stamp=t)))
    layout(0.0, 'laptop', 1)
    layout(30.0, 'robot', 2)

    def periodic(rate, spans_):
        return [a + k / rate for a, b in spans_ for k in range(int((b - a) * rate))]
    record.arrivals['/amcl_pose'] = periodic(5.0, [(0.0, 10.0), (14.0, 60.0)])   # 4 s gap
    # /image silent for 3 s twice: AR on the laptop the first time, on the robot the second.
    record.arrivals['/image'] = periodic(30.0, [(0.0, 10.0), (13.0, 40.0), (43.0, 60.0)])
    record.arrivals['/odom'] = periodic(10.0, [(0.0, 50.0), (50.9, 60.0)])        # 0.9 s gap
    # The other topics never arrive here: every connection into the robot on them is past Δ.
    heard = ('amcl_ekf', 'camera_ar', 'odometry_ekf')
    record.heard_until = 60.0
    found = record.delta_violations(2.0, 58.0, 'robot')
    # Each stretch starts 1/freq_min + the stall allowance after the last message heard.
    assert [(v.connection, round(v.start, 2)) for v in found if v.connection in heard] == [
        ('amcl_ekf', round(9.8 + 0.5 + STALL_ALLOWANCE_S, 2)),
        ('camera_ar', round(40.0 - 1 / 30 + 1.0 + STALL_ALLOWANCE_S, 2)),
        ('odometry_ekf', round(49.9 + 0.2 + STALL_ALLOWANCE_S, 2))]
    assert {v.connection for v in found} - set(heard) == {
        'laser_navigation', 'ar_navigation', 'ekf_navigation', 'odometer_odometry'}
    longest = record.longest_below(2.0, 58.0, 'robot')
    assert 2.0 < longest['amcl_ekf'] < 4.0 and longest['ar_navigation'] > 50
    assert not [v for v in record.delta_violations(15.0, 40.0, 'robot') if v.connection in heard]
