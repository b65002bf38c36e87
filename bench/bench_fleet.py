"""Two robots sharing one server, live, preemption after preemption: the time from capacity
freed to the other robot's node there, the lower robot's longest silence, and over-commit.

    python bench/bench_fleet.py [--preemptions 20] [--hysteresis 5] [--domain-id N]
                                [--keep DIR]

On this machine's loopback (anyscale_manager/testbed/fleet.py): robot_a (priority 0) and
robot_b (priority 1), each its own deployment, decider, agents and ROS domain, share one server
(capacity 100) with room for one worker (CPU 60), a plain node, moved cold. robot_a's worker
runs on the server; then, --preemptions times: robot_b starts and preempts it (robot_a takes
its worker home, then robot_b's starts there), and robot_b stops, after which robot_a's worker
goes back to the server once its hysteresis (--hysteresis s) has passed. Measured each cycle:

- preemption: from robot_a's worker process gone from the server (capacity freed) to robot_b's
  worker process started there; and the longest gap this bench's own subscriber heard on
  robot_a's worker output and on its pinned node's output across the preemption, each judged
  by the Δ rule (runtime/delta.py) against the connection's Δ of 5 s, which a cold move meets;
- return: from robot_b's worker gone from the server to robot_a's started there (robot_a's
  hysteresis counts from its move home);
- over-commit: samples at 5 Hz of the worker processes on the server (more than one) and of the
  active claims in the host's database (over the capacity), as seconds.
"""

import argparse
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from std_msgs.msg import UInt8MultiArray  # noqa: E402

from anyscale_manager.testbed.fleet import (Fleet, FleetShape, HOME, other_domain,  # noqa: E402
                                            stretches_past_delta)

SAMPLE_S = 0.2


class Bench:
    def __init__(self, fleet, executor):
        self.fleet, self.executor = fleet, executor
        self.over_s = 0.0
        self.heard = {'/robot_a/w': [], '/robot_a/p': []}

    def until(self, cond, timeout_s, what):
        end = time.monotonic() + timeout_s
        while not cond():
            on = self.fleet.on_server()
            if sum(on.values()) > 1 or self.fleet.claimed_cpu() > \
                    self.fleet.shape.capacity_cpu + 1e-9:
                self.over_s += SAMPLE_S
            dead = self.fleet.dead()
            if dead:
                raise SystemExit(f'{what}: {dead}')
            if time.monotonic() > end:
                raise SystemExit(f'{what}: not within {timeout_s} s\n{self.fleet.outputs()}')
            stop = time.monotonic() + SAMPLE_S
            while time.monotonic() < stop:
                self.executor.spin_once(timeout_sec=0.05)
        return time.monotonic()

    def longest_gap(self, topic, start, end):
        times = [t for t in self.heard[topic] if start <= t <= end]
        times = [start] + times + [end]
        return max(b - a for a, b in zip(times, times[1:]))


def _pct(values, q):
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))]


def _line(label, values, unit='s'):
    return (f'  {label:<44} p50 {statistics.median(values):.2f} {unit}  p95 '
            f'{_pct(values, 0.95):.2f} {unit}  max {max(values):.2f} {unit}  (n={len(values)})')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preemptions', type=int, default=20)
    ap.add_argument('--hysteresis', type=float, default=5.0)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 57)))
    ap.add_argument('--keep', default='')
    a = ap.parse_args(argv)
    run_dir = a.keep or tempfile.mkdtemp(prefix='fleet_bench_')
    os.makedirs(run_dir, exist_ok=True)
    shape = FleetShape(hysteresis_s=a.hysteresis)
    env = dict(os.environ, ROS_DOMAIN_ID=str(a.domain_id))
    os.environ['ROS_DOMAIN_ID'] = str(a.domain_id)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('fleet_bench', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    fleet = Fleet(run_dir, env, shape)
    bench = Bench(fleet, executor)
    for topic in bench.heard:
        node.create_subscription(UInt8MultiArray, topic,
                                 lambda m, t=topic: bench.heard[t].append(time.monotonic()),
                                 qos_profile_sensor_data)
    freed_to_b, freed_to_a, gaps_w, gaps_p, violations = [], [], [], [], 0
    try:
        fleet.start('robot_a', a.domain_id, priority=0)
        bench.until(lambda: fleet.on_server().get('robot_a') == 1, 120.0,
                    "robot_a's worker on the server")
        for i in range(a.preemptions):
            bench.until(lambda: len(bench.heard['/robot_a/w']) and
                        time.monotonic() - bench.heard['/robot_a/w'][-1] < 0.5, 30.0,
                        "robot_a's worker heard")
            start = time.monotonic()
            fleet.start('robot_b', other_domain(a.domain_id), priority=1)
            freed = bench.until(lambda: fleet.on_server().get('robot_a') == 0, 120.0,
                                "robot_a's worker leaving the server")
            b_there = bench.until(lambda: fleet.on_server().get('robot_b') == 1, 60.0,
                                  "robot_b's worker on the server")
            bench.until(lambda: fleet.workers('robot_a', HOME) == 1, 30.0,
                        "robot_a's worker home")
            bench.until(lambda: time.monotonic() - b_there > 2.0, 5.0, 'settling')
            end = time.monotonic()
            gw = bench.longest_gap('/robot_a/w', start, end)
            gp = bench.longest_gap('/robot_a/p', start, end)
            past = [stretches_past_delta(bench.heard[t], start, end, shape)[0]
                    for t in ('/robot_a/w', '/robot_a/p')]
            violations += any(past)
            freed_to_b.append(b_there - freed)
            gaps_w.append(gw)
            gaps_p.append(gp)
            fleet.stop('robot_b')
            gone = time.monotonic()
            a_there = bench.until(lambda: fleet.on_server().get('robot_a') == 1,
                                  shape.hysteresis_s + 60.0, "robot_a's worker back")
            freed_to_a.append(a_there - gone)
            print(f'[{i + 1}/{a.preemptions}] freed -> robot_b there {b_there - freed:.2f} s; '
                  f"robot_a's longest gap: worker {gw:.2f} s, pinned {gp:.2f} s; robot_b gone "
                  f'-> robot_a back {a_there - gone:.2f} s', flush=True)
    finally:
        fleet.close()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    print(f'fleet: 2 robots, one server (capacity {shape.capacity_cpu:g}, worker '
          f'{shape.worker_cpu:g}), {len(freed_to_b)} preemptions, hysteresis '
          f'{shape.hysteresis_s:g} s; run folder {run_dir}')
    if freed_to_b:
        print(_line('capacity freed -> higher robot there', freed_to_b))
        print(_line("lower robot's longest gap, worker output", gaps_w))
        print(_line("lower robot's longest gap, pinned output", gaps_p))
        print(_line('higher robot gone -> lower robot back there', freed_to_a))
    print(f'  Δ violations on the preempted robot: {violations} of {len(freed_to_b)}; '
          f'over-commit: {bench.over_s:.1f} s')
    return 1 if violations or bench.over_s else 0


if __name__ == '__main__':
    sys.exit(main())
