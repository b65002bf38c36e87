#!/usr/bin/env python3
"""CPU the test-bed's workload nodes spend on their messages: publishing (conversion and
serialisation), sending and taking them, with the CPU work per output left out.

Every workload node of a deployment runs as a plain process (``--lifecycle`` dropped, so the
lifecycle nodes work at once) with ``--work-ms 0``: the work per output is the deployment's
and does not depend on the message types, so what is left is what the types cost. A reader
node subscribes raw to every connection's topic, as the test-bed's observer does, and counts
arrivals; once every topic flows, each process's CPU (utime + stime from /proc) is read over
``--seconds``. With two deployments (the test-bed before and after a change of types, say)
the rounds alternate between them, each on its own, and the table compares them.

    .venv/bin/python bench/bench_workload_cost.py --domain N [--seconds 20] [--rounds 2]
        [DEPLOYMENT ...]            (default: config/icar2015_testbed.yaml)

DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the given domain.
"""

import argparse
import os
import statistics
import subprocess
import sys
import time

from anyscale_manager.agent.procs import stop_all

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
CLK_TCK = os.sysconf('SC_CLK_TCK')


def cpu_seconds(pid: int) -> float:
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def messaging_only(arguments):
    """The node's arguments as a plain node with no CPU work per output."""
    args = [a for a in arguments if a != '--lifecycle']
    if '--work-ms' in args:
        args[args.index('--work-ms') + 1] = '0'
    return args


def topics_of(deployment):
    """Topic -> message type of every connection (from its publisher's arguments when the
    connection does not declare one)."""
    from anyscale_manager.nodes.workload import parse_spec
    published = {}
    for node in deployment.nodes:
        if node.launch.executable == 'workload':
            for e in parse_spec(list(node.launch.arguments)).outputs:
                published[e.topic] = e.msg_type
    return {c.topic: c.msg_type or published[c.topic] for c in deployment.connections}


class Reader:
    def __init__(self, topics):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from anyscale_manager.nodes.qos import PROBE
        from anyscale_manager.nodes.workload_messages import message_class
        self._rclpy = rclpy
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(f'bench_workload_reader_{os.getpid()}', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.arrivals = {t: [] for t in topics}
        for topic, type_name in topics.items():
            self.node.create_subscription(
                message_class(type_name), topic,
                lambda _raw, t=topic: self.arrivals[t].append(time.monotonic()), PROBE, raw=True)

    def spin_until(self, condition, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.ctx)


def run_once(path, seconds, env, log):
    """{node: CPU % of one core}, {topic: Hz} for one deployment."""
    from anyscale_manager.model.loader import load_deployment
    deployment = load_deployment(path)
    procs = {}
    for node in deployment.nodes:
        if node.launch.executable != 'workload':
            continue
        argv = [sys.executable, '-m', 'anyscale_manager.nodes.workload',
                *messaging_only(node.launch.arguments)]
        procs[node.name] = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL,
                                            stderr=subprocess.STDOUT, start_new_session=True)
    reader = Reader(topics_of(deployment))
    try:
        flowing = reader.spin_until(lambda: all(len(a) >= 10 for a in reader.arrivals.values()),
                                    60.0)
        if not flowing:
            quiet = [t for t, a in reader.arrivals.items() if len(a) < 10]
            raise RuntimeError(f'{path}: no traffic on {", ".join(quiet)} within 60 s')
        t0 = time.monotonic()
        before = {n: cpu_seconds(p.pid) for n, p in procs.items()}
        reader.spin_until(lambda: time.monotonic() - t0 >= seconds, seconds + 1.0)
        t1 = time.monotonic()
        after = {n: cpu_seconds(p.pid) for n, p in procs.items()}
        cpu = {n: 100.0 * (after[n] - before[n]) / (t1 - t0) for n in procs}
        rates = {t: sum(1 for x in a if t0 <= x <= t1) / (t1 - t0)
                 for t, a in reader.arrivals.items()}
    finally:
        reader.close()
        stop_all(list(procs.values()), 10.0)
    log(f'{os.path.basename(path)}: total {sum(cpu.values()):.1f} % of a core; '
        + ', '.join(f'{t} {r:.1f} Hz' for t, r in sorted(rates.items())))
    return cpu, rates


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('deployments', nargs='*',
                    default=[os.path.join(REPO, 'config', 'icar2015_testbed.yaml')])
    ap.add_argument('--domain', required=True, help='ROS_DOMAIN_ID of this run')
    ap.add_argument('--seconds', type=float, default=20.0, help='CPU window per round')
    ap.add_argument('--rounds', type=int, default=2)
    a = ap.parse_args()
    if len(a.deployments) > 2:
        ap.error('give one deployment, or two to compare')
    os.environ['ROS_DOMAIN_ID'] = str(a.domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env = dict(os.environ, PYTHONUNBUFFERED='1')

    def log(text):
        print(text, file=sys.stderr, flush=True)

    results = {p: [] for p in a.deployments}
    for _ in range(a.rounds):
        for path in a.deployments:
            results[path].append(run_once(path, a.seconds, env, log)[0])
    nodes = sorted({n for runs in results.values() for run in runs for n in run})
    names = [os.path.basename(p) for p in a.deployments]
    print(f'CPU in % of one core of this machine, mean of {a.rounds} round(s) of '
          f'{a.seconds:g} s, --work-ms 0 (machine: {os.cpu_count()} CPUs, load '
          f'{os.getloadavg()[0]:.1f})')
    print(f'{"node":<12}' + ''.join(f'{n:>26}' for n in names)
          + (f'{"difference":>12}' if len(names) == 2 else ''))

    def mean(path, node):
        return statistics.mean(run.get(node, 0.0) for run in results[path])

    for node in nodes + ['total']:
        values = ([mean(p, node) for p in a.deployments] if node != 'total' else
                  [sum(mean(p, n) for n in nodes) for p in a.deployments])
        print(f'{node:<12}' + ''.join(f'{v:>26.2f}' for v in values)
              + (f'{values[1] - values[0]:>+12.2f}' if len(values) == 2 else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
