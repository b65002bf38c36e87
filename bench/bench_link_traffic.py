#!/usr/bin/env python3
"""What the test-bed's WiFi carries, by kind, each way, for a DDS discovery setup (needs root).

    sudo python bench/bench_link_traffic.py [--seconds 30] [--discovery SETUP] [--cold N]
                                            [--profile FILE] [--domain-id N]

Starts the ICAR test-bed, waits until AMCL and AR serve from the laptop and the layout has
settled, then counts every IPv4 UDP datagram (and ICMP message) that crosses the robot's end of
the link for ``--seconds``: what the robot sends (after its qdisc: what the link carried) and
what it receives from the laptop, by destination port: DDS user data (a participant's data
port), DDS discovery (a participant's discovery port, the discovery multicast port or the
discovery server's port) and the rest (the warden's heartbeats, the bandwidth probe, ICMP). An
IP fragment counts with the datagram it belongs to. Prints the kbit/s of each kind each way,
the busiest destinations, and how many processes on each end sent discovery (distinct source
ports).

``--discovery SETUP``: how every process of the test-bed discovers (discovery_setups.py):
``multicast`` (the test-bed's own: SUBNET and the neighbour as a static peer), ``unicast``
(LOCALHOST and the neighbour as a static peer: nothing multicast), ``server`` (a Fast DDS
discovery server on the robot, every process its client) or ``servers`` (the package's own
``discovery.mode: server``: each scale's warden runs a server, every process a client of both,
the link carries no multicast; the test-bed's ``Options.discovery``).

``--cold N``: then N times, a publisher started cold on the laptop: the time from its node's
creation until a subscriber on the robot matches it (p50, max).

``--profile FILE``: every process of the test-bed uses this Fast DDS profile instead of the
packaged config/fastdds_discovery.xml (its participant announcements every 0.25 s).
"""

import argparse
import collections
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from typing import Dict, Optional, Tuple

import discovery_setups    # this folder's discovery setups and cold-start probe

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')
PACKET_OUTGOING = 4
ETH_P_ALL, ETH_P_IP = 0x0003, 0x0800
ICMP = -2     # the destination "port" of an ICMP message (a port unreachable, mostly)


def capture(interface: str, seconds: float) -> int:
    """In the namespace: print ``time out|in src_port dst_port bytes`` per datagram that
    crosses the interface (``out``: sent on it, after its qdisc)."""
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(ETH_P_ALL))
    s.bind((interface, 0))
    s.settimeout(0.2)
    ports: Dict[Tuple[str, int], Tuple[int, int]] = {}   # IP id -> (src, dst) of 1st fragment
    end = time.monotonic() + seconds
    out = sys.stdout
    while time.monotonic() < end:
        try:
            data, addr = s.recvfrom(65535)
        except socket.timeout:
            continue
        if addr[1] != ETH_P_IP or len(data) < 34:
            continue
        way = 'out' if addr[2] == PACKET_OUTGOING else 'in'
        ip = data[14:]
        total, ident, flags = struct.unpack('!HHH', ip[2:8])
        if ip[9] == socket.IPPROTO_ICMP:
            out.write(f'{time.monotonic():.4f} {way} {ICMP} {ICMP} {total}\n')
            continue
        if ip[9] != socket.IPPROTO_UDP:
            continue
        ihl = (ip[0] & 15) * 4
        if flags & 0x1fff == 0:
            ports[(way, ident)] = struct.unpack('!HH', ip[ihl:ihl + 4])
        src, dst = ports.get((way, ident), (-1, -1))
        out.write(f'{time.monotonic():.4f} {way} {src} {dst} {total}\n')
    out.flush()
    return 0


def kind(port: int, domain: int) -> str:
    if 0 <= port - discovery_setups.SERVER_PORT < 8:
        return 'discovery'                  # a discovery server's
    base = 7400 + 250 * domain
    offset = port - base
    if offset == 0:
        return 'discovery'                  # the discovery multicast port
    if offset == 1 or (10 <= offset < 250 and offset % 2 == 1):
        return 'user data'
    if 10 <= offset < 250:
        return 'discovery'
    return 'other'


Counts = Tuple[collections.Counter, collections.Counter, set]


def capture_link(net, seconds: float, domain: int, scale: str = 'robot',
                 wire_name: Optional[str] = None) -> Dict[str, Counts]:
    """What crosses ``scale``'s end of a link of ``net`` (a netns.Network; the first link by
    default) in ``seconds``, each way (``out``: sent by ``scale``, ``in``: received): (bytes by
    kind, bytes by destination port, source ports that sent discovery)."""
    wire = net.wires[wire_name] if wire_name else next(iter(net.wires.values()))
    namespace, interface = net.namespaces[scale], net.interfaces[(wire.name, scale)]
    lines = subprocess.run(['ip', 'netns', 'exec', namespace, sys.executable,
                            os.path.abspath(__file__), '--capture', interface, str(seconds)],
                           check=True, capture_output=True, text=True).stdout.splitlines()
    out: Dict[str, Counts] = {w: (collections.Counter(), collections.Counter(), set())
                              for w in ('out', 'in')}
    for line in lines:
        _, way, src, dst, size = line.split()
        by_kind, by_port, senders = out[way]
        what = 'other' if int(dst) == ICMP else kind(int(dst), domain)
        by_kind[what] += int(size)
        by_port[int(dst)] += int(size)
        if what == 'discovery':
            senders.add(int(src))
    return out


def measure(tb, seconds: float, scale: str = 'robot') -> Counts:
    """What ``scale``'s end of the test-bed's (first) link sends for ``seconds``: (bytes by
    kind, bytes by destination port, source ports that sent discovery)."""
    return capture_link(tb.network, seconds, tb.options.domain_id, scale)['out']


def ros_processes(net, scale: str) -> int:
    """The Python processes (each one DDS participant) in ``scale``'s namespace."""
    import psutil

    out = subprocess.run(['ip', 'netns', 'pids', net.namespaces[scale]], capture_output=True,
                         text=True).stdout.split()
    count = 0
    for pid in out:
        try:
            if 'python' in os.path.basename(psutil.Process(int(pid)).exe()):
                count += 1
        except (psutil.Error, ValueError):
            continue
    return count


def testbed_class():
    """The test-bed with its processes discovering as ``setup`` says (and, for ``server``, the
    discovery server started in the robot's namespace before any other process)."""
    from anyscale_manager.testbed import harness

    class Testbed(harness.Testbed):
        def __init__(self, options, setup: str):
            super().__init__(options)
            self.setup = setup
            self.server = None

        def _env(self, scale: str):
            if self.setup == 'servers':
                return super()._env(scale)          # the package's own (Options.discovery)
            net = self.network
            return discovery_setups.environment(self.setup, super()._env(scale),
                                                net.peers(scale), net.addresses['robot'])

        def _start_observer(self, *args, **kwargs):
            if self.setup == 'server' and self.server is None:
                log = open(os.path.join(self.run_dir, 'logs', 'discovery_server.log'), 'ab')
                with log:
                    self.server = self.link_control.popen(
                        'robot', discovery_setups.server_argv(self.network.addresses['robot']),
                        discovery_setups.server_environment(self._env('robot')), True,
                        stdout=log, stderr=log)
            super()._start_observer(*args, **kwargs)

        def stop(self):
            if self.server is not None and self.server.poll() is None:
                self.server.terminate()
                self.server.wait(timeout=10.0)
            return super().stop()

    return Testbed


def print_traffic(ways: Dict[str, Counts], seconds: float, domain: int,
                  names: Tuple[str, str] = ('robot', 'laptop')) -> None:
    kbps = (lambda n: n * 8 / seconds / 1000)
    for way, (a, b) in (('out', names), ('in', names[::-1])):
        by_kind, by_port, senders = ways[way]
        print(f'{a} -> {b}: {kbps(sum(by_kind.values())):.0f} kbit/s')
        for name in ('user data', 'discovery', 'other'):
            print(f'  {name:10} {kbps(by_kind[name]):7.0f} kbit/s')
        print('  busiest destination ports: ' + ', '.join(
            f'{p if p != ICMP else "icmp"} ({kind(p, domain) if p != ICMP else "other"}) '
            f'{kbps(n):.0f}' for p, n in by_port.most_common(8)))
        print(f'  source ports on the {a} sending discovery over the link: {len(senders)}')


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == '--capture':
        return capture(sys.argv[2], float(sys.argv[3]))
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--seconds', type=float, default=30.0)
    ap.add_argument('--discovery', choices=discovery_setups.SETUPS, default='multicast')
    ap.add_argument('--cold', type=int, default=0, metavar='N',
                    help='time N publishers started cold on the laptop')
    ap.add_argument('--profile', default='', help='a Fast DDS profile for every process')
    ap.add_argument('--config', default=CONFIG)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '46')))
    args = ap.parse_args()
    if args.profile:
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = os.path.abspath(args.profile)
    from anyscale_manager.testbed import harness

    # A run folder of its own (the harness's default is a /tmp/anyscale-testbed-* one).
    run_dir = tempfile.mkdtemp(prefix='bench-link-traffic-')
    options = harness.Options(args.config, args.domain_id, mode='netns', link_up_at_start=True,
                              run_dir=run_dir,
                              discovery='server' if args.discovery == 'servers' else 'multicast')
    tb = testbed_class()(options, args.discovery).start()
    try:
        on = (lambda node: lambda r: r.where(node) == ('laptop',))
        ready = tb.wait_for(on('amcl'), 120.0, 'amcl on the laptop')
        tb.wait_for(on('ar'), 120.0, 'ar on the laptop')
        tb.wait_for(lambda r: r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), 'robot', 5.0),
                    60.0, 'a settled layout')
        print(f'AMCL and AR on the laptop {ready - tb.t0:.1f} s after the start', flush=True)
        ways = capture_link(tb.network, args.seconds, args.domain_id)
        counts = {scale: ros_processes(tb.network, scale) for scale in ('robot', 'laptop')}
        print(f'over {args.seconds:g} s with AMCL and AR on the laptop, discovery '
              f'{args.discovery} (profile: {args.profile or "packaged"}):')
        print('ROS processes: ' + ', '.join(f'{n} on the {s}' for s, n in counts.items()))
        print_traffic(ways, args.seconds, args.domain_id)
        import psutil
        servers = [tb.server.pid] if tb.server is not None else []
        for proc in psutil.process_iter(['cmdline']):
            cmd = proc.info['cmdline'] or []
            if cmd and cmd[0].endswith('fast-discovery-server') and any(
                    a in cmd for a in tb.network.addresses.values()):
                servers.append(proc.pid)
        for pid in sorted(set(servers)):
            proc = psutil.Process(pid)
            t = proc.cpu_times()
            print(f'discovery server {" ".join(proc.cmdline()[1:])}: '
                  f'{(t.user + t.system) / (time.monotonic() - tb.t0) * 100:.1f} % of a core '
                  f'since the start, {proc.memory_info().rss / 2 ** 20:.1f} MiB')
        sys.stdout.flush()
        if args.cold:
            def spawn(name, scale, argv):
                proc = tb.start_tool(name, scale, argv)
                return proc.popen, proc.log_path
            cold = discovery_setups.cold_starts(spawn, args.cold)
            print(f'a publisher started cold on the laptop, found by a subscriber on the robot: '
                  f'{discovery_setups.describe_cold(cold)}')
    finally:
        tb.stop()
        shutil.rmtree(run_dir, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
