#!/usr/bin/env python3
"""DDS discovery alone over one link, per discovery setup and participant count (needs root).

    sudo python bench/bench_discovery.py [--setups multicast,unicast,server,servers]
        [--participants 10,26,50] [--laptop 4] [--per-process 5] [--seconds 20] [--cold 10]
        [--domain-id N]

Two network namespaces joined by the test-bed's shaped link (54 Mbit/s, no CPU quotas; no
manager), for each setup of discovery_setups.py and each count P: P participants on the robot
(idle nodes, ``--per-process`` to a process, each with a publisher and a subscription on
one topic) and ``--laptop`` idle ones on the laptop; the cold-start subscriber is one more.
Prints, for each: when every node saw every other (the ROS graph each holds), the link's
discovery bytes each way over ``--seconds`` once they have (discovery ports,
bench_link_traffic.py's capture), and the time a publisher started cold on the laptop takes to
be matched by the robot's subscriber (``--cold`` starts).
"""

import argparse
import os
import signal
import statistics
import sys
import time
from typing import Dict, List, Optional, Tuple

import bench_link_traffic as link_traffic     # this folder's capture of the link
import discovery_setups

SETTLE_S = 5.0


def run_one(setup: str, robot_count: int, args) -> Dict[str, object]:
    from anyscale_manager.testbed import harness, netns

    netns.remove_stale()
    net = netns.Network(multicast=setup != 'servers').setup()
    procs = []
    folder = f'/tmp/bench_discovery_{os.getpid()}_{setup}_{robot_count}'
    os.makedirs(folder, exist_ok=True)
    master = net.addresses['robot']
    addresses = [master, net.addresses['laptop']]

    def spawn(name: str, scale: str, argv: List[str], env=None):
        log_path = os.path.join(folder, f'{name}.log')
        env = env or discovery_setups.environment(
            setup, harness.child_env(args.domain_id, folder, net.peers(scale)[0]),
            net.peers(scale), master, addresses)
        with open(log_path, 'ab') as log:
            proc = net.popen(scale, argv, env, cpu_quota=False, stdout=log, stderr=log)
        procs.append(proc)
        return proc, log_path

    result: Dict[str, object] = {}
    try:
        if setup == 'server':
            env = discovery_setups.environment(
                setup, harness.child_env(args.domain_id, folder, net.peers('robot')[0]),
                net.peers('robot'), master)
            spawn('discovery_server', 'robot', discovery_setups.server_argv(master),
                  discovery_setups.server_environment(env))
        if setup == 'servers':
            env = discovery_setups.environment(
                setup, harness.child_env(args.domain_id, folder, net.peers('robot')[0]),
                net.peers('robot'), master, addresses)
            for scale, argv in zip(('robot', 'laptop'), discovery_setups.servers_argv(addresses)):
                spawn(f'discovery_server_{scale}', scale, argv,
                      discovery_setups.server_environment(env))
        idle = [sys.executable, os.path.abspath(discovery_setups.__file__), '--role', 'idle']
        holders: List[str] = []
        started = time.monotonic()
        for scale, count in (('robot', robot_count), ('laptop', args.laptop)):
            for first in range(0, count, args.per_process):
                n = min(args.per_process, count - first)
                _, log = spawn(f'idle_{scale}_{first}', scale,
                               idle + ['--count', str(n), '--prefix', f'{scale}_{first}'])
                holders.append(log)
        total = robot_count + args.laptop
        found_at = _wait_seen(holders, total, started, 60.0)
        result['all found s'] = found_at
        result['least seen'] = _least_seen(holders)
        time.sleep(SETTLE_S)
        ways = link_traffic.capture_link(net, args.seconds, args.domain_id)
        result['ways'] = ways
        result['cold'] = discovery_setups.cold_starts(spawn, args.cold) if args.cold else []
        result['least seen after'] = _least_seen(holders)
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=15.0)
            except Exception:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        net.teardown()
    return result


def _least_seen(logs: List[str]) -> Optional[int]:
    """The fewest graph nodes any idle node saw in its last line (itself included)."""
    last = []
    for log in logs:
        lines = [x for x in discovery_setups.read_lines(log) if x.startswith('seen ')]
        if not lines:
            return None
        last.append(int(lines[-1].split()[2]))
    return min(last) if last else None


def _wait_seen(logs: List[str], total: int, since: float, timeout_s: float) -> Optional[float]:
    """Seconds from ``since`` until every idle node saw ``total`` nodes (None: not in time)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        least = _least_seen(logs)
        if least is not None and least >= total:
            return time.monotonic() - since
        time.sleep(0.25)
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--setups', default=','.join(discovery_setups.SETUPS))
    ap.add_argument('--participants', default='10,26,50',
                    help='participants on the robot, comma separated')
    ap.add_argument('--laptop', type=int, default=4, help='idle participants on the laptop')
    ap.add_argument('--per-process', type=int, default=5)
    ap.add_argument('--seconds', type=float, default=20.0)
    ap.add_argument('--cold', type=int, default=10)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '47')))
    args = ap.parse_args()
    setups = args.setups.split(',')
    bad = [s for s in setups if s not in discovery_setups.SETUPS]
    if bad:
        print(f'bench_discovery: unknown setup {bad[0]!r}; one of '
              f'{", ".join(discovery_setups.SETUPS)}', file=sys.stderr)
        return 2
    try:
        counts = [int(p) for p in args.participants.split(',')]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1 or args.laptop < 1 or args.per_process < 1:
        print(f'bench_discovery: --participants takes counts of 1 or more, comma separated, '
              f'and --laptop and --per-process 1 or more (got {args.participants!r}, '
              f'{args.laptop}, {args.per_process})', file=sys.stderr)
        return 2
    rows: List[Tuple[str, int, Dict[str, object]]] = []
    for setup in setups:
        for count in counts:
            result = run_one(setup, count, args)
            rows.append((setup, count, result))
            report(setup, count, result, args)
    print('\nsummary: setup, robot participants, discovery kbit/s robot -> laptop, '
          'laptop -> robot, all found after s, cold p50/max s')
    for setup, count, result in rows:
        ways = result['ways']
        kbps = [ways[w][0]['discovery'] * 8 / args.seconds / 1000 for w in ('out', 'in')]
        cold = sorted(t for t in result['cold'] if t is not None)
        found = result['all found s']
        print(f'  {setup:9} {count:3d}  {kbps[0]:7.0f} {kbps[1]:7.0f}  '
              f'{"never" if found is None else f"{found:.1f}":>6}  '
              + (f'{statistics.median(cold):.2f}/{cold[-1]:.2f} '
                 f'({len(cold)}/{len(result["cold"])})' if cold else '-'))
    return 0


def report(setup: str, count: int, result: Dict[str, object], args) -> None:
    found = result['all found s']
    print(f'\n{setup}: {count} participants on the robot, {args.laptop} on the laptop; every node '
          + (f'saw all {count + args.laptop} after {found:.1f} s' if found is not None else
             f'did not see all {count + args.laptop} in 60 s (fewest seen: '
             f'{result["least seen"]}, later {result["least seen after"]})'), flush=True)
    link_traffic.print_traffic(result['ways'], args.seconds, args.domain_id)
    if result['cold']:
        print("a publisher started cold on the laptop, found by the robot's subscriber: "
              + discovery_setups.describe_cold(result['cold']), flush=True)


if __name__ == '__main__':
    sys.exit(main())
