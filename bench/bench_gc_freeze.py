#!/usr/bin/env python3
"""What moving the startup's objects out of the collector's sight saves (nodes/executor.py,
``collect_between_callbacks``): the wall time of a full collection in a process that has
imported the agent's and the decider's modules and built an agent-sized set of ROS entities,
before and after ``gc.freeze()``.

    python bench/bench_gc_freeze.py [--rounds 20] [--publishers 40] [--domain 13]

One process, one rclpy context on loopback (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``); a
node with ``--publishers`` publishers and as many subscriptions of std_msgs/String, about
what an agent with its monitors and probes holds. Prints p50 and max of ``gc.collect()`` over
``--rounds`` collections each way.
"""

import argparse
import gc
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))


def collections(rounds: int):
    times = []
    for _ in range(rounds):
        t = time.perf_counter()
        gc.collect()
        times.append(time.perf_counter() - t)
    return times


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--rounds', type=int, default=20)
    ap.add_argument('--publishers', type=int, default=40)
    ap.add_argument('--domain', type=int, default=13)
    a = ap.parse_args(argv)
    if a.rounds < 1 or a.publishers < 0:
        ap.error('--rounds takes 1 or more, --publishers 0 or more')
    os.environ['ROS_DOMAIN_ID'] = str(a.domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    import rclpy
    from std_msgs.msg import String
    import anyscale_manager.nodes.agent  # noqa: F401  (the modules an agent imports)
    import anyscale_manager.nodes.decider  # noqa: F401
    rclpy.init()
    node = rclpy.create_node('gc_freeze_bench')
    try:
        for i in range(a.publishers):
            node.create_publisher(String, f'/gc_bench/p{i}', 10)
            node.create_subscription(String, f'/gc_bench/p{i}', lambda _m: None, 10)
        gc.collect()
        before = collections(a.rounds)
        gc.freeze()
        after = collections(a.rounds)
        print(f'a full collection, {gc.get_freeze_count()} objects frozen: before the freeze '
              f'p50 {statistics.median(before) * 1e3:.1f} ms (max {max(before) * 1e3:.1f}); '
              f'after it p50 {statistics.median(after) * 1e6:.0f} us '
              f'(max {max(after) * 1e6:.0f}); {a.rounds} collections each')
    finally:
        node.destroy_node()
        rclpy.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
