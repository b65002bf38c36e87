#!/usr/bin/env python3
"""Whether a scale's CPU quota is what its processes get on a busy machine (needs root).

    sudo python bench/bench_quota_share.py [--cores 0.6] [--seconds 8] [--loads 0,2,4]
                                           [--weights 1,8] [--busy 1] [--one-cpu]
                                           [--light 0] [--ticker-nice 0] [--realtime]

The test-bed caps the robot's cgroup at ``--cores`` (its quota) on a machine it shares with the
laptop's cgroup, the observers and the harness. A cgroup is one entity against every other
process of the machine: with CFS's default weights, when those want more than the machine has,
the group gets its fair share of what is left, which can be less than its quota; a real robot's
computer is its own. For each number of busy processes outside the group (``--loads``) and each
weight of the group (``--weights``, times the default), the group runs what saturates it (a busy
processes at nice 5, ``--busy`` of them, as ``agent.node_nice`` starts the heavy nodes) beside a
40 Hz ticker at nice 0 (the robot's odometer: a Δ 0 connection), and the bench prints the cores
the group got and the ticker's longest interval (its Δ 0 connection at 10 Hz plus the judge's
allowance reads below after 0.19 s). ``--one-cpu``: the group's processes run on CPU 0 only
(its quota then comes from one runqueue). ``--light N`` adds N light processes at nice 0 that
wake at 20 Hz for a little work (the robot's other nodes and the manager); ``--ticker-nice``
sets the ticker's niceness, ``--realtime`` runs it at real-time priority 5 instead (what
``agent.critical_priority`` does for a critical node).
"""

import argparse
import json
import os
import subprocess
import sys
import time

from anyscale_manager.testbed import netns

BUSY = 'while True:\n    pass\n'
LIGHT = 'import time\nwhile True:\n    time.sleep(0.05)\n    sum(range(20000))\n'
TICKER = '''
import json, sys, time
period, end = 0.025, time.monotonic() + float(sys.argv[1])
last = time.monotonic()
gaps = []
while last < end:
    time.sleep(max(0.0, period - (time.monotonic() - last)))
    now = time.monotonic()
    gaps.append(now - last)
    last = now
gaps.sort()
print(json.dumps({'max': gaps[-1], 'p99': gaps[int(len(gaps) * 0.99)], 'n': len(gaps)}))
'''


def one_case(cores: float, weight: float, load: int, seconds: float, busy: int = 1,
             one_cpu: bool = False, busy_nice: int = 5, light: int = 0,
             ticker_prefix: tuple = ()) -> dict:
    group = netns.CpuGroup(f'{netns.NAME_PREFIX}-share-{os.getpid()}')
    procs = []
    try:
        group.set_cores(cores)
        if weight != 1.0:
            group.set_weight(weight)
        outside = [subprocess.Popen([sys.executable, '-c', BUSY]) for _ in range(load)]
        procs += outside
        inside = []
        for _ in range(busy):
            heavy = subprocess.Popen(['nice', '-n', str(busy_nice), sys.executable, '-c', BUSY])
            procs.append(heavy)
            inside.append(heavy.pid)
        for _ in range(light):
            other = subprocess.Popen([sys.executable, '-c', LIGHT])
            procs.append(other)
            inside.append(other.pid)
        ticker = subprocess.Popen([*ticker_prefix, sys.executable, '-c', TICKER,
                                   str(seconds + 1.0)],
                                  stdout=subprocess.PIPE, text=True)
        procs.append(ticker)
        inside.append(ticker.pid)
        for pid in inside:
            group.add(pid)
            if one_cpu:
                os.sched_setaffinity(pid, {0})
        time.sleep(1.0)                     # the ticker's start-up is not measured
        used0, t0 = group.usage_s(), time.monotonic()
        out, _ = ticker.communicate(timeout=seconds + 30.0)
        used1, t1 = group.usage_s(), time.monotonic()
        row = json.loads(out)
        got = None if used0 is None or used1 is None else (used1 - used0) / (t1 - t0)
        return {'load': load, 'weight': weight, 'cores_got': got,
                'ticker_max_s': row['max'], 'ticker_p99_s': row['p99']}
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        group.remove()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--cores', type=float, default=0.6)
    parser.add_argument('--seconds', type=float, default=8.0)
    parser.add_argument('--loads', default='0,2,4')
    parser.add_argument('--weights', default='1,8')
    parser.add_argument('--busy', type=int, default=1, help='busy processes inside the group')
    parser.add_argument('--one-cpu', action='store_true', help='the group on CPU 0 only')
    parser.add_argument('--busy-nice', type=int, default=5, help='niceness of the busy ones')
    parser.add_argument('--light', type=int, default=0, help='light processes inside at nice 0')
    parser.add_argument('--ticker-nice', type=int, default=0, help="the ticker's niceness")
    parser.add_argument('--realtime', action='store_true',
                        help='the ticker at real-time priority 5 (SCHED_RR)')
    args = parser.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_quota_share: {why}', file=sys.stderr)
        return 2
    ticker_prefix = (('chrt', '-r', '5') if args.realtime
                     else ('nice', '-n', str(args.ticker_nice)))
    loads = [int(x) for x in args.loads.split(',')]
    weights = [float(x) for x in args.weights.split(',')]
    print(f'group quota {args.cores:g} cores{" on CPU 0" if args.one_cpu else ""}, '
          f'{args.busy} busy inside at nice {args.busy_nice}, {args.light} light, ticker '
          f'{"real-time 5" if args.realtime else f"nice {args.ticker_nice}"}, '
          f'{os.cpu_count()} CPUs, '
          f'{args.seconds:g} s a case')
    print(f'{"busy outside":>12} {"weight":>7} {"cores got":>10} {"ticker max":>11} '
          f'{"ticker p99":>11}')
    for load in loads:
        for weight in weights:
            r = one_case(args.cores, weight, load, args.seconds, args.busy, args.one_cpu,
                         args.busy_nice, args.light, ticker_prefix)
            got = '-' if r['cores_got'] is None else f'{r["cores_got"]:.2f}'
            print(f'{load:>12} {weight:>7g} {got:>10} {r["ticker_max_s"]:>10.3f}s '
                  f'{r["ticker_p99_s"]:>10.3f}s', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
