#!/usr/bin/env python3
"""What the robot's CPU does while a remote scale's agent comes back (needs root).

    sudo python bench/bench_rejoin.py [--config FILE] [--scale laptop] [--fallback robot]
        [--rounds 3] [--away-s 12] [--standby-decider] [--domain-id N]

The test-bed of ``--config`` (default the ICAR one) in namespaces. Once AMCL and AR serve on
``--scale``, each round SIGKILLs that scale's agent, waits until both serve on ``--fallback``,
``--away-s`` more, and starts the agent again; until both serve there again (+ 3 s) it prints
the robot's per-process CPU (cores of this machine, from its cgroup, in 0.25 s bins, the four
largest), AMCL's output gaps above 0.5 s as the robot's observer heard them and each
connection's longest stretch below freq_min (the Δ rule). With --standby-decider a second
decider stands by on the robot, as in the chaos soak.
"""

import argparse
import os
import signal
import sys
import threading
import time
from typing import Dict, List, Tuple

import psutil

from anyscale_manager.agent.catalogue import ENV_NODE
from anyscale_manager.testbed import harness, netns

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')
MOVING = {'amcl', 'ar'}
BIN_S = 0.25

Sample = Tuple[float, Dict[int, Tuple[str, float]]]


def robot_processes(tb: harness.Testbed) -> Dict[int, Tuple[str, float]]:
    """pid -> (who, CPU seconds) of every process in the robot's cgroup."""
    out = {}
    for pid in tb.network.groups['robot'].pids():
        try:
            p = psutil.Process(pid)
            who = p.environ().get(ENV_NODE) or ' '.join(p.cmdline()[1:3])[-30:]
            t = p.cpu_times()
            out[pid] = (who, t.user + t.system)
        except psutil.Error:
            pass
    return out


def on(scale: str):
    return lambda r: set(r.running_on(scale, ready_only=True)) >= MOVING


def bins(samples: List[Sample], start: float, end: float) -> List[Tuple[float, list]]:
    s = [x for x in samples if start <= x[0] <= end]
    out = []
    for (t0, a), (t1, b) in zip(s, s[1:]):
        by: Dict[str, float] = {}
        for pid, (who, cpu) in b.items():
            if pid in a:
                by[who] = by.get(who, 0.0) + (cpu - a[pid][1]) / (t1 - t0)
        out.append((t0 - start, sorted(by.items(), key=lambda kv: -kv[1])[:4]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--config', default=CONFIG)
    ap.add_argument('--scale', default='laptop')
    ap.add_argument('--fallback', default='robot',
                    help='where AMCL and AR serve while the agent is away (three scales: laptop)')
    ap.add_argument('--rounds', type=int, default=3)
    ap.add_argument('--away-s', type=float, default=12.0)
    ap.add_argument('--standby-decider', action='store_true')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 44)))
    args = ap.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_rejoin: no test-bed here: {why}', file=sys.stderr)
        return 2
    tb = harness.Testbed(harness.Options(args.config, args.domain_id, mode='netns')).start()
    samples: List[Sample] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            samples.append((tb.now(), robot_processes(tb)))
            stop.wait(BIN_S)
    try:
        if args.standby_decider:
            tb.start_decider('decider_standby')
        tb.wait_for(on(args.scale), 90.0, f'AMCL and AR serving on {args.scale}')
        threading.Thread(target=sample, daemon=True).start()
        for n in range(args.rounds):
            tb.kill(f'agent_{args.scale}', signal.SIGKILL)
            tb.wait_for(on(args.fallback), 40.0, f'AMCL and AR serving on {args.fallback}')
            home = tb.now()
            while tb.now() < home + args.away_s:
                time.sleep(0.2)
            t = tb.now()
            tb.start_agent(args.scale)
            tb.wait_for(on(args.scale), 60.0, f'AMCL and AR back on {args.scale}')
            end = tb.now() + 3.0
            while tb.now() < end:
                time.sleep(0.2)
            tb.wait_heard(end)
            with tb.lock:
                heard = [a for a in tb.views['robot'].arrivals.get('/amcl_pose', [])
                         if t <= a <= end]
                below = tb.views['robot'].longest_below(t, end, 'robot')
            gaps = [(round(a - t, 2), round(b - a, 2)) for a, b in zip(heard, heard[1:])
                    if b - a > 0.5]
            print(f'round {n}: longest below freq_min {below}\n'
                  f'  AMCL output gaps > 0.5 s (s after the start, gap): {gaps}\n'
                  f'  robot CPU by process, 0-3 s after the start (s, [(who, cores)]):')
            for at, top in bins(samples, t, t + 3.0):
                print(f'    {at:5.2f} ' + ', '.join(f'{w} {c:.2f}' for w, c in top))
        return 0
    finally:
        stop.set()
        notes = tb.stop()
        if notes:
            print(f'teardown: {notes}')


if __name__ == '__main__':
    sys.exit(main())
