#!/usr/bin/env python3
"""Agent figures: move latency between two agents, and the agent's own CPU.

    python bench/bench_agent.py [--moves 20] [--cpu-seconds 20] [--domain-id N]

Move latency: two agents (scales a and b) on this machine; a small rclpy talker (10 Hz) is moved
back and forth by publishing a new layout; the time runs from the layout's publication to the
first message from the talker started on the new scale (told apart by its scale tag and pid).
Measured for both move orders. Agent CPU: the agent process alone (its children excluded),
once idle with ten catalogue nodes stopped and once supervising ten running talkers at 1 Hz;
monitors hosted by the agent are included when the monitors module is present.
DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the given domain.
"""

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import psutil
import yaml

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
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


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


def talker(topic, rate_hz, **extra):
    return dict({'launch': {'command': [sys.executable, '-c', TALKER],
                            'parameters': {'topic': topic, 'rate_hz': rate_hz}},
                 'cpu': 1.0}, **extra)


def start_agent(path, scale, tmp):
    exe = os.path.join(os.path.dirname(sys.executable), 'agent')
    out = open(os.path.join(tmp, f'agent_{scale}.out'), 'ab')
    return subprocess.Popen([exe, '--ros-args', '--params-file', path, '-p', f'scale:={scale}'],
                            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def stop_agent(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


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
        self.node.create_subscription(
            String, protocol.TOPIC_AGENT_STATE, self._state,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def listen(self, topic):
        self.node.create_subscription(self.String, topic,
                                      lambda m: self.heard.append((time.monotonic(), m.data)),
                                      10)

    def _state(self, msg):
        st = self.protocol.AgentState.from_json(msg.data)
        self.states[st.scale] = st

    def publish(self, generation, assignments):
        self.pub.publish(self.String(data=json.dumps({
            'generation': generation, 'deployment': self.name, 'assignments': assignments,
            'reason': 'bench', 'stamp': time.time()})))

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.rclpy.spin_once(self.node, timeout_sec=0.01)
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


def bench_moves(tmp, moves):
    topic = '/bench_agent/chatter'
    nodes = {'sbs': talker(topic + '/sbs', 10.0),
             'sbs2': talker(topic + '/stop_first', 10.0, move_order='stop_before_start')}
    path = deployment(tmp, nodes)
    b = Bench('bench_agent')
    b.listen(topic + '/sbs')
    b.listen(topic + '/stop_first')
    agents = [start_agent(path, 'a', tmp), start_agent(path, 'b', tmp)]
    results = {}
    try:
        gen = 0
        for node in ('sbs', 'sbs2'):
            gen += 1
            b.publish(gen, {node: 'a'})
            if not b.spin_until(lambda: any(d.startswith('a ') for _, d in b.heard), 60.0):
                raise RuntimeError('the talker never published on scale a')
            samples, ready = [], []
            where = 'a'
            for _ in range(moves):
                where = 'b' if where == 'a' else 'a'
                gen += 1
                b.heard.clear()
                t0 = time.monotonic()
                b.publish(gen, {node: where})

                def moved():
                    r = b.states.get(where)
                    rep = r.nodes.get(node) if r else None
                    if rep is None or rep.state not in ('starting', 'running') or not rep.pid:
                        return False
                    return any(d == f'{where} {rep.pid}' for _, d in b.heard)

                def ready_new():
                    r = b.states.get(where)
                    rep = r.nodes.get(node) if r else None
                    if rep is not None and rep.state == 'running' and rep.ready \
                            and r.generation == gen and not ready_at:
                        ready_at.append(time.monotonic() - t0)
                    return moved() and bool(ready_at)

                ready_at = []
                if not b.spin_until(ready_new, 60.0):
                    raise RuntimeError(f'move {gen} of {node} to {where} never completed')
                rep = b.states[where].nodes[node]
                first = min(t for t, d in b.heard if d == f'{where} {rep.pid}')
                samples.append(first - t0)

                def settled():
                    old = b.states.get('a' if where == 'b' else 'b')
                    orep = old.nodes.get(node) if old else None
                    new = b.states[where].nodes[node]
                    return orep is not None and orep.state == 'stopped' and new.ready

                b.spin_until(settled, 30.0)
                ready.append(ready_at[0])
                b.heard.clear()
            results[node] = (samples, ready)
            b.publish(gen + 1, {node: 'a'})
            gen += 1
            b.spin_until(lambda: False, 0.5)
    finally:
        for a in agents:
            stop_agent(a)
        b.close()
    return results


def cpu_of(pid, seconds):
    proc = psutil.Process(pid)
    t0, c0 = time.monotonic(), proc.cpu_times()
    time.sleep(seconds)
    t1, c1 = time.monotonic(), proc.cpu_times()
    return 100.0 * ((c1.user - c0.user) + (c1.system - c0.system)) / (t1 - t0)


def bench_cpu(tmp, seconds):
    names = [f'n{i}' for i in range(10)]
    nodes = {n: talker(f'/bench_agent/cpu/{n}', 1.0) for n in names}
    path = deployment(tmp, nodes, name='bench_agent_cpu')
    b = Bench('bench_agent_cpu')
    agent = start_agent(path, 'a', tmp)
    try:
        b.publish(1, {n: 'b' for n in names})     # every node placed elsewhere: idle agent
        if not b.spin_until(lambda: 'a' in b.states and b.states['a'].generation == 1, 60.0):
            raise RuntimeError('the agent never applied the idle layout')
        b.spin_until(lambda: False, 3.0)
        idle = cpu_of(agent.pid, seconds)
        b.publish(2, {n: 'a' for n in names})
        if not b.spin_until(lambda: all(
                b.states['a'].nodes[n].state == 'running' and b.states['a'].nodes[n].ready
                for n in names), 120.0):
            raise RuntimeError('the ten nodes never became ready')
        b.spin_until(lambda: False, 3.0)
        busy = cpu_of(agent.pid, seconds)
    finally:
        stop_agent(agent)
        b.close()
    return idle, busy


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--moves', type=int, default=20)
    parser.add_argument('--cpu-seconds', type=float, default=20.0)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '42')))
    args = parser.parse_args()
    os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_STATIC_PEERS', None)
    try:
        import anyscale_manager.nodes.monitors  # noqa: F401
        monitors = 'with its monitors'
    except ImportError:
        monitors = 'without monitors (module absent)'
    print(f'machine: {os.cpu_count()} CPUs; ROS_DOMAIN_ID={args.domain_id}; agent {monitors}')
    with tempfile.TemporaryDirectory(prefix='bench_agent_') as tmp:
        moves = bench_moves(tmp, args.moves)
        for node, label in (('sbs', 'start_before_stop'), ('sbs2', 'stop_before_start')):
            for s, what in zip(moves[node], ('first message from the new copy',
                                             'new agent reports it running and ready')):
                print(f'move latency ({label}, {len(s)} moves, layout published -> {what}): '
                      f'p50 {percentile(s, 0.5) * 1000:.0f} ms, '
                      f'p95 {percentile(s, 0.95) * 1000:.0f} ms, '
                      f'max {max(s) * 1000:.0f} ms, mean {statistics.mean(s) * 1000:.0f} ms')
        idle, busy = bench_cpu(tmp, args.cpu_seconds)
        print(f'agent CPU over {args.cpu_seconds:g} s (percent of one core): idle '
              f'{idle:.1f} %, supervising ten running nodes {busy:.1f} %')
    return 0


if __name__ == '__main__':
    sys.exit(main())
