"""A decider on watch: real deciders and agents over loopback DDS.

- A second decider of a running deployment stands by: it publishes no layout, says whom it
  stands by for on /diagnostics, and when the leader is SIGKILLed it publishes the leader's
  layout at a higher term; the agents follow it and no node moves or restarts.
- A leader stopped (SIGSTOP) is taken over the same way; resumed (SIGCONT), it publishes
  nothing, says it stands by, and takes over again when the new leader dies.
- Two deciders started together: one leads, the other stands by, both stay up.
- A decider alone publishes no beat (nobody reads it), and beats while a subscription listens.
"""

import os
import signal
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import String

from anyscale_manager import protocol as p
from anyscale_manager.nodes import qos
from anyscale_manager.nodes.decider import DeciderNode
from anyscale_manager.nodes.decider_beat import ALONE_WAIT_S
from anyscale_manager.nodes.executor import make_executor
from home_away import runs, start, start_agents
from spinning import RosContext, spin_for, spin_until
from test_decider_agent import write_deployment
from test_latched_peers import write_deployment as peers_deployment


@pytest.fixture
def world(ros):
    node = ros.node('standby_decider_test')
    seen = {'layouts': [], 'states': {}, 'events': [], 'diag': {}}

    def layout(m):
        seen['layouts'].append((time.monotonic(), p.Layout.from_json(m.data)))

    def state(m):
        s = p.AgentState.from_json(m.data)
        seen['states'][s.scale] = s

    def diagnostics(m):
        for status in m.status:
            if status.name.startswith('anyscale_decider'):
                values = {kv.key: kv.value for kv in status.values}
                seen['diag'][values.get('decider', '?').split(' ')[0]] = (
                    values.get('role'), status.message)
    node.create_subscription(String, p.TOPIC_LAYOUT, layout, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_AGENT_STATE, state, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_EVENTS,
                             lambda m: seen['events'].append(p.Event.from_json(m.data)),
                             qos.EVENTS)
    node.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, diagnostics, 50)
    procs = []
    yield ros.executor, seen, procs
    for _, pr in reversed(procs):
        if pr.proc.poll() is None:
            try:
                os.kill(pr.proc.pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        pr.stop()


def follow(seen, decider_id, term=None):
    return all(seen['states'].get(s) is not None and seen['states'][s].decider == decider_id
               and (term is None or seen['states'][s].term == term) for s in ('home', 'away'))


def pids(seen):
    return {s: {n: r.pid for n, r in seen['states'][s].running().items()}
            for s in ('home', 'away')}


def leading(ex, seen, procs, name, proc):
    """The identity of the decider ``proc`` once it leads and both agents follow it."""
    spin_until(ex, lambda: any(lay.decider is not None and lay.decider.pid == proc.proc.pid
                               for _, lay in seen['layouts']), 40.0, f'a layout of {name}', procs)
    me = [lay for _, lay in seen['layouts'] if lay.decider.pid == proc.proc.pid][-1]
    spin_until(ex, lambda: follow(seen, me.decider.id), 30.0, f'both agents following {name}',
               procs)
    return me.decider


def standing_by(ex, seen, procs, proc, leader):
    """The identity id of ``proc`` once its diagnostics say it stands by for ``leader``."""
    def said():
        return [i for i, (role, msg) in seen['diag'].items()
                if role == 'standby' and f'standing by for decider {leader.id}' in msg
                and f'pid {proc.proc.pid})' in proc.text()]
    spin_until(ex, said, 30.0, 'the second decider standing by', procs)
    return said()[0]


def settled(ex, seen, procs):
    """Both agents report the worker away and the pinned node home, and nothing is pending."""
    spin_until(ex, lambda: runs(seen, 'away', 'worker') and runs(seen, 'home', 'pinned')
               and not runs(seen, 'home', 'worker'), 60.0, 'the worker running away', procs)


def leader_and_standby(ex, seen, procs, tmp_path, ros_env):
    """Agents, a leading decider with the worker moved out, and a second one standing by for
    it: (first process, its identity, second process, its id)."""
    path = write_deployment(tmp_path)
    start_agents(procs, tmp_path, ros_env, path)
    first = start(procs, tmp_path, ros_env, path, 'decider_1')
    one = leading(ex, seen, procs, 'decider_1', first)
    settled(ex, seen, procs)
    # The second listens as long as a deployment's decider does by default: it must hear the
    # leader before it would lead.
    second = start(procs, tmp_path, ros_env, path, 'decider_2', '-p', 'decider.discovery_s:=5.0')
    return first, one, second, standing_by(ex, seen, procs, second, one)


def test_a_standby_takes_over_a_killed_leader_without_moving_anything(tmp_path, ros_env, world):
    ex, seen, procs = world
    first, one, second, two_id = leader_and_standby(ex, seen, procs, tmp_path, ros_env)
    # It published no layout, and it stays up.
    assert {lay.decider.id for _, lay in seen['layouts']} == {one.id}
    assert second.proc.poll() is None
    last = seen['layouts'][-1][1]
    before = pids(seen)

    os.kill(first.proc.pid, signal.SIGKILL)
    spin_until(ex, lambda: any(lay.decider.id == two_id for _, lay in seen['layouts']), 10.0,
               'a layout of the standby', procs)
    new = next(lay for _, lay in seen['layouts'] if lay.decider.id == two_id)
    # The leader's layout at a higher term (the time it takes: bench/bench_failover.py
    # --decider-kills).
    assert new.term > last.term and new.generation > last.generation
    assert dict(new.assignments) == dict(last.assignments)
    assert f'decider {one.id}' in new.reason and 'takes over at term' in new.reason, new.reason
    spin_until(ex, lambda: follow(seen, two_id, new.term), 15.0, 'both agents following it', procs)
    assert pids(seen) == before                   # nothing moved, nothing restarted
    spin_until(ex, lambda: any(e.kind == 'takeover' for e in seen['events']), 10.0,
               'the takeover event', procs)
    codes = {name: pr.stop() for name, pr in reversed(procs) if name != 'decider_1'}
    assert codes['decider_2'] == 0, second.text()


def test_a_stopped_leader_is_taken_over_and_commands_nothing_when_it_resumes(tmp_path, ros_env,
                                                                             world):
    ex, seen, procs = world
    first, one, second, two_id = leader_and_standby(ex, seen, procs, tmp_path, ros_env)
    before = pids(seen)

    os.kill(first.proc.pid, signal.SIGSTOP)
    spin_until(ex, lambda: any(lay.decider.id == two_id for _, lay in seen['layouts']), 10.0,
               'a layout of the standby', procs)
    new = next(lay for _, lay in seen['layouts'] if lay.decider.id == two_id)
    spin_until(ex, lambda: follow(seen, two_id, new.term), 15.0, 'both agents following it', procs)
    resumed = time.monotonic()
    os.kill(first.proc.pid, signal.SIGCONT)
    spin_until(ex, lambda: 'standing by' in first.text().split('takes over')[-1]
               and seen['diag'].get(one.id, ('',))[0] == 'standby', 15.0,
               'the old leader standing by', procs)
    # Over two more seconds: no layout of the old leader, the agents on the new one.
    spin_for(ex, 2.0)
    assert not [lay for t, lay in seen['layouts'] if t > resumed and lay.decider.id == one.id]
    assert follow(seen, two_id, new.term) and pids(seen) == before
    assert first.proc.poll() is None and second.proc.poll() is None

    # The roles swap back when the new leader dies.
    os.kill(second.proc.pid, signal.SIGKILL)
    spin_until(ex, lambda: any(t > resumed and lay.decider.id == one.id and lay.term > new.term
                               for t, lay in seen['layouts']), 10.0, 'the first decider again',
               procs)
    back = [lay for t, lay in seen['layouts'] if lay.decider.id == one.id][-1]
    spin_until(ex, lambda: follow(seen, one.id, back.term), 15.0, 'the agents following it', procs)
    assert pids(seen) == before


def test_two_deciders_started_together_leave_one_leader_and_one_standby(tmp_path, ros_env,
                                                                        world):
    ex, seen, procs = world
    path = write_deployment(tmp_path)
    start_agents(procs, tmp_path, ros_env, path)
    deciders = [start(procs, tmp_path, ros_env, path, f'decider_{i}') for i in (1, 2)]
    spin_until(ex, lambda: len({i for i, (role, _) in seen['diag'].items() if role}) == 2
               and sorted(role for role, _ in seen['diag'].values()) == ['leader', 'standby'],
               60.0, 'one leader and one standby', procs)
    # Started together, both may lead for a moment at one term; the one started later then
    # hears the other and stands by. A loaded machine can stall a leader's beats past
    # takeover_s, and the other then takes over at a higher term: judged is that the deciders
    # settle on one leader that the agents follow, and that no term is ever commanded by two.

    def one_leader_followed():
        roles = sorted(role for role, _ in seen['diag'].values())
        leaders = [i for i, (role, _) in seen['diag'].items() if role == 'leader']
        return roles == ['leader', 'standby'] and follow(seen, leaders[0])
    spin_until(ex, one_leader_followed, 30.0, 'one leader, followed by both agents', procs)
    n = len(seen['layouts'])
    spin_until(ex, lambda: len(seen['layouts']) >= n + 3, 15.0, 'its re-publications', procs)
    by_term = {}
    for _, lay in seen['layouts']:
        by_term.setdefault(lay.term, set()).add(lay.decider.id)
    # Both may publish a first layout at term 1 (started together, neither heard the other);
    # every later term has one decider.
    assert all(len(ids) == 1 for term, ids in by_term.items() if term != 1), by_term
    assert all(d.proc.poll() is None for d in deciders)


def test_a_decider_alone_sends_no_beat_and_beats_while_another_listens(tmp_path):
    """Nobody reads the beats of a decider alone: it leads without publishing them, keeps
    leading (a beat not sent is not a stall) and turns less often, and beats as soon as a
    subscription appears, until it goes. Its own beats, which its own subscription receives,
    are never decoded."""
    path, _ = peers_deployment(tmp_path, decider={'discovery_s': 2.0})
    with RosContext(make_executor) as decider_ros, RosContext() as listener_ros:
        decider = decider_ros.add(DeciderNode(context=decider_ros.context,
                                              cli_args=['--ros-args', '--params-file', path]))
        published = []                  # every beat the thread hands to its publisher
        publish = decider.beat.pub.publish
        decider.beat.pub.publish = lambda msg: (published.append(msg.data), publish(msg))
        decider_ros.spin_until(lambda: decider.lead.role == 'leader', 15.0, 'the decider leading')
        decider_ros.spin_for(1.0)       # 20 beats' time, and more than takeover_s
        assert published == []
        assert decider.lead.role == 'leader' and decider.lead.may_command(decider._now())
        # Alone, it wakes every ALONE_WAIT_S, longer than a stall, not every beat_s: its quiet
        # time is no stall, and it may command throughout.
        assert decider.beat.wait_s == pytest.approx(ALONE_WAIT_S)
        assert ALONE_WAIT_S > decider.lead.stall_s
        for _ in range(10):
            decider_ros.spin_for(0.1)
            assert decider.lead.may_command(decider._now())
        heard = []
        listener = listener_ros.node('beat_listener')
        sub = listener.create_subscription(
            String, p.TOPIC_DECIDER, lambda m: heard.append(p.DeciderBeat.from_json(m.data)),
            qos.BEAT)
        end = time.monotonic() + 15.0
        while time.monotonic() < end and not heard:
            decider_ros.spin_for(0.05)
            listener_ros.spin_for(0.05)
        assert heard and heard[-1].role == 'leader' and heard[-1].decider.id == decider.identity.id
        assert published and decider._rejected == 0
        assert decider.beat.wait_s == decider.settings.beat_s
        listener.destroy_subscription(sub)
        end = time.monotonic() + 15.0
        while time.monotonic() < end and decider.beat.listened():
            decider_ros.spin_for(0.05)
        sent = len(published)
        decider_ros.spin_for(0.5)
        assert len(published) == sent and decider.lead.role == 'leader'
