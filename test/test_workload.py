"""The workload node: argument checks, message types and shapes, the output gate, CPU work, and
real processes over DDS."""

import math
import os
import re
import signal
import subprocess
import sys
import time

import pytest
import rclpy.time
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.serialization import serialize_message
from std_msgs.msg import UInt8MultiArray

from anyscale_manager.agent.catalogue import LIFECYCLE_SERVICES, LIFECYCLE_TOPICS
from anyscale_manager.agent.procs import stop_popen
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.model.types import (Connection, Deployment, Launch, MonitorSettings, Node,
                                          Scale)
from anyscale_manager.nodes.monitors import ProbeManager
from anyscale_manager.nodes.workload import (OutputGate, WorkloadNode, burn_cpu, parse_spec,
                                             publisher_qos, subscriber_qos)
from anyscale_manager.nodes.workload_lifecycle import LifecycleWorkloadNode
from anyscale_manager.nodes.workload_pose import PoseTrack, yaw_of
from anyscale_manager.nodes.workload_messages import (KINDS, Endpoint, EndpointError,
                                                      build_message, message_class,
                                                      parse_endpoint, stamper)
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from spinning import RosContext


# --- pure parts ---------------------------------------------------------------------------------

@pytest.mark.parametrize('argv, message', [
    (['--pub', '/x'], '--name'),
    (['--name', 'a'], 'nothing to do'),
    (['--name', 'a', '--pub', '/x', '--rate-hz', '0'], '--rate-hz'),
    (['--name', 'a', '--pub', '/x', '--rate-hz', 'fast'], '--rate-hz'),
    (['--name', 'a', '--pub', '/x', '--bytes', '-1'], '--bytes'),
    (['--name', 'a', '--pub', '/x', '--work-ms', 'nan'], '--work-ms'),
    (['--name', 'a', '--sub', '/x', '--once'], '--once'),
    (['--name', '9lives', '--pub', '/x'], 'valid ROS node name'),
    (['--name', 'a', '--pub', '/s:sensor_msgs/msg/Laserscan'],
     'did you mean sensor_msgs/msg/LaserScan?'),
    (['--name', 'a', '--pub', '/s:sensor_msgs/msg/Imu'], 'cannot fill this type'),
    (['--name', 'a', '--pub', '/i:sensor_msgs/msg/Image:176x144:mono9'], 'did you mean mono8?'),
    (['--name', 'a', '--pub', '/o:nav_msgs/msg/Odometry:3'], 'fixed size'),
    (['--name', 'a', '--sub', '/s:sensor_msgs/msg/LaserScan:682', '--pub', '/x'],
     'an input takes TOPIC[:TYPE]'),
    (['--name', 'a', '--sub', '/s:no_such_msgs/msg/Scan', '--pub', '/x'],
     'no message package no_such_msgs'),
    (['--name', 'a', '--pub', '/s:sensor_msgs/msg/LaserScan', '--bytes', '100'],
     '--bytes sizes std_msgs/msg/UInt8MultiArray outputs'),
])
def test_bad_arguments_are_refused_with_the_argument_named(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        parse_spec(argv)
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_lifecycle_is_a_flag_and_off_by_default():
    assert not parse_spec(['--name', 'amcl', '--sub', '/scan', '--pub', '/pose']).lifecycle
    assert parse_spec(['--name', 'amcl', '--sub', '/scan', '--pub', '/pose',
                       '--lifecycle']).lifecycle


def test_arguments_of_the_testbed_amcl():
    spec = parse_spec(['--name', 'amcl', '--sub', '/scan:sensor_msgs/msg/LaserScan', '--sub',
                       '/map:nav_msgs/OccupancyGrid', '--pub',
                       '/amcl_pose:geometry_msgs/msg/PoseWithCovarianceStamped', '--rate-hz',
                       '5.0', '--work-ms', '100', '--reference-core', '0.25'])
    assert spec.inputs == (Endpoint('/scan', 'sensor_msgs/msg/LaserScan'),
                           Endpoint('/map', 'nav_msgs/msg/OccupancyGrid'))
    assert spec.driver == '/scan'
    assert spec.outputs == (Endpoint('/amcl_pose',
                                     'geometry_msgs/msg/PoseWithCovarianceStamped'),)
    assert not spec.is_sensor
    assert spec.cpu_s_per_output == pytest.approx(0.025)


def test_untyped_arguments_mean_byte_arrays_as_before():
    spec = parse_spec(['--name', 'old', '--sub', '/in', '--pub', '/out', '--pub',
                       '/big:std_msgs/msg/UInt8MultiArray:5000', '--bytes', '128'])
    assert spec.inputs == (Endpoint('/in', 'std_msgs/msg/UInt8MultiArray'),)
    assert spec.outputs == (Endpoint('/out', 'std_msgs/msg/UInt8MultiArray', (128,)),
                            Endpoint('/big', 'std_msgs/msg/UInt8MultiArray', (5000,)))
    assert parse_spec(['--name', 'old', '--pub', '/out']).outputs[0].shape == (64,)


# The message of each type a workload fills, and what a reader should find in it.
CONTENT = {
    'sensor_msgs/msg/LaserScan': lambda m: (
        len(m.ranges) == 682 and m.intensities.tolist() == [] and m.header.frame_id == 'laser'
        and m.range_min == pytest.approx(0.02) and m.range_max == pytest.approx(5.6)
        and all(m.range_min <= r <= m.range_max for r in m.ranges)
        and m.angle_max - m.angle_min == pytest.approx(681 * 2 * 3.141592653589793 / 1024)),
    'sensor_msgs/msg/Image': lambda m: (
        (m.width, m.height, m.encoding, m.step, len(m.data)) == (176, 144, 'mono8', 176, 25344)
        and len(set(m.data)) > 10 and m.header.frame_id == 'camera'),
    'nav_msgs/msg/Odometry': lambda m: (
        (m.header.frame_id, m.child_frame_id) == ('odom', 'base_footprint')
        and m.pose.covariance[0] > 0 and m.twist.twist.linear.x > 0
        and m.pose.pose.orientation.w ** 2 + m.pose.pose.orientation.z ** 2
        == pytest.approx(1.0)),
    'geometry_msgs/msg/PoseWithCovarianceStamped': lambda m: (
        m.header.frame_id == 'map' and m.pose.covariance[35] > 0
        and m.pose.covariance[1] == m.pose.covariance[6]),
    'sensor_msgs/msg/JointState': lambda m: (
        m.name == ['wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br']
        and len(m.position) == len(m.velocity) == len(m.effort) == 4),
    'nav_msgs/msg/OccupancyGrid': lambda m: (
        (m.info.width, m.info.height, len(m.data)) == (200, 200, 40000)
        and {-1, 0, 100} == set(m.data) and m.info.resolution == pytest.approx(0.05)),
    'geometry_msgs/msg/PoseArray': lambda m: len(m.poses) == 4 and m.header.frame_id == 'camera',
    'geometry_msgs/msg/Twist': lambda m: m.linear.x > 0,
    'std_msgs/msg/UInt8MultiArray': lambda m: len(m.data) == 64,
}
# The test-bed's shapes: (output argument, serialised size).
TESTBED_OUTPUTS = {
    'sensor_msgs/msg/LaserScan': ('/t:sensor_msgs/msg/LaserScan:682', 2788),
    'sensor_msgs/msg/Image': ('/t:sensor_msgs/msg/Image:176x144:mono8', 25396),
    'nav_msgs/msg/Odometry': ('/t:nav_msgs/msg/Odometry', 724),
    'geometry_msgs/msg/PoseWithCovarianceStamped': (
        '/t:geometry_msgs/msg/PoseWithCovarianceStamped', 364),
    'sensor_msgs/msg/JointState': ('/t:sensor_msgs/msg/JointState:4', 228),
    'nav_msgs/msg/OccupancyGrid': ('/t:nav_msgs/msg/OccupancyGrid:200x200:0.05', 40104),
    'geometry_msgs/msg/PoseArray': ('/t:geometry_msgs/msg/PoseArray:4', 252),
    'geometry_msgs/msg/Twist': ('/t:geometry_msgs/msg/Twist', 52),
    'std_msgs/msg/UInt8MultiArray': ('/t', 80),
}


def test_every_type_a_workload_fills_is_covered_here():
    assert set(KINDS) == set(CONTENT) == set(TESTBED_OUTPUTS)


@pytest.mark.parametrize('type_name', sorted(TESTBED_OUTPUTS))
def test_each_type_is_filled_with_plausible_content_of_its_size(type_name):
    argument, size = TESTBED_OUTPUTS[type_name]
    endpoint = parse_endpoint(argument, output=True)
    msg = build_message(endpoint)
    assert isinstance(msg, message_class(type_name))
    assert CONTENT[type_name](msg)
    assert len(serialize_message(msg)) == size
    stamp = stamper(endpoint)
    assert (stamp is None) == (not hasattr(msg, 'header'))


@pytest.mark.parametrize('argument, expected', [
    ('/image:sensor_msgs/Image', Endpoint('/image', 'sensor_msgs/msg/Image', (640, 480, 'rgb8'))),
    ('/image:sensor_msgs/msg/Image:1280x720:bgr8',
     Endpoint('/image', 'sensor_msgs/msg/Image', (1280, 720, 'bgr8'))),
    ('/scan:sensor_msgs/msg/LaserScan:1081',
     Endpoint('/scan', 'sensor_msgs/msg/LaserScan', (1081,))),
    ('/map:nav_msgs/msg/OccupancyGrid:400x300:0.1',
     Endpoint('/map', 'nav_msgs/msg/OccupancyGrid', (400, 300, 0.1))),
    ('/joints:sensor_msgs/msg/JointState:7',
     Endpoint('/joints', 'sensor_msgs/msg/JointState', (7,))),
])
def test_output_shapes(argument, expected):
    assert parse_endpoint(argument, output=True) == expected


@pytest.mark.parametrize('argument, output, words', [
    ('/s:LaserScan', True, 'did you mean sensor_msgs/msg/LaserScan?'),
    ('/i:sensor_msgs/msg/Image:176x144:mono8:9', True, 'expected WIDTHxHEIGHT[:ENCODING]'),
    ('/i:sensor_msgs/msg/Image:0x144', True, 'width and height'),
    ('/m:nav_msgs/msg/OccupancyGrid:10x10:-1', True, 'metres per cell'),
    ('/p:geometry_msgs/msg/PoseArray:many', True, 'whole number of poses'),
    ('/x:std_msgs/msg/UInt8MultiArray:99999999999', True, 'out of range'),
    ('/s:sensor_msgs/msg/LaserScan:682', False, 'no shape'),
    ('bad topic:std_msgs/msg/String', False, 'bad topic name'),
])
def test_bad_endpoints_say_why(argument, output, words):
    with pytest.raises(EndpointError, match=re.escape(words)):
        parse_endpoint(argument, output=output)


def test_testbed_connections_carry_what_their_ends_publish_and_subscribe(testbed_path):
    """Every connection's msg_type is what its publisher's workload publishes on the topic and
    what its subscriber's workload subscribes to: no UInt8MultiArray left, and a probe on the
    declared type matches the real writer."""
    d = load_deployment(testbed_path)
    outputs, inputs = {}, {}
    for node in d.nodes:
        if node.launch.executable != 'workload':
            continue
        spec = parse_spec(list(node.launch.arguments))
        outputs.update({(node.name, e.topic): e.msg_type for e in spec.outputs})
        inputs.update({(node.name, e.topic): e.msg_type for e in spec.inputs})
    for c in d.connections:
        assert c.msg_type != 'std_msgs/msg/UInt8MultiArray', c.name
        assert outputs[(c.publisher, c.topic)] == c.msg_type, c.name
        assert inputs[(c.subscriber, c.topic)] == c.msg_type, c.name
    pose = 'geometry_msgs/msg/PoseWithCovarianceStamped'
    assert {c.topic: c.msg_type for c in d.connections} == {
        '/scan': 'sensor_msgs/msg/LaserScan', '/wheel_ticks': 'sensor_msgs/msg/JointState',
        '/image': 'sensor_msgs/msg/Image', '/amcl_pose': pose, '/odom': 'nav_msgs/msg/Odometry',
        '/pose': pose, '/markers': 'geometry_msgs/msg/PoseArray'}
    # AR's input stays about 6 Mbit/s: the camera's frame at its 30 Hz.
    image = next(c for c in d.connections if c.topic == '/image')
    camera = parse_spec(list(d.node('camera').launch.arguments))
    frame = len(serialize_message(build_message(camera.outputs[0])))
    assert frame * 8 * camera.rate_hz / 1000 == pytest.approx(6000, rel=0.03)
    assert image.bandwidth_kbps == pytest.approx(frame * 8 * camera.rate_hz / 1000, abs=1)


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


@pytest.mark.parametrize('input_hz, jitter_s, cap_hz, expected_hz', [
    (10.0, 0.0, 5.0, 5.0),
    (10.0, 0.02, 5.0, 5.0),     # jittered arrivals do not drop the output to 3.3 Hz
    (4.0, 0.0, 5.0, 4.0),       # slower input: output follows the input
    (30.0, 0.005, 30.0, 30.0),
])
def test_output_gate_caps_the_rate(input_hz, jitter_s, cap_hz, expected_hz):
    gate = OutputGate(cap_hz)
    outputs = 0
    for i in range(int(input_hz * 20)):
        now = i / input_hz + (jitter_s if i % 2 else -jitter_s)
        if gate.ready(now):
            gate.started(now)
            outputs += 1
    assert outputs / 20.0 == pytest.approx(expected_hz, rel=0.06)


def test_output_gate_does_not_burst_after_a_pause():
    gate = OutputGate(5.0)
    gate.started(0.0)
    assert not gate.ready(0.05)
    assert gate.ready(10.0)
    gate.started(10.0)      # a long pause does not leave a burst of catch-up outputs behind
    assert not gate.ready(10.05)
    assert gate.ready(10.2)


def test_output_gate_lets_a_cpu_bound_node_run_back_to_back():
    gate = OutputGate(5.0)     # 0.2 s period, but each output takes 0.3 s of work
    now, outputs = 0.0, 0
    while now < 30.0:
        assert gate.ready(now)
        gate.started(now)
        now += 0.3
        outputs += 1
    assert outputs / 30.0 == pytest.approx(1 / 0.3, rel=0.02)


def test_burn_cpu_uses_the_cpu_time_asked_for():
    start = time.thread_time()
    burn_cpu(0.05)
    used = time.thread_time() - start
    assert 0.05 <= used < 0.2
    assert burn_cpu(0.0) == 0


def test_burn_cpu_with_a_fake_clock_stops_at_the_deadline():
    ticks = iter([0.0, 0.0, 0.01, 0.02, 0.03])
    burn_cpu(0.02, clock=lambda: next(ticks))   # would raise StopIteration if it overran


# --- real processes over DDS --------------------------------------------------------------------

def _start(python, env, *args):
    return subprocess.Popen([python, '-m', 'anyscale_manager.nodes.workload', *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def _stop(proc, timeout=10.0):
    """SIGINT and wait; a workload that outlives it writes every thread's stack to its log
    (its SIGUSR1) before it is killed, so a hang at exit says where it hung."""
    try:
        os.killpg(proc.pid, signal.SIGINT)
        return proc.wait(timeout)
    except ProcessLookupError:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        try:
            proc.wait(1.0)
        except subprocess.TimeoutExpired:
            pass
    return stop_popen(proc, 0.0)


LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Counter:
    """Arrival times, sizes (of a ``data`` field) and the last message per topic, deserialised
    by a node in its own context; ``types``: topic -> message class (UInt8MultiArray)."""

    def __init__(self, topics, latched=False, types=None):
        self.ros = RosContext()
        self.node = self.ros.node('workload_test_counter')
        self.arrivals = {t: [] for t in topics}
        self.sizes = {t: set() for t in topics}
        self.messages = {t: [] for t in topics}
        for topic in topics:
            qos = LATCHED if latched else subscriber_qos()
            cls = (types or {}).get(topic, UInt8MultiArray)
            self.node.create_subscription(cls, topic, self._callback(topic), qos)

    def _callback(self, topic):
        def cb(msg):
            self.arrivals[topic].append(time.monotonic())
            if hasattr(msg, 'data'):
                self.sizes[topic].add(len(msg.data))
            self.messages[topic] = self.messages[topic][-4:] + [msg]
        return cb

    def spin_until(self, condition, timeout_s, what, state=None):
        """Spin until ``condition()``; a failure shows ``state()``, or the arrivals so far."""
        return self.ros.spin_until(condition, timeout_s, what, state=state or (
            lambda: {topic: len(times) for topic, times in self.arrivals.items()}))

    def spin_for(self, seconds):
        self.ros.spin_for(seconds)

    def rate(self, topic, window_s):
        """Messages per second over the last window_s seconds."""
        now = time.monotonic()
        return sum(1 for t in self.arrivals[topic] if t >= now - window_s) / window_s

    def close(self):
        self.ros.close()


IMAGE = 'sensor_msgs/msg/Image'
MARKERS = 'geometry_msgs/msg/PoseArray'


def test_sensor_and_processing_chain_rates_follow_input_cap_and_cpu(python, ros_env):
    """The test-bed's camera and AR, typed: Image in, marker PoseArray out."""
    camera = _start(python, ros_env, '--name', 'camera', '--pub',
                    f'/wl_image:{IMAGE}:176x144:mono8', '--rate-hz', '30')
    light = _start(python, ros_env, '--name', 'ar_light', '--sub', f'/wl_image:{IMAGE}',
                   '--pub', f'/wl_light:{MARKERS}:4', '--rate-hz', '10', '--work-ms', '5')
    # 1 s of reference work = 0.2 s of this machine's CPU per output: at most 5 Hz, cap 30 Hz.
    heavy = _start(python, ros_env, '--name', 'ar_heavy', '--sub', f'/wl_image:{IMAGE}',
                   '--pub', f'/wl_heavy:{MARKERS}:2', '--rate-hz', '30', '--work-ms', '1000')
    counter = Counter(['/wl_image', '/wl_light', '/wl_heavy'],
                      types={'/wl_image': message_class(IMAGE), '/wl_light':
                             message_class(MARKERS), '/wl_heavy': message_class(MARKERS)})
    try:
        counts = counter.arrivals.values()
        counter.spin_until(lambda: all(len(a) > 5 for a in counts), 30.0,
                           'traffic on every topic')
        counter.spin_for(4.0)
        image_hz = counter.rate('/wl_image', 4.0)
        light_hz = counter.rate('/wl_light', 4.0)
        heavy_hz = counter.rate('/wl_heavy', 4.0)
        assert 20.0 <= image_hz <= 33.0
        assert counter.sizes['/wl_image'] == {176 * 144}
        assert CONTENT[IMAGE](counter.messages['/wl_image'][-1])
        assert {len(m.poses) for m in counter.messages['/wl_light']} == {4}
        assert {len(m.poses) for m in counter.messages['/wl_heavy']} == {2}
        assert 7.0 <= light_hz <= 11.0          # the cap, not the 30 Hz input
        assert 0.5 <= heavy_hz <= 5.6           # the CPU, not the 30 Hz cap
        names = counter.node.get_node_names()
        assert {'camera', 'ar_light', 'ar_heavy'} <= set(names)
    finally:
        counter.close()
        codes = [_stop(p) for p in (camera, light, heavy)]
    assert codes == [0, 0, 0], [p.stdout.read() for p in (camera, light, heavy)]


def _probe_deployment(topic, type_name, rate_hz):
    """One connection on ``topic``, probed on the declared type, in a 2 s window."""
    return Deployment(
        name='wl', source='test_workload',
        scales=(Scale('here', 'master', 'robot', 100.0, 1, 1.0, 1.0, 'localhost'),), links=(),
        nodes=(Node('pub', Launch(), 1.0), Node('sub', Launch(), 1.0)),
        connections=(Connection('flow', topic, 'pub', 'sub', 1.0, freq_min_hz=rate_hz / 2,
                                tolerance_s=1.0, msg_type=type_name),),
        monitoring=MonitorSettings(probe_window_s=2.0, probe_publish_rate_hz=4.0))


@pytest.mark.parametrize('type_name, rate_hz', [
    ('sensor_msgs/msg/LaserScan', 10.0),
    ('sensor_msgs/msg/Image', 30.0),
    ('nav_msgs/msg/Odometry', 10.0),
    ('geometry_msgs/msg/PoseWithCovarianceStamped', 5.0),
])
def test_a_typed_workload_is_measured_by_a_probe_and_read_by_a_deserialising_subscriber(
        python, ros_env, type_name, rate_hz):
    """A real workload process publishes the type at the test-bed's rate and shape; the
    project's probe (raw, on the declared type) reads its rate and serialised size, and a
    subscriber that deserialises every message finds the content and fresh stamps."""
    argument, size = TESTBED_OUTPUTS[type_name]
    topic = f'/wl_typed_{type_name.split("/")[-1].lower()}'
    proc = _start(python, ros_env, '--name', 'wl_typed', '--pub', topic + argument[2:],
                  '--rate-hz', str(rate_hz))
    counter = Counter([topic], types={topic: message_class(type_name)})
    probes = ProbeManager(counter.node, _probe_deployment(topic, type_name, rate_hz), 'here')
    probes.set_connections(['flow'])
    readings = []

    def steady():
        reading, _ = probes.readings(time.monotonic()).get('flow', (None, ''))
        readings.append(reading)
        return (reading is not None and abs(reading.rate_hz - rate_hz) <= 0.1 * rate_hz
                and len(counter.arrivals[topic]) >= 2 * rate_hz)

    try:
        counter.spin_until(steady, 30.0, 'a steady probe reading and deserialised messages',
                           state=lambda: f'probe readings {readings[-3:]}, '
                           f'{len(counter.arrivals[topic])} deserialised')
        reading = readings[-1]
        assert reading.bytes_per_s / reading.rate_hz == pytest.approx(size, rel=1e-3)
        assert counter.rate(topic, 2.0) == pytest.approx(rate_hz, rel=0.25)
        received = counter.messages[topic]
        assert all(CONTENT[type_name](m) for m in received)
        stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in received]
        assert stamps == sorted(set(stamps)), 'each output is stamped anew'
        assert abs(stamps[-1] - time.time()) < 5.0
    finally:
        probes.destroy()
        counter.close()
        code = _stop(proc)
    assert code == 0, proc.stdout.read()


def test_processing_stops_when_its_input_stops(python, ros_env):
    laser = _start(python, ros_env, '--name', 'laser', '--pub', '/wl_scan', '--rate-hz', '10',
                   '--bytes', '2500')
    amcl = _start(python, ros_env, '--name', 'amcl', '--sub', '/wl_scan', '--pub', '/wl_pose',
                  '--rate-hz', '5', '--bytes', '128', '--work-ms', '10')
    counter = Counter(['/wl_pose'])
    try:
        counter.spin_until(lambda: len(counter.arrivals['/wl_pose']) >= 5, 30.0, 'five poses')
        assert _stop(laser) == 0
        counter.spin_for(1.0)
        seen = len(counter.arrivals['/wl_pose'])
        counter.spin_for(1.5)
        assert len(counter.arrivals['/wl_pose']) <= seen + 1
    finally:
        counter.close()
        _stop(laser)
        assert _stop(amcl) == 0


def test_publisher_qos_by_kind():
    sensor = parse_spec(['--name', 'camera', '--pub', '/image'])
    once = parse_spec(['--name', 'map_server', '--pub', '/map', '--once'])
    proc = parse_spec(['--name', 'ekf', '--sub', '/odom', '--pub', '/pose'])
    assert publisher_qos(sensor).reliability == ReliabilityPolicy.BEST_EFFORT
    assert publisher_qos(once).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert publisher_qos(proc).reliability == ReliabilityPolicy.RELIABLE
    assert subscriber_qos().reliability == ReliabilityPolicy.BEST_EFFORT


def test_once_publisher_is_latched_for_late_subscribers(python, ros_env):
    map_server = _start(python, ros_env, '--name', 'map_server', '--pub', '/wl_map', '--once',
                        '--bytes', '40000')
    try:
        time.sleep(0)   # the subscriber below may well start after the only message was sent
        counter = Counter(['/wl_map'], latched=True)
        try:
            counter.spin_until(lambda: counter.arrivals['/wl_map'], 30.0, 'the latched map')
            counter.spin_for(1.0)
            assert len(counter.arrivals['/wl_map']) == 1
            assert counter.sizes['/wl_map'] == {40000}
        finally:
            counter.close()
    finally:
        assert _stop(map_server) == 0


def test_bad_arguments_exit_2_and_start_nothing(python, ros_env):
    out = subprocess.run([python, '-m', 'anyscale_manager.nodes.workload', '--name', 'x',
                          '--pub', '/x', '--rate-hz', '-3'], env=ros_env, capture_output=True,
                         text=True, timeout=30)
    assert out.returncode == 2
    assert '--rate-hz' in out.stderr


def test_an_input_the_cap_held_back_is_served_when_the_cap_opens(ros):
    """The one retry timer: armed when the cap holds an input back, fired when it opens,
    re-armed (never created again) for the next one."""
    spec = parse_spec(['--name', 'held', '--sub', '/wl_held_in', '--pub', '/wl_held_out',
                       '--rate-hz', '4'])
    node = ros.add(WorkloadNode(spec, context=ros.context))
    timer = node._retry
    feed = node._make_callback('/wl_held_in')
    for n in (1, 2, 3):
        t0 = time.monotonic()
        feed(b'')
        if n == 1:
            assert node.outputs == 1          # the first input is served at once
            feed(b'')
        assert node.outputs == n and not timer.is_canceled()     # held back, timer armed
        ros.spin_until(lambda: node.outputs != n, 5.0 - (time.monotonic() - t0),
                       'the held-back input served')
        waited = time.monotonic() - t0
        assert node.outputs == n + 1
        assert 0.05 <= waited <= 1.0, waited   # when the 4 Hz cap opened (0.15 s early)
        assert timer.is_canceled() and node._retry is timer


class _StallingClock:
    """A clock read by a process that stalls once for 0.4 s (its quota throttled), at the
    ``stall_at``-th reading; 0.2 s pass between other readings."""

    def __init__(self, start_ns: int, stall_at: int):
        self.ns, self.reads, self.stall_at = start_ns, 0, stall_at

    def now(self):
        self.reads += 1
        self.ns += 400_000_000 if self.reads == self.stall_at else 200_000_000
        return rclpy.time.Time(nanoseconds=self.ns)


@pytest.mark.parametrize('stall_at', [2, 3, 4, 5])
def test_a_pose_output_is_where_the_robot_is_at_its_own_stamp(ros, stall_at):
    """A copy handed a pose continues from it at its stamp: every pose the node sends lies on
    one track at its own stamp, even when the process stalls inside a publish (the clock is
    read once per output)."""
    spec = parse_spec(['--name', 'amcl_wl', '--pub',
                       '/wl_pose_out:geometry_msgs/msg/PoseWithCovarianceStamped',
                       '--rate-hz', '1', '--pose-motion', '0.2,0.05'])
    node = ros.add(WorkloadNode(spec, context=ros.context))
    clock = _StallingClock(10**18, stall_at)
    node.get_clock = lambda: clock
    poses = []

    def sent(msg):
        p = msg.pose.pose
        poses.append((msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9,
                      p.position.x, p.position.y, yaw_of(p.orientation.z, p.orientation.w)))
    node._pubs = [type('Pub', (), {'publish': staticmethod(sent)})()]
    for _ in range(4):
        node._publish()
    stamp0, x0, y0, yaw0 = poses[0]
    for stamp, x, y, _ in poses[1:]:
        handed = PoseTrack(0.2, 0.05, x0, y0, yaw0, stamp0)    # a copy handed the first
        hx, hy, _ = handed.at(stamp)
        assert math.hypot(x - hx, y - hy) < 1e-6, (stamp - stamp0, x, y, hx, hy)


# --- the lifecycle node -------------------------------------------------------------------------

CONFIGURE = Transition.TRANSITION_CONFIGURE
ACTIVATE = Transition.TRANSITION_ACTIVATE
DEACTIVATE = Transition.TRANSITION_DEACTIVATE
CLEANUP = Transition.TRANSITION_CLEANUP
INACTIVE_SHUTDOWN = Transition.TRANSITION_INACTIVE_SHUTDOWN


def scale_remaps(scale):
    """The ROS arguments the agent gives one scale's copy of a lifecycle node."""
    args = ['--ros-args']
    for name in LIFECYCLE_SERVICES + LIFECYCLE_TOPICS:
        args += ['-r', f'~/{name}:=~/{scale}/{name}']
    return args


# Where each transition used in these tests ends when it succeeds.
GOAL = {CONFIGURE: 'inactive', ACTIVATE: 'active', DEACTIVATE: 'inactive',
        CLEANUP: 'unconfigured', INACTIVE_SHUTDOWN: 'finalized'}


class LifecycleProbe(Counter):
    """A Counter that also feeds an input at 20 Hz and drives lifecycle copies through
    get_state / change_state clients it keeps, every call with a deadline.

    A call not answered within 2 s is made again (a change_state only after get_state says it
    did not happen): rmw_fastrtps drops an answer when the server has not matched the client's
    response reader within 100 ms of the request, as happens on a busy machine.
    """

    ATTEMPT_S = 2.0

    def __init__(self, topics, feed=None):
        super().__init__(topics)
        self._clients = {}
        if feed:
            pub = self.node.create_publisher(UInt8MultiArray, feed, subscriber_qos())
            msg = UInt8MultiArray(data=bytes(64))
            self.node.create_timer(0.05, lambda: pub.publish(msg))

    def _client(self, services, srv_type, name):
        key = (services, name)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(srv_type, f'{services}/{name}')
        return self._clients[key]

    def _call(self, client, request, deadline):
        """The response, or None when this attempt went unanswered."""
        self.spin_until(client.service_is_ready, deadline - time.monotonic(),
                        f'{client.srv_name} ready')
        future = client.call_async(request)
        if self.ros.spin_until(future.done, min(self.ATTEMPT_S, deadline - time.monotonic()),
                               f'an answer from {client.srv_name}', required=False):
            return future.result()
        client.remove_pending_request(future)
        assert time.monotonic() < deadline, f'{client.srv_name} did not answer'
        return None

    def state(self, services, timeout_s=15.0):
        client = self._client(services, GetState, 'get_state')
        deadline = time.monotonic() + timeout_s
        while (response := self._call(client, GetState.Request(), deadline)) is None:
            pass
        return response.current_state.label

    def change(self, services, transition_id, timeout_s=15.0):
        client = self._client(services, ChangeState, 'change_state')
        request = ChangeState.Request(transition=Transition(id=transition_id))
        deadline = time.monotonic() + timeout_s
        while (response := self._call(client, request, deadline)) is None:
            if self.state(services, deadline - time.monotonic()) == GOAL[transition_id]:
                return True
        return response.success


def test_lifecycle_workload_works_only_while_active(python, ros_env):
    proc = _start(python, ros_env, '--name', 'wl_lc', '--sub', '/wl_lc_in', '--pub',
                  '/wl_lc_out', '--rate-hz', '20', '--work-ms', '2', '--lifecycle',
                  *scale_remaps('robot'))
    probe = LifecycleProbe(['/wl_lc_out'], feed='/wl_lc_in')
    robot = '/wl_lc/robot'
    out = probe.arrivals['/wl_lc_out']
    graph = probe.node
    try:
        assert probe.state(robot) == 'unconfigured'
        # Not valid from unconfigured: refused, and the node lives on (rclpy Jazzy would end).
        assert not probe.change(robot, ACTIVATE)
        assert probe.state(robot) == 'unconfigured'

        assert probe.change(robot, CONFIGURE)
        assert probe.state(robot) == 'inactive'
        probe.spin_until(lambda: graph.count_publishers('/wl_lc_out') == 1, 10.0,
                         'the output writer of the configured copy')
        probe.spin_for(1.0)        # fed at 20 Hz all along
        assert graph.count_subscribers('/wl_lc_in') == 0
        assert not out, 'an inactive copy published'

        assert probe.change(robot, ACTIVATE)
        assert probe.state(robot) == 'active'
        probe.spin_until(
            lambda: len(out) >= 5 and graph.count_subscribers('/wl_lc_in') == 1, 15.0,
            'five outputs of the active copy and its input subscription',
            state=lambda: f'{len(out)} outputs, {graph.count_subscribers("/wl_lc_in")} input '
            'subscriptions')

        assert probe.change(robot, DEACTIVATE)
        assert probe.state(robot) == 'inactive'
        probe.spin_until(lambda: graph.count_subscribers('/wl_lc_in') == 0, 10.0,
                         'the deactivated copy dropping its input subscription')
        probe.spin_for(0.3)        # what was already on its way
        seen = len(out)
        probe.spin_for(1.0)
        assert len(out) == seen, 'a deactivated copy kept publishing'
        assert graph.count_publishers('/wl_lc_out') == 1     # configured: ready to serve

        assert probe.change(robot, INACTIVE_SHUTDOWN)
        assert probe.state(robot) == 'finalized'
    finally:
        probe.close()
        code = _stop(proc)
        log = proc.stdout.read()
        print(log)      # shown when the test fails
    assert code == 0, log
    for line in ('not valid from unconfigured', 'configured: inactive',
                 'activated: publishing /wl_lc_out (UInt8MultiArray 64), driven by /wl_lc_in',
                 'deactivated:',
                 'shut down (from inactive)'):
        assert line in log, log


def test_two_copies_of_one_node_answer_only_on_their_own_scale(python, ros_env):
    """Same node name, same domain: each copy's lifecycle is reached only under its scale.
    The copies differ in payload size only so that the reader can tell who published."""
    common = ('--name', 'wl_two', '--sub', '/wl_two_in', '--pub', '/wl_two_out', '--rate-hz',
              '20', '--lifecycle')
    procs = {'robot': _start(python, ros_env, *common, '--bytes', '100',
                             *scale_remaps('robot')),
             'laptop': _start(python, ros_env, *common, '--bytes', '200',
                              *scale_remaps('laptop'))}
    probe = LifecycleProbe(['/wl_two_out'], feed='/wl_two_in')
    robot, laptop = '/wl_two/robot', '/wl_two/laptop'
    out = probe.arrivals['/wl_two_out']
    try:
        for services in (robot, laptop):
            assert probe.change(services, CONFIGURE)
        assert probe.state(robot) == probe.state(laptop) == 'inactive'

        assert probe.change(laptop, ACTIVATE)
        assert probe.state(laptop) == 'active'
        assert probe.state(robot) == 'inactive'
        probe.spin_until(
            lambda: len(out) >= 5 and probe.node.count_subscribers('/wl_two_in') == 1, 15.0,
            "five outputs of the laptop's copy and its input subscription")
        probe.spin_for(0.5)
        assert probe.sizes['/wl_two_out'] == {200}, 'the robot copy published'
        assert probe.node.count_subscribers('/wl_two_in') == 1
        assert probe.state(robot) == 'inactive'
    finally:
        probe.close()
        codes = {scale: _stop(p) for scale, p in procs.items()}
        logs = {s: p.stdout.read() for s, p in procs.items()}
        for scale, log in logs.items():
            print(f'--- {scale}:\n{log}')      # shown when the test fails, stacks included
    assert codes == {'robot': 0, 'laptop': 0}, logs


def _entities(node):
    return (len(list(node.publishers)), len(list(node.subscriptions)), len(list(node.timers)))


def _state(node):
    return node._state_machine.current_state[1]


@pytest.mark.parametrize('argv, subs, timers', [
    (['--sub', '/wl_e_scan', '--sub', '/wl_e_map', '--pub', '/wl_e_pose'], 2, 1),
    (['--pub', '/wl_e_image', '--rate-hz', '30'], 0, 2),      # the retry and the sensor timer
    (['--pub', '/wl_e_map', '--once'], 0, 1),
    (['--sub', '/wl_e_scan:sensor_msgs/msg/LaserScan', '--sub',
      '/wl_e_map:nav_msgs/msg/OccupancyGrid', '--pub',
      '/wl_e_pose:geometry_msgs/msg/PoseWithCovarianceStamped'], 2, 1),    # AMCL, typed
    (['--pub', '/wl_e_map:nav_msgs/msg/OccupancyGrid:200x200:0.05', '--once'], 0, 1),
])
def test_lifecycle_workload_has_inputs_and_timers_only_while_active(ros, argv, subs, timers):
    node = LifecycleWorkloadNode(parse_spec(['--name', 'wl_e', '--lifecycle', *argv]),
                                 context=ros.context)
    try:
        pubs, base_subs, base_timers = _entities(node)
        assert _state(node) == 'unconfigured'
        configured = (pubs + 1, base_subs, base_timers)
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == configured
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == (pubs + 1, base_subs + subs, base_timers + timers)
        assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == configured and _state(node) == 'inactive'
        assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == (pubs, base_subs, base_timers)
        assert node.trigger_configure() == node.trigger_activate() == \
            TransitionCallbackReturn.SUCCESS
        assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == (pubs, base_subs, base_timers)
        assert _state(node) == 'finalized'
    finally:
        node.destroy_node()


class RecordingLogger:
    def __init__(self):
        self.lines = []

    def __getattr__(self, level):
        return lambda text: self.lines.append((level, text))


def test_a_failing_transition_is_logged_with_its_reason_and_leaves_nothing_behind(ros):
    node = LifecycleWorkloadNode(parse_spec(['--name', 'wl_fail', '--sub', '/wl_f_in', '--pub',
                                             '/wl_f_out', '--lifecycle']), context=ros.context)
    log = RecordingLogger()
    node.get_logger = lambda: log
    try:
        before = _entities(node)
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS

        def no_subscriptions(*args, **kwargs):
            raise OSError('no route to the input')
        node.create_subscription = no_subscriptions
        assert node.trigger_activate() == TransitionCallbackReturn.ERROR
        assert ('error', 'activate failed (from inactive): OSError: no route to the input') \
            in log.lines
        # The error handler tore down what the half-done activation and configure had made.
        assert _state(node) == 'unconfigured'
        assert _entities(node) == before
        del node.create_subscription
        assert node.trigger_configure() == node.trigger_activate() == \
            TransitionCallbackReturn.SUCCESS
    finally:
        node.destroy_node()


def test_an_inactive_once_publisher_leaves_nothing_latched_for_late_readers(ros):
    """map_server as a lifecycle node: its OccupancyGrid is latched only while active."""
    node = ros.add(LifecycleWorkloadNode(parse_spec(
        ['--name', 'wl_lc_map', '--pub', '/wl_lc_map:nav_msgs/msg/OccupancyGrid:200x200',
         '--once', '--lifecycle']), context=ros.context))
    reader = ros.node('wl_lc_map_reader')
    got = []

    def late_reader():
        got.clear()
        sub = reader.create_subscription(message_class('nav_msgs/msg/OccupancyGrid'),
                                         '/wl_lc_map', got.append, LATCHED)
        ros.spin_until(lambda: node._pubs[0].get_subscription_count() == 1, 10.0,
                       'the late reader matched')
        return sub

    node.trigger_configure()
    node.trigger_activate()
    sub = late_reader()
    ros.spin_until(lambda: got, 10.0, 'the message latched by the active copy')
    assert CONTENT['nav_msgs/msg/OccupancyGrid'](got[0])
    reader.destroy_subscription(sub)
    node.trigger_deactivate()
    late_reader()
    ros.spin_for(0.5)
    assert not got, 'an inactive copy handed out its old message'
    node.trigger_activate()
    ros.spin_until(lambda: got, 10.0, 'the message latched by the copy active again')


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v']))
