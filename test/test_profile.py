"""anyscale-manager profile: the pure parts with hand-written clocks, then a real graph.

The real tests start test-bed-like workload nodes as processes (laser 10 Hz, odometer 20 Hz,
AMCL and EKF capped at 5 Hz), profile them for a few seconds, check what the file says, and run
an agent and the decider on the profiled file as it is.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest
import yaml

from anyscale_manager import cli
from anyscale_manager.model import advice
from anyscale_manager.model.loader import load_deployment, load_mapping
from anyscale_manager.agent.catalogue import build_argv
from anyscale_manager.model.types import Launch, MonitorSettings, Node
from anyscale_manager.profiling import graph as g
from anyscale_manager.profiling import processes as pr
from anyscale_manager.profiling import skeleton as sk
from anyscale_manager.profiling import stats, suggest
from anyscale_manager.profiling.cli import default_name
from processes import LoggedProcess


# --- stats ------------------------------------------------------------------------------------
def feed(meter, rate_hz, start, stop, nbytes=100, sample_from=None):
    """Arrivals every 1/rate from start to stop, a reading every second from ``sample_from``."""
    period = 1.0 / rate_hz
    t, next_read = start, sample_from if sample_from is not None else start + 1.0
    while t < stop:
        while next_read <= t:
            meter.sample(next_read)
            next_read += 1.0
        meter.add(t, nbytes)
        t += period
    return next_read


@pytest.mark.parametrize('rate_hz', [0.5, 1.0, 10.0, 200.0])
def test_topic_meter_reads_a_steady_rate(rate_hz):
    meter = stats.TopicMeter()
    feed(meter, rate_hz, 0.0, 20.0)
    s = meter.summary()
    assert s.median == pytest.approx(rate_hz, rel=0.01)
    assert s.lowest == pytest.approx(rate_hz, rel=0.05)
    assert s.mean_bytes == 100 and s.max_bytes == 100
    assert s.total_bytes == 100 * s.messages


def test_topic_meter_no_reading_before_the_second_arrival_and_gaps_read_low():
    meter = stats.TopicMeter()
    assert meter.sample(0.5) is None
    meter.add(1.0, 10)
    assert meter.sample(1.5) is None            # one arrival: no rate yet, not 0
    meter = stats.TopicMeter()
    next_read = feed(meter, 10.0, 0.0, 10.0)
    for t in range(int(next_read), 15):         # a 5 s silence
        meter.sample(float(t))
    next_read = feed(meter, 10.0, 15.0, 25.0, sample_from=15.0)
    s = meter.summary()
    assert s.median == pytest.approx(10.0, rel=0.02)
    assert s.lowest == 0.0
    assert 3.0 <= s.longest_below_s(5.0) <= 6.0


def test_longest_run_below_and_round_sig():
    assert stats.longest_run_below([5, 1, 1, 5, 1, 1, 1, 5], 2) == 3
    assert stats.longest_run_below([], 2) == 0
    assert stats.round_sig(9.9999999, 3) == 10.0
    assert stats.round_sig(12345.0, 3) == 12300.0
    assert stats.round_sig(201.28, 3, 'up') == 202.0
    assert stats.round_sig(4.995, 2, 'down') == 4.9
    assert stats.round_sig(0.0, 3) == 0.0
    with pytest.raises(ValueError):
        stats.TopicMeter(reading_period_s=0.0)


def test_cpu_meter_counts_descendants_primes_and_shares():
    meter = stats.CpuMeter()
    meter.update(0.0, {100: {100: 1.0, 101: 0.0}})          # primes
    meter.update(1.0, {100: {100: 1.5, 101: 0.25}})
    meter.update(2.0, {100: {100: 2.0, 101: 0.5, 102: 9.0}})   # 102 new: only primes
    s = meter.summary(100)
    assert s.readings == pytest.approx((0.75, 0.75))
    assert s.mean == pytest.approx(0.75) and s.highest == pytest.approx(0.75)
    assert s.share(3).mean == pytest.approx(0.25)
    assert meter.summary(999) is None


# --- the suggestion rule ----------------------------------------------------------------------
def summary(readings, messages=100, total_bytes=100 * 2516, max_bytes=2516):
    return stats.RateSummary(messages=messages, readings=tuple(readings), reading_period_s=1.0,
                             window_s=2.0, total_bytes=total_bytes, max_bytes=max_bytes)


def test_suggestion_for_a_steady_topic():
    s = suggest.suggest(summary([9.98, 10.0, 10.01, 9.99, 10.0]))
    assert (s.freq_min_hz, s.freq_opt_hz, s.tolerance_s) == (5.0, 10.0, 2.0)
    assert s.bandwidth_kbps == pytest.approx(202.0)      # 10 Hz x 2516 B, rounded up
    assert s.monitored and 'floor' in s.why[0]


@pytest.mark.parametrize('p50, opt, fmin', [
    (10.1, 10.0, 5.0), (5.02, 5.0, 2.5), (12.5, 12.5, 6.2), (29.6, 29.6, 15.0), (0.499, 0.5, 0.25),
])
def test_suggested_rates_are_rounded_only_a_little(p50, opt, fmin):
    s = suggest.suggest(summary([p50] * 5))
    assert (s.freq_opt_hz, s.freq_min_hz) == (opt, fmin)


def test_suggestion_for_a_slow_topic_covers_three_periods_at_the_minimum():
    s = suggest.suggest(summary([0.5] * 10))
    assert (s.freq_min_hz, s.freq_opt_hz) == (0.25, 0.5)
    assert s.tolerance_s == 12.0 and 'periods' in s.why[0]


def test_suggestion_never_violated_by_the_run_it_watched():
    readings = [10.0] * 10 + [1.0, 0.5, 0.0] + [10.0] * 10     # 3 s below half
    s = suggest.suggest(summary(readings))
    assert s.freq_min_hz == 5.0
    assert s.tolerance_s == 6.0 and 'twice' in s.why[0]
    assert any('3 s' in why for why in s.why)


@pytest.mark.parametrize('rate', [None, summary([10.0, 10.0]), summary([0.0, 0.0, 0.0]),
                                  summary([], messages=1)])
def test_no_suggestion_without_enough_readings(rate):
    s = suggest.suggest(rate)
    assert not s.monitored and s.tolerance_s is None and s.unmonitored


def test_tolerance_floor_is_above_a_cold_move():
    class Defaults:
        monitoring = MonitorSettings()
    assert suggest.TOLERANCE_FLOOR_S >= advice.cold_move_budget_s(Defaults())


# --- the graph --------------------------------------------------------------------------------
def test_project_and_hidden_nodes_are_left_out():
    from anyscale_manager.nodes.decider import NODE_NAME
    for name in (NODE_NAME, 'anyscale_agent_robot', 'anyscale_agent_robot_state',
                 'anyscale_status_4242', 'anyscale_testbed_observer', 'anyscale_profile_7'):
        assert g.is_project_node('/' + name) and not g.kept_node('/ns/' + name), name
    assert g.is_hidden_node('/_ros2cli_daemon_0') and not g.kept_node('/_x')
    assert g.kept_node('/amcl') and g.kept_node('/anyscale_things')
    assert g.skipped_topic('/rosout') and g.skipped_topic('/anyscale/layout')
    assert g.skipped_topic('/nav/_action/status') and not g.skipped_topic('/scan')
    assert g.full_name('amcl', '/') == '/amcl' and g.full_name('amcl', '/r1') == '/r1/amcl'


def ep(node, topic, kind, msg_type='std_msgs/msg/String', **kw):
    return g.Endpoint(node=node, topic=topic, msg_type=msg_type, kind=kind, **kw)


def test_edges_and_topic_plans():
    seen = g.GraphSeen()
    seen.add(0.0, ['/laser', '/amcl', '/anyscale_decider', '/_hidden', '/amcl'], [
        ep('/laser', '/scan', g.PUB, reliable=False),
        ep('/amcl', '/scan', g.SUB),
        ep('/nav', '/scan', g.SUB),
        ep('/_hidden', '/scan', g.SUB),
        ep('/anyscale_decider', '/scan', g.SUB),
        ep('/amcl', '/amcl_pose', g.PUB),
        ep('/amcl', '/amcl_pose', g.SUB),                    # itself: no connection
        ep('/map', '/map', g.PUB, reliable=True, transient_local=True),
        ep('/amcl', '/map', g.SUB),
        ep('/amcl', '/rosout', g.PUB),
        ep('/nav', '/rosout', g.SUB),
        ep('/laser', '/unread', g.PUB),                      # no subscriber: no connection
    ])
    assert seen.kept_nodes() == ['/amcl', '/laser', '/map', '/nav']
    assert seen.nodes['/amcl'].copies == 2
    assert [(e.topic, e.publisher, e.subscriber) for e in seen.edges()] == [
        ('/map', '/map', '/amcl'), ('/scan', '/laser', '/amcl'), ('/scan', '/laser', '/nav')]
    plans = seen.topic_plans()
    assert set(plans) == {'/map', '/scan'}
    assert not plans['/scan'].reliable and not plans['/scan'].transient_local
    assert plans['/map'].reliable and plans['/map'].transient_local


# --- node -> process --------------------------------------------------------------------------
def gid(pid, host=b'\x78\xfd', vendor=b'\x01\x0f'):
    return vendor + host + bytes([pid & 0xff, (pid >> 8) & 0xff, 0x9d, 0x3b]) + bytes(8)


def test_guid_fields_and_remaps():
    assert pr.guid_pid16(gid(5152)) == 5152 and pr.guid_host(gid(5152)) == b'\x78\xfd'
    assert pr.guid_pid16(gid(5152, vendor=b'\x01\x10')) is None
    assert pr.remapped(['python3', 'x.py', '--ros-args', '-r', '__node:=laser', '-r',
                        '__ns:=robot1']) == ('laser', '/robot1')
    assert pr.remapped(['x', '--ros-args', '--remap', 'talker:__node:=speaker']) == \
        ('speaker', None)
    assert pr.remapped(['x', '--name', 'laser']) == (None, None)


def table(*rows):
    return {pid: pr.ProcessInfo(pid, ppid, tuple(cmd)) for pid, ppid, cmd in rows}


def test_match_by_guid_on_this_host():
    procs = table((5152, 1, ['python3', 'laser.py']), (700, 1, ['bash']))
    match, why = pr.match_node('/laser', {gid(5152)}, procs, own_host=b'\x78\xfd')
    assert match == pr.ProcessMatch((5152,), pr.GUID) and not why


def test_match_by_guid_tells_apart_pids_65536_apart():
    procs = table((5152, 1, ['python3', 'laser.py']), (5152 + 65536, 1, ['python3', 'x.py']))
    fastdds = {5152 + 65536: True, 5152: False}
    match, _ = pr.match_node('/laser', {gid(5152)}, procs, b'\x78\xfd', fastdds.get)
    assert match.pids == (5152 + 65536,)
    match, _ = pr.match_node('/laser', {gid(5152)}, procs, b'\x78\xfd')
    assert match is None or match.how == pr.REMAP


def test_guid_of_another_host_needs_more_evidence():
    procs = table((5152, 1, ['python3', 'camera.py']))
    match, why = pr.match_node('/laser', {gid(5152, host=b'\x01\x02')}, procs, b'\x78\xfd')
    assert match is None and 'another host' in why
    procs = table((5152, 1, ['python3', 'driver.py', '--name', 'laser']))
    match, _ = pr.match_node('/laser', {gid(5152, host=b'\x01\x02')}, procs, b'\x78\xfd')
    assert match.pids == (5152,)


def test_match_by_remap_takes_the_top_of_a_chain():
    procs = table((10, 1, ['ros2', 'run', 'pkg', 'exe', '--ros-args', '-r', '__node:=laser']),
                  (11, 10, ['/opt/exe', '--ros-args', '-r', '__node:=laser']),
                  (12, 1, ['/opt/exe', '--ros-args', '-r', '__node:=laser', '-r',
                           '__ns:=/other']))
    match, _ = pr.match_node('/laser', set(), procs, None)
    assert match == pr.ProcessMatch((10,), pr.REMAP)
    match, _ = pr.match_node('/other/laser', set(), procs, None)
    assert match.pids == (12,)
    match, why = pr.match_node('/laser', {gid(99, vendor=b'\x01\x10')}, table(), None)
    assert match is None and 'not Fast DDS' in why


def test_shared_processes():
    matches = {'/a': pr.ProcessMatch((5,), pr.GUID), '/b': pr.ProcessMatch((5,), pr.GUID),
               '/c': pr.ProcessMatch((6,), pr.GUID)}
    assert pr.shared_processes(matches) == {5: ('/a', '/b')}


# --- the skeleton -----------------------------------------------------------------------------
@pytest.mark.parametrize('text', ['yes', 'No', '10', '1.5', '-m', '--name', "it's", 'a: b',
                                  '#x', '/scan', 'std_msgs/msg/String', '', 'null', '~', '[x]'])
def test_scalars_read_back_as_strings(text):
    assert yaml.safe_load(sk.scalar(text)) == text
    assert yaml.safe_load(sk.flow_list([text, 'b'])) == [text, 'b']


@pytest.mark.parametrize('value', [0.0, 5.0, 0.25, 202.0, 12300.0, 0.0049])
def test_float_scalars_are_decimals(value):
    text = sk.scalar(value)
    assert '.' in text and yaml.safe_load(text) == value


def test_keys_are_valid_and_unique():
    keys = sk.node_keys(['/r1/amcl', '/r2/amcl', '/laser', '/names', '/9lives'])
    assert keys == {'/r1/amcl': 'r1_amcl', '/r2/amcl': 'r2_amcl', '/laser': 'laser',
                    '/names': 'names_node', '/9lives': 'n_9lives'}


def readings(rate_hz, n=10, size=100):
    return summary([rate_hz] * n, messages=int(rate_hz * n), total_bytes=int(rate_hz * n) * size,
                   max_bytes=size)


LASER_CMD = ('/usr/bin/python3', '-m', 'drivers.laser', '--port', '/dev/ttyACM0', 'yes', '10',
             "it's", '--a-rather-long-option-name-that-makes-the-line-wrap', 'value ' * 8)


def synthetic_profile():
    edges = (
        g.Edge('/cmd_vel', '/fused_a', '/base', 'geometry_msgs/msg/Twist'),
        g.Edge('/cmd_vel', '/names', '/base', 'geometry_msgs/msg/Twist'),
        g.Edge('/map', '/names', '/fused_b', 'nav_msgs/msg/OccupancyGrid'),
        g.Edge('/odd', '/laser', '/fused_b', 'odd_msgs/msg/Odd'),
        g.Edge('/scan', '/laser', '/r1/amcl', 'sensor_msgs/msg/LaserScan'),
        g.Edge('/scan', '/laser', '/r2/amcl', 'sensor_msgs/msg/LaserScan'),
    )
    cpu = stats.CpuSummary((0.05, 0.07))
    shared = pr.ProcessMatch((200,), pr.GUID)
    nodes = (
        sk.NodeReport('/base', no_cpu_reason='no process on this host: another host?'),
        sk.NodeReport('/fused_a', cpu=cpu.share(2), process=shared, cmdline=('/bin/fuse',),
                      shares_with=('/fused_b',)),
        sk.NodeReport('/fused_b', cpu=cpu.share(2), process=shared, cmdline=('/bin/fuse',),
                      shares_with=('/fused_a',)),
        sk.NodeReport('/laser', cpu=cpu, process=pr.ProcessMatch((100,), pr.GUID),
                      cmdline=LASER_CMD, copies=2, gone_s=3.0),
        sk.NodeReport('/names', cpu=stats.CpuSummary((0.01,)),
                      process=pr.ProcessMatch((300,), pr.REMAP)),
        sk.NodeReport('/r1/amcl', cpu=cpu, process=pr.ProcessMatch((400,), pr.GUID)),
        sk.NodeReport('/r2/amcl'),
    )
    topics = {
        '/scan': sk.TopicReport('/scan', 'sensor_msgs/msg/LaserScan', readings(10.0, size=2516)),
        '/cmd_vel': sk.TopicReport('/cmd_vel', 'geometry_msgs/msg/Twist', readings(20.0)),
        '/map': sk.TopicReport('/map', 'nav_msgs/msg/OccupancyGrid',
                               summary([], messages=1, total_bytes=40000, max_bytes=40000)),
        '/odd': sk.TopicReport('/odd', 'odd_msgs/msg/Odd', None,
                               problem='cannot import odd_msgs.msg'),
    }
    return sk.Profile(name='my robot: test', host=sk.HostInfo('host-1', 4, None),
                      domain_id='151', duration_s=10.0, started='2025-01-01 00:00:00',
                      nodes=nodes, edges=edges, topics=topics)


def test_skeleton_validates_and_says_what_it_measured():
    text = sk.render(synthetic_profile())
    assert all(len(line) <= 99 for line in text.splitlines())
    d = load_mapping(yaml.safe_load(text), 'skeleton')
    assert d.name == 'my robot: test'
    assert d.scale_names == ('robot',) and d.master.capacity_cpu == 400.0 and not d.links
    assert d.node_names == ('base', 'fused_a', 'fused_b', 'laser', 'names_node', 'r1_amcl',
                            'r2_amcl')
    assert all(not n.managed and not n.launch.startable for n in d.nodes)
    assert d.node('laser').cpu == 6.0 and d.node('fused_a').cpu == 3.0
    assert d.node('base').cpu == 0.0 and d.node('r2_amcl').cpu == 0.0
    assert d.node('r1_amcl').launch.ros_name == '/r1/amcl'
    assert d.node('names_node').launch.ros_name == 'names'
    assert d.node('fused_a').coresidence == ('fused_b',)
    assert d.data_providers == ('fused_a', 'laser', 'names_node') and d.critical_nodes == ()
    assert text.count('# data provider: publishes') == 3
    scan = d.connection('laser_r1_amcl')
    assert (scan.topic, scan.msg_type) == ('/scan', 'sensor_msgs/msg/LaserScan')
    assert (scan.freq_min_hz, scan.freq_opt_hz, scan.tolerance_s) == (5.0, 10.0, 2.0)
    assert scan.bandwidth_kbps == pytest.approx(202.0)
    assert d.connection('names_node_fused_b').freq_min_hz is None       # one message
    assert d.connection('laser_fused_b').freq_min_hz is None            # not importable
    for line in text.splitlines():
        if re.match(r'\s+(freq_min_hz|freq_opt_hz|tolerance_s):', line):
            assert '# suggestion' in line
    for needle in ('critical candidate: a data provider', 'critical candidate: subscribes to '
                   '/cmd_vel', '/cmd_vel has 2 publisher nodes', 'cannot import odd_msgs.msg',
                   '2 nodes named /laser', 'left the graph 3 s', 'another host?',
                   'TODO scales', 'TODO links', 'found by the __node:= remap'):
        assert needle in text, needle


def test_skeleton_commented_examples_uncomment_to_valid_yaml():
    text = sk.render(synthetic_profile()).splitlines()
    start = text.index('        # launch:', text.index('      laser:'))
    block = []
    for line in text[start:]:
        if not line.startswith('        # ') or line.startswith('        # ') and \
                block and not line.startswith('        #   '):
            break
        block.append(line.replace('# ', '', 1))
    assert yaml.safe_load('\n'.join(block)) == {'launch': {'command': list(LASER_CMD)}}
    start = text.index('    # links:')
    links = [line.replace('# ', '', 1) for line in text[start:start + 3]]
    assert yaml.safe_load('\n'.join(links))['links']['wifi']['ends'] == ['robot', 'laptop']


def test_skeleton_of_an_empty_graph_is_refused():
    profile = synthetic_profile()
    with pytest.raises(ValueError, match='at least one node'):
        sk.render(sk.Profile(profile.name, profile.host, '1', 1.0, 'now', (), ()))


# --- the launch a node gets ------------------------------------------------------------------
TALKER = ('/usr/bin/python3', '/opt/demo/talker.py', '--rate', '10')


def agent_argv(scale='robot', lifecycle=True, ros_name='', parameters=None):
    """The command line an agent runs for a node whose launch is TALKER."""
    node = Node(name='talker', cpu=10.0, performance=1.0, lifecycle=lifecycle,
                launch=Launch(command=TALKER[:2], arguments=TALKER[2:], ros_name=ros_name,
                              parameters=parameters or {}))
    argv, problem = build_argv(node, '', scale=scale)
    assert not problem
    return argv


@pytest.mark.parametrize('scale', ['robot', 'laptop'])
@pytest.mark.parametrize('ros_name', ['', '/r1/talker'])
def test_the_launch_of_a_node_an_agent_started_is_what_its_file_says(scale, ros_name):
    argv = agent_argv(scale, ros_name=ros_name)
    assert any(a.startswith('~/change_state:=~/') for a in argv)
    launch = suggest.suggest_launch(argv)
    assert launch.command == TALKER and launch.lifecycle
    assert f'~/get_state:=~/{scale}/get_state' in launch.dropped
    # Its parameters stay: an agent would set them from launch.parameters, and a command with
    # them starts the same node.
    launch = suggest.suggest_launch(agent_argv(scale, parameters={'rate': 5}))
    assert launch.command == TALKER + ('--ros-args', '-p', 'rate:=5')


@pytest.mark.parametrize('cmdline', [
    TALKER,
    TALKER + ('--ros-args', '-r', '__node:=speaker'),          # a launch file's own remap
    TALKER + ('--ros-args', '-r', '~/get_state:=~/mine'),      # not an agent's
    TALKER + ('--ros-args', '-r', '~/get_state:=~/robot/get_state_of_another'),
    agent_argv(lifecycle=False),                               # nothing tells it apart
])
def test_a_command_line_without_an_agents_lifecycle_remaps_is_kept(cmdline):
    launch = suggest.suggest_launch(cmdline)
    assert launch.command == cmdline and not launch.lifecycle and not launch.dropped
    assert suggest.suggest_launch(cmdline, lifecycle_seen=True).lifecycle


def test_an_emptied_ros_args_section_goes_with_its_end_marker():
    argv = TALKER + ('--ros-args', '-r', '~/get_state:=~/robot/get_state', '--', 'extra')
    assert suggest.suggest_launch(argv).command == TALKER + ('extra',)


def test_the_graph_tells_a_lifecycle_node_by_its_transition_events():
    graph = g.GraphSeen()
    graph.add(0.0, ['/talker', '/listener'], [
        g.Endpoint('/talker', '/talker/robot/transition_event', suggest.LIFECYCLE_EVENT_TYPE,
                   g.PUB),
        g.Endpoint('/listener', '/talker/robot/transition_event',
                   suggest.LIFECYCLE_EVENT_TYPE, g.SUB)])
    assert graph.publishes_type('/talker', suggest.LIFECYCLE_EVENT_TYPE)
    assert not graph.publishes_type('/listener', suggest.LIFECYCLE_EVENT_TYPE)


@pytest.mark.parametrize('seen, cmdline', [(False, agent_argv()), (True, TALKER), (True, ())])
def test_skeleton_says_a_node_is_a_lifecycle_node_and_offers_standby(seen, cmdline):
    profile = synthetic_profile()
    nodes = tuple(sk.NodeReport('/laser', cpu=n.cpu, process=n.process, cmdline=cmdline,
                                lifecycle=seen) if n.name == '/laser' else n
                  for n in profile.nodes)
    text = sk.render(sk.Profile(profile.name, profile.host, profile.domain_id,
                                profile.duration_s, profile.started, nodes, profile.edges,
                                profile.topics))
    d = load_mapping(yaml.safe_load(text), 'skeleton')     # valid as it is
    assert not d.node('laser').lifecycle
    lines = text.splitlines()
    section = lines[lines.index('      laser:'):lines.index('      names_node:')]
    body = ' '.join(line.strip().lstrip('# ') for line in section)     # comments unwrapped
    assert 'lifecycle node: ' in body and 'standby: true is then possible' in body
    assert 'a move is an activation' in body
    assert ('transition events' in body) == seen
    assert "an agent's lifecycle remaps" in body or seen
    assert '        # lifecycle: true' in section and '        # standby: true' in section
    assert '~/change_state' not in ''.join(line for line in section if 'command' in line)
    if cmdline:
        start = section.index('        # launch:')
        block = [line.replace('# ', '', 1) for line in section[start:]
                 if line.startswith('        #   ') or line == '        # launch:']
        assert yaml.safe_load('\n'.join(block)) == {'launch': {'command': list(TALKER)}}
    # With a launch and without managed: false, the uncommented line loads: a lifecycle node.
    data = yaml.safe_load(text)
    laser = data['/**']['ros__parameters']['nodes']['laser']
    laser.update(launch={'command': list(TALKER)}, lifecycle=True)
    del laser['managed']
    assert load_mapping(data, 'skeleton').node('laser').lifecycle


def test_a_plain_node_gets_no_lifecycle_words():
    text = sk.render(synthetic_profile())
    assert 'lifecycle' not in text and 'standby' not in text


# --- the command: arguments -------------------------------------------------------------------
@pytest.mark.parametrize('argv, message', [
    (['--duration', '0'], '--duration'),
    (['--duration', 'inf'], '--duration'),
    (['--duration', '5', '--name', ' '], '--name'),
])
def test_bad_arguments_start_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / 'x.yaml'
    assert cli.main(['profile', '--output', str(out), *argv]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_bad_output_paths(tmp_path, capsys):
    assert cli.main(['profile', '--duration', '5', '--output', str(tmp_path)]) == 2
    assert 'is a folder' in capsys.readouterr().err
    assert cli.main(['profile', '--duration', '5', '--output',
                     str(tmp_path / 'missing' / 'x.yaml')]) == 2
    assert 'does not exist' in capsys.readouterr().err
    assert default_name('/a/b/my_robot.yaml') == 'my_robot'


# --- a real graph -----------------------------------------------------------------------------
WORKLOAD = [sys.executable, '-m', 'anyscale_manager.nodes.workload']
GRAPH = {   # test-bed-like: the test-bed's names, topics and rates, light CPU work
    'laser': ['--name', 'laser', '--pub', '/scan', '--rate-hz', '10.0', '--bytes', '2500'],
    # named through the command line's remap, as a launch file does
    'odometer': ['--name', 'odometer_raw', '--pub', '/wheel_ticks', '--rate-hz', '20.0',
                 '--bytes', '64', '--ros-args', '-r', '__node:=odometer'],
    'amcl': ['--name', 'amcl', '--sub', '/scan', '--pub', '/amcl_pose', '--rate-hz', '5.0',
             '--bytes', '128', '--work-ms', '2.0'],
    'ekf': ['--name', 'ekf', '--sub', '/amcl_pose', '--sub', '/wheel_ticks', '--pub', '/pose',
            '--rate-hz', '5.0', '--bytes', '128', '--work-ms', '2.0'],
}
EXPECTED = {   # connection -> (topic, publisher, subscriber, rate Hz)
    'laser_amcl': ('/scan', 'laser', 'amcl', 10.0),
    'amcl_ekf': ('/amcl_pose', 'amcl', 'ekf', 5.0),
    'odometer_ekf': ('/wheel_ticks', 'odometer', 'ekf', 20.0),
}
DURATION_S = 6


def wait_for(cond, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.1)
    raise AssertionError(f'{what} within {timeout_s} s')


def child_env():
    env = dict(os.environ)
    env['PYTHONUNBUFFERED'] = '1'
    return env


@pytest.fixture(scope='module')
def workloads(tmp_path_factory):
    folder = tmp_path_factory.mktemp('workloads')
    procs = {name: LoggedProcess(folder / f'{name}.out', WORKLOAD + args, child_env())
             for name, args in GRAPH.items()}
    try:
        wait_for(lambda: all('first output published' in p.text() for p in procs.values()),
                 60.0, 'every workload node publishing')
        yield procs
    finally:
        for p in procs.values():
            p.stop()


@pytest.fixture(scope='module')
def profiled(workloads, tmp_path_factory):
    out = tmp_path_factory.mktemp('profile') / 'profiled.yaml'
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'profile', '--duration',
                        str(DURATION_S), '--output', str(out)], env=child_env(),
                       capture_output=True, text=True, timeout=120)
    return r, out


def test_profile_of_a_real_graph(workloads, profiled):
    r, out = profiled
    assert r.returncode == 0, r.stderr
    progress = re.findall(rf'profile: +\d+/{DURATION_S} s: 4 nodes', r.stderr)
    assert len(progress) >= DURATION_S - 2, r.stderr
    assert f'wrote {out}: 4 nodes (4 with CPU' in r.stdout
    d = load_deployment(str(out))
    assert sorted(d.node_names) == sorted(GRAPH)
    assert sorted(c.name for c in d.connections) == sorted(EXPECTED)
    for name, (topic, pub, sub, rate) in EXPECTED.items():
        c = d.connection(name)
        assert (c.topic, c.publisher, c.subscriber) == (topic, pub, sub)
        assert re.match(r'^\w+/msg/\w+$', c.msg_type)
        assert c.freq_opt_hz == pytest.approx(rate, rel=0.1), name
        assert c.freq_min_hz == pytest.approx(c.freq_opt_hz / 2, rel=0.05)
        assert c.tolerance_s == 2.0
    # serialized UInt8MultiArray of 2500 bytes: about 2516 B at 10 Hz
    assert d.connection('laser_amcl').bandwidth_kbps == pytest.approx(201.0, rel=0.1)
    assert set(d.data_providers) == {'laser', 'odometer'}
    text = out.read_text()
    for name, proc in workloads.items():
        assert f'/{name}: pid {proc.proc.pid} on this host' in text, name
        assert d.node(name).cpu >= 0.0
    assert '__node:=odometer' in text             # its command line, for the launch to write
    assert cli.main(['validate', '--quiet', str(out)]) == 0


def test_agent_and_decider_run_on_the_profiled_file(workloads, profiled, tmp_path, ros):
    """As it is, the file runs an agent (which probes every profiled connection against the
    suggested thresholds) and the decider (which publishes its layout)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    from anyscale_manager import protocol as p

    r, path = profiled
    assert r.returncode == 0, r.stderr
    d = load_deployment(str(path))
    state = ['-p', f'agent.state_dir:={tmp_path}', '-p', f'agent.log_dir:={tmp_path}']
    agent = LoggedProcess(tmp_path / 'agent.out', [
        sys.executable, '-m', 'anyscale_manager.nodes.agent', '--ros-args', '--params-file',
        str(path), '-p', 'scale:=robot', *state], child_env())
    decider = LoggedProcess(tmp_path / 'decider.out', [
        sys.executable, '-m', 'anyscale_manager.nodes.decider', '--ros-args', '--params-file',
        str(path), '-p', 'decider.discovery_s:=1.0', '-p', 'decider.period_s:=0.2'],
        child_env())
    node = ros.node('profile_test_listener')
    layouts, events, readings = [], [], {}
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, p.TOPIC_LAYOUT,
                             lambda m: layouts.append(p.Layout.from_json(m.data)), latched)
    node.create_subscription(String, p.TOPIC_EVENTS,
                             lambda m: events.append(json.loads(m.data)), 100)

    def on_status(msg):
        for name, reading in p.ConnectionStatus.from_json(msg.data).connections.items():
            readings.setdefault(name, []).append(reading)
    node.create_subscription(String, p.TOPIC_CONNECTION_STATUS, on_status, 10)

    def healthy(name):
        c = d.connection(name)
        return any(x.rate_hz >= c.freq_min_hz and x.level == p.OK
                   for x in readings.get(name, ()))
    try:
        ros.spin_until(lambda: layouts and all(healthy(n) for n in EXPECTED), 45.0,
                       'a layout and every profiled connection healthy',
                       {'agent': agent, 'decider': decider}, watch=True,
                       state=lambda: {n: readings.get(n, [])[-1:] for n in EXPECTED},
                       spin_s=0.1)
        assert layouts[-1].deployment == d.name and layouts[-1].assignments == {}
        assert not [e for e in events if e['kind'] == 'violation'
                    and any(n in e['reason'] for n in EXPECTED)], events
    finally:
        codes = [decider.stop(), agent.stop()]
    assert codes == [0, 0], decider.text() + agent.text()


def test_empty_graph_exits_1_and_writes_nothing(tmp_path):
    env = child_env()
    domain = int(env['ROS_DOMAIN_ID'])
    env['ROS_DOMAIN_ID'] = str(domain + 1 if domain < 232 else domain - 1)   # nobody there
    out = tmp_path / 'empty.yaml'
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'profile', '--duration',
                        '1.5', '--output', str(out)], env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1, r.stderr
    assert 'no node to profile was seen' in r.stderr and 'not written' in r.stderr
    assert not out.exists()


def test_sigint_ends_the_watch_early_and_writes(workloads, tmp_path):
    out = tmp_path / 'short.yaml'
    proc = subprocess.Popen([sys.executable, '-m', 'anyscale_manager.cli', 'profile',
                             '--duration', '60', '--output', str(out)], env=child_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        # Three seconds of progress, the last with every node seen (discovery on a loaded
        # machine may take longer than the first progress lines).
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not (
                len(lines) >= 3 and f': {len(GRAPH)} nodes' in lines[-1]):
            line = proc.stderr.readline()
            if not line:
                break
            lines += [line] if re.match(r'profile: +\d+/60 s', line) else []
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, stderr
    assert '(Ctrl-C)' in stderr and 'cut short by Ctrl-C' in out.read_text()
    assert sorted(load_deployment(str(out)).node_names) == sorted(GRAPH)
