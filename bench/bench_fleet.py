"""Two robots sharing one server, live, preemption after preemption (or the holder's link cut
after cut): the time from capacity freed to the other robot's node there, the longest silence
of the robot that gave the room up, and over-commit.

    python bench/bench_fleet.py [--preemptions 20] [--hysteresis 5] [--domain-id N]
                                [--keep DIR]
    python bench/bench_fleet.py --cuts 10 [--hysteresis 6] [--domain-id N] [--keep DIR]

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

``--cuts N`` (root): the fleet in network namespaces instead (testbed/fleet_netns.py FleetBed,
as test/test_fleet_netns.py), both robots of priority 0, brought up once. N times: once one
robot's worker serves from the server and the other's from home, the layout quiet, the
holder's link is cut. Measured from the bed's samples at 5 Hz: the holder's worker home, its
server copy gone and its claim released (the room freed: the later of the two), the other
robot's worker started there and serving there (its home copy let go); the holder's longest
stretch below freq_min, judged by the Δ rule on what its namespace heard from 2 s before the
cut. Then the link is restored and the next round waits for the layout to be quiet again: the
other robot holds the server, the first one's agent judged its link up, past the first one's
hysteresis since its move home (so room, not T, decides the next hand-over), and nothing moved
for 5 s; the next round cuts the new holder.
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

from anyscale_manager.runtime.delta import rate_below  # noqa: E402
from anyscale_manager.testbed import netns  # noqa: E402
from anyscale_manager.testbed.fleet import (Fleet, FleetShape, HOME, other_domain,  # noqa: E402
                                            SERVER, stretches_past_delta)
from anyscale_manager.testbed.fleet_netns import FleetBed  # noqa: E402

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
    return (f'  {label:<46} p50 {statistics.median(values):.2f} {unit}  p95 '
            f'{_pct(values, 0.95):.2f} {unit}  max {max(values):.2f} {unit}  (n={len(values)})')


ROBOTS = ('robot_a', 'robot_b')
# How long the layout must stay as it is before a cut: several turns of both deciders.
QUIET_S = 5.0


def heard_rate(record, robot, now, window_s=1.0):
    """Messages a second ``robot``'s users heard over the ``window_s`` before ``now``."""
    return sum(1 for t in record.heard(robot) if now - window_s <= t <= now) / window_s


def link_judged_up(bed, robot):
    """``robot``'s home agent has not said its link to the server is DOWN since it last said
    it is up."""
    said = bed.fleet.text(robot, HOME)
    return said.rfind('link to away is up') >= said.rfind('link to away is DOWN')


def over_commit(samples, shape):
    """(samples with two workers on the server or claims above its capacity, their seconds:
    each such sample counted until the next one)."""
    over = [s.on_server > 1 or s.claimed_cpu > shape.capacity_cpu + 1e-9 for s in samples]
    seconds = sum(b.t - a.t for a, b, o in zip(samples, samples[1:], over) if o)
    return sum(over), seconds


def quiet(bed, shape, not_before, what):
    """Wait until one robot's worker serves from the server and is heard at freq_min or more,
    the other's is home, each link up and judged up, at or after ``not_before``, and the layout
    has not changed for QUIET_S; return (holder, other)."""
    since = {'t': None, 'layout': None}

    def holds(s):
        layout = tuple(s.where(r) for r in ROBOTS)
        if sorted(layout) != [SERVER, HOME] or s.on_server != 1:
            since['t'] = None
            return False
        holder = ROBOTS[layout.index(SERVER)]
        if not (all(s.links_up.values()) and all(link_judged_up(bed, r) for r in ROBOTS)
                and {r for r, cpu in s.claims_cpu.items() if cpu} <= {holder}):
            since['t'] = None
            return False
        if since['t'] is None or layout != since['layout']:
            since['t'], since['layout'] = s.t, layout
        return (s.t >= not_before and s.t - since['t'] >= QUIET_S
                and not rate_below(shape.freq_min_hz,
                                   heard_rate(bed.record, holder, s.t - 0.6)))
    s = bed.until(holds, 120.0, what)
    holder = next(r for r in ROBOTS if s.where(r) == SERVER)
    return holder, next(r for r in ROBOTS if r != holder)


def cuts(a) -> int:
    """The holder's link cut, ``a.cuts`` times, in namespaces (the module's docstring)."""
    ok, why = netns.available()
    if not ok:
        print(f'--cuts needs the test-bed: {why}', file=sys.stderr)
        return 2
    run_dir = a.keep or tempfile.mkdtemp(prefix='fleet_cuts_')
    os.makedirs(run_dir, exist_ok=True)
    shape = FleetShape(hysteresis_s=a.hysteresis)
    domains = {'robot_a': a.domain_id, 'robot_b': other_domain(a.domain_id)}
    rows = {k: [] for k in ('home', 'freed', 'serving', 'gap')}
    violations, early, notes = 0, 0, []
    bed = FleetBed(run_dir, ROBOTS, shape)
    try:
        bed.setup()
        for robot in ROBOTS:
            bed.start(robot, domains[robot])
        not_before = 0.0
        for i in range(a.cuts):
            holder, other = quiet(bed, shape, not_before, f'round {i + 1}: the layout quiet')
            cut = bed.cut(holder)
            done = bed.until(lambda s: s.where(holder) == HOME and s.where(other) == SERVER
                             and not s.claims_cpu.get(holder), 60.0,
                             f"round {i + 1}: {holder}'s worker home, its claim gone, "
                             f"{other}'s on the server")
            rec = bed.record
            h = rec.hand_over(holder, other, cut)
            home, fenced, released, started, serving, freed = \
                h.home, h.fenced, h.released, h.started, h.serving, h.freed
            bed.until(lambda s: rec.judged_until(holder) >= done.t, 10.0,
                      f"{holder}'s observer's lines past the move")
            past, longest = stretches_past_delta(rec.heard(holder), cut - 2.0, done.t, shape)
            violations += past > 0
            early += started < freed
            rows['home'].append(home - cut)
            rows['freed'].append(freed - cut)
            rows['serving'].append(serving - freed)
            rows['gap'].append(longest)
            bed.restore(holder)
            not_before = home + shape.hysteresis_s + 1.0
            print(f'[{i + 1}/{a.cuts}] {holder} cut: home {home - cut:.2f} s, server copy gone '
                  f'{fenced - cut:.2f} s, claim released {released - cut:.2f} s; {other} '
                  f'started there {started - cut:.2f} s, serving {serving - cut:.2f} s '
                  f'(freed -> serving {serving - freed:.2f} s); {holder} below freq_min '
                  f'{longest:.2f} s at most{", PAST Δ" if past else ""}', flush=True)
    finally:
        notes = bed.close()
    over_n, over_s = over_commit(bed.record.samples, shape)
    print(f'fleet, link cuts: 2 robots in namespaces, one server (capacity '
          f'{shape.capacity_cpu:g}, worker {shape.worker_cpu:g}), {len(rows["home"])} cuts, '
          f'hysteresis {shape.hysteresis_s:g} s, Δ {shape.tolerance_s:g} s; run folder {run_dir}')
    if rows['home']:
        print(_line("cut -> the holder's worker home", rows['home']))
        print(_line('cut -> room freed (copy gone, claim released)', rows['freed']))
        print(_line("room freed -> the other's worker serving there", rows['serving']))
        print(_line("the holder's longest stretch below freq_min", rows['gap']))
    print(f'  Δ violations on the cut robot: {violations} of {len(rows["home"])}; started '
          f'before the room was freed: {early}; over-commit: {over_n} samples of '
          f'{len(bed.record.samples)}, {over_s:.1f} s; teardown cleaned: {notes or "nothing"}')
    return 1 if violations or early or over_n else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preemptions', type=int, default=20)
    ap.add_argument('--cuts', type=int, default=0,
                    help="instead of preemptions, this many cuts of the holder's link, the "
                         'fleet in network namespaces (root)')
    ap.add_argument('--hysteresis', type=float, default=None,
                    help='seconds (default 5, with --cuts 6)')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 57)))
    ap.add_argument('--keep', default='')
    a = ap.parse_args(argv)
    if a.cuts < 0 or a.preemptions < 0:
        ap.error('--cuts and --preemptions take a count of 0 or more')
    if a.hysteresis is None:
        a.hysteresis = 6.0 if a.cuts else 5.0
    if a.cuts:
        return cuts(a)
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
