"""Faults of a node or an agent, judged at a consumer of our own: failover of a crashed
lifecycle node to its standby copy, a plain node restarted in place, agents restarted in place
(SIGHUP), a remote agent SIGKILLed (fencing), the leading decider SIGKILLed beside a standby.

    python bench/bench_failover.py [--kills 20] [--in-place-kills 10] [--hups 10]
                                   [--both-hups 20] [--agent-kills 10] [--decider-kills 20]
                                   [--decider-stops 10] [--rate-hz 20] [--domain-id N]
                                   [--keep DIR] [--no-profile]
                                   [--own-namespace] [--node-transports T] [--state]
                                   [--kill-every S]

Two scales of this machine (home, the master, and away) each run an agent, and a decider runs
beside them, all real processes on DDS over loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
the given domain). The deployment: sensor (home) -> worker (a lifecycle workload with a standby
copy on both scales) -> pinned (home, a plain workload), every output at --rate-hz.

- Failover: SIGKILL of the worker's serving copy, wherever it serves, --kills times (each after
  the hysteresis has passed and the stream has been steady for a second; with --kill-every S,
  every S seconds, a crash loop, as soon as a standby is ready): the longest gap a subscriber of
  this bench heard on the worker's output. (The killed copy is gone before the
  standby serves: two senders cannot overlap here.)
- In place: SIGKILL of pinned (no standby copy, it may run only home) after a healthy run,
  --in-place-kills times: the longest gap on its output (process start, discovery, first input).
- SIGHUP of each agent (restart in place), --hups times each: moves back, relocations and
  failovers, node restarts and link down reports while it restarts, and the longest gap on the
  worker's output.
- SIGHUP of both agents at once, --both-hups times: the time until each is back as a new
  process that follows the current layout again and reports its copy of the worker as it was
  (serving and ready, or standing by inactive); an agent not back DEAF_S (25 s) after its
  signal is counted as deaf (it reports, but hears neither its layout nor its nodes: the new
  process's DDS participant found no peer), and the run goes on once it is back.
- SIGKILL of the away agent while the worker serves there, --agent-kills times (a new agent is
  started after each): the time until its worker process is gone (its warden's fencing), how
  long the old and the new copy were both heard, and the longest gap.
- SIGKILL of the leading decider while a second one stands by, --decider-kills times (the killed
  one is started again and stands by before the next): the time until the first layout of the
  other decider arrives here, the moves and node restarts it caused, and the longest gap on the
  worker's output.
- SIGSTOP of the leading decider for 2 s, then SIGCONT, --decider-stops times: the time until the
  standby's first layout, whether any layout of the stopped one arrived after it resumed, and
  whether an agent ever reported following it again (both must be no).
With --state the worker carries a state, as the test-bed's AMCL does: its output is the robot's
pose (geometry_msgs/msg/PoseWithCovarianceStamped, moving at 0.2 m/s), declared with
``state: {topic, restore}``, so each failover hands the last pose to the copy that takes over.
The bench then also prints, over the failovers, how many first outputs did not continue the
last pose (a jump larger than the robot could have moved, testbed/poses.py) and the age of the
state when handed over (from the agents' logs).
Prints one line per fault, then p50/p95/max of each figure. Every process uses the packaged
discovery profile (config/fastdds_discovery.xml) unless the environment names a profile or
--no-profile is given: without it a restarted node waits up to Fast DDS's 3 s announcement
period to be found.
"""

import argparse
import contextlib
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import psutil
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
BIN = os.path.dirname(sys.executable)
HYSTERESIS_S = 4.0
DEAF_S = 25.0            # an agent not back this long after its SIGHUP heard nothing
HEALTHY_RUN_S = 3.0      # restart_backoff_max_s: a node up this long crashes as a first crash


POSE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
SPEED_MPS = 0.2


def deployment(folder, topic, rate_hz, node_transports=None, state=False):
    from anyscale_manager.testbed import ports

    def workload(name, *args):
        return {'command': [os.path.join(BIN, 'workload'), '--name', name, *args,
                            '--rate-hz', str(rate_hz)]}
    conn = {'msg_type': 'std_msgs/msg/UInt8MultiArray', 'bandwidth_kbps': 1.0,
            'freq_min_hz': rate_hz / 2, 'tolerance_s': 1.0}
    out = f'{topic}/w:{POSE}' if state else topic + '/w'
    carried = ('--pose-motion', f'{SPEED_MPS},0.05', '--restore', topic + '/restore') \
        if state else ()
    params = {
        'deployment': {'name': f'bench_failover_{os.getpid()}'},
        'scales': {'names': ['home', 'away'],
                   'home': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100000.0,
                            'cores': 2, 'clock_ghz': 1.0},
                   'away': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100000.0,
                            'cores': 4, 'clock_ghz': 2.0, 'gain': 3.0}},
        'links': {'names': ['net'], 'net': {'ends': ['home', 'away'],
                                            'bandwidth_kbps': 100000.0, 'medium': 'wired'}},
        'nodes': {'names': ['sensor', 'worker', 'pinned'],
                  'sensor': {'launch': workload('sensor', '--pub', topic + '/s'), 'cpu': 1.0,
                             'residence': ['home']},
                  'worker': {'launch': workload('worker', '--sub', topic + '/s', '--pub',
                                                out, '--lifecycle', *carried),
                             'cpu': 1.0, 'lifecycle': True, 'standby': True,
                             'move_order': 'start_before_stop'},
                  'pinned': {'launch': workload('pinned', '--sub', out, '--pub',
                                                topic + '/p'),
                             'cpu': 1.0, 'residence': ['home']}},
        'connections': {'names': ['sensor_worker', 'worker_pinned'],
                        'sensor_worker': dict(conn, topic=topic + '/s', publisher='sensor',
                                              subscriber='worker'),
                        'worker_pinned': dict(conn, topic=topic + '/w', publisher='worker',
                                              subscriber='pinned',
                                              msg_type=POSE if state else conn['msg_type'])},
        'decider': {'cpu_headroom': 1.0, 'period_s': 0.25, 'grace_s': 1.0,
                    'agent_timeout_s': 3.0, 'observation_max_age_s': 3.0,
                    'hysteresis_s': HYSTERESIS_S},
        'monitoring': {'heartbeat_rate_hz': 4.0, 'heartbeat_misses_down': 12,
                       'scale_rate_hz': 4.0, 'bandwidth_probe_interval_s': 86400.0,
                       'bandwidth_probe_port': ports.port_base()},
        'agent': {'sigint_grace_s': 1.0, 'sigterm_grace_s': 1.0, 'readiness_timeout_s': 5.0,
                  'restart_backoff_s': 0.5, 'restart_backoff_max_s': HEALTHY_RUN_S,
                  'state_dir': os.path.join(folder, 'state'),
                  'log_dir': os.path.join(folder, 'log')},
    }
    if node_transports is not None:
        params['agent']['node_dds_transports'] = node_transports
    if state:
        params['nodes']['worker']['state'] = {'topic': topic + '/w', 'restore': topic + '/restore'}
    path = os.path.join(folder, 'deployment.yaml')
    with open(path, 'w') as f:
        yaml.safe_dump({'/**': {'ros__parameters': params}}, f)
    return path


def stats(values):
    values = sorted(values)
    if not values:
        return 'none'
    p95 = values[min(len(values) - 1, int(round(0.95 * (len(values) - 1))))]
    return (f'p50 {statistics.median(values):.3f} s, p95 {p95:.3f} s, max {values[-1]:.3f} s '
            f'(n = {len(values)})')


IN_NAMESPACE = 'BENCH_FAILOVER_NAMESPACE'
HANDED = re.compile(r'worker: state of (\d+\.\d+) s ago handed')


def handed_ages(folder):
    """The age of each state the agents handed over, from their logs."""
    ages = []
    for name in sorted(os.listdir(folder)):
        if name.startswith('agent') and name.endswith('.out'):
            with open(os.path.join(folder, name), errors='replace') as f:
                ages += [float(m.group(1)) for m in HANDED.finditer(f.read())]
    return ages


def in_own_namespace() -> int:
    """Runs this command again inside a new network namespace with only loopback up."""
    name = f'anyscale_bf_{os.getpid()}'
    subprocess.run(['ip', 'netns', 'add', name], check=True)
    try:
        subprocess.run(['ip', 'netns', 'exec', name, 'ip', 'link', 'set', 'lo', 'up'],
                       check=True)
        return subprocess.run(['ip', 'netns', 'exec', name, sys.executable, *sys.argv],
                              env=dict(os.environ, **{IN_NAMESPACE: name})).returncode
    finally:
        subprocess.run(['ip', 'netns', 'del', name], check=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--kills', type=int, default=20)
    ap.add_argument('--kill-every', type=float, default=0.0, metavar='S',
                    help='kill the serving copy every S seconds (a crash loop) instead of once '
                         'the hysteresis has passed and the output has been steady for 1 s')
    ap.add_argument('--in-place-kills', type=int, default=10)
    ap.add_argument('--hups', type=int, default=10, help='SIGHUPs of each agent')
    ap.add_argument('--both-hups', type=int, default=20,
                    help='SIGHUPs of both agents at once')
    ap.add_argument('--agent-kills', type=int, default=10,
                    help='SIGKILLs of the remote agent while the worker serves there')
    ap.add_argument('--decider-kills', type=int, default=20,
                    help='SIGKILLs of the leading decider with a standby running')
    ap.add_argument('--decider-stops', type=int, default=10,
                    help='SIGSTOPs (2 s) of the leading decider with a standby running')
    ap.add_argument('--rate-hz', type=float, default=20.0)
    ap.add_argument('--keep', metavar='DIR',
                    help='write the deployment and every log into DIR and keep them')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '44')))
    ap.add_argument('--no-profile', action='store_true',
                    help="without the packaged config/fastdds_discovery.xml (Fast DDS's "
                         'defaults, or the profile the environment names)')
    ap.add_argument('--own-namespace', action='store_true',
                    help='run in a network namespace of its own (loopback only, needs root) '
                         'with ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, where the transports of '
                         '--node-transports apply (under LOCALHOST, rmw_fastrtps adds '
                         'shared memory whatever they say)')
    ap.add_argument('--node-transports', default=None,
                    help="the deployment's agent.node_dds_transports (default: the setting's "
                         "default; '' for Fast DDS's default, shared memory included)")
    ap.add_argument('--state', action='store_true',
                    help='the worker carries a state (a pose), handed over at each failover')
    args = ap.parse_args()
    if args.own_namespace and os.environ.get(IN_NAMESPACE) is None:
        return in_own_namespace()
    os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    if args.own_namespace:
        # The namespace's only interface is loopback: SUBNET reaches nothing else.
        os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', ROS_STATIC_PEERS='127.0.0.1')
        print(f'in network namespace {os.environ[IN_NAMESPACE]}, discovery range SUBNET',
              flush=True)
    else:
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        print('discovery range LOCALHOST: every participant has the shared-memory transport',
              flush=True)
    from anyscale_manager import config_files
    if not args.no_profile:
        os.environ.update(config_files.with_discovery_profile(os.environ))
    print('Fast DDS profile: ' + next((os.environ[v] for v in config_files.PROFILE_VARS
                                       if os.environ.get(v)), "none (Fast DDS's defaults)"),
          flush=True)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String, UInt8MultiArray

    from anyscale_manager.testbed.poses import pose_jumps

    from anyscale_manager import protocol as p
    from anyscale_manager.nodes import qos
    from anyscale_manager.agent.procs import stop_popen
    from anyscale_manager.nodes.monitors.clocks import clock_offset_s
    from anyscale_manager.nodes.monitors.probes import received_at

    topic = f'/bench_failover_{os.getpid()}'
    rclpy.init()
    node = rclpy.create_node('bench_failover_consumer')
    lock = threading.Lock()
    heard = {'/s': [], '/w': [], '/p': []}      # arrival times
    sent = {'/s': [], '/w': [], '/p': []}       # the same messages' source times
    states, events, links, layouts, beats, ready = {}, [], [], [], {}, set()

    offset = [clock_offset_s()]
    poses = []                                  # (arrival, x, y, stamp) with --state

    def keep(suffix):
        def take(_raw, info):
            # At its DDS reception time, as the test-bed's observer and the probes place it:
            # this process runs its callbacks late when the machine is busy (a failover starts
            # a process and a participant joins), and a burst stamped at callback time would
            # show a gap no subscriber lived through.
            at = received_at(info, offset[0], time.monotonic())
            source_ns = info.get('source_timestamp', 0) if isinstance(info, dict) else 0
            with lock:
                heard[suffix].append(at)
                if source_ns:
                    sent[suffix].append(source_ns / 1e9 - offset[0])
            if args.state and suffix == '/w':
                msg = deserialize_message(_raw, PoseWithCovarianceStamped)
                stamp = msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9
                with lock:
                    poses.append((at, msg.pose.pose.position.x, msg.pose.pose.position.y, stamp))
        return take
    for suffix in heard:
        cls = PoseWithCovarianceStamped if args.state and suffix == '/w' else UInt8MultiArray
        node.create_subscription(cls, topic + suffix, keep(suffix), qos.PROBE, raw=True)

    def state(m):
        s = p.AgentState.from_json(m.data)
        with lock:
            states[s.scale] = s
    node.create_subscription(String, p.TOPIC_AGENT_STATE, state, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_EVENTS,
                             lambda m: events.append((time.monotonic(),
                                                      p.Event.from_json(m.data))), qos.EVENTS)
    node.create_subscription(String, p.TOPIC_LINK_STATUS,
                             lambda m: links.append((time.monotonic(),
                                                     p.LinkStatus.from_json(m.data))),
                             qos.MONITOR_READER)
    node.create_subscription(String, p.TOPIC_LAYOUT,
                             lambda m: layouts.append((time.monotonic(),
                                                       p.Layout.from_json(m.data))),
                             qos.LATCHED_READER)

    def beat(m):
        b = p.DeciderBeat.from_json(m.data)
        with lock:
            beats[b.decider.pid] = (time.monotonic(), b.role)
    node.create_subscription(String, p.TOPIC_DECIDER, beat, qos.BEAT)

    def diagnostics(m):
        # A standby is ready once it stands by for a leader it hears (its diagnostics say so).
        for status in m.status:
            values = {kv.key: kv.value for kv in status.values}
            found = re.search(r'pid (\d+)\)', values.get('decider', ''))
            if found and status.message.startswith('standing by for decider'):
                with lock:
                    ready.add(int(found.group(1)))
    node.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, diagnostics, 50)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stop = threading.Event()
    node.create_timer(1.0, lambda: offset.__setitem__(0, clock_offset_s()))
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    spinner.start()

    def copy(scale, name):
        with lock:
            s = states.get(scale)
        return s.nodes.get(name) if s else None

    def serving():
        """(scale serving the worker, the other scale) when the other keeps a standby."""
        for here, other in (('home', 'away'), ('away', 'home')):
            a, b = copy(here, 'worker'), copy(other, 'worker')
            if a and b and a.state == 'running' and a.ready and b.state == 'standby':
                return here, a
        return None

    def wait(cond, timeout_s, what):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            value = cond()
            if value:
                return value
            time.sleep(0.05)
        raise RuntimeError(f'timed out after {timeout_s} s waiting for {what}')

    def steady(suffix, seconds):
        with lock:
            n = len(heard[suffix])
        wait(lambda: len(heard[suffix]) >= n + seconds * args.rate_hz, 20.0,
             f'{seconds} s of {suffix}')

    def judge(suffix, t0, t1, where=False, stamps=heard):
        """The longest gap on ``suffix`` that ends after t0 (and, with ``where``, when it
        began, from t0); by reception time, or by source time with ``stamps=sent``."""
        with lock:
            times = sorted(t for t in stamps[suffix] if t0 - 1.0 <= t <= t1)
        gap, began = max(((b - a, a - t0) for a, b in zip(times, times[1:]) if b > t0),
                         default=(float('nan'), float('nan')))
        return (gap, began) if where else gap

    procs = []
    if args.keep:
        os.makedirs(args.keep, exist_ok=True)
    with (contextlib.nullcontext(args.keep) if args.keep
          else tempfile.TemporaryDirectory()) as folder:
        path = deployment(folder, topic, args.rate_hz, args.node_transports, args.state)
        env = dict(os.environ, PYTHONUNBUFFERED='1')

        def start(exe, *extra):
            log = open(os.path.join(folder, f'{exe}{len(procs)}.out'), 'w')
            procs.append(subprocess.Popen([os.path.join(BIN, exe), '--ros-args',
                                           '--params-file', path, *extra], env=env,
                                          stdout=log, stderr=subprocess.STDOUT,
                                          start_new_session=True))
            return procs[-1]
        failover, in_place, jumped = [], [], 0
        hups = {'home': [], 'away': []}      # (moves, restarts, links down, longest gap)
        both_back, deaf = [], 0
        fenced, overlap, agent_gap = [], [], []
        takeover, takeover_moves, takeover_gap = [], 0, []
        stop_takeover, stale_layouts, stale_followed = [], 0, 0
        try:
            start('agent', '-p', 'scale:=home')
            start('agent', '-p', 'scale:=away')
            start('decider')
            wait(serving, 90.0, 'the worker serving with a standby on the other scale')
            print(f'ROS_DOMAIN_ID={args.domain_id}; outputs at {args.rate_hz:g} Hz; '
                  f'hysteresis {HYSTERESIS_S:g} s')
            last_kill = time.monotonic()
            for k in range(args.kills):
                if args.kill_every:
                    # A crash loop: the serving copy killed every --kill-every seconds.
                    time.sleep(max(0.0, last_kill + args.kill_every - time.monotonic()))
                else:
                    time.sleep(HYSTERESIS_S)      # past T since the last crash
                where, victim = wait(serving, 60.0, 'a serving copy and a standby')
                if not args.kill_every:
                    steady('/w', 1.0)
                t0 = last_kill = time.monotonic()
                os.kill(victim.pid, signal.SIGKILL)
                now_at, _ = wait(lambda: (serving() if (serving() or ('', None))[0]
                                          not in ('', where) else None), 30.0,
                                 'the standby copy serving')
                t_serving = time.monotonic()
                steady('/w', 1.0)
                t1 = time.monotonic()
                gap, began = judge('/w', t0, t1, where=True)
                # Where a gap was made: the worker's input as heard here, and the worker's
                # output by the time it was sent.
                input_gap, input_began = judge('/s', t0, t1, where=True)
                sent_gap, sent_began = judge('/w', t0, t1, where=True, stamps=sent)
                input_sent_gap = judge('/s', t0, t1, stamps=sent)
                kinds = [e.kind for _, e in events if e.node == 'worker']
                failover.append(gap)
                if args.state:
                    with lock:
                        jumps = pose_jumps(poses, t0 - 1.0, t1, SPEED_MPS)
                    jumped += bool(jumps)
                    if jumps:
                        print(f'failover {k + 1:2}: the pose jumped: '
                              f'{", ".join(str(j) for j in jumps)}', flush=True)
                # Where the time went: the decider's failover event, the agent's report of the
                # copy serving (both as heard here) and the first output after the kill.
                decided = next((t for t, e in events if t > t0 and e.node == 'worker'
                                and e.kind == 'failover'), float('nan'))
                with lock:
                    first = min((t for t in heard['/w'] if t > t0 + 0.001), default=float('nan'))
                print(f'failover {k + 1:2}: {where} -> {now_at}, longest gap {gap:.3f} s '
                      f'from +{began:.3f} s (decided +{decided - t0:.3f} s, reported serving '
                      f'+{t_serving - t0:.3f} s (polled), first output +{first - t0:.3f} s); '
                      f'by send time {sent_gap:.3f} s from +{sent_began:.3f} s; its input '
                      f'{input_gap:.3f} s from +{input_began:.3f} s '
                      f'({input_sent_gap:.3f} s by send time); '
                      f'failover events so far {kinds.count("failover")}', flush=True)
            for k in range(args.in_place_kills):
                victim = wait(lambda: (copy('home', 'pinned') if copy('home', 'pinned') and
                                       copy('home', 'pinned').state == 'running' else None),
                              30.0, 'pinned running')
                time.sleep(HEALTHY_RUN_S + 0.5)     # a healthy run: its crash is a first one
                steady('/p', 1.0)
                t0 = time.monotonic()
                os.kill(victim.pid, signal.SIGKILL)
                wait(lambda: copy('home', 'pinned') and copy('home', 'pinned').pid not in
                     (0, victim.pid), 30.0, 'pinned restarted')
                t_spawned = time.monotonic()
                steady('/p', 1.0)
                gap = judge('/p', t0, time.monotonic())
                in_place.append(gap)
                with lock:
                    first = min((t for t in heard['/p'] if t > t0 + 0.001), default=float('nan'))
                print(f'in place {k + 1:2}: longest gap {gap:.3f} s (new pid reported '
                      f'+{t_spawned - t0:.3f} s (polled), first output +{first - t0:.3f} s)',
                      flush=True)
            agents = {'home': procs[0], 'away': procs[1]}
            for k in range(args.hups):
                for scale in ('home', 'away'):
                    wait(serving, 60.0, 'a serving copy and a standby')
                    steady('/w', 1.0)
                    with lock:
                        instance = states[scale].instance
                        restarts = {s: {n: r.restarts for n, r in st.nodes.items()}
                                    for s, st in states.items()}
                    t0 = time.monotonic()
                    os.kill(agents[scale].pid, signal.SIGHUP)
                    wait(lambda: states[scale].instance != instance, 30.0,
                         f'the {scale} agent back after SIGHUP')
                    steady('/w', 2.0)
                    t1 = time.monotonic()
                    with lock:
                        # A restart must bring nothing back nor relocate anything (a planned
                        # move out after the hysteresis is not its doing).
                        backs = [e for t, e in events if t0 <= t <= t1 and e.kind in
                                 ('migrate_back', 'relocate', 'failover')]
                        moved = len(backs)
                        down = sum(1 for t, s in links if t0 <= t <= t1 and not s.up)
                        again = sum(r.restarts - restarts.get(s, {}).get(n, r.restarts)
                                    for s, st in states.items() for n, r in st.nodes.items())
                    gap = judge('/w', t0, t1)
                    hups[scale].append((moved, again, down, gap))
                    print(f'SIGHUP {scale} {k + 1:2}: moves back {moved}, node restarts {again}, '
                          f'link down reports {down}, longest gap {gap:.3f} s'
                          + ''.join(f'; {e.kind} {e.node}: {e.reason[:160]}' for e in backs),
                          flush=True)
            for k in range(args.both_hups):
                wait(serving, 60.0, 'a serving copy and a standby')
                steady('/w', 1.0)
                with lock:
                    before = {scale: states[scale].instance for scale in agents}
                    was = {scale: (states[scale].nodes['worker'].state,
                                   states[scale].nodes['worker'].lifecycle) for scale in agents}
                    generation = max((lay.generation for _, lay in layouts), default=-1)

                def back(scale):
                    # A new process, the current layout applied, its copy of the worker seen
                    # in the state it had (serving and ready, or standing by inactive).
                    with lock:
                        s = states[scale]
                    w = s.nodes.get('worker')
                    return (s.instance != before[scale] and s.generation >= generation
                            and w is not None and (w.state, w.lifecycle) == was[scale]
                            and (w.ready or w.state == 'standby'))
                t0 = time.monotonic()
                for scale in agents:
                    os.kill(agents[scale].pid, signal.SIGHUP)
                times = {}
                end = t0 + DEAF_S
                while len(times) < len(agents) and time.monotonic() < end:
                    for scale in agents:
                        if scale not in times and back(scale):
                            times[scale] = time.monotonic() - t0
                    time.sleep(0.02)
                missing = [scale for scale in agents if scale not in times]
                deaf += len(missing)
                both_back.extend(times.values())
                print(f'SIGHUP of both {k + 1:2}: back after '
                      + ', '.join(f'{scale} {t:.2f} s' for scale, t in sorted(times.items()))
                      + (f'; not back within {DEAF_S:g} s: {", ".join(missing)}'
                         if missing else ''),
                      flush=True)
                if missing:
                    wait(lambda: all(back(scale) for scale in agents), 120.0,
                         'both agents back after a deaf restart')
            for k in range(args.agent_kills):
                time.sleep(HYSTERESIS_S)
                wait(lambda: (serving() or ('',))[0] == 'away', 120.0,
                     'the worker serving on away')
                steady('/w', 1.0)
                victim = psutil.Process(copy('away', 'worker').pid)
                t0 = time.monotonic()
                agents['away'].kill()
                agents['away'].wait()
                wait(lambda: not victim.is_running()
                     or victim.status() == psutil.STATUS_ZOMBIE, 60.0,
                     "the warden stopping the dead agent's worker")
                t_fenced = time.monotonic()
                wait(lambda: copy('home', 'worker') and copy('home', 'worker').state ==
                     'running', 30.0, 'the worker serving home')
                steady('/w', 1.0)
                with lock:
                    times = [t for t in heard['/w'] if t >= t0 - 1.0]
                last_old = max((t for t in times if t <= t_fenced), default=t0)
                first_new = min((t for t in times if t > t_fenced), default=float('nan'))
                gap = judge('/w', t0, time.monotonic())
                fenced.append(t_fenced - t0)
                overlap.append(max(0.0, last_old - first_new))
                agent_gap.append(gap)
                print(f'agent kill {k + 1:2}: its worker stopped {t_fenced - t0:.2f} s after, '
                      f'longest gap {gap:.3f} s', flush=True)
                agents['away'] = start('agent', '-p', 'scale:=away')
            deciders = [procs[2]]
            if args.decider_kills or args.decider_stops:
                deciders.append(start('decider'))

            def role(proc, wanted):
                with lock:
                    t, r = beats.get(proc.pid, (0.0, ''))
                return r == wanted and time.monotonic() - t < 1.0

            def leader_and_standby():
                leader = wait(lambda: next((d for d in deciders if role(d, 'leader')), None),
                              30.0, 'a leading decider')
                other = wait(lambda: next((d for d in deciders if d is not leader
                                           and role(d, 'standby') and d.pid in ready), None),
                             30.0, 'a standby decider standing by for it')
                return leader, other
            for k in range(args.decider_kills):
                leader, other = leader_and_standby()
                steady('/w', 1.0)
                with lock:
                    restarts = {s: {n: r.restarts for n, r in st.nodes.items()}
                                for s, st in states.items()}
                t0 = time.monotonic()
                leader.kill()
                leader.wait()
                t_new = wait(lambda: next((t for t, lay in list(layouts) if t > t0
                                           and lay.decider and lay.decider.pid == other.pid),
                                          None), 10.0, "the standby's first layout")
                steady('/w', 1.0)
                t1 = time.monotonic()
                with lock:
                    moved = sum(1 for t, e in events if t0 <= t <= t1 and e.kind in
                                ('migrate', 'migrate_back', 'relocate', 'failover'))
                    again = sum(r.restarts - restarts.get(s, {}).get(n, r.restarts)
                                for s, st in states.items() for n, r in st.nodes.items())
                gap = judge('/w', t0, t1)
                takeover.append(t_new - t0)
                takeover_moves += moved + again
                takeover_gap.append(gap)
                print(f'decider kill {k + 1:2}: first layout of the standby after '
                      f'{t_new - t0:.3f} s, moves {moved}, node restarts {again}, longest gap '
                      f'{gap:.3f} s', flush=True)
                deciders = [other, start('decider')]
            for k in range(args.decider_stops):
                leader, other = leader_and_standby()
                steady('/w', 1.0)
                t0 = time.monotonic()
                os.kill(leader.pid, signal.SIGSTOP)
                t_new = wait(lambda: next((t for t, lay in list(layouts) if t > t0
                                           and lay.decider and lay.decider.pid == other.pid),
                                          None), 10.0, "the standby's first layout")
                with lock:
                    new_id = next(lay.decider.id for t, lay in layouts if t == t_new)
                time.sleep(max(0.0, t0 + 2.0 - time.monotonic()))
                t_cont = time.monotonic()
                os.kill(leader.pid, signal.SIGCONT)
                wait(lambda: role(leader, 'standby'), 10.0, 'the resumed one standing by')
                steady('/w', 1.0)
                with lock:
                    stale = sum(1 for t, lay in layouts if t > t_cont and lay.decider
                                and lay.decider.pid == leader.pid)
                    followed = sum(1 for st in states.values() if st.decider != new_id)
                stop_takeover.append(t_new - t0)
                stale_layouts += stale
                stale_followed += followed
                print(f'decider stop {k + 1:2}: first layout of the standby after '
                      f'{t_new - t0:.3f} s; layouts of the resumed one {stale}; agents not '
                      f'following the new leader {followed}', flush=True)
                deciders = [other, leader]
            ages = handed_ages(folder) if args.state else []
        finally:
            for proc in reversed(procs):
                stop_popen(proc, 5.0, 5.0)
            stop.set()
            spinner.join(2.0)
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
    print(f'failover to a standby copy, longest gap at the consumer: {stats(failover)}')
    if args.state:
        print(f'state carried: failovers whose first output did not continue the last pose '
              f'{jumped} of {len(failover)}; age of the state when handed over {stats(ages)}')
    print(f'plain node restarted in place, longest gap: {stats(in_place)}')
    for scale, rows in hups.items():
        if rows:
            print(f'SIGHUP of the {scale} agent ({len(rows)}): moves back '
                  f'{sum(r[0] for r in rows)}, '
                  f'node restarts {sum(r[1] for r in rows)}, link down reports '
                  f'{sum(r[2] for r in rows)}; longest gap {stats([r[3] for r in rows])}')
    if both_back or deaf:
        print(f'SIGHUP of both agents at once ({args.both_hups}): each back (new process, '
              f'current layout, its nodes seen) after {stats(both_back)}; not back within '
              f'{DEAF_S:g} s: {deaf}')
    if fenced:
        print(f'remote agent SIGKILLed: its worker stopped after {stats(fenced)}; two senders '
              f'heard at once {stats(overlap)}; longest gap {stats(agent_gap)}')
    if takeover:
        print(f'leading decider SIGKILLed with a standby: its first layout after '
              f'{stats(takeover)}; moves and node restarts {takeover_moves}; longest gap '
              f'{stats(takeover_gap)}')
    if stop_takeover:
        print(f"leading decider SIGSTOPped for 2 s: the standby's first layout after "
              f'{stats(stop_takeover)}; layouts of the resumed one {stale_layouts}; agents '
              f'left following it {stale_followed}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
