"""A node's state goes with it (agent/state.py, nodes/state_relay.py): a counting lifecycle node
of a user's own (fixtures/state_counter.py) continues its count across two failovers of a crash
loop, a restart in place, a relocation after its agent died and a planned cold move; a count
set by a person on its restore topic reaches the serving copy. Real decider, real agents, real
processes over DDS; judged by a reader of the test's own on the node's output."""

import os
import signal
import sys
import threading
import time

import pytest
from std_msgs.msg import Int64

import home_away as ha
from spinning import RosContext, spin_until

RATE_HZ = 20.0
HYSTERESIS_S = 5.0
# A takeover continues the count when it goes on from one heard at most this long before.
CONTINUED_S = 1.0
COUNTER = os.path.join(os.path.dirname(__file__), 'fixtures', 'state_counter.py')


def deployment(tmp_path, topic, standby, hysteresis_s=60.0):
    counter = {'launch': {'command': [sys.executable, COUNTER],
                          'parameters': {'input': topic + '/tick', 'output': topic + '/count'}},
               'cpu': 1.0, 'lifecycle': True, 'move_order': 'start_before_stop',
               'state': {'topic': topic + '/count', 'restore': '/restore',
                         'msg_type': 'std_msgs/msg/Int64'}}
    if standby:
        counter['standby'] = True
    nodes = {'sensor': {'launch': ha.workload('sensor', '--pub', topic + '/tick', '--rate-hz',
                                              str(RATE_HZ)),
                        'cpu': 1.0, 'residence': ['home']},
             'counter': counter}
    connections = {'sensor_counter': dict(ha.CONNECTION, topic=topic + '/tick',
                                          publisher='sensor', subscriber='counter')}
    return ha.write_deployment(tmp_path, f'state_{os.getpid()}', (nodes, connections),
                               decider={'hysteresis_s': hysteresis_s})


class Counts:
    """Every count the node publishes, with its arrival time, on a context of its own."""

    def __init__(self, topic):
        self.ros = RosContext()
        self.node = self.ros.node('state_counts')
        self.heard = []
        self.node.create_subscription(Int64, topic, self._take, 100)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _take(self, msg):
        self.heard.append((time.monotonic(), msg.data))

    def _spin(self):
        while not self._stop.is_set():
            self.ros.executor.spin_once(timeout_sec=0.05)

    def since(self, t):
        return [v for at, v in list(self.heard) if at >= t]

    def restarts(self):
        return restarts(list(self.heard))

    def close(self):
        self._stop.set()
        self._thread.join(5.0)
        self.ros.close()


def node_copy(seen, scale):
    s = seen['states'].get(scale)
    return s.nodes.get('counter') if s else None


def serving(seen, scale, standby_elsewhere=True):
    here = node_copy(seen, scale)
    other = node_copy(seen, 'away' if scale == 'home' else 'home')
    ok = here is not None and here.state == 'running' and here.ready
    return ok and (not standby_elsewhere or (other is not None and other.state == 'standby'))


def takeovers(heard):
    """Each count (of ``heard``: (arrival, count)) that did not go up from the highest before
    it, another copy's output, as (arrival, highest before, count, lag); the first of each run
    of one copy's counts only. ``lag``: how much older the count it continued from is than the
    highest heard before it, by when each was first heard (None: never heard). A copy handed
    its state goes on from a count a moment old; during a ``start_before_stop`` overlap the copy
    being replaced counts on from the hand-over until it is stopped, so the new one falls behind
    it by what arrived since."""
    out, top, first, run = [], None, {}, None
    for at, v in heard:
        if top is not None and v <= top:
            if run is None or v != run + 1:              # not the same copy counting on
                base = first.get(v - 1)
                out.append((round(at, 3), top, v,
                            None if base is None else round(first[top] - base, 3)))
            run = v
        elif run is not None and v == run + 1:
            run = None                                   # it caught up: no longer behind
        first.setdefault(v, at)
        top = v if top is None else max(top, v)
    return out


def restarts(heard):
    """The takeovers by a copy that did not continue: it went on from a count first heard more
    than ``CONTINUED_S`` before the highest one (a state from before the last copy served, or
    none at all)."""
    return [t for t in takeovers(heard) if t[3] is None or t[3] > CONTINUED_S]


def test_the_judge_tells_a_copy_that_continued_from_one_that_started_anew():
    step = 1.0 / RATE_HZ
    old = [(i * step, i) for i in range(1, 101)]                     # 5 s of one copy
    # A start_before_stop overlap: handed 90 at 4.5 s, it counts from 91 at 4.9 s beside the
    # old copy (at 98 by then), which stops at 100.
    overlap = sorted(old + [(4.9 + j * step + 0.01, 91 + j) for j in range(20)])
    assert [t[2] for t in takeovers(overlap)] == [91] and not restarts(overlap)
    # A copy after the old one died, handed its last count: no fall at all.
    assert takeovers(old + [(6.0 + j * step, 101 + j) for j in range(5)]) == []
    # A failover that took 2 s, handed the count one before the last heard: it continued.
    late = old + [(7.0 + j * step, 100 + j) for j in range(5)]
    assert [t[2] for t in takeovers(late)] == [100] and not restarts(late)
    # Started anew, or from a count 1.5 s older than the highest: restarts.
    assert [t[2] for t in restarts(old + [(5.5 + j * step, 1 + j) for j in range(5)])] == [1]
    assert [t[2] for t in restarts(overlap[:90] + [(4.6, 61), (4.65, 62)])] == [61]


@pytest.fixture
def listener():
    with ha.listening('state_listener') as heard:
        yield heard


def counting_on(ex, counts, procs, what):
    n = len(counts.heard)
    spin_until(ex, lambda: len(counts.heard) >= n + RATE_HZ, 15.0, f'a second of counts {what}',
               procs)


def handed(tmp_path, scale):
    """How many states the agent logged as ``agent_<scale>.out`` handed over (0: none yet)."""
    path = tmp_path / f'agent_{scale}.out'
    return path.read_text(errors='replace').count('counter: state of ') if path.exists() else 0


@pytest.mark.timeout(240)
def test_the_count_continues_across_a_move_and_every_failover_of_a_crash_loop(
        tmp_path, ros_env, listener):
    ex, seen = listener
    topic = f'/state_{os.getpid()}'
    path = deployment(tmp_path, topic, standby=True)
    counts = Counts(topic + '/count')
    procs = []
    try:
        ha.start_agents(procs, tmp_path, ros_env, path)
        ha.start(procs, tmp_path, ros_env, path, 'decider')
        # The decider moves the counter out to the stronger scale at once (an activation
        # there, with no state heard yet).
        spin_until(ex, lambda: serving(seen, 'away') and len(counts.heard) > RATE_HZ, 90.0,
                   'the counter serving on away with a standby home', procs)
        counting_on(ex, counts, procs, 'on away')
        # A crash loop: the serving copy killed twice, within the hysteresis T of each other;
        # each time the standby on the other scale takes over, with the count.
        for victim_scale, heir in (('away', 'home'), ('home', 'away')):
            victim = node_copy(seen, victim_scale)
            before = len([e for e in seen['events'] if e.kind == 'failover'])
            os.kill(victim.pid, signal.SIGKILL)
            spin_until(ex, lambda: len([e for e in seen['events'] if e.kind == 'failover'])
                       > before, 15.0, f'the failover from {victim_scale}', procs)
            spin_until(ex, lambda: serving(seen, heir), 30.0,
                       f'the counter serving on {heir} with a standby again', procs)
            counting_on(ex, counts, procs, f'on {heir}')
        failovers = [e for e in seen['events'] if e.kind == 'failover']
        pairs = [(e.from_scale, e.to_scale) for e in failovers]
        assert pairs == [('away', 'home'), ('home', 'away')], failovers
        assert handed(tmp_path, 'home') >= 1 and handed(tmp_path, 'away') >= 1
        assert not counts.restarts(), f'copies that started their count anew: ' \
                                      f'{counts.restarts()} (every takeover: ' \
                                      f'{takeovers(list(counts.heard))})'
        print('takeovers (arrival, highest, count, lag):', takeovers(list(counts.heard)))
    finally:
        counts.close()
        for name, pr in reversed(procs):
            pr.stop()


@pytest.mark.timeout(240)
def test_the_count_continues_across_a_restart_in_place_a_relocation_and_a_planned_cold_move(
        tmp_path, ros_env, listener):
    ex, seen = listener
    topic = f'/state_cold_{os.getpid()}'
    path = deployment(tmp_path, topic, standby=False, hysteresis_s=HYSTERESIS_S)
    counts = Counts(topic + '/count')
    procs = []
    try:
        agents = ha.start_agents(procs, tmp_path, ros_env, path)
        ha.start(procs, tmp_path, ros_env, path, 'decider')
        spin_until(ex, lambda: serving(seen, 'away', standby_elsewhere=False)
                   and len(counts.heard) > RATE_HZ, 90.0, 'the counter moved to away', procs)
        counting_on(ex, counts, procs, 'on away')
        # No standby anywhere: a crash is restarted in place, with the count.
        victim = node_copy(seen, 'away')
        os.kill(victim.pid, signal.SIGKILL)
        spin_until(ex, lambda: node_copy(seen, 'away').pid != victim.pid
                   and serving(seen, 'away', standby_elsewhere=False), 30.0,
                   'the counter restarted in place on away', procs)
        counting_on(ex, counts, procs, 'after the restart in place')
        assert handed(tmp_path, 'away') >= 1
        # away's agent dies: the decider relocates the counter home, a process started there
        # and handed the count home's agent heard last.
        agents['away'].stop(signal.SIGKILL)
        spin_until(ex, lambda: serving(seen, 'home', standby_elsewhere=False), 30.0,
                   'the counter relocated home', procs)
        counting_on(ex, counts, procs, 'at home')
        assert handed(tmp_path, 'home') >= 1
        # away's agent back: after T the decider moves the counter out again, a process
        # started there and handed the count.
        before = handed(tmp_path, 'away_again')
        ha.start(procs, tmp_path, ros_env, path, 'agent_away_again', '-p', 'scale:=away')
        spin_until(ex, lambda: serving(seen, 'away', standby_elsewhere=False)
                   and handed(tmp_path, 'away_again') > before, HYSTERESIS_S + 60.0,
                   'the counter moved out to away again, handed its count', procs)
        counting_on(ex, counts, procs, 'on away again')
        assert not counts.restarts(), f'copies that started their count anew: ' \
                                      f'{counts.restarts()} (every takeover: ' \
                                      f'{takeovers(list(counts.heard))})'
        print('takeovers (arrival, highest, count, lag):', takeovers(list(counts.heard)))
        # A person sets the count on the node's own restore topic: the serving copy takes it.
        ros = RosContext()
        try:
            writer = ros.node('state_setter').create_publisher(Int64, '/restore', 1)
            ros.spin_until(lambda: writer.get_subscription_count() >= 1, 10.0,
                           'an agent reading /restore')
            # Sent again until taken: the serving agent's reader may be found after another's.
            spin_until(ex, lambda: any(v > 100000 for _, v in counts.heard), 15.0,
                       'the count continuing from the one set by hand', procs,
                       tick=lambda: writer.publish(Int64(data=100000)), tick_every_s=1.0)
        finally:
            ros.close()
    finally:
        counts.close()
        for name, pr in reversed(procs):
            pr.stop()
        ha.stop_wardens(tmp_path)
