"""The agent node end to end: real agent processes, real rclpy nodes, real DDS on loopback."""

import json
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
import yaml
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from lifecycle_msgs.srv import GetState
from std_msgs.msg import String

from anyscale_manager import protocol
from anyscale_manager.agent import ports
from processes import LoggedProcess

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURES = os.path.join(HERE, 'fixtures')
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def write_deployment(tmp_path, run_id, name='agent_test'):
    chatter = f'/agent_test_{run_id}'
    env = {'AGENT_TEST_RUN': run_id}

    def talker(topic, ros_name, **extra):
        # Node names of this test only: a leftover of another run must not look ready.
        return dict({'launch': {'command': [sys.executable,
                                            os.path.join(FIXTURES, 'agent_talker.py')],
                                'parameters': {'topic': topic, 'rate_hz': 10.0},
                                'ros_name': f'{ros_name}_{run_id}', 'env': dict(env)},
                     'cpu': 1.0}, **extra)

    data = {'/**': {'ros__parameters': {
        'deployment': {'name': name},
        'scales': {'names': ['a', 'b'],
                   'a': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 200.0},
                   'b': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 200.0}},
        'nodes': {
            'names': ['talker', 'talker2', 'stubborn', 'forker', 'warm'],
            'talker': talker(chatter + '/sbs', 'talker'),
            'warm': dict(talker(chatter + '/warm', 'warm', lifecycle=True, standby=True),
                         launch={'command': [sys.executable,
                                             os.path.join(FIXTURES, 'agent_lifecycle_talker.py')],
                                 'parameters': {'topic': chatter + '/warm', 'rate_hz': 10.0},
                                 'ros_name': f'warm_{run_id}', 'env': dict(env)}),
            'talker2': talker(chatter + '/stop_first', 'talker2',
                              move_order='stop_before_start'),
            'stubborn': {'launch': {'command': [sys.executable,
                                                os.path.join(FIXTURES, 'agent_stubborn.py')],
                                    'env': dict(env)},
                         'cpu': 1.0},
            'forker': {'launch': {'command': [sys.executable,
                                              os.path.join(FIXTURES, 'agent_forker.py'),
                                              str(tmp_path / 'forker_pids')],
                                  'env': dict(env)},
                       'cpu': 1.0},
        },
        'decider': {'agent_timeout_s': 3.0},
        'agent': {'sigint_grace_s': 1.0, 'sigterm_grace_s': 1.0, 'readiness_timeout_s': 10.0,
                  'restart_backoff_s': 0.2, 'restart_backoff_max_s': 2.0,
                  'heartbeat_rate_hz': 4.0, 'state_dir': str(tmp_path / 'state'),
                  'log_dir': str(tmp_path / 'log')},
    }}}
    path = tmp_path / 'deployment.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path), chatter


class Agent(LoggedProcess):
    """One agent process on one scale, output in a file."""

    def __init__(self, tmp_path, deployment, scale, env, *extra):
        super().__init__(tmp_path / f'agent_{scale}_{time.monotonic_ns()}.out',
                         [os.path.join(os.path.dirname(sys.executable), 'agent'), '--ros-args',
                          '--params-file', deployment, '-p', f'scale:={scale}', *extra], env)
        self.scale = scale

    def stop(self, sig=signal.SIGINT, timeout=20.0):
        return super().stop(sig, timeout, must_exit=True)


class Harness:
    """The test's own rclpy node: publishes layouts, records agent states and chatter."""

    def __init__(self, ros, deployment_name, chatter):
        self.ros = ros
        self.node = ros.node('agent_test_harness')
        self.name = deployment_name
        self.layout_pub = self.node.create_publisher(String, protocol.TOPIC_LAYOUT, LATCHED)
        self.states = {}          # scale -> latest AgentState
        self.history = []         # (monotonic, AgentState)
        self.heard = []           # (monotonic, 'scale pid seq', topic)
        self.agents = []          # the test's agent processes, their output shown on a failure
        self.node.create_subscription(String, protocol.TOPIC_AGENT_STATE, self._on_state,
                                      QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                                 durability=DurabilityPolicy.TRANSIENT_LOCAL))
        for suffix in ('/sbs', '/stop_first', '/warm'):
            topic = chatter + suffix
            self.node.create_subscription(
                String, topic, lambda m, topic=topic: self.heard.append(
                    (time.monotonic(), m.data, topic)), 10)

    def _on_state(self, msg):
        state = protocol.AgentState.from_json(msg.data)
        self.states[state.scale] = state
        self.history.append((time.monotonic(), state))

    def publish(self, generation, assignments, **extra):
        data = dict(generation=generation, deployment=self.name, assignments=assignments,
                    reason='test', stamp=time.time(), **extra)
        self.publish_raw(json.dumps(data))

    def publish_raw(self, text):
        self.layout_pub.publish(String(data=text))

    def wait(self, cond, timeout=30.0, what='condition'):
        """Spin until ``cond()``; a failure shows the agents' last states and output."""
        self.ros.spin_until(cond, timeout, what, [(f'agent {a.scale}', a) for a in self.agents],
                            state=lambda: {s: st.to_dict() for s, st in self.states.items()})

    def report(self, scale, node):
        state = self.states.get(scale)
        return state.nodes.get(node) if state else None

    def running(self, scale, node):
        r = self.report(scale, node)
        return r is not None and r.state == 'running' and r.ready

    def state_is(self, scale, node, state):
        r = self.report(scale, node)
        return r is not None and r.state == state

    def standby(self, scale, node):
        """A configured, inactive copy (not one still on its way there)."""
        r = self.report(scale, node)
        return r is not None and r.state == 'standby' and r.lifecycle == 'inactive'


def run_processes(run_id):
    """Live processes started for one test run (found by the run's environment marker)."""
    out = []
    for p in psutil.process_iter(['pid', 'status']):
        try:
            if p.info['status'] != psutil.STATUS_ZOMBIE and \
                    p.environ().get('AGENT_TEST_RUN') == run_id:
                out.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return out


@pytest.fixture
def setup(tmp_path, ros_env, ros):
    run_id = f'{os.getpid()}_{time.monotonic_ns() % 10 ** 9}'
    deployment, chatter = write_deployment(tmp_path, run_id)
    harness = Harness(ros, 'agent_test', chatter)
    agents = harness.agents

    def agent(scale, *extra):
        a = Agent(tmp_path, deployment, scale, ros_env, *extra)
        agents.append(a)
        return a

    yield harness, agent, deployment, run_id
    for a in agents:
        if a.proc.poll() is None:
            a.stop(signal.SIGTERM)
    # A failed test may have killed an agent on purpose: leave no node of this run behind.
    leftovers = run_processes(run_id)
    for p in leftovers:
        p.kill()
    assert not leftovers, f'processes outlived their agents: {leftovers}'


def gone(pid):
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def first_time(history, scale, node, states, after=0.0):
    for stamp, st in history:
        r = st.nodes.get(node)
        if st.scale == scale and stamp >= after and r is not None and r.state in states:
            return stamp
    return None


def test_bad_arguments_exit_non_zero_and_start_nothing(tmp_path, ros_env, setup):
    _, agent, deployment, _ = setup
    a = agent('nowhere')
    assert a.proc.wait(30) == 2
    assert "scale 'nowhere' is not a scale of deployment 'agent_test'" in a.text()
    bad = tmp_path / 'bad.yaml'
    bad.write_text(open(deployment).read().replace('cpu: 1.0', 'cpu: lots', 1))
    a = Agent(tmp_path, str(bad), 'a', ros_env)
    assert a.proc.wait(30) == 2
    assert 'nodes.' in a.text() and 'cpu' in a.text() and 'expected a number' in a.text()
    noscale = subprocess.run([os.path.join(os.path.dirname(sys.executable), 'agent'),
                              '--ros-args', '--params-file', deployment], env=ros_env,
                             capture_output=True, text=True, timeout=30)
    assert noscale.returncode == 2 and 'scale parameter is required' in noscale.stderr
    assert not os.path.exists(tmp_path / 'log' / 'agent_test' / 'a')


def test_start_move_stop_and_hostile_layouts(setup):
    h, agent, _, _ = setup
    a, b = agent('a'), agent('b')
    h.publish(1, {'talker': 'a', 'talker2': 'a'})
    h.wait(lambda: h.running('a', 'talker') and h.running('a', 'talker2')
           and 'b' in h.states and h.states['b'].generation == 1,
           what='both talkers running and ready on a, b at the same layout')
    h.wait(lambda: any(d.startswith('a ') for _, d, _ in h.heard), what='chatter from a')
    assert h.states['a'].generation == 1 and h.states['b'].generation == 1
    assert h.report('b', 'talker').state == 'stopped'
    old = {n: h.report('a', n).pid for n in ('talker', 'talker2')}

    t_move = time.monotonic()
    h.publish(2, {'talker': 'b', 'talker2': 'b'})
    h.wait(lambda: h.running('b', 'talker') and h.running('b', 'talker2')
           and h.state_is('a', 'talker', 'stopped') and h.state_is('a', 'talker2', 'stopped'),
           what='both talkers moved to b')
    h.wait(lambda: any(d.startswith('b ') and t > t_move for t, d, _ in h.heard),
           what='chatter from b')
    assert all(gone(pid) for pid in old.values())
    # start_before_stop: the old copy stopped only after the new one was ready.
    ready_b = first_time(h.history, 'b', 'talker', ('running',), t_move)
    stopping_a = first_time(h.history, 'a', 'talker', ('stopping', 'stopped'), t_move)
    assert ready_b is not None and stopping_a is not None and stopping_a >= ready_b
    # stop_before_start: the new copy started only after the old one was reported stopped.
    stopped_a = first_time(h.history, 'a', 'talker2', ('stopped',), t_move)
    started_b = first_time(h.history, 'b', 'talker2', ('starting', 'running'), t_move)
    assert stopped_a is not None and started_b is not None and started_b >= stopped_a

    moved = {n: h.report('b', n).pid for n in ('talker', 'talker2')}
    # The layout topic keeps one message: send each hostile one after the previous is handled.
    hostile = [
        ('{not json', 'not valid JSON'),
        (json.dumps({'generation': 3, 'deployment': 'agent_test', 'reason': 'x', 'stamp': 0.0,
                     'assignments': {'talker': 'a', 'talker2': 'a'},
                     'command': ['rm', '-rf', '/']}), "unknown field 'command'"),
        (json.dumps({'generation': 3, 'deployment': 'agent_test', 'reason': 'x', 'stamp': 0.0,
                     'assignments': {'talker': 'b', 'talker2': 'b', 'ghost': 'a'}}),
         "'ghost': unknown node; entry ignored"),
        (json.dumps({'generation': 1, 'deployment': 'agent_test', 'reason': 'x', 'stamp': 0.0,
                     'assignments': {'talker': 'a', 'talker2': 'a'}}),
         'generation 1 is not newer than the applied 3'),
        (json.dumps({'generation': 9, 'deployment': 'other', 'reason': 'x', 'stamp': 0.0,
                     'assignments': {'talker': 'a'}}), "deployment 'other'"),
        (json.dumps({'generation': 10, 'deployment': 'agent_test', 'reason': 'x',
                     'stamp': float('nan'), 'assignments': {'talker': 'a'}}),
         'NaN is not allowed'),
    ]
    for text, logged in hostile:
        h.publish_raw(text)
        for agent_ in (a, b):
            # Each kind of malformed layout is logged at once (then throttled for 10 s).
            h.wait(lambda: logged in agent_.text(), timeout=25.0, what=f'log line {logged!r}')
    h.publish(4, {'talker': 'b', 'talker2': 'b'})
    h.wait(lambda: h.states['a'].generation == 4 and h.states['b'].generation == 4,
           what='both agents at generation 4')
    assert {n: h.report('b', n).pid for n in ('talker', 'talker2')} == moved
    assert all(h.report('b', n).restarts == 0 for n in moved)
    assert h.states['a'].running() == {}
    assert 'ignored a layout message' in a.text()

    assert b.stop(signal.SIGINT) == 0 and a.stop(signal.SIGINT) == 0
    assert all(gone(pid) for pid in moved.values())


def test_crash_restart_adoption_and_shutdown(tmp_path, setup):
    h, agent, _, run_id = setup
    a = agent('a')
    h.publish(1, {'talker': 'a', 'stubborn': 'a', 'forker': 'a'})
    h.wait(lambda: h.running('a', 'talker') and h.state_is('a', 'stubborn', 'starting')
           and os.path.exists(tmp_path / 'forker_pids'), what='three nodes started on a')
    talker = h.report('a', 'talker').pid
    os.kill(talker, signal.SIGKILL)
    h.wait(lambda: h.running('a', 'talker') and h.report('a', 'talker').pid != talker,
           what='the killed talker restarted')
    r = h.report('a', 'talker')
    assert r.restarts == 1
    assert any('crashed: killed by SIGKILL (Killed)' in line for line in a.text().splitlines())
    assert gone(talker)

    # 'warm' keeps an inactive standby copy here although the layout does not place it.
    pids = {n: h.report('a', n).pid for n in ('talker', 'stubborn', 'forker', 'warm')}
    parent, grandchild = map(int, open(tmp_path / 'forker_pids').read().split())
    assert parent == pids['forker']
    a.proc.kill()                       # the agent dies hard; its nodes keep running
    a.proc.wait(10)
    assert not any(gone(pid) for pid in pids.values())

    a2 = agent('a')
    h.wait(lambda: f'adopted pid {pids["stubborn"]}' in a2.text()
           and h.running('a', 'talker') and h.states['a'].generation == 1,
           what='the restarted agent adopting its nodes')
    assert {n: h.report('a', n).pid for n in pids} == pids
    # No second copy of anything: exactly the adopted processes and the grandchild.
    expected = sorted(list(pids.values()) + [grandchild])
    assert sorted(p.pid for p in run_processes(run_id)) == expected
    assert os.path.getsize(tmp_path / 'log' / 'agent_test' / 'a' / 'stubborn.log') > 0

    t0 = time.monotonic()
    assert a2.stop(signal.SIGTERM) == 0
    # The stubborn node needs both graces and then SIGKILL.
    assert time.monotonic() - t0 >= 2.0
    assert 'sending SIGKILL' in a2.text()
    for pid in list(pids.values()) + [grandchild]:
        assert gone(pid), f'pid {pid} survived the agent'


def lifecycle_state(h, service, timeout=10.0):
    """The label ``service`` (a get_state service) answers, from a client of the test's own.

    A request is sent again each second without an answer: rmw_fastrtps reports a service ready
    once the server's request reader matched, and drops the reply if the server's reply writer
    has not matched the client's reply reader yet (the agent's own driver asks again too)."""
    client = h.node.create_client(GetState, service)
    try:
        h.wait(client.service_is_ready, timeout, f'{service} reachable')
        end = time.monotonic() + timeout
        while True:
            future = client.call_async(GetState.Request())
            try:
                h.wait(future.done, min(1.0, max(0.05, end - time.monotonic())),
                       f'an answer from {service}')
                return future.result().current_state.label
            except AssertionError:
                client.remove_pending_request(future)
                if time.monotonic() >= end:
                    raise
    finally:
        h.node.destroy_client(client)


def test_standby_copies_on_both_scales_one_active_moves_are_activations(setup, tmp_path):
    h, agent, _, run_id = setup
    a, b = agent('a'), agent('b')
    h.publish(1, {'warm': 'a'})
    h.wait(lambda: h.running('a', 'warm') and h.standby('b', 'warm'),
           what='warm active on a, inactive on b')
    pids = {s: h.report(s, 'warm').pid for s in ('a', 'b')}
    assert h.report('a', 'warm').lifecycle == 'active'
    assert h.report('b', 'warm').lifecycle == 'inactive'
    assert 'warm' not in h.states['b'].running()
    # Two copies share the node name; each answers on its own scale's services only.
    name = f'/warm_{run_id}'
    assert lifecycle_state(h, f'{name}/a/get_state') == 'active'
    assert lifecycle_state(h, f'{name}/b/get_state') == 'inactive'
    assert f'{name}/get_state' not in dict(h.node.get_service_names_and_types())
    h.wait(lambda: any(d.startswith(f'a {pids["a"]} ') for _, d, _ in h.heard),
           what='chatter from the active copy')
    assert not any(d.startswith(f'b {pids["b"]} ') for _, d, _ in h.heard)

    def move(generation, to, other):
        t0 = time.monotonic()
        h.publish(generation, {'warm': to})
        h.wait(lambda: any(d.startswith(f'{to} {pids[to]} ') and t > t0
                           for t, d, _ in h.heard), what=f'chatter from {to} after the move')
        h.wait(lambda: h.running(to, 'warm') and h.standby(other, 'warm'),
               what=f'warm active on {to}, inactive on {other}')
        first = min(t for t, d, _ in h.heard if d.startswith(f'{to} {pids[to]} ') and t > t0)
        # The losing copy stops publishing once deactivated: its last message came before
        # its standby report, and none after.
        t_standby = first_time(h.history, other, 'warm', ('standby',), t0)
        h.wait(lambda: time.monotonic() > t_standby + 0.5, what='half a second more')
        late = [t for t, d, _ in h.heard if d.startswith(f'{other} ') and t > t_standby + 0.1]
        assert late == [], f'{other} still published after its deactivation'
        return first - t0

    latencies = [move(2, 'b', 'a'), move(3, 'a', 'b')]
    # Same processes all along: moves are activations, not starts.
    assert {s: h.report(s, 'warm').pid for s in ('a', 'b')} == pids
    assert all(h.report(s, 'warm').restarts == 0 for s in ('a', 'b'))
    print(f'standby moves: first message from the activated copy '
          f'{", ".join(f"{x * 1000:.0f}" for x in latencies)} ms after the layout')

    # A standby copy killed: restarted inactive, and the active one untouched.
    os.kill(pids['b'], signal.SIGKILL)
    h.wait(lambda: h.standby('b', 'warm') and h.report('b', 'warm').pid
           not in (0, pids['b']), what='the killed standby copy back, inactive')
    assert h.report('a', 'warm').pid == pids['a'] and h.running('a', 'warm')
    pids['b'] = h.report('b', 'warm').pid
    assert lifecycle_state(h, f'{name}/b/get_state') == 'inactive'

    # The agent of b killed and restarted while its copy is inactive: adopted as it is.
    b.proc.kill()
    b.proc.wait(10)
    b2 = agent('b')
    h.wait(lambda: f'adopted pid {pids["b"]}' in b2.text() and
           h.standby('b', 'warm') and h.states['b'].generation == 3,
           what='b adopting its inactive copy')
    assert h.report('b', 'warm').pid == pids['b'] and h.running('a', 'warm')

    # Stopped with the agents: finalized through the lifecycle before any signal.
    assert b2.stop(signal.SIGINT) == 0 and a.stop(signal.SIGINT) == 0
    log = (tmp_path / 'log' / 'agent_test' / 'a' / 'warm.log').read_text()
    tail = log[log.rindex('transition: activate'):]
    assert [line.split(': ')[1] for line in tail.splitlines()
            if line.startswith('transition: ')] == ['activate', 'deactivate', 'cleanup',
                                                    'shutdown']
    assert all(gone(pid) for pid in pids.values())


def test_restart_in_place_keeps_every_node_running_and_adopts_it(setup, tmp_path):
    """The documented restart (SIGHUP; ``systemctl reload``): the agent re-executes itself and
    adopts its nodes. A plain node, an active lifecycle copy and an inactive standby copy keep
    their processes, states and restart counts; nothing is started twice; the active copy is
    never deactivated. An adopted node that dies afterwards is reaped, reported with its exit
    status and restarted; SIGINT then stops everything as usual."""
    h, agent, _, run_id = setup
    a, b = agent('a'), agent('b')
    h.publish(1, {'talker': 'a', 'warm': 'a'})
    h.wait(lambda: h.running('a', 'talker') and h.running('a', 'warm')
           and h.standby('b', 'warm'), what='talker and warm on a, warm standing by on b')
    pids = {('a', 'talker'): h.report('a', 'talker').pid, ('a', 'warm'): h.report('a', 'warm').pid,
            ('b', 'warm'): h.report('b', 'warm').pid}
    before = {s: h.states[s].instance for s in ('a', 'b')}
    agent_pids = {'a': a.proc.pid, 'b': b.proc.pid}
    log_a = tmp_path / 'log' / 'agent_test' / 'a' / 'warm.log'
    transitions_before = log_a.read_text().count('transition: ')

    domain = ports.domain_of(os.environ)
    dds_before = {s: ports.unicast_ports([agent_pids[s]], domain) for s in agent_pids}
    assert all(dds_before.values()), dds_before
    for scale, proc in (('a', a), ('b', b)):
        os.kill(proc.proc.pid, signal.SIGHUP)
    h.wait(lambda: all(h.states[s].instance != before[s] for s in ('a', 'b')),
           what='both agents reporting as new processes')
    # Each new participant took ports of its own: the old one's are held through the exec
    # (peers that missed its goodbye would leave a participant on them unmatched).
    for s in agent_pids:
        now = ports.unicast_ports([agent_pids[s]], domain)
        assert dds_before[s] <= now and now - dds_before[s], (s, dds_before[s], now)
    assert "the previous participant's DDS ports" in a.text() + b.text()
    for (scale, node), pid in pids.items():
        proc = a if scale == 'a' else b
        h.wait(lambda: f'{node}: adopted pid {pid}' in proc.text(), timeout=15.0,
               what=f'{scale} adopting {node}')
    h.wait(lambda: h.running('a', 'talker') and h.running('a', 'warm') and h.standby('b', 'warm')
           and h.states['a'].generation == 1 and h.states['b'].generation == 1,
           what='the same layout served again by the new agents')
    assert {(s, n): h.report(s, n).pid for s, n in pids} == pids
    assert all(h.report(s, n).restarts == 0 for s, n in pids)
    assert {s: p.proc.pid for s, p in (('a', a), ('b', b))} == agent_pids   # same processes
    assert a.proc.poll() is None and b.proc.poll() is None
    assert 'restarting in place' in a.text() and 'restarting in place' in b.text()
    # Nothing started twice, and the active copy went on serving: no transition since.
    assert sorted(p.pid for p in run_processes(run_id)) == sorted(pids.values())
    assert log_a.read_text().count('transition: ') == transitions_before
    t0 = time.monotonic()
    h.wait(lambda: any(d.startswith(f'a {pids["a", "warm"]} ') and t > t0
                       for t, d, _ in h.heard), what='the active copy still publishing')

    # The adopted talker is still a child of the (re-executed) agent: when it dies it is
    # reaped, with its exit status, and restarted.
    os.kill(pids['a', 'talker'], signal.SIGKILL)
    h.wait(lambda: h.running('a', 'talker') and h.report('a', 'talker').pid
           != pids['a', 'talker'], what='the killed adopted talker restarted')
    assert 'talker: crashed: killed by SIGKILL' in a.text()
    assert not psutil.pid_exists(pids['a', 'talker'])        # reaped, not a zombie

    # Restarted with no layout to be had (the decider gone): fail-static, the adopted active
    # copy keeps serving as it reports it, neither deactivated nor finalized.
    h.node.destroy_publisher(h.layout_pub)
    h.wait(lambda: a.text().count('applied (test)') == 2, what='a has applied the layout again')
    instance = h.states['a'].instance
    os.kill(a.proc.pid, signal.SIGHUP)
    h.wait(lambda: h.states['a'].instance != instance and h.running('a', 'warm')
           and h.states['a'].generation == -1, what='a back without a layout, warm active')
    heard = len(h.history)
    h.wait(lambda: sum(st.scale == 'a' for _, st in h.history[heard:]) >= 4,
           what='four more reports from a')
    assert all(st.nodes['warm'].state == 'running' for _, st in h.history[heard:]
               if st.scale == 'a')
    assert log_a.read_text().count('transition: ') == transitions_before

    assert a.stop(signal.SIGINT) == 0 and b.stop(signal.SIGINT) == 0
    assert all(gone(pid) for pid in pids.values())


def test_a_layout_is_word_from_the_master_a_remote_agent_long_alone_serves_what_it_places(
        setup):
    """A remote agent that has heard nothing from the master for longer than agent_timeout_s
    (the link was down since it started) takes the layout that arrives when the link comes
    back as word from there: it starts what the layout places on it at once, rather than
    taking the silence before it for a cut and holding the node until a newer layout."""
    h, agent, _, _ = setup
    b = agent('b')
    h.wait(lambda: 'b' in h.states, what='the agent of b reporting')
    alone_since = first_time(h.history, 'b', 'talker', ('stopped',)) or time.monotonic()
    h.wait(lambda: time.monotonic() - alone_since > 3.5, timeout=10.0,
           what='the agent of b alone for longer than agent_timeout_s (3 s)')
    h.publish(1, {'talker': 'b'})
    h.wait(lambda: h.running('b', 'talker'), timeout=15.0, what='talker running on b')
    assert 'cut off from a' not in b.text()
