#!/usr/bin/env python3
"""The DDS discovery setups the link benches compare, and the cold-start probe they time.

Setups (``SETUPS``), for processes in the test-bed's namespaces:

- ``multicast``: ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, ROS_STATIC_PEERS = the neighbours: every
  participant announces to the discovery multicast group and to the first four participant
  ports of each peer (Fast DDS's maxInitialPeersRange), and rmw_fastrtps adds the multicast
  group as a peer of its own.
- ``unicast``: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, ROS_STATIC_PEERS = the neighbours:
  nothing multicast; rmw_fastrtps announces to 32 participant ports of each peer and of
  127.0.0.1 (its maxInitialPeersRange), so two participants past the 32nd of their hosts
  never meet, and it adds shared memory whatever FASTDDS_BUILTIN_TRANSPORTS says.
- ``server``: a Fast DDS discovery server on the master (``server_argv``), every process its
  client (ROS_DISCOVERY_SERVER): a participant announces itself to the server only, which
  hands each client the participants and matching endpoints it needs.
- ``servers``: the package's own (``discovery.mode: server``): a server on each scale
  (``servers_argv``: server i on scale i's address, port SERVER_PORT + i), every process a
  client of both with the package's profile for them (config/fastdds_discovery_server.xml),
  and the link carries no multicast.

Each with the packaged discovery profile (config/fastdds_discovery.xml) unless the caller's
environment names one.

The probe, run by the benches in a namespace (``--role``):

    python bench/discovery_setups.py --role subscriber   # prints 'matched T N' per change
    python bench/discovery_setups.py --role publisher    # prints 'created T publishing T2',
                                                         # holds, exits
    python bench/discovery_setups.py --role idle --count N --prefix P
        # N idle nodes, each its own context (its own DDS participant, as a process has one),
        # with a publisher and a subscription on one topic; prints 'seen T LEAST' every 0.5 s,
        # LEAST the fewest nodes of the graph any of them sees (itself included)

``T`` is time.monotonic(), one clock for every namespace of this machine: a publisher started
cold on one scale is found by the subscriber on another ``matched T - created T`` after its
node (and with it its DDS participant) was created.
"""

import argparse
import os
import signal
import statistics
import subprocess
import sys
import time
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from anyscale_manager.agent.discovery import server_command, server_environment  # noqa: F401

SETUPS = ('multicast', 'unicast', 'server', 'servers')
SERVER_PORT = 11811
COLD_TOPIC = '/discovery_cold'


def environment(setup: str, base: Mapping[str, str], peers: Sequence[str],
                master_address: str, addresses: Sequence[str] = ()) -> Dict[str, str]:
    """``base`` (a test-bed process's environment) with ``setup``'s discovery; ``addresses``:
    every scale's, the master's first (``servers``)."""
    env = {k: v for k, v in base.items()
           if k not in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS',
                        'ROS_DISCOVERY_SERVER')}
    env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    if setup == 'multicast':
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', ROS_STATIC_PEERS=';'.join(peers))
    elif setup == 'unicast':
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_STATIC_PEERS=';'.join(peers))
    elif setup == 'server':
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET',
                   ROS_DISCOVERY_SERVER=f'{master_address}:{SERVER_PORT}')
    elif setup == 'servers':
        from anyscale_manager import config_files
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', ROS_DISCOVERY_SERVER=';'.join(
            f'{a}:{SERVER_PORT + i}' for i, a in enumerate(addresses)))
        env.update(config_files.with_server_profile(env))    # the package's, as it sets it
    else:
        raise ValueError(f'unknown discovery setup {setup!r}; one of {", ".join(SETUPS)}')
    return env


def server_argv(address: str) -> List[str]:
    """The Fast DDS discovery server (server 0 of ROS_DISCOVERY_SERVER) on ``address``."""
    return servers_argv([address])[0]


def servers_argv(addresses: Sequence[str]) -> List[List[str]]:
    """The servers of the ``server`` and ``servers`` setups, one per address: server i on the
    i-th (the package's server command, as a warden finds it)."""
    command = server_command('', os.environ)
    return [command + ['-i', str(i), '-l', a, '-p', str(SERVER_PORT + i)]
            for i, a in enumerate(addresses)]


def read_lines(path: str) -> List[str]:
    try:
        with open(path, errors='replace') as f:
            return f.read().splitlines()
    except OSError:
        return []


Spawn = Callable[[str, str, List[str]], Tuple[subprocess.Popen, str]]


def cold_starts(spawn: Spawn, count: int, timeout_s: float = 15.0) -> List[Optional[float]]:
    """``count`` times: a publisher started cold on the laptop; the seconds from its node's
    creation until a subscriber on the robot matches it (None: not within ``timeout_s``).
    ``spawn(name, scale, argv)`` starts a process there and returns it with its log's path."""
    probe = [sys.executable, os.path.abspath(__file__)]
    sub, sub_log = spawn('cold_subscriber', 'robot', probe + ['--role', 'subscriber'])
    times: List[Optional[float]] = []
    try:
        _wait(lambda: any(x.startswith('ready') for x in read_lines(sub_log)), 30.0)
        for i in range(count):
            seen = len(read_lines(sub_log))
            pub, pub_log = spawn(f'cold_publisher_{i}', 'laptop', probe + ['--role', 'publisher'])
            created = found = None

            def heard() -> bool:
                nonlocal created, found
                created = created or next((float(x.split()[1]) for x in read_lines(pub_log)
                                           if x.startswith('created ')), None)
                found = next((float(x.split()[1]) for x in read_lines(sub_log)[seen:]
                              if x.startswith('matched ') and int(x.split()[2]) > 0), None)
                return found is not None
            _wait(heard, timeout_s)
            times.append(None if created is None or found is None else found - created)
            pub.wait(timeout=30.0)
            # The next start is cold again only once the robot has let this one go.
            _wait(lambda: any(x.startswith('matched ') and x.split()[2] == '0'
                              for x in read_lines(sub_log)[seen:]), 10.0)
    finally:
        sub.send_signal(signal.SIGINT)
        sub.wait(timeout=10.0)
    return times


def describe_cold(times: Sequence[Optional[float]]) -> str:
    found = sorted(t for t in times if t is not None)
    if not found:
        return f'none of {len(times)} found'
    text = (f'p50 {statistics.median(found):.2f} s, max {found[-1]:.2f} s '
            f'({len(found)} of {len(times)} found)')
    return text + ': ' + ' '.join(f'{t:.2f}' if t is not None else '-' for t in times)


def _wait(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _say(text: str) -> None:
    sys.stdout.write(text + '\n')
    sys.stdout.flush()


def subscriber() -> int:
    import rclpy
    from rclpy.event_handler import SubscriptionEventCallbacks
    from rclpy.executors import ExternalShutdownException
    from std_msgs.msg import Empty

    rclpy.init()
    node = rclpy.create_node('discovery_cold_subscriber')
    callbacks = SubscriptionEventCallbacks(
        matched=lambda info: _say(f'matched {time.monotonic():.4f} {info.current_count}'))
    node.create_subscription(Empty, COLD_TOPIC, lambda _m: None, 10,
                             event_callbacks=callbacks)
    _say(f'ready {time.monotonic():.4f}')
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def publisher(hold_s: float) -> int:
    import rclpy
    from std_msgs.msg import Empty

    rclpy.init()
    created = time.monotonic()
    node = rclpy.create_node('discovery_cold_publisher')
    node.create_publisher(Empty, COLD_TOPIC, 10)
    _say(f'created {created:.4f} publishing {time.monotonic():.4f}')
    try:
        time.sleep(hold_s)
    except KeyboardInterrupt:
        pass
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def idle(count: int, prefix: str) -> int:
    import rclpy
    from rclpy.context import Context
    from std_msgs.msg import Empty

    pairs = []
    try:
        for i in range(count):
            context = Context()
            rclpy.init(context=context)
            node = rclpy.create_node(f'{prefix}_{i}', context=context)
            node.create_publisher(Empty, '/discovery_idle', 10)
            node.create_subscription(Empty, '/discovery_idle', lambda _m: None, 10)
            pairs.append((context, node))
        while True:
            least = min(len(node.get_node_names()) for _, node in pairs)
            _say(f'seen {time.monotonic():.4f} {least}')
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        for context, node in pairs:
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--role', choices=('subscriber', 'publisher', 'idle'), required=True)
    ap.add_argument('--hold', type=float, default=2.0, help="the publisher's life, s")
    ap.add_argument('--count', type=int, default=1, help='idle: how many nodes')
    ap.add_argument('--prefix', default='idle', help="idle: the nodes' name prefix")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    if args.role == 'subscriber':
        return subscriber()
    if args.role == 'idle':
        return idle(args.count, args.prefix)
    return publisher(args.hold)


if __name__ == '__main__':
    sys.exit(main())
