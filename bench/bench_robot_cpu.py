#!/usr/bin/env python3
"""Where the test-bed robot's CPU goes, and AMCL's rate on it after cuts (needs root).

    sudo python bench/bench_robot_cpu.py [--cuts 4] [--seconds 10] [--domain-id N]
                                         [--config FILE]

The calibration behind AMCL's ``--work-ms`` (docs/testbed.md): once AMCL and AR run on the
laptop, the CPU of each process in the robot's cgroup over ``--seconds`` (percent of one core of
this machine), then ``--cuts`` times: cut the link, wait until AMCL and AR serve on the robot,
read ``/amcl_pose`` at the robot (the harness's observer) in 2 s windows from 3 to 14 s after
the cut, print the lowest and the mean window, restore the link and wait for both to go out
again. The first cut also prints the robot's per-process CPU with everything on the robot.
"""

import argparse
import os
import sys
import time

import psutil

from anyscale_manager.testbed import harness, netns

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')


def robot_cpu(tb: harness.Testbed, seconds: float, label: str) -> None:
    procs = {}
    for pid in tb.network.groups['robot'].pids():
        try:
            p = psutil.Process(pid)
            t = p.cpu_times()
            procs[pid] = (p, ' '.join(p.cmdline()[1:5])[:70], t.user + t.system)
        except psutil.Error:
            continue
    group0, t0 = tb.network.cpu_usage_s('robot'), time.monotonic()
    tb.sleep(seconds)
    dt = time.monotonic() - t0
    total = 100.0 * (tb.network.cpu_usage_s('robot') - group0) / dt
    print(f'{label}: the robot cgroup {total:.1f} % of one core over {dt:.0f} s')
    rows = []
    for pid, (p, name, c0) in procs.items():
        try:
            t = p.cpu_times()
            rows.append((100.0 * (t.user + t.system - c0) / dt, pid, name))
        except psutil.Error:
            continue
    for share, pid, name in sorted(rows, reverse=True):
        if share >= 0.1:
            print(f'  {share:5.1f} %  {pid}  {name}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=CONFIG)
    parser.add_argument('--cuts', type=int, default=4)
    parser.add_argument('--seconds', type=float, default=10.0)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '47') or 47))
    args = parser.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_robot_cpu: {why}', file=sys.stderr)
        return 2
    tb = harness.Testbed(harness.Options(args.config, args.domain_id, mode='netns')).start()
    try:
        def on(node, scale):
            return lambda r: r.where(node) == (scale,)
        for i in range(args.cuts + 1):
            tb.wait_for(on('amcl', 'laptop'), 120.0, 'amcl on the laptop')
            tb.wait_for(on('ar', 'laptop'), 120.0, 'ar on the laptop')
            if i == 0:
                robot_cpu(tb, args.seconds, 'AMCL and AR on the laptop')
                continue
            tb.sleep(5.0)
            tb.cut()
            t_cut = tb.now()
            tb.wait_for(lambda r: {'amcl', 'ar'} <= set(r.running_on('robot', ready_only=True)),
                        10.0, 'amcl and ar serving on the robot')
            if i == 1:
                robot_cpu(tb, args.seconds, 'cut, all on the robot')
            rates = []
            while tb.now() - t_cut < 14.0:
                tb.sleep(0.5)
                if tb.now() - t_cut > 3.0:
                    with tb.lock:
                        rates.append(tb.record.topic_rate('/amcl_pose', tb.now()))
            print(f'cut {i}: /amcl_pose at the robot, 2 s windows 3-14 s after the cut: '
                  f'lowest {min(rates):.2f} Hz, mean {sum(rates) / len(rates):.2f} Hz',
                  flush=True)
            tb.restore()
    finally:
        notes = tb.stop()
    if notes:
        print('teardown: ' + '; '.join(notes))
    return 0


if __name__ == '__main__':
    sys.exit(main())
