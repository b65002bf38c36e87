"""The real decider process over real DDS, driven by a real rclpy test node.

The test node plays the agents and monitors (it publishes AgentState, LinkStatus, ScaleStatus
and ConnectionStatus as they would) and reads what the decider publishes.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from anyscale_manager import protocol as p
from anyscale_manager.agent.procs import stop_popen
from anyscale_manager.model.loader import load_deployment
from home_away import ONE_DECIDER_DISCOVERY_S
from spinning import spin_until

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
AGENT_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)

FAST = ['-p', 'decider.period_s:=0.2', '-p', 'decider.agent_timeout_s:=3.0',
        '-p', 'decider.grace_s:=1.0', '-p', 'decider.observation_max_age_s:=1.5',
        '-p', f'decider.discovery_s:={ONE_DECIDER_DISCOVERY_S}']


def start_decider(params_file, ros_env, *extra):
    cmd = [sys.executable, '-m', 'anyscale_manager.nodes.decider', '--ros-args',
           '--params-file', params_file, *FAST, *extra]
    return subprocess.Popen(cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


def stop(proc, timeout=10.0):
    stop_popen(proc, timeout)
    out = proc.stdout.read() if proc.stdout else ''
    return proc.returncode, out


class FakeWorld(Node):
    """Agents and monitors as the decider hears them; records what the decider says."""

    def __init__(self, context, deployment):
        super().__init__('decider_test_world', context=context)
        self.d = deployment
        self.layouts, self.events, self.objectives, self.plans, self.diags = [], [], [], [], []
        self.agent_pub = self.create_publisher(String, p.TOPIC_AGENT_STATE, AGENT_QOS)
        self.pubs = {t: self.create_publisher(String, t, 10)
                     for t in (p.TOPIC_LINK_STATUS, p.TOPIC_SCALE_STATUS,
                               p.TOPIC_CONNECTION_STATUS)}
        self.create_subscription(String, p.TOPIC_LAYOUT, self._layout, LATCHED)
        self.create_subscription(String, p.TOPIC_EVENTS, self._event, 100)
        self.create_subscription(String, p.TOPIC_OBJECTIVE,
                                 lambda m: self.objectives.append(json.loads(m.data)), 10)
        self.create_subscription(String, p.TOPIC_PLAN_CHECK,
                                 lambda m: self.plans.append(json.loads(m.data)), 10)
        self.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, self.diags.append, 10)
        self.running = {}              # node -> scale, what the fake agents report
        self.generation = {s: 0 for s in deployment.scale_names}
        self.link_up = True
        self.link_kbps = None          # the link's measured bandwidth (None: not measured)
        self.apply_layouts = True
        self.silent = set()            # scales whose agent says nothing
        self.follows = {}              # scale -> the decider id its agent reports following
        self.extra_readings = {}       # connection -> rate_hz, for unmonitored connections

    def _layout(self, msg):
        layout = p.Layout.from_json(msg.data)
        self.layouts.append(layout)
        if self.apply_layouts:
            self.running = dict(layout.assignments)
            for s in self.generation:
                self.generation[s] = layout.generation

    def _event(self, msg):
        self.events.append(p.Event.from_json(msg.data))

    def report(self):
        """One round of agent states and monitor readings."""
        for scale in self.d.scale_names:
            if scale in self.silent:
                continue
            nodes = {n: p.NodeReport(state='running', pid=100, since=0.0, restarts=0,
                                     ready=True, exit_reason='')
                     for n, s in self.running.items() if s == scale}
            self.agent_pub.publish(String(data=p.AgentState(
                scale=scale, generation=self.generation[scale], stamp=time.time(),
                nodes=nodes, decider=self.follows.get(scale)).to_json()))
            self.pubs[p.TOPIC_SCALE_STATUS].publish(String(data=p.ScaleStatus(
                scale=scale, stamp=time.time(), cpu_total=40.0, capacity_cpu=100.0,
                cpu_by_node={}, mem_percent=10.0, load_1m=0.1).to_json()))
        master = self.d.master.name
        if master in self.silent:
            return      # the link monitor and the probes below live in the master's agent
        for remote in self.d.remote_scales:
            if self.d.link_between(master, remote.name) is None:
                continue
            self.pubs[p.TOPIC_LINK_STATUS].publish(String(data=p.LinkStatus(
                master=master, remote=remote.name, stamp=time.time(), up=self.link_up,
                rtt_ms=2.0, loss=0.0, bandwidth_available_kbps=self.link_kbps,
                bandwidth_available_age_s=None if self.link_kbps is None else 1.0,
                bandwidth_used_kbps=0.0).to_json()))
        readings = {c.name: p.ConnectionReading(rate_hz=c.freq_opt_hz, bytes_per_s=100.0,
                                                below_for_s=0.0, level=0)
                    for c in self.d.connections if c.monitored}
        for name, rate in self.extra_readings.items():
            readings[name] = p.ConnectionReading(rate_hz=rate, bytes_per_s=10.0,
                                                 below_for_s=0.0, level=0)
        self.pubs[p.TOPIC_CONNECTION_STATUS].publish(String(data=p.ConnectionStatus(
            scale=master, stamp=time.time(), connections=readings).to_json()))


@pytest.fixture
def world(request, testbed_path, ros):
    path = getattr(request, 'param', testbed_path)
    yield ros.add(FakeWorld(ros.context, load_deployment(path))), ros.executor


def world_until(ex, world, cond, timeout, what, decider=None):
    """Spin until ``cond()`` while ``world`` reports every 0.2 s; the end of the ``decider``
    process ends the wait at once. A failure shows the decider's last events."""
    return spin_until(ex, cond, timeout, what, {} if decider is None else {'decider': decider},
                      watch=True, tick=world.report, tick_every_s=0.2,
                      state=lambda: [f'{e.kind}: {e.reason}' for e in world.events[-8:]])


def set_param(ex, node, name, value, type_, field, timeout=10.0):
    client = node.create_client(SetParameters, '/anyscale_decider/set_parameters')
    world_until(ex, node, client.service_is_ready, timeout, "the decider's parameter service")
    val = ParameterValue(type=type_)
    setattr(val, field, value)
    future = client.call_async(SetParameters.Request(
        parameters=[ParameterMsg(name=name, value=val)]))
    world_until(ex, node, future.done, timeout, f'the answer setting {name}')
    node.destroy_client(client)
    return future.result().results[0]


def test_layout_latched_adopted_republished_and_robust(world, testbed_path, ros_env):
    node, ex = world
    # What already runs: everything on the robot except AMCL, adopted on the laptop; the
    # agents report generation 7 from an earlier decider.
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    node.running['amcl'] = 'laptop'
    node.generation = {'robot': 7, 'laptop': 7}
    # A link measured at 1 Mbit/s: AMCL's 206 kbit/s fit, AR's 6 Mbit/s do not, so AR cannot
    # move out before this test has seen the first layout.
    node.link_kbps = 1000.0
    proc = start_decider(testbed_path, ros_env)
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        first = node.layouts[0]
        assert first.generation > 7
        assert first.assignments['amcl'] == 'laptop'           # adopted, not restarted
        assert all(first.assignments[n] == 'robot' for n in first.assignments
                   if n != 'amcl')
        assert 'decision' not in first.assignments              # not managed by an agent

        # With the link at its full rate, AR moves out next: a new generation.
        node.link_kbps = None
        world_until(ex, node, lambda: node.layouts[-1].assignments.get('ar') == 'laptop',
                    20.0, 'AR placed on the laptop', proc)
        moved = node.layouts[-1]
        assert moved.generation > first.generation
        world_until(ex, node, lambda: any(e.kind == 'migrate' and e.node == 'ar'
                                          and 'wifi' in e.reason for e in node.events),
                    5.0, 'the event of AR migrating, naming wifi', proc)

        # A late joiner gets the latest layout (latched).
        late = []
        sub = node.create_subscription(String, p.TOPIC_LAYOUT,
                                       lambda m: late.append(p.Layout.from_json(m.data)),
                                       LATCHED)
        world_until(ex, node, lambda: late, 10.0, 'the latched layout at a late joiner', proc)
        assert late[-1].generation == node.layouts[-1].generation
        node.destroy_subscription(sub)

        # Hostile and malformed messages on every topic it reads: logged, ignored.
        garbage = ['', 'not json', '[]', '{"scale": 5}', 'NaN', '{' * 5000, 'x' * 300000,
                   json.dumps({'scale': 'moon', 'generation': 1, 'stamp': 0.0, 'nodes': {}}),
                   json.dumps({'scale': 'robot', 'generation': -1, 'stamp': 1e308,
                               'nodes': {'amcl': {'state': 'rm -rf', 'pid': 1}}}),
                   json.dumps({'master': 'laptop', 'remote': 'robot', 'stamp': 0.0,
                               'up': False, 'rtt_ms': None, 'loss': 0.0,
                               'bandwidth_available_kbps': -5.0,
                               'bandwidth_available_age_s': None,
                               'bandwidth_used_kbps': 0.0})]
        for text in garbage:
            node.agent_pub.publish(String(data=text))
            for pub in node.pubs.values():
                pub.publish(String(data=text))
        count = len(node.objectives)
        world_until(ex, node, lambda: len(node.objectives) > count + 5, 10.0,
                    'six more objective messages', proc)
        ignored = [kv.value for a in node.diags[-3:] for s in a.status for kv in s.values
                   if kv.key == 'messages ignored']
        assert ignored and int(ignored[-1]) > 0
        assert node.diags[-1].status[0].level in (bytes([p.OK]), bytes([p.WARN]))

        # Thresholds change at run time, validated.
        bad = set_param(ex, node, 'decider.hysteresis_s', -1.0, ParameterType.PARAMETER_DOUBLE,
                        'double_value')
        assert not bad.successful and 'hysteresis_s' in bad.reason
        fixed = set_param(ex, node, 'scales.laptop.gain', 9.0, ParameterType.PARAMETER_DOUBLE,
                          'double_value')
        assert not fixed.successful
        good = set_param(ex, node, 'decider.hysteresis_s', 60.0,
                         ParameterType.PARAMETER_DOUBLE, 'double_value')
        assert good.successful, good.reason
        scope = set_param(ex, node, 'decider.hysteresis_scope', 'link',
                          ParameterType.PARAMETER_STRING, 'string_value')
        assert not scope.successful and 'hysteresis_scope' in scope.reason
        scope = set_param(ex, node, 'decider.hysteresis_scope', 'node',
                          ParameterType.PARAMETER_STRING, 'string_value')
        assert scope.successful, scope.reason

        # The link goes down: both come back, in a new generation, each with its reason.
        before = node.layouts[-1].generation
        node.link_up = False
        world_until(ex, node, lambda: node.layouts[-1].assignments.get('amcl') == 'robot'
                    and node.layouts[-1].assignments.get('ar') == 'robot', 10.0,
                    'AMCL and AR back on the robot', proc)
        assert node.layouts[-1].generation > before
        backs = [e for e in node.events if e.kind == 'migrate_back']
        world_until(ex, node, lambda: {e.node for e in node.events
                                       if e.kind == 'migrate_back'} == {'amcl', 'ar'},
                    5.0, 'the migrate_back events of AMCL and AR', proc)
        backs = [e for e in node.events if e.kind == 'migrate_back']
        assert all('wifi' in e.reason for e in backs)
        assert node.objectives[-1]['integral'] > 0
        assert node.plans and 'overall_deviation' in node.plans[-1]
    finally:
        code, out = stop(proc)
    assert code == 0, out


def test_an_agent_following_another_decider_is_said_once_and_not_out_counted(
        world, testbed_path, ros_env):
    # Re-publishing above a generation an agent reports would let two deciders out-count each
    # other for ever: the decider says it and goes on re-publishing its own layout, same
    # generation.
    node, ex = world
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    proc = start_decider(testbed_path, ros_env, '-p', 'decider.migration:=false')
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        g = node.layouts[-1].generation
        me = node.layouts[-1].decider
        assert me is not None and node.layouts[-1].seq is not None
        node.apply_layouts = False
        node.generation['laptop'] = g + 10
        node.follows['laptop'] = 'f00dfeedf00dfeed'
        heard = len(node.layouts)
        # Re-publications keep coming (the agents' lease), all of generation g.
        world_until(ex, node, lambda: len(node.layouts) >= heard + 3, 15.0,
                    'three re-publications', proc)
        assert {lay.generation for lay in node.layouts} == {g}
        assert {lay.decider.id for lay in node.layouts} == {me.id}
        seqs = [lay.seq for lay in node.layouts]
        assert seqs == sorted(set(seqs))
        assert not [e for e in node.events if e.kind == 'migrate']    # baseline: no moves
    finally:
        code, out = stop(proc)
    assert code == 0, out
    assert out.count('the agent of laptop follows decider f00dfeedf00dfeed') == 1, out


def test_silent_agent_loses_its_scale(world, testbed_path, ros_env):
    node, ex = world
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    node.running['ar'] = 'laptop'
    proc = start_decider(testbed_path, ros_env)
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        assert node.layouts[0].assignments['ar'] == 'laptop'
        node.silent.add('laptop')          # the laptop's agent goes silent
        world_until(ex, node, lambda: node.layouts[-1].assignments['ar'] == 'robot',
                    15.0, 'AR placed on the robot', proc)
        world_until(ex, node, lambda: any(e.kind == 'relocate' and e.node == 'ar'
                                          for e in node.events), 5.0, 'the relocate event of AR',
                    proc)
        # The link is reported up all along: the agent is gone, not the link, and it is said.
        assert any(e.kind == 'agent_silent' and e.from_scale == 'laptop'
                   and 'while link wifi is up: the agent, not the link' in e.reason
                   for e in node.events), [e.reason for e in node.events]
    finally:
        code, out = stop(proc)
    assert code == 0, out


def test_a_silent_master_agent_is_said_and_the_layout_kept(world, testbed_path, ros_env):
    """The robot's agent (with its link monitor and probes) goes silent while AMCL and AR run
    on the laptop: said in an event and the diagnostics naming the robot's agent, nothing moved;
    said again when it is back."""
    node, ex = world
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    node.running.update(amcl='laptop', ar='laptop')
    proc = start_decider(testbed_path, ros_env)

    def said(kind, scale):
        return [e for e in node.events if e.kind == kind and e.from_scale == scale]
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        kept = dict(node.layouts[-1].assignments)
        assert kept['amcl'] == 'laptop' and kept['ar'] == 'laptop'
        node.silent.add('robot')
        world_until(ex, node, lambda: said('scale_lost', 'robot'), 15.0,
                    'the scale_lost event of the robot', proc)
        (silent,) = said('agent_silent', 'robot')
        assert 'the agent of robot (the master scale) has been silent' in silent.reason
        world_until(ex, node, lambda: any(
            'agent of robot lost' in st.message and st.level == bytes([p.WARN])
            for a in node.diags[-3:] for st in a.status), 5.0,
            'a diagnostics warning that the agent of robot is lost', proc)
        node.silent.discard('robot')
        world_until(ex, node, lambda: said('agent_back', 'robot'), 10.0,
                    'the agent_back event of the robot', proc)
        assert all(lay.assignments == kept for lay in node.layouts), node.layouts
        assert not [e for e in node.events if e.kind in ('migrate', 'migrate_back', 'relocate')]
    finally:
        code, out = stop(proc)
    assert code == 0, out


IROS_1 = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'config', 'iros2016',
                      'instance_1.yaml')


@pytest.mark.parametrize('world', [IROS_1], indirect=True)
def test_first_layout_from_the_problem_1_planner(world, ros_env):
    node, ex = world
    from anyscale_manager.planning import solve
    plan = solve(node.d, problem=1)
    proc = start_decider(IROS_1, ros_env, '-p', 'decider.initial_layout:=problem1')
    try:
        world_until(ex, node, lambda: node.layouts, 60.0, 'a layout', proc)
        first = node.layouts[0]
        assert first.assignments == {n: pl.scale for n, pl in plan.layout.items()
                                     if node.d.node(n).managed}
        assert 'problem1' in first.reason
        # Plan against reality (Eq. 10): the tracker planned at 25 Hz is measured at 20 Hz.
        assert plan.layout['tracker_1'].parameter_value == 25.0
        node.extra_readings['tracker_1__environment_1'] = 20.0
        world_until(ex, node, lambda: node.plans and 'tracker_1' in node.plans[-1]['nodes'],
                    10.0, 'a plan check naming tracker_1', proc)
        tracker = node.plans[-1]['nodes']['tracker_1']
        assert tracker['measured_hz'] == 20.0 and tracker['expected_hz'] == 25.0
        assert tracker['deviation'] == pytest.approx(-0.2)
        assert tracker['measured_performance'] == pytest.approx(
            plan.layout['tracker_1'].performance * 0.8)
    finally:
        code, out = stop(proc)
    assert code == 0, out


def test_bad_parameters_file_fails_clearly(tmp_path, testbed_path, ros_env):
    text = open(testbed_path).read().replace('capacity_cpu: 700.0', 'capacity_cpu: lots')
    bad = tmp_path / 'bad.yaml'
    bad.write_text(text)
    proc = start_decider(str(bad), ros_env)
    try:
        proc.wait(30)
    finally:
        code, out = stop(proc)
    assert code == 2
    assert 'scales.laptop.capacity_cpu' in out


def test_status_once_shows_the_live_table(world, testbed_path, ros_env):
    node, ex = world
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    proc = start_decider(testbed_path, ros_env)
    status = None
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        status = subprocess.Popen(
            [sys.executable, '-m', 'anyscale_manager.cli', 'status', '--params-file',
             testbed_path, '--once', '--wait', '8'], env=ros_env, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, start_new_session=True)
        world_until(ex, node, lambda: status.poll() is not None, 30.0,
                    'the end of status --once', proc)
        out, err = status.communicate()
    finally:
        if status is not None and status.poll() is None:
            os.killpg(status.pid, signal.SIGKILL)
            status.wait(5)
        code, log = stop(proc)
    print(out)
    assert status.returncode == 0, err
    assert f'layout generation {node.layouts[-1].generation}' in out
    assert 'laser_amcl' in out and 'wifi' in out and 'up' in out
    assert 'generation' in out and 'amcl' in out
    assert code == 0, log


def test_status_bad_file_fails_clearly(tmp_path, ros_env):
    bad = tmp_path / 'nope.yaml'
    bad.write_text('/**:\n  ros__parameters: {scales: 5}\n')
    res = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'status',
                          '--params-file', str(bad), '--once'], env=ros_env,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and 'scales' in res.stderr


def test_a_link_going_down_is_decided_at_once_not_at_the_next_period(world, testbed_path,
                                                                     ros_env):
    node, ex = world
    node.running = {n.name: 'robot' for n in node.d.nodes if n.managed}
    node.running.update(amcl='laptop', ar='laptop')
    proc = start_decider(testbed_path, ros_env)
    try:
        world_until(ex, node, lambda: node.layouts, 30.0, 'a layout', proc)
        assert node.layouts[-1].assignments['amcl'] == 'laptop'
        # A period far longer than the test: only the link-down itself can trigger a turn.
        slow = set_param(ex, node, 'decider.period_s', 300.0, ParameterType.PARAMETER_DOUBLE,
                         'double_value')
        assert slow.successful, slow.reason
        node.link_up = False
        world_until(ex, node, lambda: node.layouts[-1].assignments.get('amcl') == 'robot',
                    20.0, 'AMCL placed on the robot', proc)
        world_until(ex, node, lambda: any(e.kind == 'migrate_back' and e.node == 'amcl'
                                          for e in node.events), 5.0,
                    'the migrate_back event of AMCL', proc)
    finally:
        code, out = stop(proc)
    assert code == 0, out
