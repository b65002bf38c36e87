#!/usr/bin/env python3
"""A node's state across every kind of change of serving copy, on the ICAR test-bed (needs
root): the test-bed's AMCL, whose state is the robot's pose (declared with ``state:``), judged on
the poses the harness's own observer heard on /amcl_pose.

    sudo python bench/bench_state.py [--moves 40] [--cold 20] [--in-place 20] [--out FILE]

1. Planned moves (AMCL with a standby copy on both scales, as config/icar2015_testbed.yaml
   has it): the WiFi is cut (AMCL's robot copy is activated) and restored (after the hysteresis
   T, its laptop copy is activated), ``--moves`` changes of serving copy in all.
2. Cold moves (the same file with ``standby`` off): the same cuts and restores, each move a
   process started on the other scale, ``--cold`` changes in all.
3. Restarts in place (standby off): AMCL's serving copy SIGKILLed, restarted by its agent,
   ``--in-place`` times.
(Failovers to a standby copy: bench/bench_failover.py --state.)

    python bench/bench_state.py --cost [--seconds 60]

What keeping a state costs each agent, on loopback (no root): two scales of this machine, a
worker whose output is a pose at AMCL's 5 Hz (bench_failover.py's deployment), once without and
once with ``state:`` declared; each agent's CPU (its own process, % of one core) over
``--seconds`` after the layout has settled, and the state messages each agent's reader
receives (bytes/s of serialised payload, counted by a reader of this bench with the same QoS:
what DDS delivers to each reading participant; on a real link add RTPS and UDP headers, about
90 bytes a message).

For each change: whether the first pose of the copy that took over continued the last one (a
jump larger than the robot could have moved between the two stamps, testbed/poses.py, is a
change that did not), and the age of the state each agent handed over (from its log). Runs with
the decider's hysteresis T set to --hysteresis (8 s) so that forty moves take minutes.
"""

import argparse
import json
import os
import re
import signal
import statistics
import sys
import tempfile

import yaml

from anyscale_manager.testbed import harness, netns
from anyscale_manager.testbed.poses import pose_jumps, pose_speed

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from bench_failover import stats  # noqa: E402  (one p50/p95/max for the benches)
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')
HANDED = re.compile(r'\[(\d+\.\d+)\] \[[^]]+\]: amcl: state of (\d+\.\d+) s ago handed')
NO_STATE = 'amcl: no state heard yet'


def without_standby(folder):
    """The test-bed's file with AMCL's standby copies off: every move is a cold start."""
    with open(CONFIG) as f:
        data = yaml.safe_load(f)
    data['/**']['ros__parameters']['nodes']['amcl']['standby'] = False
    path = os.path.join(folder, 'icar2015_testbed_cold.yaml')
    with open(path, 'w') as f:
        yaml.safe_dump(data, f)
    return path


def serving_on(scale):
    return lambda r: r.where('amcl') == (scale,) and bool(r.running_on(scale, ready_only=True)
                                                           .get('amcl'))


class Run:
    """One test-bed and its changes of serving copy: (kind, time of the change)."""

    def __init__(self, path, domain_id, hysteresis_s):
        options = harness.Options(path, domain_id, mode='netns',
                                  decider_parameters={'decider.hysteresis_s': str(hysteresis_s)},
                                  link_up_at_start=False)
        self.tb = harness.Testbed(options).start()
        self.speed = pose_speed(self.tb.deployment.node('amcl').launch.arguments)
        self.changes = []
        self.hysteresis_s = hysteresis_s

    def settle(self, scale, timeout_s):
        self.tb.wait_for(serving_on(scale), timeout_s, f'AMCL serving on {scale} only')
        self.tb.sleep(2.0)                      # poses of the new copy, before the next change

    def moves(self, count, kind):
        tb = self.tb
        tb.restore()
        tb.throttle(netns.DEFAULT_RATE_KBPS)
        self.settle('laptop', 90.0)
        while len([c for c in self.changes if c[0] == kind]) < count:
            tb.sleep(self.hysteresis_s / 2)
            t = tb.now()
            tb.cut()
            self.settle('robot', 30.0)
            self.changes.append((kind, t, 'laptop -> robot'))
            print(f'{kind} {len(self.changes)}: laptop -> robot', flush=True)
            t = tb.now()
            tb.restore()
            self.settle('laptop', self.hysteresis_s + 60.0)
            self.changes.append((kind, t, 'robot -> laptop'))
            print(f'{kind} {len(self.changes)}: robot -> laptop', flush=True)

    def restarts(self, count):
        tb = self.tb
        for k in range(count):
            where = tb.record.where('amcl')
            scale = where[0] if where else 'robot'
            tb.sleep(4.0)                       # a healthy run: each crash is a first one
            t = tb.now()
            with tb.lock:
                old = tb.record.running_on(scale)['amcl'].pid
            if old not in tb.node_pids('amcl', scale):
                raise RuntimeError(f'pid {old} reported for AMCL on {scale} is not its process')
            os.kill(old, signal.SIGKILL)
            tb.mark(f'amcl on {scale} (pid {old}) sent SIGKILL')
            tb.wait_for(lambda r: serving_on(scale)(r)
                        and r.running_on(scale)['amcl'].pid != old, 30.0,
                        'AMCL restarted in place')
            tb.sleep(2.0)
            self.changes.append(('in place', t, f'on {scale}'))
            print(f'in place {k + 1}: on {scale}', flush=True)

    def judge(self):
        """(kind, change, jumped, age handed over or None, state period) for each change, and
        every handed state's age, and the copies started with no state heard."""
        tb = self.tb
        tb.wait_heard(tb.now())
        with tb.lock:
            heard = list(tb.record.poses.get('/amcl_pose', []))
            offset = tb.record.wall_offset
        handed, fresh = [], 0            # (monotonic time of the hand-over, age)
        for scale in ('robot', 'laptop'):
            log = os.path.join(tb.run_dir, 'logs', f'agent_{scale}.log')
            with open(log, errors='replace') as f:
                text = f.read()
            handed += [(float(m.group(1)) - offset, float(m.group(2)))
                       for m in HANDED.finditer(text)]
            fresh += text.count(NO_STATE)
        out = []
        for kind, t, what in self.changes:
            jumps = pose_jumps(heard, t - 1.0, t + 15.0, self.speed)
            ages = [age for at, age in handed if t <= at <= t + 15.0]
            before = sorted(a for a, *_ in heard if t - 5.0 <= a <= t)
            period = statistics.median([b - a for a, b in zip(before, before[1:])]) \
                if len(before) > 2 else float('nan')
            out.append((kind, what, [str(j) for j in jumps], ages[0] if ages else None,
                        period))
        return out, [age for _, age in handed], fresh

    def stop(self):
        return self.tb.stop()


def cost(seconds: float, domain_id: int) -> int:
    """The --cost measurement (see the module)."""
    import subprocess
    import time

    import psutil
    import bench_failover as bf
    os.environ.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    from anyscale_manager import config_files
    os.environ.update(config_files.with_discovery_profile(os.environ))
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from anyscale_manager.agent.procs import stop_popen
    from anyscale_manager.nodes.state_relay import READER_QOS
    rclpy.init()
    node = rclpy.create_node('bench_state_cost')
    rows = {}
    try:
        for state in (False, True):
            with tempfile.TemporaryDirectory() as folder:
                topic = f'/bench_state_{os.getpid()}_{int(state)}'
                path = bf.deployment(folder, topic, 5.0, state=True)
                if not state:
                    with open(path) as f:
                        data = yaml.safe_load(f)
                    del data['/**']['ros__parameters']['nodes']['worker']['state']
                    with open(path, 'w') as f:
                        yaml.safe_dump(data, f)
                sizes = []
                sub = node.create_subscription(PoseWithCovarianceStamped, topic + '/w',
                                               lambda raw: sizes.append(len(raw)), READER_QOS,
                                               raw=True)
                procs = [subprocess.Popen([os.path.join(bf.BIN, exe), '--ros-args',
                                           '--params-file', path, *extra],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                                          start_new_session=True)
                         for exe, extra in (('agent', ('-p', 'scale:=home')),
                                            ('agent', ('-p', 'scale:=away')), ('decider', ()))]
                try:
                    end = time.monotonic() + 20.0           # the worker moves out, settles
                    while time.monotonic() < end:
                        rclpy.spin_once(node, timeout_sec=0.1)
                    agents = [psutil.Process(p.pid) for p in procs[:2]]
                    before = [sum(a.cpu_times()[:2]) for a in agents]
                    del sizes[:]
                    t0 = time.monotonic()
                    while time.monotonic() < t0 + seconds:
                        rclpy.spin_once(node, timeout_sec=0.1)
                    took = time.monotonic() - t0
                    used = [sum(a.cpu_times()[:2]) - b for a, b in zip(agents, before)]
                    rows[state] = ([100.0 * u / took for u in used], sum(sizes) / took,
                                   len(sizes) / took)
                finally:
                    for p in reversed(procs):
                        stop_popen(p, 5.0, 5.0)
                    node.destroy_subscription(sub)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    for state, (cpu, rate_bytes, rate_msgs) in rows.items():
        print(f'{"with" if state else "without"} state: agent home {cpu[0]:.2f} %, agent away '
              f'{cpu[1]:.2f} % of one core over {seconds:g} s; the state topic carries '
              f'{rate_msgs:.1f} messages/s, {rate_bytes:.0f} B/s of payload to each reader')
    (home0, away0), (home1, away1) = rows[False][0], rows[True][0]
    print(f'keeping the state costs: agent home {home1 - home0:+.2f} %, agent away '
          f'{away1 - away0:+.2f} % of one core; {rows[True][1] * 8 / 1000:.1f} kbit/s of '
          'payload into each agent that reads it from across a link')
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--moves', type=int, default=40)
    ap.add_argument('--cold', type=int, default=20)
    ap.add_argument('--in-place', type=int, default=20)
    ap.add_argument('--hysteresis', type=float, default=8.0)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '61')))
    ap.add_argument('--out', help='write the figures as JSON here')
    ap.add_argument('--cost', action='store_true', help='measure what keeping a state costs')
    ap.add_argument('--seconds', type=float, default=60.0)
    args = ap.parse_args()
    if args.cost:
        return cost(args.seconds, args.domain_id)
    ok, why = netns.available()
    if not ok:
        print(f'bench_state: needs the test-bed: {why}', file=sys.stderr)
        return 2
    results, ages, fresh = [], [], 0
    with tempfile.TemporaryDirectory() as folder:
        for path, phases in ((CONFIG, ('moves',)),
                             (without_standby(folder), ('cold', 'in place'))):
            wanted = {'moves': args.moves, 'cold': args.cold, 'in place': args.in_place}
            if not any(wanted[p] for p in phases):
                continue
            run = Run(path, args.domain_id, args.hysteresis)
            try:
                for phase in phases:
                    if phase == 'in place':
                        run.restarts(args.in_place)
                    elif wanted[phase]:
                        run.moves(wanted[phase], phase)
                found, handed, none = run.judge()
                results += found
                ages += handed
                fresh += none
                for kind in phases:
                    rows = [f for f in found if f[0] == kind]
                    print(f'{kind}: {sum(bool(f[2]) for f in rows)} of {len(rows)} changes did '
                          f'not continue the last pose', flush=True)
                    for what in sorted({f[1] for f in rows}):
                        aged = [(f[3], f[4]) for f in rows if f[1] == what and f[3] is not None]
                        within = sum(1 for age, period in aged if age <= period + 0.05)
                        print(f'  {what}: state age when handed over '
                              f'{stats([a for a, _ in aged])}; within one state period '
                              f'(median {stats([p for _, p in aged])}) + 50 ms: '
                              f'{within} of {len(aged)}', flush=True)
            finally:
                notes = run.stop()
                if notes:
                    print(f'teardown: {notes}', flush=True)
    by_kind = {}
    for kind, what, jumps, _, _ in results:
        n, bad = by_kind.get(kind, (0, 0))
        by_kind[kind] = (n + 1, bad + bool(jumps))
        if jumps:
            print(f'{kind} {what}: the pose jumped: {jumps}', flush=True)
    for kind, (n, bad) in by_kind.items():
        print(f'{kind}: changes of serving copy whose first pose did not continue the last: '
              f'{bad} of {n}')
    print(f'state handed over: age {stats(ages)}; copies started with no state heard: {fresh}')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump({'changes': {k: {'n': n, 'not_continued': b}
                                   for k, (n, b) in by_kind.items()},
                       'ages_s': ages, 'no_state': fresh}, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
