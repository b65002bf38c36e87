"""Layouts only from the leading decider: real deciders and agents over loopback DDS.

- without a key, a plain script's layout is refused by agents that follow a live decider
  (a second decider stands by: test_standby_decider.py);
- with a key: the decider moves nodes as before; a forged layout (generation 10**15) and a
  replayed one (a real signed message sent again) are dropped by the agents, each with its
  reason in their log, and nothing moves; so are a forged agent state, and a forged or
  replayed link status (the away link down) or scale status (the away scale full) at the
  decider.
"""

import json
import os
import signal
import time

import pytest
import yaml
from std_msgs.msg import String

from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.nodes import qos
from home_away import runs, start, start_agents
from spinning import spin_until
from test_decider_agent import write_deployment


@pytest.fixture
def world(ros):
    node = ros.node('decider_authority_test')
    seen = {'layouts': [], 'raw': [], 'states': {}, 'links': []}

    def layout(m):
        seen['raw'].append(m.data)
        seen['layouts'].append(p.Layout.from_json(m.data))

    def state(m):
        s = p.AgentState.from_json(m.data)
        if s.instance != 'f00d':          # the test's own forgery
            seen['states'][s.scale] = s
    node.create_subscription(String, p.TOPIC_LAYOUT, layout, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_AGENT_STATE, state, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_LINK_STATUS,
                             lambda m: seen['links'].append(m.data), qos.MONITOR_READER)
    procs = []
    yield node, ros.executor, seen, procs
    for _, pr in reversed(procs):
        pr.stop()


def deployment(tmp_path, key=False):
    path = write_deployment(tmp_path)
    if key:
        key_path = tmp_path / 'deployment.key'
        auth.write_key(str(key_path))
        with open(path) as f:
            data = yaml.safe_load(f)
        data['/**']['ros__parameters']['security'] = {'key_file': str(key_path)}
        with open(path, 'w') as f:
            yaml.safe_dump(data, f)
    return path


def until_logged(ex, send, agents, why, timeout=30.0):
    """Send each second until every agent has logged ``why``: drops are logged once per 10 s
    (throttled)."""
    spin_until(ex, lambda: all(why in agent.text() for agent in agents.values()), timeout,
               f'every agent logging {why!r}', agents, tick=send, tick_every_s=1.0, spin_s=0.1)


def serving(seen, scales):
    """node -> pid of what runs (starting or running) on each scale."""
    return {s: {n: r.pid for n, r in seen['states'][s].running().items()} for s in scales}


def follow(seen, decider_id):
    return all(seen['states'].get(s) is not None and seen['states'][s].decider == decider_id
               for s in ('home', 'away'))


def test_a_plain_scripts_layout_is_refused_while_the_decider_lives(tmp_path, ros_env, world):
    node, ex, seen, procs = world
    path = deployment(tmp_path)
    agents = start_agents(procs, tmp_path, ros_env, path)
    first = start(procs, tmp_path, ros_env, path, 'decider_1')
    spin_until(ex, lambda: seen['layouts'] and seen['layouts'][-1].decider is not None, 40.0,
               "the first decider's layout", procs)
    one = seen['layouts'][-1].decider
    assert one.pid == first.proc.pid
    spin_until(ex, lambda: follow(seen, one.id), 30.0, 'both agents following the first decider',
               procs)

    # Without a key, a plain script's layout (no decider identity) is refused while the
    # followed decider lives, and nothing moves.
    pids = {s: {n: r.pid for n, r in seen['states'][s].nodes.items()} for s in agents}
    forger = node.create_publisher(String, p.TOPIC_LAYOUT, qos.LATCHED)
    forger.publish(String(data=json.dumps({
        'generation': 10 ** 15, 'deployment': seen['layouts'][-1].deployment,
        'assignments': {'worker': 'home', 'pinned': 'home'}, 'reason': 'forged',
        'stamp': time.time()})))
    for scale, agent in agents.items():
        spin_until(ex, lambda: 'layout of decider without identity (anonymous) (term 0) ignored: '
                   f'following {one.id}' in agent.text(), 15.0, f'the {scale} agent refusing it',
                   procs)
    # (The decider may move the worker meanwhile: its own layouts still count.)
    real = {lay.generation for lay in seen['layouts'] if lay.decider is not None}
    assert all(st.generation in real for st in seen['states'].values()), seen['states']
    assert seen['states']['home'].nodes['pinned'].pid == pids['home']['pinned']
    assert follow(seen, one.id)
    assert 'security.key_file is not set' in agents['home'].text()
    # The decider logs the foreign layout and does not answer it with a layout of its own.
    spin_until(ex, lambda: 'ignored a layout of this deployment without a decider identity '
               '(generation 1000000000000000' in first.text(), 15.0, 'the decider logging it',
               procs)
    assert 're-published above' not in first.text()
    assert max(lay.generation for lay in seen['layouts'] if lay.decider) < 10 ** 15
    codes = {name: pr.stop() for name, pr in reversed(procs)}
    assert codes['decider_1'] == 0 and codes['agent_home'] == 0


def test_with_a_key_layouts_move_nodes_and_forged_or_replayed_ones_do_not(tmp_path, ros_env,
                                                                          world):
    node, ex, seen, procs = world
    path = deployment(tmp_path, key=True)
    agents = start_agents(procs, tmp_path, ros_env, path)
    decider = start(procs, tmp_path, ros_env, path, 'decider')
    spin_until(ex, lambda: seen['layouts'], 40.0, 'the first layout', procs)
    assert seen['layouts'][0].assignments['worker'] == 'home'
    first_raw = seen['raw'][0]
    assert auth.check_signature(auth.load_key(str(tmp_path / 'deployment.key')),
                                first_raw) == ''
    # The decider moves the worker out as it does without a key.
    spin_until(ex, lambda: runs(seen, 'away', 'worker') and not runs(seen, 'home', 'worker'),
               60.0, 'worker running on away', procs)
    me = seen['layouts'][-1].decider.id
    spin_until(ex, lambda: follow(seen, me), 10.0, 'both agents following the decider', procs)
    spin_until(ex, lambda: seen['states']['home'].nodes['worker'].state == 'stopped', 30.0,
               'the home copy of the worker stopped', procs)
    pids = serving(seen, agents)
    generations = {s: seen['states'][s].generation for s in agents}

    forger = node.create_publisher(String, p.TOPIC_LAYOUT, qos.LATCHED)
    forged = json.loads(seen['raw'][-1])
    forged.update(generation=10 ** 15, assignments={'worker': 'home', 'pinned': 'home'},
                  seq=forged['seq'] + 1000, stamp=time.time())
    checks = [
        # unsigned: a plain rclpy script with the decider's identity copied
        ({k: v for k, v in forged.items() if k != 'auth'}, 'not signed (no auth field)'),
        # signed with another key
        (dict(forged, auth=auth.sign(bytes(32), forged)), 'bad authenticator'),
        # a real signed layout of the decider, sent again: it placed the worker home
        (json.loads(first_raw), 'a replay'),
    ]
    for data, why in checks:
        until_logged(ex, lambda: forger.publish(String(data=json.dumps(data))), agents, why)
    assert 'dropped layout generation 1000000000000000 of decider ' + me in \
        agents['home'].text()
    # An agent state is signed too: a forged one (the away agent's worker 'stopped') is dropped
    # by the other agent and by the decider, and the worker is not brought home for it.
    fake = p.AgentState(scale='away', generation=generations['away'], stamp=time.time(),
                        nodes={}, decider=me, instance='f00d', seq=1)
    states = node.create_publisher(String, p.TOPIC_AGENT_STATE, qos.LATCHED)

    def forge_state():
        fake.seq += 1
        fake.stamp = time.time()
        states.publish(String(data=fake.to_json()))
    # The home agent and the decider each read it: the wait is for both logs.
    until_logged(ex, forge_state, {'home': agents['home'], 'decider': decider},
                 "agent state claiming scale 'away': not signed")
    assert "dropped an agent state claiming scale 'away': not signed" in agents['home'].text()
    # The monitors' topics are signed too: the away link reported down (unsigned, then a real
    # signed report sent again), the away scale reported full (unsigned): dropped.
    assert seen['links'] and auth.check_signature(
        auth.load_key(str(tmp_path / 'deployment.key')), seen['links'][-1]) == ''
    real_link = seen['links'][-1]
    down = dict(json.loads(real_link), up=False, stamp=time.time(), seq=10 ** 9)
    down.pop('auth')
    links = node.create_publisher(String, p.TOPIC_LINK_STATUS, qos.STATUS)
    scales = node.create_publisher(String, p.TOPIC_SCALE_STATUS, qos.STATUS)
    full = p.ScaleStatus(scale='away', stamp=time.time(), cpu_total=1000.0, capacity_cpu=100.0,
                         cpu_by_node={'worker': 1000.0}, mem_percent=99.0, load_1m=9.0,
                         sender='agent away/f00d', seq=1)
    for pub, text, why in ((links, json.dumps(down), 'ignored a message on '
                            f'{p.TOPIC_LINK_STATUS}: dropped: not signed'),
                           (links, real_link, f'ignored a message on {p.TOPIC_LINK_STATUS}: '
                            'dropped: sequence'),
                           (scales, full.to_json(), 'ignored a message on '
                            f'{p.TOPIC_SCALE_STATUS}: dropped: not signed')):
        until_logged(ex, lambda: pub.publish(String(data=text)), {'decider': decider}, why)
    # Nothing moved, nothing restarted, no generation taken; the decider goes on.
    spin_until(ex, lambda: len(seen['layouts']) >= 3, 10.0, 'layouts', procs)
    assert serving(seen, agents) == pids
    assert {s: seen['states'][s].generation for s in agents} == generations
    assert runs(seen, 'away', 'worker') and follow(seen, me)
    assert decider.proc.poll() is None
    assert 'security.key_file is not set' not in agents['home'].text()
    codes = {name: pr.stop(signal.SIGINT) for name, pr in reversed(procs)}
    assert codes['decider'] == 0


def test_a_key_file_open_to_others_stops_the_decider_and_the_agents(tmp_path, ros_env, world):
    node, ex, seen, procs = world
    path = deployment(tmp_path, key=True)
    os.chmod(tmp_path / 'deployment.key', 0o644)
    started = [start(procs, tmp_path, ros_env, path, 'decider'),
               start(procs, tmp_path, ros_env, path, 'agent_home', '-p', 'scale:=home')]
    for proc in started:
        assert proc.proc.wait(60) == 2, proc.text()
        assert 'mode 0644 lets group or others read it' in proc.text()
    assert not seen['layouts'] and not seen['states']
