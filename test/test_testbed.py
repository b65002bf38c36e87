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
from anyscale_manager.testbed.record import HEARD_LAG_S, Record, Violation
from anyscale_manager.testbed.report import (category, draw_timeline, event_log, spans,
                                             status_table, write_event_log)

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
    v = Violation('odometer_odometry', 2.67, 3.0, 0.0, 'observer')
    record.arrival_seqs['/wheel_ticks'] = list(range(1, 102))
    assert record.silence(v) == 'silent 0.52 s from 2.475, lost 0'
    record.arrival_seqs['/wheel_ticks'] = list(range(1, 101)) + [121]
    assert record.silence(v) == 'silent 0.52 s from 2.475, lost 20'
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
