"""The monitors' rclpy glue with real nodes, real publishers and real DDS (loopback only)."""

import dataclasses
import socket
import subprocess
import sys
import threading
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import String, UInt8MultiArray

from anyscale_manager import protocol as p
from anyscale_manager.agent import warden
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.nodes.monitors import (LATCHED_QOS, STATUS_QOS, LinkMonitor,
                                             ProbeManager, ProbeServer, ScaleMonitor,
                                             import_message_class, probe_throughput)
from anyscale_manager.nodes.workload_messages import build_message, parse_endpoint
from spinning import spin_until

pytestmark = pytest.mark.timeout(60)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture
def deployment(testbed_path):
    """The ICAR test-bed on loopback, with monitors fast enough for a short test."""
    d = load_deployment(testbed_path)
    scales = tuple(dataclasses.replace(s, host='127.0.0.1') for s in d.scales)
    monitoring = dataclasses.replace(
        d.monitoring, scale_rate_hz=5.0, heartbeat_rate_hz=10.0, heartbeat_misses_down=3,
        probe_window_s=1.0, probe_publish_rate_hz=10.0, bandwidth_probe_interval_s=0.5,
        bandwidth_probe_duration_s=0.2, bandwidth_probe_port=free_port())
    return dataclasses.replace(d, scales=scales, monitoring=monitoring)


class Listener:
    """Keeps the last decoded project message and every diagnostic status, by name."""

    def __init__(self, node, topic, cls, qos=STATUS_QOS):
        self.cls = cls
        self.messages = []
        self.statuses = {}
        node.create_subscription(String, topic, self._on, qos)
        node.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, self._on_diag, 50)

    def _on(self, msg):
        self.messages.append(self.cls.from_json(msg.data))

    def _on_diag(self, msg):
        for s in msg.status:
            self.statuses.setdefault(s.name, []).append(s)

    def last_status(self, name):
        found = self.statuses.get(name)
        return found[-1] if found else None


# What the test-bed's nodes publish on its topics (type and shape, as the workload takes them).
TESTBED_TYPES = {'/scan': 'sensor_msgs/msg/LaserScan:682',
                 '/amcl_pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
                 '/image': 'sensor_msgs/msg/Image:176x144:mono8'}


class Publisher:
    """Publishes at ``rate_hz`` what the test-bed publishes on ``topic`` (a test-bed workload's
    message), or a byte array of ``nbytes``."""

    def __init__(self, node, topic, rate_hz, nbytes=None):
        self.node = node
        if nbytes is None:
            self.msg = build_message(parse_endpoint(f'{topic}:{TESTBED_TYPES[topic]}', True))
        else:
            self.msg = UInt8MultiArray(data=bytes(nbytes))
        self.pub = node.create_publisher(type(self.msg), topic, 10)
        self.sent = 0
        self.timer = node.create_timer(1.0 / rate_hz, self._send)

    def _send(self):
        self.pub.publish(self.msg)
        self.sent += 1

    def stop(self):
        self.node.destroy_timer(self.timer)


def reading(listener, name):
    for message in reversed(listener.messages):
        if name in message.connections:
            return message.connections[name]
    return None


# --- probes ------------------------------------------------------------------------------------

def test_probe_reads_a_real_publisher_then_judges_its_stop(ros, deployment):
    make, executor = ros.node, ros.executor
    agent = make('agent_probe')
    listener = Listener(make('listener'), p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus)
    probes = ProbeManager(agent, deployment, 'laptop')
    probes.set_connections(['laser_amcl'])
    laser = Publisher(make('laser'), '/scan', rate_hz=20.0)

    def steady():
        r = reading(listener, 'laser_amcl')
        return r if r is not None and abs(r.rate_hz - 20.0) < 2.0 else None

    r = spin_until(executor, steady, 15.0, 'a 20 Hz reading of laser_amcl')
    assert r.level == p.OK and r.below_for_s == 0.0
    # Raw bytes: the serialised LaserScan of a Hokuyo URG-04LX (682 beams), 2788 B.
    assert r.bytes_per_s / r.rate_hz == pytest.approx(2788, rel=1e-3)
    diag = spin_until(executor, lambda: listener.last_status('anyscale/connection/laser_amcl'),
                      5.0, 'the probe on /diagnostics')
    assert diag.hardware_id == '127.0.0.1'
    assert {kv.key for kv in diag.values} >= {'rate_hz', 'bytes_per_s', 'below_for_s', 'topic'}
    laser.stop()
    warn = spin_until(executor, lambda: (reading(listener, 'laser_amcl').level == p.WARN
                                         and reading(listener, 'laser_amcl')),
                      5.0, 'WARN after the publisher stopped')
    assert warn.rate_hz < 5.0
    stopped_at = time.monotonic()
    error = spin_until(executor, lambda: (reading(listener, 'laser_amcl').level == p.ERROR
                                          and reading(listener, 'laser_amcl')),
                       6.0, 'ERROR once below freq_min for longer than Δ = 2 s')
    assert time.monotonic() - stopped_at >= 1.5
    assert error.below_for_s >= 2.0
    zero = spin_until(executor, lambda: reading(listener, 'laser_amcl').rate_hz == 0.0
                      and reading(listener, 'laser_amcl'), 3.0, 'a stopped topic to read 0')
    assert zero.bytes_per_s == 0.0
    status = spin_until(
        executor, lambda: (listener.last_status('anyscale/connection/laser_amcl').level
                           == bytes([p.ERROR])
                           and listener.last_status('anyscale/connection/laser_amcl')),
        3.0, 'ERROR on /diagnostics')
    assert 'below freq_min' in status.message
    probes.destroy()


def test_probe_places_arrivals_at_their_reception_time(ros, deployment):
    """The probe drains its subscription in batches (every 50 ms, and before each report): a
    batch taken late, here after 1.5 s in which nothing was spun (a starved agent), reads the
    rate the topic had, not a burst at the time of the take."""
    make, executor = ros.node, ros.executor
    probes = ProbeManager(make('agent_batch'), deployment, 'laptop')
    probes.set_connections(['laser_amcl'])
    node = make('laser_batch')
    msg = build_message(parse_endpoint(f'/scan:{TESTBED_TYPES["/scan"]}', output=True))
    pub = node.create_publisher(type(msg), '/scan', 10)
    try:
        spin_until(executor, lambda: pub.get_subscription_count() >= 1, 10.0,
                   'the probe to match the writer')
        start = time.monotonic()
        for k in range(30):        # 20 Hz on an absolute schedule; nothing spun meanwhile
            time.sleep(max(0.0, start + k * 0.05 - time.monotonic()))
            pub.publish(msg)
        reading, _ = probes.readings(time.monotonic())['laser_amcl']
        assert reading.rate_hz == pytest.approx(20.0, rel=0.05)
        assert reading.bytes_per_s == pytest.approx(20.0 * 2788, rel=0.05)
    finally:
        probes.destroy()


def test_slow_topics_are_drained_at_the_reports_and_a_fast_one_every_50_ms(ros, deployment):
    """A graph of topics at a few hertz is taken only when the probes report (the queue holds
    far more than a report period of them); a topic fast enough to fill a quarter of it in that
    time makes the probes drain every 50 ms again. The readings are the same either way."""
    make, executor = ros.node, ros.executor
    deployment = dataclasses.replace(deployment, monitoring=dataclasses.replace(
        deployment.monitoring, probe_publish_rate_hz=2.0))
    listener = Listener(make('drain_listener'), p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus)
    probes = ProbeManager(make('agent_drain'), deployment, 'laptop')
    probes.set_connections(['laser_amcl', 'camera_ar'])
    assert probes.tick_s == 0.05                  # rates not known yet
    try:
        laser = Publisher(make('laser_slow'), '/scan', rate_hz=5.0)
        spin_until(executor, lambda: probes.tick_s == 0.5, 15.0, 'the probes ticking at 2 Hz',
                   state=lambda: f'tick {probes.tick_s} s')
        n = len(listener.messages)
        spin_until(executor, lambda: len(listener.messages) >= n + 4, 5.0, 'four reports')
        assert reading(listener, 'laser_amcl').rate_hz == pytest.approx(5.0, rel=0.05)
        assert probes.tick_s == 0.5
        camera = Publisher(make('camera_fast'), '/image', rate_hz=200.0)
        spin_until(executor, lambda: probes.tick_s == 0.05, 10.0, 'the probes ticking at 20 Hz')
        spin_until(executor, lambda: (reading(listener, 'camera_ar') is not None and
                                      reading(listener, 'camera_ar').rate_hz > 150.0), 10.0,
                   'the fast topic read', state=lambda: reading(listener, 'camera_ar'))
        assert reading(listener, 'laser_amcl').rate_hz == pytest.approx(5.0, rel=0.05)
        camera.stop()
        laser.stop()
    finally:
        probes.destroy()


def test_probe_hears_a_newly_started_writer_of_a_migratable_publisher(ros, deployment):
    """What the agent asks before it lets a moving node's old copy go: has this scale heard the
    copy started elsewhere? Two real writers of /amcl_pose (AMCL is migratable), one long
    running, one started later."""
    make, executor = ros.node, ros.executor
    agent = make('agent_watch')
    probes = ProbeManager(agent, deployment, 'robot', handovers=True)
    probes.set_connections(['amcl_ekf', 'laser_navigation'])
    try:
        old = Publisher(make('amcl_old'), '/amcl_pose', rate_hz=20.0)

        def polled(cond):
            def check():
                probes.poll_writers()
                return cond()
            return check
        # The old copy's stream builds up (its numbers run past what the new copy will send).
        spin_until(executor, polled(lambda: old.sent >= 40 and
                                    probes.writer_joined_since('amcl_ekf', 0.0) is not None),
                   15.0, 'the old writer heard through the watch')
        assert probes.writer_joined_since('amcl_ekf', 0.0) is False
        assert probes.writer_joined_since('laser_navigation', 0.0) is None   # laser: pinned
        assert probes.writer_joined_since('camera_ar', 0.0) is None           # not probed here
        moved = time.monotonic()
        new = Publisher(make('amcl_new'), '/amcl_pose', rate_hz=5.0)
        spin_until(executor, polled(lambda: probes.writer_joined_since('amcl_ekf', moved)),
                   10.0, 'the new writer heard')
        assert new.sent >= 1
        assert not probes.writer_joined_since('amcl_ekf', time.monotonic() + 1.0)
        new.stop()
        old.stop()
    finally:
        probes.destroy()


def test_two_writers_heard_at_once_past_the_bound_are_an_error_diagnostic(ros, deployment):
    """Two real writers of /amcl_pose (AMCL is migratable) heard at once for longer than
    duplicate_sender_s: the reading counts them and for how long, the connection's diagnostic
    is an error naming the senders; once one stops, one sender and no error again."""
    make, executor = ros.node, ros.executor
    deployment = dataclasses.replace(deployment, monitoring=dataclasses.replace(
        deployment.monitoring, duplicate_sender_s=1.0))
    agent = make('agent_two')
    listener = Listener(make('two_listener'), p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus)
    probes = ProbeManager(agent, deployment, 'robot', handovers=True)
    probes.set_connections(['amcl_ekf'])
    diagnostic = 'anyscale/connection/amcl_ekf'

    def polled(cond):
        def check():
            probes.poll_writers()
            r = reading(listener, 'amcl_ekf')
            return r is not None and cond(r, listener.last_status(diagnostic))
        return check
    try:
        first = Publisher(make('amcl_first'), '/amcl_pose', rate_hz=10.0)
        spin_until(executor, polled(lambda r, _s: r.senders == 1), 15.0, 'one sender heard')
        assert reading(listener, 'amcl_ekf').senders_for_s == 0.0
        second = Publisher(make('amcl_second'), '/amcl_pose', rate_hz=10.0)
        spin_until(executor, polled(lambda r, s: r.senders == 2 and s is not None
                                    and s.level == bytes([p.ERROR])), 15.0,
                   'two senders, an error diagnostic')
        r, s = reading(listener, 'amcl_ekf'), listener.last_status(diagnostic)
        assert r.senders_for_s > 1.0 and r.level == p.OK       # the rate itself is fine
        assert s.message.startswith('2 senders for ') and 'copies of amcl' in s.message
        first.stop()
        spin_until(executor, polled(lambda r, s: r.senders == 1 and r.senders_for_s == 0.0
                                    and s.level != bytes([p.ERROR])), 15.0,
                   'one sender again')
        second.stop()
    finally:
        probes.destroy()


def test_probe_learns_the_type_from_the_graph_and_moves(ros, deployment):
    make, executor = ros.node, ros.executor
    conns = tuple(dataclasses.replace(c, msg_type='') if c.name == 'camera_ar' else c
                  for c in deployment.connections)
    deployment = dataclasses.replace(deployment, connections=conns)
    agent = make('agent_graph')
    listener = Listener(make('listener'), p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus)
    probes = ProbeManager(agent, deployment, 'laptop')
    probes.set_connections(['camera_ar'])
    # No publisher yet: the probe says what it waits for and reads nothing.
    waiting = spin_until(
        executor, lambda: listener.last_status('anyscale/connection/camera_ar'), 5.0,
        'a diagnostic of the waiting probe')
    assert 'waiting for a publisher' in waiting.message
    Publisher(make('camera'), '/image', rate_hz=30.0)
    spin_until(executor, lambda: (reading(listener, 'camera_ar') is not None
                                  and abs(reading(listener, 'camera_ar').rate_hz - 30.0) < 3.0),
               15.0, 'camera_ar at 30 Hz once the type is learnt')
    # The layout changes: the probe is removed; a bad name changes nothing.
    with pytest.raises(ValueError, match='no connection .nope.'):
        probes.set_connections(['camera_ar', 'nope'])
    assert probes.connections == ('camera_ar',)
    probes.set_connections(['ar_navigation'])
    assert probes.connections == ('ar_navigation',)
    listener.messages.clear()
    last = spin_until(executor, lambda: listener.messages and listener.messages[-1], 3.0,
                      'a status after the move')
    assert set(last.connections) == {'ar_navigation'}
    probes.destroy()


def test_unusable_message_type_is_stale_not_zero(ros, deployment):
    make, executor = ros.node, ros.executor
    conns = tuple(dataclasses.replace(c, msg_type='no_such_pkg/msg/Nothing')
                  if c.name == 'amcl_ekf' else c for c in deployment.connections)
    deployment = dataclasses.replace(deployment, connections=conns)
    listener = Listener(make('listener'), p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus)
    probes = ProbeManager(make('agent_bad'), deployment, 'robot')
    probes.set_connections(['amcl_ekf', 'odometry_ekf'])
    s = spin_until(executor, lambda: listener.last_status('anyscale/connection/amcl_ekf'), 5.0,
                   'the stale probe')
    assert s.level == bytes([p.STALE]) and 'no_such_pkg' in s.message
    msg = spin_until(executor, lambda: listener.messages and listener.messages[-1], 3.0,
                     'a connection status')
    assert set(msg.connections) == {'odometry_ekf'}
    probes.destroy()


@pytest.mark.parametrize('name', ['', 'std_msgs', 'std_msgs/msg/', '../x/msg/Y',
                                  'std_msgs/msg/NoSuchType', 'os/msg/path'])
def test_import_message_class_refuses_bad_names(name):
    with pytest.raises(ValueError, match='message type'):
        import_message_class(name)


def test_import_message_class():
    assert import_message_class('std_msgs/msg/String') is String
    assert import_message_class('std_msgs/UInt8MultiArray') is UInt8MultiArray


# --- scale monitor -----------------------------------------------------------------------------

BUSY_PARENT = ('import subprocess, sys, time\n'
               'child = subprocess.Popen([sys.executable, "-c", "while True: pass"])\n'
               'print(child.pid, flush=True)\n'
               'time.sleep(60)\n')


def test_scale_monitor_publishes_sane_values_with_children(ros, deployment, python):
    make, executor = ros.node, ros.executor
    parent = subprocess.Popen([python, '-c', BUSY_PARENT], stdout=subprocess.PIPE, text=True)
    idle = subprocess.Popen([python, '-c', 'import time; time.sleep(60)'])
    try:
        child = int(parent.stdout.readline())
        listener = Listener(make('listener'), p.TOPIC_SCALE_STATUS, p.ScaleStatus)
        monitor = ScaleMonitor(make('agent_scale'), deployment, 'robot',
                               lambda: {'busy': parent.pid, 'idle': idle.pid,
                                        'gone': 999999999})
        robot = deployment.scale('robot')
        # Two readings so the busy loop has run over a whole period.
        spin_until(executor, lambda: len(listener.messages) >= 3, 10.0, 'scale status')
        s = listener.messages[-1]
        assert s.scale == 'robot' and s.capacity_cpu == robot.capacity_cpu
        assert 0.0 < s.cpu_total <= robot.capacity_cpu
        assert 0.0 < s.mem_percent <= 100.0 and s.load_1m >= 0.0
        # The CPUs its readings are spread over: the machine's, or fewer under a quota.
        assert s.cores is not None and 0.0 < s.cores <= psutil_cpus()
        assert 'gone' not in s.cpu_by_node
        assert 0.0 <= s.cpu_by_node['idle'] < 5.0
        # The parent sleeps; its child spins. The node's CPU includes the child's: on a busy
        # shared machine it gets at least a fifth of a core (one core = capacity / cores).
        one_core = robot.capacity_cpu / psutil_cpus()
        assert s.cpu_by_node['busy'] >= 0.2 * one_core
        assert s.cpu_by_node['busy'] <= 1.1 * one_core
        assert s.cpu_by_node['busy'] <= s.cpu_total + 0.2 * one_core
        assert child > 0
        diag = spin_until(executor, lambda: listener.last_status('anyscale/scale/robot'), 3.0,
                          'the scale diagnostic')
        assert diag.hardware_id == '127.0.0.1'
        monitor.destroy()
    finally:
        for proc in psutil_tree(parent.pid):
            proc.kill()
        parent.wait(timeout=5)
        idle.kill()
        idle.wait(timeout=5)


def psutil_cpus():
    import psutil
    return psutil.cpu_count()


def psutil_tree(pid):
    import psutil
    try:
        leader = psutil.Process(pid)
        return leader.children(recursive=True) + [leader]
    except psutil.Error:
        return []


def test_scale_monitor_survives_a_failing_pids_callback(ros, deployment):
    make, executor = ros.node, ros.executor
    listener = Listener(make('listener'), p.TOPIC_SCALE_STATUS, p.ScaleStatus)

    def broken():
        raise RuntimeError('agent bug')

    monitor = ScaleMonitor(make('agent_broken'), deployment, 'laptop', broken)
    spin_until(executor, lambda: len(listener.messages) >= 2, 10.0, 'scale status')
    assert listener.messages[-1].cpu_by_node == {}
    monitor.destroy()
    with pytest.raises(ValueError, match='no scale'):
        ScaleMonitor(make('agent_unknown'), deployment, 'mars', dict)


# --- link monitor ------------------------------------------------------------------------------

def test_link_monitor_heartbeats_bandwidth_and_down(ros, deployment, python, tmp_path,
                                                    request):
    make, executor = ros.node, ros.executor
    listener = Listener(make('listener'), p.TOPIC_LINK_STATUS, p.LinkStatus)
    master = LinkMonitor(make('agent_robot'), deployment, 'robot')
    remote = LinkMonitor(make('agent_laptop'), deployment, 'laptop')   # the probe server
    # The laptop's warden answers the heartbeats; no agent has written its state file, so it
    # reports the agent gone, then fenced (nothing to stop).
    echo = subprocess.Popen(
        [python, '-m', 'anyscale_manager.agent.warden', '--state', str(tmp_path / 'a.json'),
         '--scale', 'laptop', '--deployment', deployment.name, '--host', '127.0.0.1',
         '--port', str(warden.warden_port(deployment, 'laptop')), '--adopt-grace', '0.2'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    request.addfinalizer(lambda: (echo.kill(), echo.wait()))
    feeder = make('feeder')
    # Where nodes run and what the probes measured: laser (robot) -> amcl (laptop) crosses.
    state_pub = feeder.create_publisher(String, p.TOPIC_AGENT_STATE, LATCHED_QOS)
    conn_pub = feeder.create_publisher(String, p.TOPIC_CONNECTION_STATUS, STATUS_QOS)
    running = p.NodeReport(state='running', pid=1, since=0.0, restarts=0, ready=True,
                           exit_reason='')
    for scale, nodes in (('robot', ['laser', 'navigation']), ('laptop', ['amcl'])):
        state = p.AgentState(scale=scale, generation=1, stamp=0.0,
                             nodes={n: running for n in nodes})
        state_pub.publish(String(data=state.to_json()))
    readings = p.ConnectionStatus(scale='laptop', stamp=0.0, connections={
        'laser_amcl': p.ConnectionReading(rate_hz=10.0, bytes_per_s=25000.0, below_for_s=0.0,
                                          level=p.OK),
        'laser_navigation': p.ConnectionReading(rate_hz=10.0, bytes_per_s=25000.0,
                                                below_for_s=0.0, level=p.OK)})
    feeder.create_timer(0.2, lambda: conn_pub.publish(String(data=readings.to_json())))

    def measured():
        m = listener.messages[-1] if listener.messages else None
        ok = m is not None and m.up and m.bandwidth_available_kbps is not None \
            and m.bandwidth_used_kbps > 0
        return m if ok else None

    status = spin_until(executor, measured, 20.0, 'an up link with both bandwidths')
    assert status.master == 'robot' and status.remote == 'laptop'
    assert status.rtt_ms is not None and 0.0 < status.rtt_ms < 200.0
    assert status.loss <= 0.2
    # Only laser_amcl crosses (navigation runs on the robot): 25000 B/s = 200 kbit/s.
    assert status.bandwidth_used_kbps == pytest.approx(200.0)
    assert status.bandwidth_available_kbps > 10000.0            # loopback is fast
    assert 0.0 <= status.bandwidth_available_age_s < 5.0
    spin_until(executor, lambda: listener.messages[-1].peer_agent == 'fenced', 5.0,
               "the warden's word on the (absent) agent")
    diag = listener.last_status('anyscale/link/wifi')
    assert diag is not None and diag.hardware_id == '127.0.0.1'

    # The whole process stalls (a paused machine, a saturated scale): nothing spins for 2 s, so
    # no beat goes out and no echo is read. That is no cut: the link stays up throughout.
    period = 1.0 / deployment.monitoring.heartbeat_rate_hz
    stall = 2.0
    assert stall > deployment.monitoring.heartbeat_misses_down * period
    before = len(listener.messages)
    time.sleep(stall)                                           # the stall itself, not a wait
    spin_until(executor, lambda: len(listener.messages) >= before + 4, 10.0,
               'four link statuses after the stall')
    assert all(m.up for m in listener.messages[before:]), [
        m.up for m in listener.messages[before:]]

    echo.kill()                                                 # the remote stops answering
    echo.wait()
    remote.destroy()
    cut = time.monotonic()
    spin_until(executor, lambda: listener.messages and not listener.messages[-1].up, 5.0,
               'the link reported down')
    # Down within misses_down periods of the last echo (plus scheduling slack on a busy box).
    assert time.monotonic() - cut <= deployment.monitoring.heartbeat_misses_down * period + 1.0
    spin_until(executor, lambda: (listener.last_status('anyscale/link/wifi').level
                                  == bytes([p.ERROR])), 3.0, 'ERROR on /diagnostics')
    master.destroy()


def watched_link(make, deployment, python, tmp_path, request, tag):
    """A listener of /anyscale/link_status, the robot's watching LinkMonitor, the laptop's
    (its probe server) and the laptop's warden answering the beats (a process, killed at the
    test's end)."""
    listener = Listener(make(f'{tag}_listener'), p.TOPIC_LINK_STATUS, p.LinkStatus)
    master = LinkMonitor(make(f'agent_robot_{tag}'), deployment, 'robot')
    remote = LinkMonitor(make(f'agent_laptop_{tag}'), deployment, 'laptop')
    echo = subprocess.Popen(
        [python, '-m', 'anyscale_manager.agent.warden', '--state', str(tmp_path / 'a.json'),
         '--scale', 'laptop', '--deployment', deployment.name, '--host', '127.0.0.1',
         '--port', str(warden.warden_port(deployment, 'laptop'))],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    request.addfinalizer(lambda: (echo.kill(), echo.wait()))
    return listener, master, remote, echo


def test_a_link_up_and_not_probed_wakes_its_monitor_for_the_beats_only(
        ros, deployment, python, tmp_path, request):
    """While the link is up and not probed, the watching monitor's timer wakes at the beats and
    at the first moment the down rule could be met, not CHECKS_PER_BEAT times a period; a cut
    is still judged within misses_down periods of the last echo, and a link down is checked
    every quarter period again."""
    make, executor = ros.node, ros.executor
    deployment = dataclasses.replace(deployment, monitoring=dataclasses.replace(
        deployment.monitoring, bandwidth_probe_interval_s=86400.0))
    listener, master, remote, echo = watched_link(make, deployment, python, tmp_path, request,
                                                  'quiet')
    try:
        # Up, and probed once (at once, then not for a day).
        spin_until(executor, lambda: master.quiet and listener.messages
                   and listener.messages[-1].up
                   and listener.messages[-1].bandwidth_available_kbps is not None, 20.0,
                   'the link up and probed, its monitor quiet')
        wakes = []
        run = master._cadence.run
        master._cadence.run = lambda now: (wakes.append(now), run(now))
        before = len(listener.messages)
        spin_until(executor, lambda: len(wakes) > 0 and wakes[-1] - wakes[0] >= 2.0, 10.0,
                   'two seconds of wakes')
        rate_hz = deployment.monitoring.heartbeat_rate_hz
        assert (len(wakes) - 1) / (wakes[-1] - wakes[0]) <= 1.25 * rate_hz, len(wakes)
        assert all(m.up for m in listener.messages[before:])
        # Nothing the decider acts on changed: a status per refresh, not one per beat.
        sent = len(listener.messages) - before
        assert master._refresh_s > 1.5 / rate_hz
        assert sent <= (wakes[-1] - wakes[0]) / master._refresh_s + 2, sent
        echo.kill()
        echo.wait()
        cut = time.monotonic()
        spin_until(executor, lambda: not listener.messages[-1].up, 5.0, 'the link down')
        period = 1.0 / rate_hz
        assert time.monotonic() - cut <= deployment.monitoring.heartbeat_misses_down * period \
            + 1.0
        assert not master.quiet
    finally:
        remote.destroy()
        master.destroy()


def test_the_status_a_link_monitor_publishes_is_the_verdict_it_judged_and_logged(
        ros, deployment, python, tmp_path, request):
    """What goes out on /anyscale/link_status is the verdict the monitor judged with the echoes
    read (and logged on a change), never one worked out again at the beat: there the beat just
    sent counted as unanswered against echoes not yet read, and a "down" that the monitor
    never logged reached the decider, which moved nodes home (an e2e run, 1 in 2)."""
    make, executor = ros.node, ros.executor
    listener, master, remote, _ = watched_link(make, deployment, python, tmp_path, request,
                                               'verdict')
    try:
        spin_until(executor, lambda: listener.messages and listener.messages[-1].up, 20.0,
                   'the link up')
        watched = master._remotes['laptop']
        assert watched.was_up
        # A judgement at the beat that the checked verdict does not share.
        master._up = lambda _remote, _now: False
        before = len(listener.messages)
        with master._beats_lock:
            master._publish(watched, time.monotonic(), 0.0)
        spin_until(executor, lambda: len(listener.messages) > before, 5.0, 'the status')
        assert listener.messages[-1].up and watched.was_up
    finally:
        remote.destroy()
        master.destroy()


def test_the_probe_reads_when_the_link_last_acknowledged_its_data():
    """The ACK age the link monitor counts as the link heard during its own probe
    (TCP_INFO's tcpi_last_ack_recv): small just after data is acknowledged, growing while the
    connection is idle."""
    from anyscale_manager.nodes.monitors.throughput import last_ack_age_s
    with socket.create_server(('127.0.0.1', 0)) as server:
        sender = socket.create_connection(server.getsockname())
        receiver, _ = server.accept()
        with sender, receiver:
            sender.sendall(b'x' * 1000)
            assert receiver.recv(1000)
            deadline = time.monotonic() + 5.0
            while (last_ack_age_s(sender) or 0.0) < 0.3:       # idle: the age grows
                assert time.monotonic() < deadline, last_ack_age_s(sender)
                time.sleep(0.02)
            sent = time.monotonic()
            sender.sendall(b'y' * 1000)
            assert receiver.recv(1000)
            deadline = time.monotonic() + 5.0
            while last_ack_age_s(sender) > time.monotonic() - sent + 0.02:
                assert time.monotonic() < deadline, last_ack_age_s(sender)  # never acked
                time.sleep(0.005)
    assert last_ack_age_s(socket.socket(socket.AF_INET, socket.SOCK_DGRAM)) is None


def test_probe_server_measures_and_refuses_strangers():
    port = free_port()
    server = ProbeServer('127.0.0.1', port)
    try:
        bps = probe_throughput('127.0.0.1', port, 0.2)
        assert bps > 1e6
        with socket.create_connection(('127.0.0.1', port), timeout=3.0) as s:
            s.sendall(b'GET / HTTP/1.0\r\n\r\n')
            s.settimeout(3.0)
            try:
                assert s.recv(100) == b''                  # dropped without an answer
            except ConnectionResetError:
                pass
        assert probe_throughput('127.0.0.1', port, 0.1) > 0  # and still serving
    finally:
        server.close()
    with pytest.raises(OSError):
        probe_throughput('127.0.0.1', port, 0.1, timeout_s=1.0)


def test_probe_server_of_another_deployment_or_scale_is_not_measured():
    port = free_port()
    server = ProbeServer('127.0.0.1', port, deployment='lab', scale='laptop')
    try:
        assert probe_throughput('127.0.0.1', port, 0.1, deployment='lab', scale='laptop') > 0
        for deployment, scale in (('field', 'laptop'), ('lab', 'server')):
            with pytest.raises(ValueError) as e:
                probe_throughput('127.0.0.1', port, 0.1, deployment=deployment, scale=scale)
            assert "scale 'laptop' of deployment 'lab'" in str(e.value)
            assert f'not scale {scale!r} of deployment {deployment!r}' in str(e.value)
        assert probe_throughput('127.0.0.1', port, 0.1, deployment='lab', scale='laptop') > 0
    finally:
        server.close()


def test_a_slow_request_does_not_hold_the_probe_server():
    """A sender trickling its request a byte at a time is dropped REQUEST_S after it began:
    the one probe server is free again for the master (which waits up to its timeout)."""
    from anyscale_manager.nodes.monitors import throughput
    port = free_port()
    server = ProbeServer('127.0.0.1', port, deployment='lab', scale='laptop')
    stop, connected = threading.Event(), threading.Event()

    def trickle():
        with socket.create_connection(('127.0.0.1', port), timeout=3.0) as s:
            connected.set()             # in the backlog first: the server takes it first
            for byte in throughput.PROBE_MAGIC + bytes(100):
                if stop.wait(0.5):      # the header alone would take 7 s
                    return
                try:
                    s.sendall(bytes([byte]))
                except OSError:
                    return          # dropped
    slow = threading.Thread(target=trickle, daemon=True)
    try:
        slow.start()
        assert connected.wait(5.0)
        assert probe_throughput('127.0.0.1', port, 0.1, timeout_s=throughput.REQUEST_S + 3.0,
                                deployment='lab', scale='laptop') > 0
    finally:
        stop.set()
        slow.join(5.0)
        server.close()


def test_link_monitor_refuses_unknown_scale(ros, deployment):
    make = ros.node
    with pytest.raises(ValueError, match='no scale'):
        LinkMonitor(make('x'), deployment, 'mars')
    with pytest.raises(ValueError, match='no scale'):
        ProbeManager(make('y'), deployment, 'mars')


def test_a_message_is_placed_at_its_dds_reception_time_never_in_the_future():
    from anyscale_manager.nodes.monitors.probes import received_at
    info = {'received_timestamp': int(1000.25 * 1e9)}
    assert received_at(info, offset_s=990.0, now=20.0) == 10.25
    assert received_at(info, offset_s=990.0, now=10.0) == 10.0     # a clock step: not later
    assert received_at({}, offset_s=990.0, now=12.0) == 12.0        # none given: now
    assert received_at(None, offset_s=990.0, now=12.0) == 12.0


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v']))
