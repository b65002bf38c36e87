"""The agent's turn without ROS: a hand-written clock, real short processes, and lifecycle
services that answer at once (agent/turn.py)."""

import ast
import dataclasses
import inspect
import subprocess
import sys
import time

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.agent import lifecycle as lc
from anyscale_manager.agent import turn as agent_turn
from anyscale_manager.agent.reconcile import SUPERSEDED_QUIET_S
from anyscale_manager.agent.turn import (AgentInputs, AgentTurn, IDLE_TICK_S, name_counts,
                                         NOT_A_PEER, NOT_FOLLOWED_EVERY_S, STOPPING_TICK_S,
                                         TICK_S)
from anyscale_manager.model.loader import load_mapping
from supervision import py_entry, SLEEPER
from test_agent_supervisor import deployment_dict

WALL_OFFSET = 1.7e9
# A node that ignores SIGINT, once it says so by creating the file named by its argument: it
# stops only at SIGTERM, after sigint_grace_s, and so is seen stopping for a few steps.
SIGINT_DEAF = ('import signal, sys, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n'
               'open(sys.argv[1], "w").close()\nwhile True: time.sleep(1)')


def deployment():
    return load_mapping(deployment_dict({
        'plain': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0},
        'lc': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'lifecycle': True,
               'standby': True},
    }))


def layout(generation, decider='d1', term=1, reason='test', **assignments):
    who = p.DeciderIdentity(id=decider, host='h', pid=1, started=0.0)
    return p.Layout(generation=generation, deployment='unit', reason=reason, stamp=0.0,
                    assignments=assignments, decider=who, term=term)


def peer_report(scale, generation, **nodes):
    return p.AgentState(scale=scale, generation=generation, stamp=0.0, instance='peer',
                        nodes={n: p.NodeReport(state=state, pid=9, since=0.0, restarts=0,
                                               ready=state == p.ProcState.RUNNING,
                                               exit_reason='')
                               for n, state in nodes.items()})


class Agent:
    """An AgentTurn of scale 'a' (the master; or ``scale``) on a hand-written clock. Its
    lifecycle copies answer each service call at once, as a node would (their states are kept
    per process)."""

    def __init__(self, make_sup, entries, turn_class=AgentTurn, scale='a'):
        self.now = 100.0
        self.sup = make_sup(entries)
        self.turn = turn_class(deployment(), scale, {e.name: e for e in entries}, self.sup,
                               instance='me', wall_offset=WALL_OFFSET)
        self.labels = {}          # (node, pid) -> its lifecycle state
        self.visible = {}         # what the ROS graph shows: name -> count
        assert self.turn.begin(self.now).logs == []

    def label(self, name):
        return self.labels.get((name, self.sup.pids().get(name, 0)), 'unconfigured')

    def poll(self, name):
        driver = self.turn.drivers[name]
        request = driver.next_request(self.now, reachable=True)
        if request is None:
            return
        key = (name, self.sup.pids().get(name, 0))
        if request.kind == 'get':
            driver.answered_state(request.serial, self.label(name), self.now)
        else:
            self.labels[key] = lc.TRANSITIONS[request.transition][1]
            driver.answered_change(request.serial, True, self.now)

    def step(self, dt=0.1):
        self.now += dt
        return self.turn.step(self.now, AgentInputs(wall=self.now + WALL_OFFSET,
                                                    visible=self.visible, poll=self.poll))

    def until(self, cond, what, timeout=15.0):
        """Step until ``cond(output)`` holds (processes start and stop in real time)."""
        end = time.monotonic() + timeout
        while True:
            out = self.step()
            if cond(out):
                return out
            assert time.monotonic() < end, f'{what}: not within {timeout} s'
            time.sleep(0.02)


def lifecycle_entry(name='lc'):
    return dataclasses.replace(py_entry(name, SLEEPER), lifecycle=True, services=f'/{name}/a')


def test_a_layout_placing_a_node_here_starts_it_and_reports_only_what_changed(make_sup):
    agent = Agent(make_sup, [py_entry('plain', SLEEPER)])
    out = agent.step()
    assert out.wanted == set() and out.report is None      # no layout, nothing ran: no news
    assert out.tick_s == IDLE_TICK_S                        # nor anything to do
    out = agent.turn.on_layout(layout(1, plain='a'), agent.now)
    assert out.step
    assert ('info', 'following decider d1 (host h, pid 1) (term 1)') in out.logs
    assert any('layout generation 1 applied (test); here: plain' in t for _, t in out.logs)
    out = agent.step()
    assert out.wanted == {'plain'}
    assert agent.sup.state('plain') == p.ProcState.STARTING
    assert out.report is not None and out.report.generation == 1
    assert out.report.nodes['plain'].state == p.ProcState.STARTING
    assert out.report.decider == 'd1' and out.report.term == 1 and out.report.instance == 'me'
    assert agent.step().report is None                      # nothing changed
    agent.visible = {'plain': 1}
    out = agent.step()
    assert out.report is not None
    node = out.report.nodes['plain']
    assert node.state == p.ProcState.RUNNING and node.ready and node.pid > 0
    assert node.since == pytest.approx(agent.now + WALL_OFFSET)     # the wall clock
    assert out.report.stamp == agent.now + WALL_OFFSET
    assert agent.step().report is None
    # The followed decider's re-publication: its lease, nothing new, no step.
    out = agent.turn.on_layout(layout(1, plain='a'), agent.now)
    assert not out.step and out.logs == []
    # A new generation that changes nothing here is still news for the others.
    out = agent.turn.on_layout(layout(2, plain='a'), agent.now)
    assert out.step
    out = agent.step()
    assert out.report is not None and out.report.generation == 2
    assert agent.step().report is None


def test_a_lifecycle_copy_is_activated_where_placed_kept_inactive_as_standby_and_finalized(
        make_sup):
    agent = Agent(make_sup, [lifecycle_entry()])
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    out = agent.step()
    # Started, and only asked for its state until it is known: activating it blind could
    # leave two copies serving.
    assert out.wanted == {'lc'} and out.goals == {'lc': None}
    assert agent.turn.drivers['lc'].known
    out = agent.until(lambda out: agent.label('lc') == lc.ACTIVE, 'the copy activated')
    assert out.goals == {'lc': lc.ACTIVE}
    assert out.report.nodes['lc'].state == p.ProcState.RUNNING
    assert out.report.nodes['lc'].lifecycle == lc.ACTIVE
    assert agent.turn.serving() == {'lc'}
    assert agent.turn.serving_pids() == {'lc': agent.sup.pids()['lc']}
    # Moved to b, where it keeps a standby copy here: let go once b serves it.
    agent.turn.on_layout(layout(2, lc='b'), agent.now)
    out = agent.step()
    assert out.goals == {'lc': lc.ACTIVE}
    assert any('lc: kept until it is running and ready on b' in t for _, t in out.logs)
    assert agent.turn.on_agent_state(peer_report('b', 2, lc=p.ProcState.RUNNING),
                                     agent.now).step
    out = agent.until(lambda out: agent.label('lc') == lc.INACTIVE, 'the copy deactivated')
    assert out.goals == {'lc': lc.INACTIVE} and out.wanted == {'lc'}   # its process runs on
    assert out.report.nodes['lc'].state == p.ProcState.STANDBY
    assert agent.turn.serving() == set()
    # Shut down: finalized first, then signalled.
    out = agent.turn.request_shutdown(agent.now)
    assert out.step and out.logs == [('info', 'shutting down: stopping every node of this scale')]
    out = agent.step()
    assert out.goals == {'lc': lc.FINALIZED} and out.wanted == {'lc'}
    out = agent.until(lambda out: agent.turn.finished, 'every node stopped')
    assert out.wanted == set() and out.report.nodes['lc'].state == p.ProcState.STOPPED


def test_a_lifecycle_copy_is_finalized_before_its_process_is_signalled(make_sup):
    agent = Agent(make_sup, [lifecycle_entry()])
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    agent.until(lambda out: agent.label('lc') == lc.ACTIVE, 'the copy activated')
    pid = agent.sup.pids()['lc']
    agent.turn.request_shutdown(agent.now)
    seen = []
    agent.until(lambda out: seen.append((agent.sup.state('lc'), agent.labels[('lc', pid)]))
                or agent.sup.state('lc') != p.ProcState.RUNNING, 'the copy signalled')
    # Deactivated, cleaned up and shut down while its process runs; signalled only then.
    running = p.ProcState.RUNNING
    assert seen[:-1] == [(running, lc.INACTIVE), (running, lc.UNCONFIGURED),
                         (running, lc.FINALIZED)]
    assert seen[-1][1] == lc.FINALIZED


def test_the_tick_quickens_while_a_node_stops(make_sup, tmp_path):
    said = tmp_path / 'deaf'
    entry = py_entry('plain', SIGINT_DEAF)
    agent = Agent(make_sup, [dataclasses.replace(entry, argv=entry.argv + (str(said),))])
    agent.turn.on_layout(layout(1, plain='a'), agent.now)
    agent.visible = {'plain': 1}
    agent.until(lambda out: said.exists() and agent.sup.state('plain') == p.ProcState.RUNNING,
                'the node running, deaf to SIGINT')
    agent.turn.request_shutdown(agent.now)
    out = agent.step()
    assert agent.sup.state('plain') == p.ProcState.STOPPING
    assert out.tick_s == STOPPING_TICK_S
    outs = [out]
    agent.until(lambda out: outs.append(out) or agent.turn.finished, 'the node stopped')
    assert all(o.tick_s == STOPPING_TICK_S for o in outs[:-1]) and outs[-1].tick_s == TICK_S
    assert any('sending SIGTERM' in text for o in outs for _, text in o.logs)


def test_an_agent_with_nothing_under_way_steps_only_when_something_is_due(make_sup):
    """A node on its way asks for a step every TICK_S; once it is up and seen, and its DDS
    ports given up for (a plain process has none; they are looked for every 0.25 s, 30 s at
    most), the next step is due only IDLE_TICK_S later. A peer's unchanged heartbeat asks for
    no step, its news does."""
    agent = Agent(make_sup, [py_entry('plain', SLEEPER)])
    agent.turn.on_layout(layout(1, plain='a'), agent.now)
    out = agent.step()
    assert agent.sup.state('plain') == p.ProcState.STARTING and out.tick_s == TICK_S
    assert agent.turn.watches_graph                 # looked for in the ROS graph
    agent.visible = {'plain': 1}
    out = agent.step()
    assert agent.sup.state('plain') == p.ProcState.RUNNING and not agent.turn.watches_graph
    assert STOPPING_TICK_S <= out.tick_s <= 0.25    # its DDS ports, looked for again
    assert agent.step(dt=31.0).tick_s == IDLE_TICK_S
    assert agent.turn.on_agent_state(peer_report('b', 1, plain='stopped'), agent.now).step
    agent.now += 0.5
    assert not agent.turn.on_agent_state(peer_report('b', 1, plain='stopped'), agent.now).step
    agent.now += 0.5
    assert agent.turn.on_agent_state(peer_report('b', 2, plain='stopped'), agent.now).step
    agent.now += 0.5
    assert not agent.turn.on_agent_state(peer_report('b', 2, plain='stopped'), agent.now).step
    agent.now += SUPERSEDED_QUIET_S                  # heard again after a silence: it counts
    assert agent.turn.on_agent_state(peer_report('b', 2, plain='stopped'), agent.now).step
    assert agent.step().tick_s == IDLE_TICK_S


def test_a_node_backing_off_asks_for_its_step_at_its_restart(make_sup):
    """A crash loop's second crash waits restart_backoff_s (0.2 s here): with nothing else
    under way the next step is due then, not every TICK_S meanwhile, nor IDLE_TICK_S later."""
    agent = Agent(make_sup, [py_entry('plain', 'raise SystemExit(3)')])
    agent.turn.on_layout(layout(1, plain='a'), agent.now)
    out = agent.until(lambda out: agent.sup.state('plain') == p.ProcState.BACKOFF,
                      'the node backing off')
    assert out.tick_s == pytest.approx(0.2)


def test_a_remote_agent_steps_when_the_masters_silence_would_change_what_it_runs(make_sup):
    """On a remote scale the master's silence stands a copy down after SUPERSEDED_QUIET_S (if a
    peer serves it under a newer layout) and stops the migratable nodes after agent_timeout_s:
    with nothing else under way, the next step is due a millisecond past each."""
    agent = Agent(make_sup, [py_entry('plain', SLEEPER)], scale='b')
    start = agent.now                                # the agent's start is word from the master
    out = agent.step()
    assert out.tick_s == pytest.approx(start + SUPERSEDED_QUIET_S + 1e-3 - agent.now)
    out = agent.step(dt=out.tick_s)
    timeout_s = agent.turn.deployment.decider.agent_timeout_s
    assert out.tick_s == pytest.approx(min(IDLE_TICK_S, start + timeout_s + 1e-3 - agent.now))
    agent.turn.on_objective(None, agent.now)        # word from the master again
    word = agent.now
    assert agent.step().tick_s == pytest.approx(word + SUPERSEDED_QUIET_S + 1e-3 - agent.now)


def test_an_activation_held_back_keeps_the_copy_inactive_until_released(make_sup):
    class Held(AgentTurn):
        hold = 'waiting for its state'

        def activation_held(self, name, now, inputs):
            return self.hold

    agent = Agent(make_sup, [lifecycle_entry()], turn_class=Held)
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    outs = []
    agent.until(lambda out: outs.append(out) or agent.label('lc') == lc.INACTIVE,
                'the copy configured and kept inactive')
    said = [t for out in outs for _, t in out.logs if t == 'lc: waiting for its state']
    assert said == ['lc: waiting for its state']             # said once
    assert outs[-1].goals == {'lc': lc.INACTIVE} and outs[-1].wanted == {'lc'}
    for _ in range(3):
        assert agent.step().goals == {'lc': lc.INACTIVE}
    assert agent.label('lc') == lc.INACTIVE and agent.turn.serving() == set()
    agent.turn.hold = ''
    out = agent.until(lambda out: agent.label('lc') == lc.ACTIVE, 'the copy activated')
    assert out.goals == {'lc': lc.ACTIVE}


def test_peer_reports_count_their_machines_and_strangers_are_noted(make_sup):
    agent = Agent(make_sup, [py_entry('plain', SLEEPER)])
    turn = agent.turn
    stranger = peer_report('zz', 1)
    out = turn.on_agent_state(stranger, agent.now)
    assert not out.step and out.notes[0][:2] == (NOT_A_PEER, 'warn')
    assert 'unknown scale' in out.notes[0][2]
    turn.host_id = 'machine-1'
    peer = dataclasses.replace(peer_report('b', 1), host_id='machine-1', host='robot')
    out = turn.on_agent_state(peer, agent.now)
    assert out.step and out.notes == []
    assert turn.shared_with(agent.now) == ('b',)
    assert turn.shared_with(agent.now + 60.0) == ()
    assert turn.is_own(dataclasses.replace(peer, scale='a', instance='me'))
    assert not turn.is_own(dataclasses.replace(peer, scale='a', instance='other'))


def test_a_decider_not_followed_is_said_once_per_interval(make_sup):
    agent = Agent(make_sup, [py_entry('plain', SLEEPER)])
    turn, now = agent.turn, agent.now
    followed = layout(1, decider='d1', term=2, plain='a')
    assert turn.on_layout(followed, now).step
    rival = layout(5, decider='d2', term=1, plain='b')
    first = turn.on_layout(rival, now)
    assert not first.step and first.logs[0][0] == 'warn' and 'ignored' in first.logs[0][1]
    said = []
    for t in (1.0, 2.0, NOT_FOLLOWED_EVERY_S - 1.0, NOT_FOLLOWED_EVERY_S):
        assert turn.on_layout(followed, now + t).logs == []      # its lease, renewed
        said.append(turn.on_layout(rival, now + t).logs)
    assert said == [[], [], [], first.logs]
    assert turn.reconciler.assignments == {'plain': 'a'}


def test_graph_names_are_counted_by_full_name_and_plain_name_at_the_root():
    assert name_counts([('talker', '/'), ('talker', '/'), ('amcl', '/nav')]) == {
        'talker': 2, '/talker': 2, '/nav/amcl': 1}


def test_the_turn_reads_no_clock_and_imports_no_ros():
    tree = ast.parse(inspect.getsource(agent_turn))
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module or '' for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom)}
    assert not {'time', 'datetime', 'rclpy'} & imported
    r = subprocess.run([sys.executable, '-c', 'import sys, anyscale_manager.agent.turn; '
                        'assert "rclpy" not in sys.modules'], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
