#!/usr/bin/env python3
"""CPU cost of a raw probe against a deserialising subscriber, on one 1 kHz topic.

Three processes in one run: a publisher (one pre-serialised message sent at 1 kHz, absolute
schedule), a probe process hosting the project's ProbeManager (raw subscription, arrival time
and size only), and a subscriber that deserialises every message and keeps the inter-arrival
gaps the way ``ros2 topic hz`` does. Both subscribers use the same QoS (the probe's: best
effort, depth 100) and the same executor (the events executor the agent spins, or ``--executor
single``); the probe drains its subscription in batches, as the agent's does. After a warm-up,
the CPU time (user + system, psutil) each subscriber process spends over the same interval is
divided by the interval, with the count of messages each received, and the ratio reported.

    python bench/bench_probe_cost.py [--seconds 10] [--rate 1000] [--domain 12]
        [--type image|laserscan|bytes|structured] [--shape SHAPE] [--kbytes 100]

Types: ``image`` (sensor_msgs/Image, the test-bed camera's 176x144 mono8 frame by default;
``--shape 640x480:rgb8`` for another), ``laserscan`` (sensor_msgs/LaserScan, a Hokuyo
URG-04LX's 682 beams; ``--shape BEAMS``), both filled as the test-bed's workload nodes fill
them; ``bytes`` (a flat std_msgs/UInt8MultiArray of ``--kbytes``) and ``structured`` (a
DiagnosticArray of many small nested fields, about ``--kbytes``, where deserialisation is what
costs).
"""

import argparse
import os
import signal
import subprocess
import sys
import time

from anyscale_manager.agent.procs import stop_all

TOPIC = '/bench/cost'
TYPES = {'bytes': 'std_msgs/msg/UInt8MultiArray',
         'structured': 'diagnostic_msgs/msg/DiagnosticArray',
         'image': 'sensor_msgs/msg/Image',
         'laserscan': 'sensor_msgs/msg/LaserScan'}
DEFAULT_SHAPES = {'image': '176x144:mono8', 'laserscan': '682'}


def make_message(kind: str, nbytes: int, shape: str = ''):
    """A message of the kind: an Image or LaserScan as the workload fills it, or one of about
    nbytes serialised: one byte array, or many small nested fields."""
    if kind in DEFAULT_SHAPES:
        from anyscale_manager.nodes.workload_messages import build_message, parse_endpoint
        endpoint = parse_endpoint(f'{TOPIC}:{TYPES[kind]}:{shape or DEFAULT_SHAPES[kind]}',
                                  output=True)
        return build_message(endpoint)
    if kind == 'bytes':
        from std_msgs.msg import UInt8MultiArray
        return UInt8MultiArray(data=bytes(nbytes))
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    status = DiagnosticStatus(name='n' * 8, message='m' * 8, hardware_id='h' * 8,
                              values=[KeyValue(key='k' * 8, value='v' * 8) for _ in range(4)])
    one = 180                                        # about its serialised size
    return DiagnosticArray(status=[status] * max(1, nbytes // one))


def _counter_line(count: int) -> None:
    print(f'count {count}', flush=True)


def publisher(rate: float, nbytes: int, kind: str, shape: str) -> int:
    import rclpy
    from rclpy.serialization import serialize_message
    rclpy.init()
    node = rclpy.create_node('bench_cost_publisher')
    msg = make_message(kind, nbytes, shape)
    pub = node.create_publisher(type(msg), TOPIC, 10)
    raw = serialize_message(msg)
    print(f'size {len(raw)}', flush=True)
    nxt = time.monotonic()
    try:
        while True:
            now = time.monotonic()
            while nxt <= now:
                pub.publish(raw)
                nxt += 1.0 / rate
            time.sleep(max(0.0, nxt - time.monotonic()))
    except KeyboardInterrupt:
        pass
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _make_executor(kind: str):
    from rclpy.executors import SingleThreadedExecutor
    if kind == 'single':
        return SingleThreadedExecutor()
    from anyscale_manager.nodes.executor import make_executor
    return make_executor()


def _spin_reporting(node, count, executor_kind: str) -> None:
    """Spin until SIGINT; print the received count whenever a line arrives on stdin."""
    import select
    executor = _make_executor(executor_kind)
    executor.add_node(node)
    stop = []
    # A flag, not KeyboardInterrupt: an interrupt inside a take would end in a traceback.
    signal.signal(signal.SIGINT, lambda *_: stop.append(True))
    while not stop:
        executor.spin_once(timeout_sec=0.01)
        if select.select([sys.stdin], [], [], 0)[0]:
            sys.stdin.readline()
            _counter_line(count())
    executor.shutdown()


def probe(kind: str, executor_kind: str) -> int:
    import rclpy
    from anyscale_manager.model.types import (Connection, Deployment, Launch, MonitorSettings,
                                              Node, Scale)
    from anyscale_manager.nodes.monitors import ProbeManager
    rclpy.init()
    node = rclpy.create_node('bench_cost_probe')
    deployment = Deployment(
        name='bench', source='bench_probe_cost',
        scales=(Scale('bench', 'master', 'robot', 100.0, 1, 1.0, 1.0, 'localhost'),),
        links=(), nodes=(Node('pub', Launch(), 1.0), Node('sub', Launch(), 1.0)),
        connections=(Connection('cost', TOPIC, 'pub', 'sub', 1.0, freq_min_hz=500.0,
                                tolerance_s=1.0, msg_type=TYPES[kind]),),
        monitoring=MonitorSettings(probe_window_s=2.0, probe_publish_rate_hz=2.0))
    probes = ProbeManager(node, deployment, 'bench')
    probes.set_connections(['cost'])
    window = probes._topics[TOPIC].window          # a bench may read the private count
    print('ready', flush=True)
    _spin_reporting(node, lambda: window.count, executor_kind)
    probes.destroy()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def deserialising(kind: str, executor_kind: str) -> int:
    import collections
    import rclpy
    from anyscale_manager.nodes.monitors import PROBE_QOS, import_message_class
    rclpy.init()
    node = rclpy.create_node('bench_cost_hz')
    gaps = collections.deque(maxlen=10000)
    state = {'last': None, 'count': 0}

    def on_message(msg) -> None:
        now = time.monotonic()
        if state['last'] is not None:
            gaps.append(now - state['last'])
        state['last'] = now
        state['count'] += 1

    node.create_subscription(import_message_class(TYPES[kind]), TOPIC, on_message, PROBE_QOS)
    print('ready', flush=True)
    _spin_reporting(node, lambda: state['count'], executor_kind)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--seconds', type=float, default=10.0)
    parser.add_argument('--rate', type=float, default=1000.0)
    parser.add_argument('--kbytes', type=int, default=100, help='size of bytes, structured')
    parser.add_argument('--type', choices=sorted(TYPES), default='image',
                        help='image: sensor_msgs/Image; laserscan: sensor_msgs/LaserScan; '
                             'bytes: UInt8MultiArray; structured: DiagnosticArray')
    parser.add_argument('--shape', default='',
                        help='of an image (WIDTHxHEIGHT:ENCODING, default '
                             f'{DEFAULT_SHAPES["image"]}) or a laserscan (BEAMS, default '
                             f'{DEFAULT_SHAPES["laserscan"]})')
    parser.add_argument('--executor', choices=('events', 'single'), default='events',
                        help="both subscribers' executor: the agent's (events) or rclpy's "
                             'default (single)')
    parser.add_argument('--domain', default=os.environ.get('ROS_DOMAIN_ID', '12'))
    parser.add_argument('--role', choices=('publisher', 'probe', 'deserialising'),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    if args.shape and args.type not in DEFAULT_SHAPES:
        parser.error(f'--shape is for {" and ".join(DEFAULT_SHAPES)}')
    if args.role == 'publisher':
        return publisher(args.rate, args.kbytes * 1000, args.type, args.shape)
    if args.role == 'probe':
        return probe(args.type, args.executor)
    if args.role == 'deserialising':
        return deserialising(args.type, args.executor)

    import psutil
    env = dict(os.environ, PYTHONUNBUFFERED='1')

    def start(role):
        return subprocess.Popen([sys.executable, __file__, '--role', role, '--domain',
                                 str(args.domain), '--rate', str(args.rate), '--kbytes',
                                 str(args.kbytes), '--type', args.type, '--shape', args.shape,
                                 '--executor', args.executor], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True, env=env)

    subs = {'raw probe': start('probe'), 'deserialising': start('deserialising')}
    procs = list(subs.values())
    try:
        for proc in subs.values():
            assert proc.stdout.readline().strip() == 'ready'
        pub = start('publisher')
        procs.append(pub)
        size = int(pub.stdout.readline().split()[1])
        time.sleep(3.0)                                   # discovery and warm-up

        def snapshot():
            out = {}
            for name, proc in subs.items():
                proc.stdin.write('\n')
                proc.stdin.flush()
                count = int(proc.stdout.readline().split()[1])
                t = psutil.Process(proc.pid).cpu_times()
                out[name] = (time.monotonic(), t.user + t.system, count)
            t = psutil.Process(pub.pid).cpu_times()
            out['publisher'] = (time.monotonic(), t.user + t.system, None)
            return out

        before = snapshot()
        time.sleep(args.seconds)
        after = snapshot()
    finally:
        stop_all(procs, 10.0, session=False)
    shape = f' {args.shape or DEFAULT_SHAPES[args.type]}' if args.type in DEFAULT_SHAPES else ''
    print(f'{args.rate:g} Hz of {TYPES[args.type]}{shape} ({size} B serialised) for '
          f'{args.seconds:g} s, {args.executor} executor '
          f'(machine: {psutil.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})')
    cpu, per_msg = {}, {}
    for name in ('raw probe', 'deserialising', 'publisher'):
        (t0, c0, n0), (t1, c1, n1) = before[name], after[name]
        cpu[name] = 100.0 * (c1 - c0) / (t1 - t0)
        received = ''
        if n0 is not None:
            per_msg[name] = (c1 - c0) / max(1, n1 - n0) * 1e6
            received = (f', received {(n1 - n0) / (t1 - t0):7.1f} msg/s, '
                        f'{per_msg[name]:7.1f} us CPU per message')
        print(f'  {name:<14} CPU {cpu[name]:6.1f} % of one core{received}')
    print(f'  ratio raw probe / deserialising: CPU {cpu["raw probe"] / cpu["deserialising"]:.2f}'
          f', CPU per message {per_msg["raw probe"] / per_msg["deserialising"]:.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
