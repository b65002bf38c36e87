"""The workload node: argument checks, the output gate, CPU work, and real processes over DDS."""

import os
import signal
import subprocess
import sys
import time

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import UInt8MultiArray

from anyscale_manager.nodes.workload import (OutputGate, WorkloadNode, burn_cpu, parse_spec,
                                             publisher_qos, subscriber_qos)
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


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
])
def test_bad_arguments_are_refused_with_the_argument_named(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        parse_spec(argv)
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_arguments_of_the_testbed_amcl():
    spec = parse_spec(['--name', 'amcl', '--sub', '/scan', '--sub', '/map', '--pub',
                       '/amcl_pose', '--rate-hz', '5.0', '--bytes', '128', '--work-ms', '100',
                       '--reference-core', '0.25'])
    assert spec.subs == ('/scan', '/map') and spec.pubs == ('/amcl_pose',)
    assert not spec.is_sensor
    assert spec.cpu_s_per_output == pytest.approx(0.025)


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
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Counter:
    """Arrival times and sizes per topic, from a node in its own context."""

    def __init__(self, topics, latched=False):
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('workload_test_counter', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.arrivals = {t: [] for t in topics}
        self.sizes = {t: set() for t in topics}
        for topic in topics:
            qos = LATCHED if latched else subscriber_qos()
            self.node.create_subscription(UInt8MultiArray, topic, self._callback(topic), qos)

    def _callback(self, topic):
        def cb(msg):
            self.arrivals[topic].append(time.monotonic())
            self.sizes[topic].add(len(msg.data))
        return cb

    def spin_until(self, condition, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return condition()

    def rate(self, topic, window_s):
        """Messages per second over the last window_s seconds."""
        now = time.monotonic()
        return sum(1 for t in self.arrivals[topic] if t >= now - window_s) / window_s

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


def test_sensor_and_processing_chain_rates_follow_input_cap_and_cpu(python, ros_env):
    camera = _start(python, ros_env, '--name', 'camera', '--pub', '/wl_image', '--rate-hz',
                    '30', '--bytes', '25000')
    light = _start(python, ros_env, '--name', 'ar_light', '--sub', '/wl_image', '--pub',
                   '/wl_light', '--rate-hz', '10', '--bytes', '256', '--work-ms', '5')
    # 1 s of reference work = 0.2 s of this machine's CPU per output: at most 5 Hz, cap 30 Hz.
    heavy = _start(python, ros_env, '--name', 'ar_heavy', '--sub', '/wl_image', '--pub',
                   '/wl_heavy', '--rate-hz', '30', '--bytes', '256', '--work-ms', '1000')
    counter = Counter(['/wl_image', '/wl_light', '/wl_heavy'])
    try:
        counts = counter.arrivals.values()
        assert counter.spin_until(lambda: all(len(a) > 5 for a in counts), 30.0), \
            f'no traffic: { {k: len(v) for k, v in counter.arrivals.items()} }'
        counter.spin_until(lambda: False, 4.0)
        image_hz = counter.rate('/wl_image', 4.0)
        light_hz = counter.rate('/wl_light', 4.0)
        heavy_hz = counter.rate('/wl_heavy', 4.0)
        assert 20.0 <= image_hz <= 33.0
        assert counter.sizes['/wl_image'] == {25000}
        assert counter.sizes['/wl_light'] == {256}
        assert 7.0 <= light_hz <= 11.0          # the cap, not the 30 Hz input
        assert 0.5 <= heavy_hz <= 5.6           # the CPU, not the 30 Hz cap
        names = counter.node.get_node_names()
        assert {'camera', 'ar_light', 'ar_heavy'} <= set(names)
    finally:
        counter.close()
        codes = [_stop(p) for p in (camera, light, heavy)]
    assert codes == [0, 0, 0], [p.stdout.read() for p in (camera, light, heavy)]


def test_processing_stops_when_its_input_stops(python, ros_env):
    laser = _start(python, ros_env, '--name', 'laser', '--pub', '/wl_scan', '--rate-hz', '10',
                   '--bytes', '2500')
    amcl = _start(python, ros_env, '--name', 'amcl', '--sub', '/wl_scan', '--pub', '/wl_pose',
                  '--rate-hz', '5', '--bytes', '128', '--work-ms', '10')
    counter = Counter(['/wl_pose'])
    try:
        assert counter.spin_until(lambda: len(counter.arrivals['/wl_pose']) >= 5, 30.0)
        assert _stop(laser) == 0
        counter.spin_until(lambda: False, 1.0)
        seen = len(counter.arrivals['/wl_pose'])
        counter.spin_until(lambda: False, 1.5)
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
            assert counter.spin_until(lambda: counter.arrivals['/wl_map'], 30.0)
            counter.spin_until(lambda: False, 1.0)
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


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v']))


def test_an_input_the_cap_held_back_is_served_when_the_cap_opens():
    """The one retry timer: armed when the cap holds an input back, fired when it opens,
    re-armed (never created again) for the next one."""
    ctx = Context()
    rclpy.init(context=ctx)
    spec = parse_spec(['--name', 'held', '--sub', '/wl_held_in', '--pub', '/wl_held_out',
                       '--rate-hz', '4'])
    node = WorkloadNode(spec, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        timer = node._retry
        feed = node._make_callback('/wl_held_in')
        for n in (1, 2, 3):
            t0 = time.monotonic()
            feed(b'')
            if n == 1:
                assert node.outputs == 1          # the first input is served at once
                feed(b'')
            assert node.outputs == n and not timer.is_canceled()     # held back, timer armed
            while node.outputs == n and time.monotonic() - t0 < 5.0:
                ex.spin_once(timeout_sec=0.05)
            waited = time.monotonic() - t0
            assert node.outputs == n + 1, 'the held-back input was never served'
            assert 0.05 <= waited <= 1.0, waited   # when the 4 Hz cap opened (0.15 s early)
            assert timer.is_canceled() and node._retry is timer
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
