#!/usr/bin/env python3
"""Agent figures: move latency between two agents, and the agent's own CPU.

    python bench/bench_agent.py [--moves 20] [--cpu-seconds 20] [--domain-id N]
        [--jitter-s 3.0] [--standby] [--no-profile] [--scales netns|loopback]

Move latency: two agents (scales a and b); a small rclpy talker (10 Hz) is moved back and forth
by publishing a new layout; the time runs from the layout's publication to the first message
from the talker started on the new scale (told apart by its scale tag and pid) at a consumer on
the other scale. Measured for both move orders. Where the scales run (bench/scales.py):

- netns (the default where this machine can build them, as root): scale a in the test-bed's
  "robot" network namespace, b in its "laptop" one, joined by a veth link shaped at 54 Mbit/s,
  DDS over UDP on the link as between two computers; this process (on a) and a listener process
  on b are the consumers, and each move is timed at the one on the scale the copy left (the
  one on its own scale is printed too);
- loopback: both agents on this machine's loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST),
  timed here, a consumer on neither scale. Fast DDS discovers on loopback by unicast to 32
  ports and is slower to match a new participant there than over a link.

On the way:

- started: the new copy's process was created (its start time in /proc, 10 ms resolution);
- matched: the consumer's subscription matched a new writer (DDS discovery of the new copy,
  its participant first; a message can arrive only after this);
- first message: the headline figure;
- ready: the gaining agent reports the new copy running and ready (it sees it in its graph).

A random pause of up to --jitter-s precedes each move. Without it the moves lock to the phase of
this process's own DDS participant announcements (Fast DDS: every 3 s): a new participant
usually misses the answer to its first announcement (it announces before it listens) and is
discovered at the next periodic announcement of the participant that should hear it, and a
move that starts as soon as the previous one ended meets that announcement at the same point
every time, so every move measured the same part of the 3 s.

With --standby the talker is a lifecycle node kept as an inactive standby copy on the other
scale (``lifecycle: true``, ``standby: true``); a move is an activation, with no process to start
(started and matched then do not apply). It fails with the agents' own words when the package's
agent does not support lifecycle nodes.

Without --standby the talker is then also started directly, with no agent, as many times, the
agents and their nodes still running (with namespaces, on b and a in turn, heard on the other):
process start -> first message is what the node's own start and DDS discovery cost, the part of
a cold move that is not the agent's.

Agent CPU: the agent process alone (its children excluded), once idle with ten catalogue nodes
stopped and once supervising ten running talkers at 1 Hz; monitors hosted by the agent are
included when the monitors module is present; --cpu-seconds 0 skips it.
DDS stays on loopback or the bench's own namespaces, in the given domain. The packaged
discovery profile (config/fastdds_discovery.xml), or a Fast DDS profile the environment names
(FASTRTPS_DEFAULT_PROFILES_FILE for Jazzy's Fast DDS 2.x, FASTDDS_DEFAULT_PROFILES_FILE for 3.x),
applies to this process, the agents and, through them, the talkers; it is printed.
--no-profile leaves the packaged one out.
"""

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time

import psutil
import yaml
from scales import SPIN, Listener, Loopback, Namespaces, choose, run_inside

from anyscale_manager.agent.procs import stop_popen
from anyscale_manager.protocol import LIVE_STATES, ProcState

TALKER = r'''
import os, sys
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import String
rclpy.init(args=sys.argv)
node = Node('bench_talker')
node.declare_parameter('topic', '/bench_agent/chatter')
node.declare_parameter('rate_hz', 10.0)
pub = node.create_publisher(String, node.get_parameter('topic').value, 10)
tag = os.environ.get('ANYSCALE_AGENT_SCALE', '?') + ' ' + str(os.getpid())
node.create_timer(1.0 / node.get_parameter('rate_hz').value,
                  lambda: pub.publish(String(data=tag)))
''' + SPIN

# A lifecycle talker as docs/lifecycle.md asks: the publisher from configure, the timer only
# while active, one message at once on activation (it serves at once, not one period later).
LIFECYCLE_TALKER = r'''
import os, sys
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from std_msgs.msg import String
SUCCESS = TransitionCallbackReturn.SUCCESS
TAG = os.environ.get('ANYSCALE_AGENT_SCALE', '?') + ' ' + str(os.getpid())


class Talker(LifecycleNode):
    def __init__(self):
        super().__init__('bench_talker')
        self.declare_parameter('topic', '/bench_agent/chatter')
        self.declare_parameter('rate_hz', 10.0)
        self.pub = None
        self.timer = None

    def on_configure(self, state):
        self.pub = self.create_lifecycle_publisher(
            String, self.get_parameter('topic').value, 10)
        return SUCCESS

    def on_activate(self, state):
        super().on_activate(state)
        self.timer = self.create_timer(1.0 / self.get_parameter('rate_hz').value, self.tick)
        self.tick()
        return SUCCESS

    def on_deactivate(self, state):
        self.drop_timer()
        super().on_deactivate(state)
        return SUCCESS

    def on_cleanup(self, state):
        self.drop_timer()
        if self.pub is not None:
            self.destroy_lifecycle_publisher(self.pub)
            self.pub = None
        return SUCCESS

    def on_shutdown(self, state):
        return self.on_cleanup(state)

    def tick(self):
        self.pub.publish(String(data=TAG))

    def drop_timer(self):
        if self.timer is not None:
            self.destroy_timer(self.timer)
            self.timer = None


rclpy.init(args=sys.argv)
node = Talker()
''' + SPIN


def deployment(tmp, nodes, name='bench_agent'):
    data = {'/**': {'ros__parameters': {
        'deployment': {'name': name},
        'scales': {'names': ['a', 'b'],
                   'a': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 200.0},
                   'b': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 200.0}},
        'nodes': dict({'names': list(nodes)}, **nodes),
        'decider': {'agent_timeout_s': 3.0},
        'agent': {'sigint_grace_s': 2.0, 'sigterm_grace_s': 1.0, 'readiness_timeout_s': 10.0,
                  'state_dir': os.path.join(tmp, 'state'), 'log_dir': os.path.join(tmp, 'log')},
    }}}
    path = os.path.join(tmp, f'{name}.yaml')
    with open(path, 'w') as f:
        yaml.safe_dump(data, f)
    return path


def talker(topic, rate_hz, source=TALKER, **extra):
    return dict({'launch': {'command': [sys.executable, '-c', source],
                            'parameters': {'topic': topic, 'rate_hz': rate_hz}},
                 'cpu': 1.0}, **extra)


def start_agent(path, scale, tmp, place):
    exe = os.path.join(os.path.dirname(sys.executable), 'agent')
    log = os.path.join(tmp, f'agent_{scale}.out')
    out = open(log, 'ab')
    proc = place.popen(scale, [exe, '--ros-args', '--params-file', path, '-p', f'scale:={scale}'],
                       stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    proc.log_path = log
    return proc


def stop_process(proc, timeout_s=30.0):
    """SIGINT, then SIGKILL past ``timeout_s``."""
    stop_popen(proc, timeout_s, session=False)


def tail(path, lines=15):
    try:
        with open(path, errors='replace') as f:
            return ''.join(f.readlines()[-lines:])
    except OSError as e:
        return f'({e})'


class Bench:
    def __init__(self, name):
        import rclpy
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String

        from anyscale_manager import protocol
        self.rclpy, self.String, self.protocol = rclpy, String, protocol
        rclpy.init()
        self.node = Node('bench_agent_harness')
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.name = name
        self.pub = self.node.create_publisher(String, protocol.TOPIC_LAYOUT, latched)
        self.states = {}
        self.heard = []
        self.matched = []          # (time, topic) of each new writer matched
        self.agents = []
        self.node.create_subscription(
            String, protocol.TOPIC_AGENT_STATE, self._state,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def listen(self, topic):
        def on_matched(event):
            if event.current_count_change > 0:
                self.matched.append((time.monotonic(), topic))

        kwargs = {}
        try:
            from rclpy.event_handler import SubscriptionEventCallbacks
            kwargs['event_callbacks'] = SubscriptionEventCallbacks(matched=on_matched)
        except (ImportError, TypeError):     # an rclpy without matched events: no 'matched'
            pass
        self.node.create_subscription(self.String, topic,
                                      lambda m: self.heard.append((time.monotonic(), m.data)),
                                      10, **kwargs)

    def _state(self, msg):
        st = self.protocol.AgentState.from_json(msg.data)
        self.states[st.scale] = st

    def publish(self, generation, assignments):
        stamp = time.time()
        self.pub.publish(self.String(data=json.dumps({
            'generation': generation, 'deployment': self.name, 'assignments': assignments,
            'reason': 'bench', 'stamp': stamp})))
        return stamp

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.rclpy.spin_once(self.node, timeout_sec=0.01)
            for a in self.agents:
                if a.poll() is not None:
                    raise RuntimeError(f'an agent exited with code {a.returncode}; its output:\n'
                                       + tail(a.log_path))
            if cond():
                return True
        return False

    def close(self):
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def percentile(values, q):
    ordered = sorted(values)
    k = (len(ordered) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


STAGES = ('started', 'matched', 'first', 'first_same', 'ready', 'after_match')


class Consumers:
    """Who hears a copy started on a scale. Loopback: this process, on neither scale. With
    namespaces: the consumer on the other scale (the figure) and the one on the same scale."""

    def __init__(self, bench, listener=None):
        self.bench, self.listener = bench, listener

    def _on(self, scale):
        if scale == 'b':
            return self.listener.heard, self.listener.matched
        return self.bench.heard, self.bench.matched

    def other(self, scale):
        return self._on('a') if self.listener is None else self._on('b' if scale == 'a' else 'a')

    def same(self, scale):
        return None if self.listener is None else self._on(scale)

    def heard(self, scale, tag, since):
        """(when the other scale's consumer first heard ``tag`` after ``since``, the same
        scale's), None where not yet."""
        out = []
        for lists in (self.other(scale), self.same(scale)):
            if lists is not None:
                times = [t for t, d in list(lists[0]) if d == tag and t >= since]
                out.append(min(times) if times else None)
        return tuple(out)

    def matched(self, scale, topic, since):
        """When the other scale's consumer first matched a writer on ``topic`` after ``since``."""
        times = [t for t, tp in list(self.other(scale)[1]) if tp == topic and t >= since]
        return min(times) if times else None


def bench_moves(tmp, moves, place, jitter_s=3.0, standby=False):
    """{node: {stage: [seconds after the layout, one per move]}} for both move orders."""
    topic = '/bench_agent/chatter'
    extra = {'lifecycle': True, 'standby': True} if standby else {}
    source = LIFECYCLE_TALKER if standby else TALKER
    nodes = {'sbs': talker(topic + '/sbs', 10.0, source, **extra),
             'sbs2': talker(topic + '/stop_first', 10.0, source,
                            move_order='stop_before_start', **extra)}
    path = deployment(tmp, nodes)
    topics = {'sbs': topic + '/sbs', 'sbs2': topic + '/stop_first', 'bare': topic + '/bare'}
    b = Bench('bench_agent')
    for t in topics.values():
        b.listen(t)
    b.agents = [start_agent(path, 'a', tmp, place), start_agent(path, 'b', tmp, place)]
    listener = None
    rng = random.Random(1)
    results = {}
    try:
        if place.here is not None:
            listener = Listener(place, list(topics.values()), os.path.join(tmp, 'listener.out'))
            if not b.spin_until(listener.ready.is_set, 60.0):
                raise RuntimeError('the listener on scale b never started:\n'
                                   + tail(listener.log_path))
        consumers = Consumers(b, listener)
        gen = 0
        for node in ('sbs', 'sbs2'):
            gen += 1
            b.publish(gen, {node: 'a'})
            if not b.spin_until(lambda: any(d.startswith('a ') for _, d in b.heard), 60.0):
                raise RuntimeError(f'the talker {node} never published on scale a; agent a:\n'
                                   + tail(b.agents[0].log_path))
            first_tag = next(d for _, d in b.heard if d.startswith('a '))
            if not b.spin_until(lambda: None not in consumers.heard('a', first_tag, 0.0), 60.0):
                raise RuntimeError(f'the consumer on scale b never heard {node} on scale a; '
                                   'its log:\n' + (tail(listener.log_path) if listener else ''))
            if standby and not b.spin_until(
                    lambda: getattr(b.states.get('b'), 'nodes', {}).get(node) is not None
                    and b.states['b'].nodes[node].state == ProcState.STANDBY, 30.0):
                rep = getattr(b.states.get('b'), 'nodes', {}).get(node)
                raise RuntimeError(
                    f'--standby: agent b never reported {node} as a standby copy (its report: '
                    f'{rep}); this agent does not keep lifecycle standby copies. Agent b:\n'
                    + tail(b.agents[1].log_path))
            samples = {s: [] for s in STAGES}
            where = 'a'
            for _ in range(moves):
                b.spin_until(lambda: False, rng.uniform(0.0, jitter_s))
                where = 'b' if where == 'a' else 'a'
                gen += 1
                b.heard.clear()
                b.matched.clear()
                t0 = time.monotonic()
                boot0 = time.clock_gettime(time.CLOCK_BOOTTIME)
                b.publish(gen, {node: where})
                ready_at = []

                def new_copy():
                    r = b.states.get(where)
                    rep = r.nodes.get(node) if r else None
                    if rep is None or rep.state not in LIVE_STATES or not rep.pid:
                        return None
                    return rep

                def moved():
                    rep = new_copy()
                    return rep is not None \
                        and None not in consumers.heard(where, f'{where} {rep.pid}', t0)

                def ready_new():
                    r = b.states.get(where)
                    rep = new_copy()
                    if rep is not None and rep.state == ProcState.RUNNING and rep.ready \
                            and r.generation == gen and not ready_at:
                        ready_at.append(time.monotonic() - t0)
                    return moved() and bool(ready_at)

                if not b.spin_until(ready_new, 60.0):
                    raise RuntimeError(f'move {gen} of {node} to {where} never completed')
                rep = b.states[where].nodes[node]
                firsts = consumers.heard(where, f'{where} {rep.pid}', t0)
                samples['first'].append(firsts[0] - t0)
                if len(firsts) > 1:
                    samples['first_same'].append(firsts[1] - t0)
                samples['ready'].append(ready_at[0])
                if not standby:
                    started = start_time(rep.pid)
                    if started is not None:
                        samples['started'].append(started - boot0)
                    seen = consumers.matched(where, topics[node], t0)
                    if seen is not None:
                        samples['matched'].append(seen - t0)
                        samples['after_match'].append(firsts[0] - seen)

                def settled():
                    old = b.states.get('a' if where == 'b' else 'b')
                    orep = old.nodes.get(node) if old else None
                    new = b.states[where].nodes[node]
                    return orep is not None and new.ready \
                        and orep.state in (ProcState.STOPPED, ProcState.STANDBY)

                b.spin_until(settled, 30.0)
                b.heard.clear()
            results[node] = samples
            b.publish(gen + 1, {node: 'a'})
            gen += 1
            b.spin_until(lambda: False, 0.5)
        if not standby:
            results['bare'] = bare_starts(b, consumers, place, moves, jitter_s, rng,
                                          topics['bare'], tmp)
    finally:
        for a in b.agents:
            stop_process(a)
        if listener is not None:
            listener.close(stop_process)
        b.close()
    return results


def bare_starts(b, consumers, place, count, jitter_s, rng, topic, tmp):
    """The same talker started ``count`` times with no agent involved (on the scales in turn,
    heard on the other one), the agents and their nodes still running: process start -> first
    message received, its own start."""
    out = {s: [] for s in STAGES}
    log = open(os.path.join(tmp, 'bare_talker.out'), 'ab')
    try:
        for i in range(count):
            b.spin_until(lambda: False, rng.uniform(0.0, jitter_s))
            b.heard.clear()
            b.matched.clear()
            scale = 'b' if i % 2 == 0 else 'a'
            t0 = time.monotonic()
            proc = place.popen(scale, [sys.executable, '-c', TALKER, '--ros-args', '-r',
                                       '__node:=bench_bare_talker',
                                       '-p', f'topic:={topic}', '-p', 'rate_hz:=10.0'],
                               stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            tag = f'? {proc.pid}'
            try:
                if not b.spin_until(lambda: None not in consumers.heard(scale, tag, t0), 60.0):
                    raise RuntimeError('a talker started without an agent was never heard')
                firsts = consumers.heard(scale, tag, t0)
                out['first'].append(firsts[0] - t0)
                if len(firsts) > 1:
                    out['first_same'].append(firsts[1] - t0)
                seen = consumers.matched(scale, topic, t0)
                if seen is not None:
                    out['matched'].append(seen - t0)
                    out['after_match'].append(firsts[0] - seen)
            finally:
                stop_process(proc, 10.0)
    finally:
        log.close()
    return out


def start_time(pid):
    """When a process was created, on CLOCK_BOOTTIME (what /proc/<pid>/stat counts in)."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            return int(f.read().rsplit(')', 1)[1].split()[19]) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return None


def cpu_of(pid, seconds):
    proc = psutil.Process(pid)
    t0, c0 = time.monotonic(), proc.cpu_times()
    time.sleep(seconds)
    t1, c1 = time.monotonic(), proc.cpu_times()
    return 100.0 * ((c1.user - c0.user) + (c1.system - c0.system)) / (t1 - t0)


def bench_cpu(tmp, seconds, place):
    names = [f'n{i}' for i in range(10)]
    nodes = {n: talker(f'/bench_agent/cpu/{n}', 1.0) for n in names}
    path = deployment(tmp, nodes, name='bench_agent_cpu')
    b = Bench('bench_agent_cpu')
    agent = start_agent(path, 'a', tmp, place)
    b.agents = [agent]
    try:
        b.publish(1, {n: 'b' for n in names})     # every node placed elsewhere: idle agent
        if not b.spin_until(lambda: 'a' in b.states and b.states['a'].generation == 1, 60.0):
            raise RuntimeError('the agent never applied the idle layout')
        b.spin_until(lambda: False, 3.0)
        idle = cpu_of(agent.pid, seconds)
        b.publish(2, {n: 'a' for n in names})
        if not b.spin_until(lambda: all(
                b.states['a'].nodes[n].state == ProcState.RUNNING and b.states['a'].nodes[n].ready
                for n in names), 120.0):
            raise RuntimeError('the ten nodes never became ready')
        b.spin_until(lambda: False, 3.0)
        busy = cpu_of(agent.pid, seconds)
    finally:
        stop_process(agent)
        b.close()
    return idle, busy


def figures(values):
    return (f'p50 {percentile(values, 0.5) * 1000:.0f} ms, '
            f'p95 {percentile(values, 0.95) * 1000:.0f} ms, '
            f'max {max(values) * 1000:.0f} ms, mean {statistics.mean(values) * 1000:.0f} ms')


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--moves', type=int, default=20)
    parser.add_argument('--cpu-seconds', type=float, default=20.0)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '42')))
    parser.add_argument('--jitter-s', type=float, default=3.0,
                        help='random pause of up to this long before each move (see above)')
    parser.add_argument('--standby', action='store_true',
                        help='move a lifecycle talker kept as a standby copy (activation)')
    parser.add_argument('--no-profile', action='store_true',
                        help="without the packaged config/fastdds_discovery.xml (Fast DDS's "
                             'defaults, or the profile the environment names)')
    parser.add_argument('--scales', choices=('netns', 'loopback'),
                        help='where the two scales run (default: netns when this machine can '
                             'build network namespaces, else loopback; see above)')
    parser.add_argument('--inside', metavar='TAG', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.moves < 1 or args.jitter_s < 0 or args.cpu_seconds < 0:
        parser.error('--moves must be >= 1, --jitter-s and --cpu-seconds >= 0')
    if args.inside is None:
        mode, why = choose(args.scales)
        print(f'scales: {mode} ({why})', flush=True)
        if mode == 'netns':
            return run_inside([sys.executable, os.path.abspath(__file__)] + sys.argv[1:],
                              args.domain_id, not args.no_profile)
    os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    from anyscale_manager import config_files
    with tempfile.TemporaryDirectory(prefix='bench_agent_') as tmp:
        if args.inside is None:
            place = Loopback()
            place.prepare_environment()
            if not args.no_profile:
                os.environ.update(config_files.with_discovery_profile(os.environ))
        else:
            place = Namespaces(args.inside, args.domain_id, os.path.join(tmp, 'ros_log'),
                               profile=not args.no_profile)
        try:
            import anyscale_manager.nodes.monitors  # noqa: F401
            monitors = 'with its monitors'
        except ImportError:
            monitors = 'without monitors (module absent)'
        import anyscale_manager
        profile = ', '.join(f'{v}={os.environ[v]}' for v in config_files.PROFILE_VARS
                            if os.environ.get(v)) \
            or 'none (Fast DDS defaults)'
        load = ' '.join(f'{x:.2f}' for x in os.getloadavg())
        print(f'machine: {os.cpu_count()} CPUs, load average {load}; ROS_DOMAIN_ID='
              f'{args.domain_id}; agent {monitors}; package '
              f'{os.path.dirname(anyscale_manager.__file__)}; DDS profile: {profile}')
        print(f'scales: {place.describe()}')
        other = ' at a consumer on the other scale' if place.here else ''
        who = 'the consumer on the other scale' if place.here else 'this consumer'
        labels = {'started': 'the gaining agent started the new copy',
                  'matched': f'{who} matched the new copy (DDS discovery)',
                  'first': f'first message from the new copy{other}',
                  'first_same': 'first message from the new copy at a consumer on its own scale',
                  'ready': 'new agent reports it running and ready'}
        try:
            moves = bench_moves(tmp, args.moves, place, args.jitter_s, args.standby)
        except RuntimeError as e:
            hint = (' (--standby needs agents that keep lifecycle standby copies: '
                    'nodes.<name>.lifecycle and .standby in the deployment)'
                    if args.standby else '')
            print(f'bench_agent: move latency failed{hint}:\n{e}', file=sys.stderr)
            return 1
        kind = 'standby activation, ' if args.standby else ''
        for node, label in (('sbs', 'start_before_stop'), ('sbs2', 'stop_before_start')):
            for stage in ('first', 'first_same', 'ready', 'started', 'matched'):
                s = moves[node][stage]
                if s:
                    print(f'move latency ({kind}{label}, {len(s)} moves, layout published -> '
                          f'{labels[stage]}): {figures(s)}')
            s = moves[node]['after_match']
            if s:
                print(f'move ({label}, {len(s)} moves): {who} matched the new copy -> its '
                      f'first message: {figures(s)}')
        bare = moves.get('bare', {})
        s = bare.get('after_match')
        if s:
            print(f'the same talker started without an agent ({len(s)} starts): {who} '
                  f'matched it -> its first message: {figures(s)}')
        for stage in ('first', 'first_same', 'matched'):
            s = bare.get(stage)
            if s:
                print(f'the same talker started without an agent, beside the same processes '
                      f'({len(s)} starts, process started -> {labels[stage]}): {figures(s)}')
        if args.cpu_seconds > 0:
            idle, busy = bench_cpu(tmp, args.cpu_seconds, place)
            print(f'agent CPU over {args.cpu_seconds:g} s (percent of one core): idle '
                  f'{idle:.1f} %, supervising ten running nodes {busy:.1f} %')
    load = ' '.join(f'{x:.2f}' for x in os.getloadavg())
    print(f'load average at the end: {load}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
