"""A crashed serving copy hands over to its standby copy on the other scale (real decider, real
agents, real lifecycle nodes over DDS), judged by a consumer of our own with the Δ rule."""

import os
import signal
import threading
import time

import pytest
from std_msgs.msg import UInt8MultiArray

import home_away as ha
from spinning import RosContext, spin_until
from anyscale_manager.nodes import qos
from anyscale_manager.runtime.delta import below_spans

RATE_HZ = 20.0
FREQ_MIN_HZ = 10.0
DELTA_S = 0.5        # a cold restart (process start, configure, activate) cannot meet this


def failover_deployment(tmp_path, topic):
    nodes, connections = ha.chain(topic, RATE_HZ, freq_min_hz=FREQ_MIN_HZ,
                                  tolerance_s=DELTA_S)
    worker = nodes['worker']
    worker['launch']['command'].append('--lifecycle')
    worker.update(lifecycle=True, standby=True, move_order='start_before_stop')
    return ha.write_deployment(tmp_path, f'failover_{os.getpid()}', (nodes, connections),
                               decider={'hysteresis_s': 60.0})


class Consumer:
    """A subscriber no agent started: every arrival of one topic, with its writer's sequence
    number, on a context and thread of its own."""

    def __init__(self, topic):
        self.ros = RosContext()
        self.node = self.ros.node('failover_consumer')
        self.arrivals, self.seqs = [], []
        self.node.create_subscription(UInt8MultiArray, topic, self._heard, qos.PROBE, raw=True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _heard(self, _raw, info):
        self.arrivals.append(time.monotonic())
        self.seqs.append(info.get('publication_sequence_number', -1))

    def _spin(self):
        while not self._stop.is_set():
            self.ros.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self._stop.set()
        self._thread.join(5.0)
        self.ros.close()


@pytest.fixture
def listener():
    with ha.listening('failover_listener') as heard:
        yield heard


def copy(seen, scale, node='worker'):
    s = seen['states'].get(scale)
    return s.nodes.get(node) if s else None


def serving_with_standby(seen):
    """The scale whose copy of the worker serves while the other keeps a standby, or None."""
    for here, other in (('home', 'away'), ('away', 'home')):
        a, b = copy(seen, here), copy(seen, other)
        if a and b and a.state == 'running' and a.ready and b.state == 'standby':
            return here
    return None


@pytest.mark.timeout(180)
def test_a_crashed_serving_copy_fails_over_to_its_standby_within_delta(
        tmp_path, ros_env, listener):
    ex, seen = listener
    topic = f'/failover_{os.getpid()}'
    path = failover_deployment(tmp_path, topic)
    procs = []
    consumer = Consumer(topic + '/w')
    try:
        ha.start_agents(procs, tmp_path, ros_env, path)
        ha.start(procs, tmp_path, ros_env, path, 'decider')
        # The decider moves the worker out to the stronger scale; both keep a copy.
        spin_until(ex, lambda: serving_with_standby(seen) == 'away' and len(consumer.arrivals)
                   > 2 * RATE_HZ, 90.0, 'the worker serving on away with a standby home', procs)
        victim = copy(seen, 'away')
        generation = seen['layouts'][-1].generation
        # A settled stream from the serving copy before the crash (judged from a second before).
        settled = len(consumer.arrivals)
        spin_until(ex, lambda: len(consumer.arrivals) >= settled + RATE_HZ, 10.0,
                   'a second of the worker output', procs)
        killed_at = time.monotonic()
        os.kill(victim.pid, signal.SIGKILL)

        def failed_over():
            return [e for e in seen['events'] if e.kind == 'failover' and e.node == 'worker']
        spin_until(ex, failed_over, 10.0, 'the failover event', procs)
        event = failed_over()[0]
        assert (event.from_scale, event.to_scale) == ('away', 'home'), event
        assert 'crashed on away' in event.reason and 'SIGKILL' in event.reason
        assert seen['layouts'][-1].assignments['worker'] == 'home'
        assert seen['layouts'][-1].generation > generation
        # The standby copy serves; the crashed one is back as a standby, restarted once.
        spin_until(ex, lambda: serving_with_standby(seen) == 'home', 30.0,
                   'the worker serving home with a standby on away again', procs)
        assert copy(seen, 'away').restarts == victim.restarts + 1
        assert copy(seen, 'home').pid != victim.pid
        after = len(consumer.arrivals)
        spin_until(ex, lambda: len(consumer.arrivals) >= after + RATE_HZ, 10.0,
                   'a second of output from the copy that took over', procs)
        end = time.monotonic()
        arrivals = list(consumer.arrivals)
        spans = below_spans(arrivals, FREQ_MIN_HZ, killed_at - 1.0, end)
        gap = max(b - a for a, b in zip(arrivals, arrivals[1:]) if b > killed_at)
        assert all(b - a <= DELTA_S for a, b in spans), (
            f'past Δ = {DELTA_S} s at the consumer: {spans}; longest gap {gap:.3f} s')
        # Nothing moved back to the crashed scale (the hysteresis holds it home).
        assert seen['layouts'][-1].assignments['worker'] == 'home'
    finally:
        consumer.close()
        for name, pr in reversed(procs):
            pr.stop()
