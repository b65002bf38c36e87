#!/usr/bin/env python3
"""The manager's own CPU on a test-bed's robot, settled (needs root).

    sudo python bench/bench_testbed_footprint.py [--config FILE] [--on laptop]
        [--window 60] [--settle 10] [--master] [--discovery server] [--default-rates]
        [--domain-id N] [--out FILE]

The test-bed of ``--config`` (default the ICAR one) in namespaces, the robot under its CPU
quota. Once AMCL and AR serve on ``--on`` and ``--settle`` seconds more have passed, the CPU
every process of the robot's cgroup spends over ``--window`` seconds (/proc, user + system),
by process: the manager's (its agent, its decider, its warden) in % of one core of this machine
and of the robot's quota, beside its nodes; and the manager's by thread (the Python threads by
their names, the DDS middleware's and the executor's by theirs), each split into user and
system time: the system time of a send on the test-bed's veth link carries the receiving end's
kernel work as well (this kernel charges a softirq to the task it interrupts), which a real
radio's driver does not. ``--master``: the robot runs the agent and the decider as one process
(`ros2 run anyscale_manager master`). ``--discovery server``: the deployment's discovery through
the scales' discovery servers, on links without multicast. ``--default-rates``: the file's own
rates of the decider's turn and the monitors (``RATE_KEYS``) left out, so that the package's
defaults apply (a copy of the file without them, for this run).
"""

import argparse
import json
import os
import sys
import tempfile
import time
from typing import Dict, Tuple

import psutil
import yaml

from anyscale_manager.agent.catalogue import ENV_NODE
from anyscale_manager.testbed import harness, netns

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')
MOVING = {'amcl', 'ar'}
MANAGER = ('agent', 'decider', 'master', 'warden')
# What --default-rates leaves out of the file: (section, key).
RATE_KEYS = (('decider', 'period_s'), ('monitoring', 'scale_rate_hz'),
             ('monitoring', 'heartbeat_rate_hz'), ('monitoring', 'probe_publish_rate_hz'))


def without_rates(path: str, into: str) -> str:
    """A copy of deployment file ``path`` in directory ``into`` without RATE_KEYS; its
    path."""
    with open(path) as f:
        data = yaml.safe_load(f)
    params = next(iter(data.values()))['ros__parameters']
    for section, key in RATE_KEYS:
        params.get(section, {}).pop(key, None)
    out = os.path.join(into, os.path.basename(path))
    with open(out, 'w') as f:
        yaml.safe_dump(data, f, sort_keys=False)
    return out


def who(p: psutil.Process) -> str:
    """A node by its catalogue name; the manager's processes by their module."""
    node = p.environ().get(ENV_NODE)
    if node:
        return node
    line = ' '.join(p.cmdline())
    for name in ('warden', 'master', 'decider', 'agent'):
        if f'anyscale_manager.nodes.{name}' in line or f'agent.{name}' in line:
            return name
    return os.path.basename(p.cmdline()[0]) if p.cmdline() else str(p.pid)


Times = Tuple[str, float, float]     # who, user CPU seconds, system CPU seconds


def robot_cpu(tb: harness.Testbed) -> Dict[object, Times]:
    """pid -> (who, user, system CPU seconds) of every process in the robot's cgroup; and of
    each thread of the manager's processes, under (pid, tid) -> ('process/thread name', user,
    system)."""
    out: Dict[object, Times] = {}
    for pid in tb.network.groups['robot'].pids():
        try:
            p = psutil.Process(pid)
            t = p.cpu_times()
            name = who(p)
            out[pid] = (name, t.user, t.system)
            if name in MANAGER:
                out.update(thread_cpu(pid, name))
        except psutil.Error:
            pass
    return out


def thread_cpu(pid: int, process: str) -> Dict[Tuple[int, int], Times]:
    """(pid, tid) -> ('process/thread', user, system CPU seconds), from
    /proc/PID/task/TID/stat."""
    tick = os.sysconf('SC_CLK_TCK')
    out = {}
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as f:
                stat = f.read()
        except OSError:
            continue
        comm = stat[stat.index('(') + 1:stat.rindex(')')]
        fields = stat[stat.rindex(')') + 2:].split()
        # a thread pool's numbered names counted as one
        out[(pid, int(tid))] = (f'{process}/{comm.rstrip("0123456789-")}',
                                int(fields[11]) / tick, int(fields[12]) / tick)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--config', default=CONFIG)
    ap.add_argument('--on', default='laptop', help='where AMCL and AR serve when measured')
    ap.add_argument('--window', type=float, default=60.0)
    ap.add_argument('--settle', type=float, default=10.0)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 44)))
    ap.add_argument('--master', action='store_true',
                    help='the robot runs `master` (agent and decider in one process)')
    ap.add_argument('--discovery', choices=('multicast', harness.SERVER), default='multicast',
                    help="the deployment's discovery.mode")
    ap.add_argument('--default-rates', action='store_true',
                    help="the package's default rates for the decider's turn and the monitors")
    ap.add_argument('--out', default='', help='write the figures as JSON')
    args = ap.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_testbed_footprint: no test-bed here: {why}', file=sys.stderr)
        return 2
    if not args.default_rates:
        return measure(args, args.config)
    with tempfile.TemporaryDirectory(prefix='bench-footprint-') as into:
        return measure(args, without_rates(args.config, into))


def measure(args, config: str) -> int:
    """The run of ``main``'s arguments on deployment file ``config``."""
    options = harness.Options(config, args.domain_id, mode='netns',
                              master_process=args.master, discovery=args.discovery)
    tb = harness.Testbed(options).start()
    try:
        tb.wait_for(lambda r: set(r.running_on(args.on, ready_only=True)) >= MOVING, 120.0,
                    f'AMCL and AR serving on {args.on}')
        end = time.monotonic() + args.settle
        while time.monotonic() < end:
            time.sleep(0.2)
        t0, before = time.monotonic(), robot_cpu(tb)
        end = t0 + args.window
        while time.monotonic() < end:
            time.sleep(0.5)
        t1, after = time.monotonic(), robot_cpu(tb)
        quota = tb.cpu_cores['robot']
        by: Dict[str, float] = {}
        threads: Dict[str, float] = {}
        system: Dict[str, float] = {}       # the system part of each, by the same names
        for key, (name, user_s, sys_s) in after.items():
            if key in before:
                into = threads if isinstance(key, tuple) else by
                _, user0, sys0 = before[key]
                into[name] = into.get(name, 0.0) + (user_s + sys_s - user0 - sys0) / (t1 - t0)
                system[name] = system.get(name, 0.0) + (sys_s - sys0) / (t1 - t0)
        manager = sum(v for k, v in by.items() if k in MANAGER)
        manager_sys = sum(v for k, v in system.items() if k in MANAGER)
        print(f'{os.path.basename(args.config)}: AMCL and AR on {args.on}, {args.window:g} s '
              f'after {args.settle:g} s; robot quota {quota:.2f} cores of this machine'
              f'{"; the robot runs master" if args.master else ""}; discovery {args.discovery}'
              f'{"; the default rates" if args.default_rates else ""}')
        print(f'{"process":24s} {"% of a core":>12s} {"% of quota":>11s} {"of it system":>13s}')
        for name, cores in sorted(by.items(), key=lambda kv: -kv[1]):
            print(f'{name:24s} {100 * cores:12.2f} {100 * cores / quota:11.2f} '
                  f'{100 * system[name]:13.2f}')
        print("the manager's processes by thread:")
        for name, cores in sorted(threads.items(), key=lambda kv: -kv[1]):
            if cores > 0:
                print(f'{name:24s} {100 * cores:12.2f} {100 * cores / quota:11.2f} '
                      f'{100 * system[name]:13.2f}')
        print(f'the manager (agent + decider + warden): {100 * manager:.2f} % of one core '
              f'({100 * manager_sys:.2f} system), {100 * manager / quota:.2f} % of the '
              "robot's quota")
        if args.out:
            with open(args.out, 'w') as f:
                json.dump({'quota_cores': quota, 'window_s': args.window,
                           'master': args.master, 'discovery': args.discovery,
                           'default_rates': args.default_rates,
                           'cores_by_process': by, 'cores_by_thread': threads,
                           'system_cores_by_name': system, 'manager_cores': manager,
                           'manager_system_cores': manager_sys}, f, indent=1)
        return 0
    finally:
        notes = tb.stop()
        if notes:
            print(f'teardown: {notes}')


if __name__ == '__main__':
    sys.exit(main())
