#!/usr/bin/env python3
"""What each input costs a workload stand-in that does no work: the CPU of one node paced at
10 Hz (its first ``--sub``) with 0, 1, 2 and 5 more inputs, each another publisher's 10 Hz
stream of 64-byte arrays, as the IROS case study's live stand-ins are (testbed/iros_live.py).

    .venv/bin/python bench/bench_input_cost.py --domain N [--seconds 20] [--rounds 2]
        [--inputs 0,1,2,5] [--rate 10] [--factor 0.15]

The node under test runs ``--work-ms 0``: its CPU is the middleware's and the executor's for its
pacer, its inputs and its output. Each count runs on its own (its publishers started fresh),
the counts alternate over ``--rounds``; CPU is utime + stime from /proc over ``--seconds``
once every input flows. Printed per count: % of one core (mean of the rounds, and each) and in
reference units at ``--factor`` (one reference core as a fraction of one core here; 0.15 in
the IROS live run), and the cost of one more input from the fit. DDS stays on loopback
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the given domain.
"""

import argparse
import os
import statistics
import subprocess
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from anyscale_manager.agent.procs import stop_all  # noqa: E402

CLK_TCK = os.sysconf('SC_CLK_TCK')


def cpu_seconds(pid: int) -> float:
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def workload(*args: str, env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-m', 'anyscale_manager.nodes.workload', *args],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)


def output_flows(env, topic: str, timeout_s: float) -> bool:
    """Whether ``topic`` carries messages within ``timeout_s`` (a reader of this run)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from anyscale_manager.nodes.qos import PROBE
    from anyscale_manager.nodes.workload_messages import message_class
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(f'bench_input_cost_{os.getpid()}', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    seen = []
    node.create_subscription(message_class('std_msgs/msg/UInt8MultiArray'), topic,
                             lambda _m: seen.append(1), PROBE, raw=True)
    deadline = time.monotonic() + timeout_s
    try:
        while len(seen) < 10 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return len(seen) >= 10


def run_once(n: int, rate: float, seconds: float, env) -> float:
    """CPU (% of one core) of a node paced at 10 Hz with ``n`` more inputs at ``rate``."""
    pubs = [workload('--name', 'pacer', '--pub', '/pace', '--rate-hz', '10', env=env)]
    pubs += [workload('--name', f'source_{k}', '--pub', f'/in_{k}', '--rate-hz', f'{rate:g}',
                      env=env) for k in range(n)]
    subs = ['--sub', '/pace'] + [a for k in range(n) for a in ('--sub', f'/in_{k}')]
    node = workload('--name', 'under_test', *subs, '--pub', '/out', '--rate-hz', '10',
                    '--work-ms', '0', env=env)
    try:
        if not output_flows(env, '/out', 60.0):
            raise RuntimeError(f'{n} inputs: the node under test published nothing in 60 s')
        time.sleep(2.0)                   # its discovery of the others settles
        c0, t0 = cpu_seconds(node.pid), time.monotonic()
        time.sleep(seconds)
        return 100.0 * (cpu_seconds(node.pid) - c0) / (time.monotonic() - t0)
    finally:
        stop_all(pubs + [node], 10.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--domain', required=True, help='ROS_DOMAIN_ID of this run')
    ap.add_argument('--seconds', type=float, default=20.0)
    ap.add_argument('--rounds', type=int, default=2)
    ap.add_argument('--inputs', default='0,1,2,5')
    ap.add_argument('--rate', type=float, default=10.0, help='each input, Hz')
    ap.add_argument('--factor', type=float, default=0.15,
                    help='one reference core as a fraction of one core here')
    a = ap.parse_args()
    try:
        counts = [int(x) for x in a.inputs.split(',') if x.strip()]
    except ValueError:
        ap.error(f'--inputs: {a.inputs!r} is not a comma-separated list of counts')
    if not counts or min(counts) < 0 or a.rounds < 1 or a.seconds <= 0 or a.factor <= 0:
        ap.error('--inputs needs counts >= 0; --rounds, --seconds and --factor must be > 0')
    env = dict(os.environ, ROS_DOMAIN_ID=str(a.domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1')
    os.environ.update(ROS_DOMAIN_ID=str(a.domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    got = {n: [] for n in counts}
    for r in range(a.rounds):
        for n in counts:
            got[n].append(run_once(n, a.rate, a.seconds, env))
            print(f'round {r + 1}, {n} input(s): {got[n][-1]:.2f} % of a core', flush=True)
    print(f'a node paced at 10 Hz, no work, with more inputs at {a.rate:g} Hz each '
          f'({a.seconds:g} s windows, {a.rounds} round(s); reference units at {a.factor:g}):')
    for n in counts:
        mean = statistics.mean(got[n])
        print(f'  {n} input(s): {mean:.2f} % of a core ({", ".join(f"{x:.2f}" for x in got[n])})'
              f' = {mean / a.factor:.1f} reference units')
    if len(counts) > 1:
        xs = counts
        ys = [statistics.mean(got[n]) for n in counts]
        mx, my = statistics.mean(xs), statistics.mean(ys)
        slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / \
            sum((x - mx) ** 2 for x in xs)
        print(f'  each more input: {slope:.2f} % of a core = {slope / a.factor:.1f} reference '
              'units (least squares)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
