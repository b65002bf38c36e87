"""The agent node end to end: real agent processes, real rclpy nodes, real DDS on loopback."""

import json
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from anyscale_manager import protocol
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
            'warm': talker(chatter + '/warm', 'warm', standby=True),
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

    def stop(self, sig=signal.SIGINT, timeout=20.0):
        return super().stop(sig, timeout, must_exit=True)


class Harness:
    """The test's own rclpy node: publishes layouts, records agent states and chatter."""

    def __init__(self, deployment_name, chatter):
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = Node('agent_test_harness', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.name = deployment_name
        self.layout_pub = self.node.create_publisher(String, protocol.TOPIC_LAYOUT, LATCHED)
        self.states = {}          # scale -> latest AgentState
        self.history = []         # (monotonic, AgentState)
        self.heard = []           # (monotonic, 'scale pid seq', topic)
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
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            if cond():
                return
        raise AssertionError(f'timed out after {timeout} s waiting for {what}; last states: '
                             f'{ {s: st.to_dict() for s, st in self.states.items()} }')

    def report(self, scale, node):
        state = self.states.get(scale)
        return state.nodes.get(node) if state else None

    def running(self, scale, node):
        r = self.report(scale, node)
        return r is not None and r.state == 'running' and r.ready

    def state_is(self, scale, node, state):
        r = self.report(scale, node)
        return r is not None and r.state == state

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


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
def setup(tmp_path, ros_env):
    run_id = f'{os.getpid()}_{time.monotonic_ns() % 10 ** 9}'
    deployment, chatter = write_deployment(tmp_path, run_id)
    harness = Harness('agent_test', chatter)
    agents = []

    def agent(scale, *extra):
        a = Agent(tmp_path, deployment, scale, ros_env, *extra)
        agents.append(a)
        return a

    yield harness, agent, deployment, run_id
    for a in agents:
        if a.proc.poll() is None:
            a.stop(signal.SIGTERM)
    harness.close()
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
           and 'b' in h.states, what='both talkers running and ready on a')
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
            h.wait(lambda: logged in agent_.text(), timeout=15.0, what=f'log line {logged!r}')
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

    pids = {n: h.report('a', n).pid for n in ('talker', 'stubborn', 'forker')}
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


def test_standby_node_moved_away_is_frozen_and_comes_back_at_once(setup):
    h, agent, _, _ = setup
    a, b = agent('a'), agent('b')          # a is the master: it keeps the warm copy
    h.publish(1, {'warm': 'a'})
    h.wait(lambda: h.running('a', 'warm') and 'b' in h.states, what='warm running on a')
    pid = h.report('a', 'warm').pid
    t_move = time.monotonic()
    h.publish(2, {'warm': 'b'})
    h.wait(lambda: h.running('b', 'warm') and h.state_is('a', 'warm', 'standby'),
           what='warm on b, frozen on a')
    r = h.report('a', 'warm')
    assert r.pid == pid and not r.ready and psutil.Process(pid).status() == psutil.STATUS_STOPPED
    assert 'warm' not in h.states['a'].running()
    # Frozen only after the new copy was ready (start_before_stop).
    ready_b = first_time(h.history, 'b', 'warm', ('running',), t_move)
    frozen_a = first_time(h.history, 'a', 'warm', ('standby',), t_move)
    assert ready_b is not None and frozen_a >= ready_b
    h.wait(lambda: any(d.startswith('b ') and t > t_move for t, d, _ in h.heard),
           what='chatter from b')

    t_back = time.monotonic()
    h.publish(3, {'warm': 'a'})
    h.wait(lambda: h.running('a', 'warm'), what='warm back on a')
    back = time.monotonic() - t_back
    r = h.report('a', 'warm')
    assert r.pid == pid and r.restarts == 0 and \
        psutil.Process(pid).status() != psutil.STATUS_STOPPED
    h.wait(lambda: any(d.startswith(f'a {pid} ') and t > t_back for t, d, _ in h.heard),
           what='chatter from the resumed copy')
    first = min(t for t, d, _ in h.heard if d.startswith(f'a {pid} ') and t > t_back) - t_back
    h.wait(lambda: h.state_is('b', 'warm', 'stopped'), what='the copy on b stopped')
    print(f'standby: back on a (same pid, resumed) {back * 1000:.0f} ms after the layout, '
          f'first message from it {first * 1000:.0f} ms after')
    # A start would take the interpreter and rclpy's start (about 0.5 s unloaded, more on a
    # loaded machine); a resume is a signal. Honest slack for a loaded 2-core machine.
    assert back < 2.0
    assert b.stop(signal.SIGINT) == 0 and a.stop(signal.SIGINT) == 0
    assert gone(pid)
