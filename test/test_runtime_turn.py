"""The decider's turn without ROS (runtime/turn.py): the ICAR test-bed's deployment, the
agents' and monitors' messages fed to its book by hand, a hand-written clock."""

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.turn import DeciderTurn


@pytest.fixture(scope='module')
def d():
    from conftest import TESTBED
    return load_deployment(TESTBED)


def agent(d, scale, where, generation=0, standby=()):
    nodes = {}
    for n in d.nodes:
        if not n.managed:
            continue
        if where.get(n.name) == scale:
            nodes[n.name] = p.NodeReport(state='running', pid=100 + len(nodes), since=1.0,
                                         restarts=0, ready=True, exit_reason='',
                                         lifecycle='active' if n.lifecycle else None)
        elif n.name in standby:
            nodes[n.name] = p.NodeReport(state='standby', pid=200 + len(nodes), since=1.0,
                                         restarts=0, ready=False, exit_reason='',
                                         lifecycle='inactive')
    return p.AgentState(scale=scale, generation=generation, stamp=0.0, nodes=nodes,
                        instance=f'{scale}-1')


def feed(turn, d, now, where, generation=0):
    """Every agent, scale, link and connection report of one moment, all healthy."""
    book = turn.book
    standby = [n for n in d.node_names if d.standby_scales(n)]
    for scale in d.scale_names:
        book.agent_state(agent(d, scale, where, generation, standby), now)
        cpu = {n: d.node(n).cpu for n, s in where.items() if s == scale}
        book.scale_status(p.ScaleStatus(scale=scale, stamp=now, cpu_total=sum(cpu.values()),
                                        capacity_cpu=d.scale(scale).capacity_cpu,
                                        cpu_by_node=cpu, mem_percent=10.0, load_1m=0.5), now)
    book.link_status(p.LinkStatus(master='robot', remote='laptop', stamp=now, up=True,
                                  rtt_ms=1.0, loss=0.0, bandwidth_available_kbps=50000.0,
                                  bandwidth_available_age_s=1.0, bandwidth_used_kbps=0.0), now)
    for scale in d.scale_names:
        readings = {c.name: p.ConnectionReading(rate_hz=c.freq_opt_hz, bytes_per_s=1000.0,
                                                below_for_s=0.0, level=p.OK)
                    for c in d.connections if c.monitored and where.get(c.subscriber) == scale}
        book.connection_status(p.ConnectionStatus(scale=scale, stamp=now,
                                                  connections=readings), now)


def test_nothing_before_the_agents_report_then_the_first_layout(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    out = turn.turn(0.5)
    assert not out.layouts and turn.layout is None
    assert out.message == 'waiting for the agents to report what runs' and not out.events
    where = master_layout(d)
    feed(turn, d, 1.0, where, generation=6)
    out = turn.turn(1.0)
    # Above what the agents applied; with every scale observed, the first move out is
    # decided in the same turn: two layouts to publish, in order, each with its events.
    (g1, first, why1), (g2, second, why2) = out.layouts
    assert (g1, first) == (7, where) and why1 == 'first layout (master)'
    assert g2 == 8 and second == dict(where, amcl='laptop') and why2.startswith('migrate amcl')
    assert turn.generation == 8 and turn.layout == second
    assert out.events[0] == ('layout', '', '', '', why1, 7)
    assert ('migrate', 'amcl', 'robot', 'laptop') == out.events[2][:4] and out.events[2][5] == 8
    assert ('info', f'generation 7: {why1}') in out.logs
    assert out.objective is not None and out.plan is not None
    assert out.values['generation'] == 8 and out.values['nodes running'] == len(where)


def test_without_all_agents_the_first_layout_waits_for_agent_timeout(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    turn.book.agent_state(agent(d, 'robot', master_layout(d)), 1.0)
    assert not turn.turn(d.decider.agent_timeout_s - 0.1).layouts
    out = turn.turn(d.decider.agent_timeout_s + 0.1)
    assert out.layouts and out.layouts[0][2] == 'first layout (master)'
    assert any(e[0] == 'warning' and 'laptop' in e[4] for e in out.events)


def test_the_next_move_waits_for_the_last_one_to_run_and_be_measured(d):
    """AR out only once AMCL runs on the laptop and the laptop's CPU was measured with it
    there (its first report at 1.5 s); one move per turn, then nothing more."""
    turn = DeciderTurn(d, d.decider, started=0.0)
    where = master_layout(d)
    feed(turn, d, 1.0, where)
    turn.turn(1.0)
    assert turn.layout['amcl'] == 'laptop'
    t, moves = 1.0, []
    while t < 30.0:
        t += d.decider.period_s
        # The agents apply what the turn asked for (AMCL first), a period later.
        feed(turn, d, t, dict(turn.layout), turn.generation)
        out = turn.turn(t)
        moves += [(t, e[1], e[3]) for e in out.events if e[0] == 'migrate']
        assert len(out.layouts) <= 1
    assert [(n, to) for _, n, to in moves] == [('ar', 'laptop')]
    assert moves[0][0] > 1.5
    assert turn.layout == dict(where, amcl='laptop', ar='laptop')


def test_two_turns_fed_alike_say_the_same(d):
    a, b = DeciderTurn(d, d.decider, 0.0), DeciderTurn(d, d.decider, 0.0)
    where = master_layout(d)
    said = []
    for turn in (a, b):
        lines = []
        for k in range(40):
            t = 1.0 + k * d.decider.period_s
            feed(turn, d, t, where, turn.generation)
            out = turn.turn(t)
            lines.append((out.layouts, out.events, out.logs, out.level, out.message))
        said.append(lines)
    assert said[0] == said[1]


def test_a_standby_takes_over_from_the_leaders_layout_and_moves_nothing(d):
    # The leader had moved AMCL and AR out and brought AR back 2 s ago (its event heard).
    where = dict(master_layout(d), amcl='laptop')
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 10.0, where, generation=12)
    turn.heard_decision('migrate_back', 'ar', 'laptop', 8.0)
    out = turn.take_over(10.0, dict(where), 12, 'decider a (term 1) silent for 0.30 s')
    ((generation, layout, why),) = out.layouts
    assert generation == 13 and layout == where and why.startswith('decider a (term 1)')
    assert turn.policy.memory.last_back[('ar', 'laptop')] == 8.0       # its hysteresis goes on
    # Every node runs where the layout has it: no grace period, no move in the next turns.
    assert turn.policy.memory.last_move == {}
    for now in (10.25, 10.5, 11.0):
        feed(turn, d, now, where, generation=13)
        assert not turn.turn(now).layouts
    assert turn.layout == where and turn.generation == 13


def test_a_takeover_gives_a_grace_period_only_to_nodes_not_yet_where_placed(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 10.0, master_layout(d), generation=3)
    # The leader had just moved AMCL out; its copy on the laptop does not serve yet.
    placed = dict(master_layout(d), amcl='laptop')
    turn.take_over(10.0, placed, 4, 'takeover')
    memory = turn.policy.memory
    assert set(memory.last_move) == {'amcl'} and set(memory.pending) == {'amcl'}


# --- which layout a decider that comes to lead starts from ----------------------------------

TAKEOVER = 'decider a (term 1) silent for 0.30 s'


def test_leading_on_from_the_leaders_layout_when_heard(d):
    where = dict(master_layout(d), amcl='laptop')
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 10.0, master_layout(d), generation=11)
    # What the leader last published wins over what the agents report (AMCL still starting).
    out = turn.lead(10.0, TAKEOVER, took_over=True, heard=(12, where))
    assert out is not None and out.layouts == [(13, where, TAKEOVER)]
    assert out.events == [('layout', '', '', '', TAKEOVER, 13),
                          ('takeover', '', '', '', TAKEOVER, 13)]
    assert turn.layout == where and turn.generation == 13


def test_leading_on_from_what_runs_when_the_leaders_layout_was_not_heard(d):
    runs = dict(master_layout(d), amcl='laptop')
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 10.0, runs, generation=5)
    out = turn.lead(10.0, TAKEOVER, took_over=True)
    reason = (f'{TAKEOVER}; its layout was not heard: what runs is adopted '
              '(adopted amcl where it runs (laptop; planned robot))')
    assert out is not None and out.layouts == [(6, runs, reason)]
    assert [e[0] for e in out.events] == ['layout', 'takeover']
    assert out.events[1][4] == TAKEOVER
    assert ('info', f'generation 6: {reason}') in out.logs
    # AMCL runs where the adopted layout has it: the next turn leaves it there.
    feed(turn, d, 10.5, runs, generation=6)
    assert all(m.node != 'amcl' for m in turn.turn(10.5).decisions)
    assert turn.layout['amcl'] == 'laptop'


def test_a_takeover_of_an_unheard_layout_waits_for_every_agents_report(d):
    """A standby just started heard the leader's beat but neither its layout nor the laptop's
    agent before the leader died: adopting then would bring home what serves on the laptop
    (seen in CI: the worker sent home by the takeover). It waits for that report, at most
    agent_timeout_s after its start."""
    runs = dict(master_layout(d), amcl='laptop')
    standby = [n for n in d.node_names if d.standby_scales(n)]
    turn = DeciderTurn(d, d.decider, started=10.0)
    turn.book.agent_state(agent(d, 'robot', runs, 5, standby), 10.2)
    out = turn.lead(10.9, TAKEOVER, took_over=True)
    assert out is not None and not out.layouts and turn.layout is None
    assert [e[0] for e in out.events] == ['takeover']
    assert any('not yet: laptop' in text for _, text in out.logs), out.logs
    assert not turn.turn(11.0).layouts                      # still not heard: nothing said
    turn.book.agent_state(agent(d, 'laptop', runs, 5, standby), 11.1)
    out = turn.turn(11.2)
    ((generation, layout, why),) = out.layouts
    assert layout == runs and generation == 6 and why.startswith(TAKEOVER), why
    assert 'its layout was not heard: what runs is adopted' in why
    # A laptop that never reports: adopted from the robot alone, agent_timeout_s after start.
    late = DeciderTurn(d, d.decider, started=10.0)
    late.book.agent_state(agent(d, 'robot', runs, 5, standby), 10.2)
    late.lead(10.9, TAKEOVER, took_over=True)
    assert not late.turn(10.0 + d.decider.agent_timeout_s - 0.1).layouts
    assert late.turn(10.0 + d.decider.agent_timeout_s).layouts
    # Stood down while waiting, then leading with nobody to take over from: a first layout,
    # not the stale takeover.
    again = DeciderTurn(d, d.decider, started=10.0)
    again.lead(10.9, TAKEOVER, took_over=True)
    assert again.lead(20.0, 'no leader heard for 3 s', took_over=False) is None
    ((_, _, why),) = again.turn(20.0).layouts
    assert why.startswith('first layout'), why


def test_a_leader_that_stood_down_leads_on_from_its_own_layout(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 1.0, master_layout(d))
    turn.turn(1.0)
    mine, generation = dict(turn.layout), turn.generation
    out = turn.lead(5.0, 'no leader heard for 0.40 s', took_over=False)
    assert out is not None and out.layouts == [(generation + 1, mine,
                                                'no leader heard for 0.40 s')]
    assert [e[0] for e in out.events] == ['layout']         # no takeover: it led before


def test_a_decider_that_leads_without_following_anyone_waits_for_its_first_turn(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    assert turn.lead(3.0, 'no leader heard for 3 s', took_over=False) is None
    assert turn.layout is None and turn.generation == 0


def test_two_senders_past_a_moves_overlap_are_an_error_event_once_then_cleared(d):
    """A probe that has heard two writers of /amcl_pose at once for longer than
    duplicate_sender_s: one 'duplicate' event naming the topic, the publisher and the scale
    (not one per turn), an error line, then 'cleared' once it hears one again."""
    turn = DeciderTurn(d, d.decider, started=0.0)
    where = master_layout(d)
    bound = d.monitoring.duplicate_sender_s

    def amcl_pose(now, senders, for_s):
        conn = d.connection('amcl_ekf')
        reading = p.ConnectionReading(rate_hz=conn.freq_opt_hz, bytes_per_s=1000.0,
                                      below_for_s=0.0, level=p.OK, senders=senders,
                                      senders_for_s=for_s)
        turn.book.connection_status(p.ConnectionStatus(
            scale='robot', stamp=now, connections={'amcl_ekf': reading}), now)

    def duplicates(out):
        return [e for e in out.events if e[0] == 'duplicate']
    said = []
    for k, (senders, for_s) in enumerate([(2, bound - 0.5), (2, bound + 0.5), (2, bound + 1.5),
                                          (1, 0.0)]):
        t = 1.0 + k
        feed(turn, d, t, dict(turn.layout or where), turn.generation)
        amcl_pose(t, senders, for_s)
        said.append(turn.turn(t))
    assert not duplicates(said[0])
    (event,) = duplicates(said[1])
    assert event[1] == 'amcl' and event[2] == 'robot'
    assert '/amcl_pose' in event[4] and '2 senders' in event[4]
    assert any(level == 'error' and '/amcl_pose' in text for level, text in said[1].logs)
    assert not duplicates(said[2])
    assert any(e[0] == 'cleared' and e[4] == 'amcl_ekf: one sender again'
               for e in said[3].events)
