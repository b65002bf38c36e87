"""The Δ judge against real silences: paused publishers, a subscriber of our own, the probes.

    python bench/bench_judge.py [--trials 3] [--rates 5,10,20,100] [--tolerance 1.0]
                                [--domain-id N]

A real workload process publishes at each rate (freq_min is half of it) on this machine's
loopback; it is paused with SIGSTOP and resumed with SIGCONT so that the gap a subscriber
lives through is ``Δ + 1/freq_min ± 0.2 s``. The truth of each trial is that gap, measured by a
raw subscription of this bench (a reader no part of the package started): the connection was
below freq_min for ``gap - 1/freq_min`` seconds, a violation when that exceeds Δ. Two judges are
scored against it: the project's probe (ProbeManager, as on every agent, read through its
published ConnectionStatus: a violation when a reading says ERROR or an ended stretch longer
than Δ), and ``below_spans`` on this bench's own arrivals (the observer's judge in the test-bed).
Prints one line per trial and the false and missed violations of each judge.
"""

import argparse
import os
import signal
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')

MARGIN_S = 0.2


def deployment(topic, rate_hz, tolerance_s):
    from anyscale_manager.model.types import (Connection, Deployment, Launch, MonitorSettings,
                                              Node, Scale)
    return Deployment(
        name='judge', source='bench_judge',
        scales=(Scale('here', 'master', 'robot', 100.0, 1, 1.0, 1.0, 'localhost'),), links=(),
        nodes=(Node('pub', Launch(), 1.0), Node('sub', Launch(), 1.0)),
        connections=(Connection('flow', topic, 'pub', 'sub', 1.0, freq_min_hz=rate_hz / 2,
                                tolerance_s=tolerance_s,
                                msg_type='std_msgs/msg/UInt8MultiArray'),),
        monitoring=MonitorSettings(probe_window_s=2.0, probe_publish_rate_hz=4.0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--trials', type=int, default=3, help='pauses per rate and side (3)')
    ap.add_argument('--rates', default='5,10,20,100', help='publisher rates in Hz')
    ap.add_argument('--tolerance', type=float, default=1.0, help='Δ in seconds (1.0)')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '43')))
    args = ap.parse_args()
    os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String, UInt8MultiArray

    from anyscale_manager import protocol as p
    from anyscale_manager.nodes.monitors import ProbeManager
    from anyscale_manager.nodes.qos import PROBE
    from anyscale_manager.runtime.delta import below_spans

    rclpy.init()
    node = rclpy.create_node('bench_judge')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    lock = threading.Lock()
    arrivals, readings = {}, []
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    node.create_subscription(
        String, p.TOPIC_CONNECTION_STATUS,
        lambda m: readings.append((time.monotonic(), p.ConnectionStatus.from_json(m.data))), 50)
    spinner.start()
    rows = []
    scores = {'probe': [0, 0], 'observer': [0, 0]}      # [false, missed]
    print(f'ROS_DOMAIN_ID={args.domain_id}, Δ = {args.tolerance:g} s, freq_min = rate / 2, '
          f'pauses making a gap of Δ + 1/freq_min ± {MARGIN_S:g} s at the subscriber')
    print(f'{"rate":>5} {"fmin":>5} {"side":>4} {"gap s":>6} {"below s":>7} {"truth":>5} '
          f'{"probe":>5} {"observer":>8}')
    try:
        for rate in [float(r) for r in args.rates.split(',')]:
            topic = f'/bench_judge_{int(rate)}hz'
            fmin = rate / 2
            d = deployment(topic, rate, args.tolerance)
            with lock:
                arrivals[topic] = []

            def heard(_raw, topic=topic):
                with lock:
                    arrivals[topic].append(time.monotonic())
            sub = node.create_subscription(UInt8MultiArray, topic, heard, PROBE, raw=True)
            probes = ProbeManager(node, d, 'here')
            probes.set_connections(['flow'])
            talker = subprocess.Popen(
                [sys.executable, '-m', 'anyscale_manager.nodes.workload', '--name',
                 f'judge_talker_{int(rate)}', '--pub', f'{topic}:std_msgs/msg/UInt8MultiArray',
                 '--rate-hz', str(rate)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True)
            try:
                deadline = time.monotonic() + 30.0
                while time.monotonic() < deadline:
                    with lock:
                        if len(arrivals[topic]) >= 3 * rate:
                            break
                    time.sleep(0.1)
                else:
                    print(f'{rate:g} Hz: no messages heard in 30 s', file=sys.stderr)
                    return 1
                for trial in range(2 * args.trials):
                    side = +1 if trial % 2 == 0 else -1
                    time.sleep(2.5)      # a full window of steady arrivals before each pause
                    t0 = time.monotonic()
                    pause = args.tolerance + 1.0 / fmin + side * MARGIN_S - 0.5 / rate
                    os.kill(talker.pid, signal.SIGSTOP)
                    time.sleep(pause)
                    os.kill(talker.pid, signal.SIGCONT)
                    time.sleep(2.5)
                    t1 = time.monotonic()
                    with lock:
                        times = list(arrivals[topic])
                        seen = [r for t, r in readings if t0 <= t <= t1 + 0.5]
                    inside = [t for t in times if t0 - 2.0 <= t <= t1]
                    gap = max(b - a for a, b in zip(inside, inside[1:]))
                    truth = gap - 1.0 / fmin > args.tolerance
                    spans = below_spans(times, fmin, t0, t1)
                    observer = any(b - a > args.tolerance for a, b in spans)
                    flow = [r.connections['flow'] for r in seen if 'flow' in r.connections]
                    probe = any(x.level == p.ERROR or (x.ended_below_s or 0) > args.tolerance
                                for x in flow)
                    longest = max((b - a for a, b in spans), default=0.0)
                    for name, said in (('probe', probe), ('observer', observer)):
                        if said and not truth:
                            scores[name][0] += 1
                        if truth and not said:
                            scores[name][1] += 1
                    rows.append((rate, gap, truth, probe, observer))
                    print(f'{rate:5g} {fmin:5g} {"+" if side > 0 else "-":>4} {gap:6.2f} '
                          f'{longest:7.2f} {"VIOL" if truth else "ok":>5} '
                          f'{"VIOL" if probe else "ok":>5} {"VIOL" if observer else "ok":>8}',
                          flush=True)
            finally:
                os.killpg(talker.pid, signal.SIGCONT)
                os.killpg(talker.pid, signal.SIGINT)
                try:
                    talker.wait(10.0)
                except subprocess.TimeoutExpired:
                    os.killpg(talker.pid, signal.SIGKILL)
                    talker.wait()
                probes.destroy()
                node.destroy_subscription(sub)
    finally:
        stop.set()
        spinner.join(2.0)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    truths = sum(1 for r in rows if r[2])
    print(f'{len(rows)} pauses ({truths} past Δ by the gap our subscriber lived through)')
    for name, (false, missed) in scores.items():
        print(f'{name:9} false violations {false}, missed violations {missed}')
    return 0 if all(f == m == 0 for f, m in scores.values()) else 1


if __name__ == '__main__':
    sys.exit(main())
