"""Warm standby on DDS: time from SIGCONT to the first message of a resumed (frozen) node.

    .venv/bin/python bench/bench_standby.py --domain-id N [--freeze 2,10,30] [--rounds 3]

A 10 Hz rclpy talker (the agent tests' fixture) runs in a process group of its own, with this
script's listener (best effort, as the test-bed's sensor subscribers) and a reliable listener in
another process-free rclpy node. For each freeze length the talker is frozen (SIGSTOP to its
group), left frozen that long, thawed (SIGCONT) and the time to the first message received from
it is taken; also whether the listener's graph still listed the talker just before the thaw (a
frozen participant is dropped by the others when its DDS lease, 20 s in Fast DDS, runs out).
Loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from bench_agent import stop_agent      # SIGINT, then kill past a deadline

HERE = os.path.dirname(os.path.abspath(__file__))
TALKER = os.path.join(os.path.dirname(HERE), 'test', 'fixtures', 'agent_talker.py')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--domain-id', type=int, required=True)
    ap.add_argument('--freeze', default='2,10,30', help='freeze lengths in seconds')
    ap.add_argument('--rounds', type=int, default=3)
    ap.add_argument('--out', default='')
    args = ap.parse_args()
    freezes = [float(x) for x in args.freeze.split(',') if x]
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    os.environ.update(ROS_DOMAIN_ID=str(args.domain_id),
                      ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    topic = f'/bench_standby_{os.getpid()}'
    name = f'bench_standby_talker_{os.getpid()}'
    ctx = Context()
    rclpy.init(context=ctx)
    node = Node('bench_standby_listener', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    heard = {'best_effort': [], 'reliable': []}
    node.create_subscription(String, topic, lambda m: heard['best_effort'].append(
        time.monotonic()), QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    node.create_subscription(String, topic, lambda m: heard['reliable'].append(
        time.monotonic()), 10)
    proc = subprocess.Popen([sys.executable, TALKER, '--ros-args', '-r', f'__node:={name}',
                             '-p', f'topic:={topic}', '-p', 'rate_hz:=10.0'], env=env,
                            start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT)
    results = []

    def spin_until(cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
            if cond():
                return True
        return False

    def listed():
        return any(n == name for n, _ in node.get_node_names_and_namespaces())

    try:
        if not spin_until(lambda: heard['reliable'] and heard['best_effort'], 30.0):
            print('the talker never reached the listener', file=sys.stderr)
            return 1
        for freeze in freezes:
            for _ in range(args.rounds):
                spin_until(lambda: False, 1.0)
                os.killpg(proc.pid, signal.SIGSTOP)
                spin_until(lambda: False, freeze)
                still_listed = listed()
                t_cont = time.monotonic()
                os.killpg(proc.pid, signal.SIGCONT)
                first = {}
                spin_until(lambda: (first.update({k: v[-1] - t_cont for k, v in heard.items()
                                                  if v and v[-1] > t_cont and k not in first})
                                    or len(first) == 2), 30.0)
                row = {'freeze_s': freeze, 'listed_before_thaw': still_listed,
                       'first_best_effort_s': first.get('best_effort'),
                       'first_reliable_s': first.get('reliable')}
                results.append(row)
                print(json.dumps(row), flush=True)
    finally:
        os.killpg(proc.pid, signal.SIGCONT)
        stop_agent(proc)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    for freeze in freezes:
        rows = [r for r in results if r['freeze_s'] == freeze]
        for key in ('first_best_effort_s', 'first_reliable_s'):
            vals = [r[key] for r in rows if r[key] is not None]
            if vals:
                print(f'freeze {freeze:g} s, {key}: median {statistics.median(vals) * 1000:.0f} '
                      f'ms, max {max(vals) * 1000:.0f} ms ({len(vals)}/{len(rows)} heard); '
                      f'listed before the thaw {sum(r["listed_before_thaw"] for r in rows)}'
                      f'/{len(rows)}')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
