#!/usr/bin/env python3
"""The link monitor on a real shaped link: bandwidth estimates and how fast a cut shows.

Builds the test-bed's "robot" and "laptop" network namespaces joined by a veth pair shaped with
tbf (anyscale_manager.testbed.netns), runs the master's LinkMonitor in the robot namespace and
the remote's in the laptop namespace (two processes, DDS over UDP on the pair only), then:

* for each shaped rate (5, 20, 54 Mbit/s by default) waits for ``--samples`` fresh active
  bandwidth measurements and reports them against the shaped rate (target: within 20%);
* cuts the link ``--cuts`` times (both ends' qdisc replaced by blackhole) and reports how long
  after each cut the master published ``up: false`` (target: within three heartbeat periods),
  and how long after the restore it was up again.

    sudo python bench/bench_link.py [--rates 5000,20000,54000] [--samples 3] [--cuts 5]
                                    [--interval 2] [--domain 12]

Needs root (namespaces, tc); says plainly why when it cannot run. Everything it creates is
removed on exit, also on error or Ctrl-C.
"""

import argparse
import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time

from anyscale_manager.agent.procs import stop_all

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEPLOYMENT = os.path.join(REPO, 'config', 'icar2015_testbed.yaml')


def child(args) -> int:
    """One side: a node hosting a LinkMonitor; the master prints every LinkStatus it sends."""
    import rclpy
    from std_msgs.msg import String

    from anyscale_manager import protocol as p
    from anyscale_manager.model.loader import load_deployment
    from anyscale_manager.nodes.monitors import STATUS_QOS, LinkMonitor

    d = load_deployment(DEPLOYMENT)
    hosts = {'robot': args.robot, 'laptop': args.laptop}
    d = dataclasses.replace(
        d, scales=tuple(dataclasses.replace(s, host=hosts[s.name]) for s in d.scales),
        monitoring=dataclasses.replace(d.monitoring, bandwidth_probe_interval_s=args.interval))
    rclpy.init()
    node = rclpy.create_node(f'bench_link_{args.role}')
    monitor = LinkMonitor(node, d, args.role)
    if args.role != 'robot':
        # The laptop's warden answers the heartbeats (in a thread here, a process of its own
        # beside a real agent).
        import tempfile
        import threading
        from anyscale_manager.agent import warden
        state = os.path.join(tempfile.mkdtemp(), 'agent.json')
        threading.Thread(target=warden.main, daemon=True, args=([
            '--state', state, '--scale', args.role, '--deployment', d.name, '--host',
            hosts[args.role], '--port', str(warden.warden_port(d, args.role))],)).start()
    if args.role == 'robot':
        node.create_subscription(String, p.TOPIC_LINK_STATUS, lambda m: print(
            f'status {time.monotonic():.6f} {m.data}', flush=True), STATUS_QOS)
    print(f'ready {d.monitoring.heartbeat_rate_hz} {d.monitoring.heartbeat_misses_down}',
          flush=True)
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(True))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.05)
    monitor.destroy()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


class Reader:
    """Collects the master's LinkStatus lines: (its monotonic stamp, decoded dict)."""

    def __init__(self, stream):
        self.items = []
        self.first_line = stream.readline().split()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in stream:
            parts = line.split(' ', 2)
            if len(parts) == 3 and parts[0] == 'status':
                self.items.append((float(parts[1]), json.loads(parts[2])))

    def wait(self, condition, timeout_s, after=0.0):
        deadline = time.monotonic() + timeout_s
        seen = 0
        while time.monotonic() < deadline:
            items = self.items
            for t, s in items[seen:]:
                if t >= after and condition(t, s):
                    return t, s
            seen = len(items)
            time.sleep(0.01)
        return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--rates', default='5000,20000,54000', help='kbit/s, comma separated')
    parser.add_argument('--samples', type=int, default=3)
    parser.add_argument('--cuts', type=int, default=5)
    parser.add_argument('--interval', type=float, default=2.0,
                        help='bandwidth_probe_interval_s for the run (default 2)')
    parser.add_argument('--domain', default=os.environ.get('ROS_DOMAIN_ID', '12'))
    parser.add_argument('--role', choices=('robot', 'laptop'), help=argparse.SUPPRESS)
    parser.add_argument('--robot', help=argparse.SUPPRESS)
    parser.add_argument('--laptop', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role:
        return child(args)

    from anyscale_manager.testbed import netns
    ok, why = netns.available()
    if not ok:
        print(f'bench_link: cannot run: {why}', file=sys.stderr)
        return 2
    rates = [float(r) for r in args.rates.split(',')]
    env = {k: v for k, v in os.environ.items()
           if k in ('PATH', 'HOME', 'LANG', 'PYTHONPATH', 'LD_LIBRARY_PATH', 'VIRTUAL_ENV',
                    'AMENT_PREFIX_PATH', 'RMW_IMPLEMENTATION')}
    env.update(PYTHONUNBUFFERED='1', ROS_DOMAIN_ID=str(args.domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', FASTDDS_BUILTIN_TRANSPORTS='UDPv4')
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    procs = []
    results = {'rates': [], 'cuts': []}
    with netns.Network(rate_kbps=rates[0]) as net:
        try:
            addr = net.addresses
            for scale in ('laptop', 'robot'):
                other = 'robot' if scale == 'laptop' else 'laptop'
                argv = [sys.executable, os.path.abspath(__file__), '--role', scale,
                        '--robot', addr['robot'], '--laptop', addr['laptop'],
                        '--interval', str(args.interval)]
                procs.append(net.popen(scale, argv, dict(env, ROS_STATIC_PEERS=addr[other]),
                                       cpu_quota=False, stdout=subprocess.PIPE,
                                       text=True))
            reader = Reader(procs[-1].stdout)
            heartbeat_hz, misses = float(reader.first_line[1]), int(reader.first_line[2])
            period = 1.0 / heartbeat_hz
            if reader.wait(lambda t, s: s['up'], 30.0) is None:
                print('bench_link: the link never came up (DDS discovery on the pair failed)',
                      file=sys.stderr)
                return 1
            for rate in rates:
                net.throttle(rate)
                since = time.monotonic()
                measured = []
                while len(measured) < args.samples:
                    hit = reader.wait(
                        lambda t, s: (s['bandwidth_available_age_s'] is not None
                                      and t - s['bandwidth_available_age_s'] > since + 0.05
                                      and all(abs((t - s['bandwidth_available_age_s']) - m) > 0.1
                                              for m, _ in measured)),
                        6 * args.interval + 10.0, after=since)
                    if hit is None:
                        break
                    t, s = hit
                    measured.append((t - s['bandwidth_available_age_s'],
                                     s['bandwidth_available_kbps']))
                values = [v for _, v in measured]
                results['rates'].append((rate, values))
            net.throttle(rates[-1])
            for _ in range(args.cuts):
                reader.wait(lambda t, s: s['up'], 20.0, after=time.monotonic())
                time.sleep(1.0 + random.uniform(0.0, period))   # at a random phase of the beats
                cut_at = time.monotonic()
                net.cut()
                down = reader.wait(lambda t, s: not s['up'], 10.0, after=cut_at)
                time.sleep(0.5)
                restored_at = time.monotonic()
                net.restore()
                up = reader.wait(lambda t, s: s['up'], 30.0, after=restored_at)
                results['cuts'].append((None if down is None else down[0] - cut_at,
                                        None if up is None else up[0] - restored_at))
        finally:
            stop_all(procs, 10.0, session=False)
    report(results, period, misses, args)
    return 0


def report(results, period, misses, args) -> None:
    print(f'veth pair shaped with tbf (both directions), heartbeats at {1 / period:g} Hz, '
          f'down after {misses} misses, probe bursts of 0.5 s every {args.interval:g} s')
    print(f'{"shaped kbit/s":>14} {"estimates kbit/s":>32} {"mean":>9} {"error":>7} '
          f'{"within 20%":>10}')
    for rate, values in results['rates']:
        if not values:
            print(f'{rate:14.0f} {"no measurement":>32}')
            continue
        mean = sum(values) / len(values)
        worst = max(abs(v - rate) / rate for v in values)
        print(f'{rate:14.0f} {", ".join(f"{v:.0f}" for v in values):>32} {mean:9.0f} '
              f'{(mean - rate) / rate:+7.1%} {str(worst <= 0.2):>10}')
    downs = [d for d, _ in results['cuts'] if d is not None]
    ups = [u for _, u in results['cuts'] if u is not None]
    print(f'cuts: {len(results["cuts"])}, reported down after '
          f'{", ".join(f"{d:.2f}" for d in downs)} s '
          f'({", ".join(f"{d / period:.1f}" for d in downs)} periods); '
          f'max {max(downs) / period if downs else float("nan"):.2f} periods '
          f'(target <= 3: {bool(downs) and max(downs) <= 3 * period})')
    print(f'up again after restore: {", ".join(f"{u:.2f}" for u in ups)} s')
    missed = sum(1 for d, _ in results['cuts'] if d is None)
    if missed:
        print(f'{missed} cut(s) were never reported down within 10 s')


if __name__ == '__main__':
    sys.exit(main())
