#!/usr/bin/env python3
"""What the test-bed's WiFi carries, by kind, as the robot's end sends it (needs root).

    sudo python bench/bench_link_traffic.py [--seconds 30] [--profile FILE] [--domain-id N]

Starts the ICAR test-bed, waits until AMCL and AR serve from the laptop and the layout has
settled, then counts every IPv4 UDP datagram that leaves the robot's end of the link (after its
qdisc: what the link carried) for ``--seconds``, by destination port: DDS user data (a
participant's data port), DDS discovery (a participant's discovery port, or the discovery
multicast port) and the rest (the warden's heartbeats, the bandwidth probe). An IP fragment
counts with the datagram it belongs to. Prints the kbit/s of each kind, the busiest
destinations, and how many processes on the robot sent discovery (distinct source ports).

``--profile FILE``: every process of the test-bed uses this Fast DDS profile instead of the
packaged config/fastdds_discovery.xml (its participant announcements every 0.25 s).
"""

import argparse
import collections
import os
import socket
import struct
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')
PACKET_OUTGOING = 4
ETH_P_ALL, ETH_P_IP = 0x0003, 0x0800


def capture(interface: str, seconds: float) -> int:
    """In the namespace: print ``time src_port dst_port bytes`` per datagram sent on it."""
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(ETH_P_ALL))
    s.bind((interface, 0))
    s.settimeout(0.2)
    ports = {}          # IP id -> (src, dst) of its first fragment
    end = time.monotonic() + seconds
    out = sys.stdout
    while time.monotonic() < end:
        try:
            data, addr = s.recvfrom(65535)
        except socket.timeout:
            continue
        if addr[2] != PACKET_OUTGOING or addr[1] != ETH_P_IP or len(data) < 34:
            continue
        ip = data[14:]
        if ip[9] != socket.IPPROTO_UDP:
            continue
        ihl = (ip[0] & 15) * 4
        total, ident, flags = struct.unpack('!HHH', ip[2:8])
        if flags & 0x1fff == 0:
            ports[ident] = struct.unpack('!HH', ip[ihl:ihl + 4])
        src, dst = ports.get(ident, (-1, -1))
        out.write(f'{time.monotonic():.4f} {src} {dst} {total}\n')
    out.flush()
    return 0


def kind(port: int, domain: int) -> str:
    base = 7400 + 250 * domain
    offset = port - base
    if offset == 0:
        return 'discovery'                  # the discovery multicast port
    if offset == 1 or (10 <= offset < 250 and offset % 2 == 1):
        return 'user data'
    if 10 <= offset < 250:
        return 'discovery'
    return 'other'


def measure(tb, seconds: float, scale: str = 'robot'):
    """Capture what ``scale``'s end of the test-bed's (first) link sends for ``seconds``:
    (bytes by kind, bytes by destination port, source ports that sent discovery)."""
    net = tb.network
    wire = next(iter(net.wires.values()))
    namespace, interface = net.namespaces[scale], net.interfaces[(wire.name, scale)]
    lines = subprocess.run(['ip', 'netns', 'exec', namespace, sys.executable,
                            os.path.abspath(__file__), '--capture', interface, str(seconds)],
                           check=True, capture_output=True, text=True).stdout.splitlines()
    by_kind, by_port = collections.Counter(), collections.Counter()
    senders = set()
    for line in lines:
        _, src, dst, size = line.split()
        what = kind(int(dst), tb.options.domain_id)
        by_kind[what] += int(size)
        by_port[int(dst)] += int(size)
        if what == 'discovery':
            senders.add(int(src))
    return by_kind, by_port, senders


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == '--capture':
        return capture(sys.argv[2], float(sys.argv[3]))
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=30.0)
    ap.add_argument('--profile', default='', help='a Fast DDS profile for every process')
    ap.add_argument('--config', default=CONFIG)
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '46')))
    args = ap.parse_args()
    if args.profile:
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = os.path.abspath(args.profile)
    from anyscale_manager.testbed import harness

    options = harness.Options(args.config, args.domain_id, mode='netns', link_up_at_start=True)
    tb = harness.Testbed(options).start()
    try:
        on = (lambda node: lambda r: r.where(node) == ('laptop',))
        tb.wait_for(on('amcl'), 120.0, 'amcl on the laptop')
        tb.wait_for(on('ar'), 120.0, 'ar on the laptop')
        tb.wait_for(lambda r: r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), 'robot', 5.0),
                    60.0, 'a settled layout')
        by_kind, by_port, senders = measure(tb, args.seconds)
    finally:
        tb.stop()
    kbps = (lambda n: n * 8 / args.seconds / 1000)
    print(f'robot -> laptop over {args.seconds:g} s with AMCL and AR on the laptop '
          f'(profile: {args.profile or "packaged"}): {kbps(sum(by_kind.values())):.0f} kbit/s')
    for name in ('user data', 'discovery', 'other'):
        print(f'  {name:10} {kbps(by_kind[name]):7.0f} kbit/s')
    print('  busiest destination ports: ' + ', '.join(
        f'{p} ({kind(p, args.domain_id)}) {kbps(n):.0f}' for p, n in by_port.most_common(8)))
    print(f'  processes on the robot sending discovery over the link: {len(senders)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
