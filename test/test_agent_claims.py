"""Agents of two deployments on one shared host (agent/claims.py over agent/ledger.py): their
turns with a hand-written clock, real short processes and one real claims database. Only one
copy fits; the other is refused, said, reported, and kept serving where it was."""

import dataclasses
import time

from anyscale_manager import protocol as p
from anyscale_manager.agent import lifecycle as lc
from anyscale_manager.agent.claims import HostClaims
from anyscale_manager.agent.ledger import Ledger
from anyscale_manager.agent.reconcile import Reconciler
from anyscale_manager.agent.turn import AgentInputs, AgentTurn
from anyscale_manager.model.capacity import claim_lease_s as lease_s
from anyscale_manager.model.loader import load_mapping
from supervision import py_entry, SLEEPER
from test_agent_turn import layout as unit_layout

WALL_OFFSET = 1.7e9


def layout(generation, deployment='robot_a', **assignments):
    return dataclasses.replace(unit_layout(generation, **assignments), deployment=deployment)


def fleet_member(name, priority=0):
    """Robot ``name``'s deployment: its robot (master) and the shared server (capacity 100),
    one node of CPU 60."""
    return load_mapping({'/**': {'ros__parameters': {
        'deployment': {'name': name, 'priority': priority},
        'scales': {'names': ['robot', 'server'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                   'server': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100.0,
                              'shared': True}},
        'nodes': {'names': ['amcl'], 'amcl': {'launch': {'command': ['sleep', '5']},
                                              'cpu': 60.0, 'memory_mb': 70.0}},
    }}})


class ServerAgent:
    """The server's agent of one deployment, on a hand-written clock shared with the others."""

    def __init__(self, make_sup, deployment, state_dir, clock):
        entry = py_entry('amcl', SLEEPER)
        self.clock = clock
        self.sup = make_sup([entry])
        self.turn = AgentTurn(deployment, 'server', {'amcl': entry}, self.sup,
                              instance=deployment.name, wall_offset=WALL_OFFSET)
        self.turn.claims = HostClaims(Ledger(state_dir, deployment.name, lease_s(deployment)),
                                      deployment, 'server')
        self.logs = list(self.turn.begin(clock[0]).logs)

    def step(self):
        self.turn.reconciler.heard_master(self.clock[0])     # the robot is heard throughout
        out = self.turn.step(self.clock[0], AgentInputs(wall=self.clock[0] + WALL_OFFSET,
                                                        visible={'amcl': 1}))
        self.logs += out.logs
        return out


def both_want_the_server(make_sup, tmp_path):
    """robot_a's and robot_b's server agents on one host, each given a layout placing its
    AMCL there; (the shared clock, a, b)."""
    clock = [100.0]
    a = ServerAgent(make_sup, fleet_member('robot_a'), str(tmp_path), clock)
    b = ServerAgent(make_sup, fleet_member('robot_b'), str(tmp_path), clock)
    a.turn.on_layout(layout(1, amcl='server'), clock[0])
    b.turn.on_layout(layout(1, 'robot_b', amcl='server'), clock[0])
    return clock, a, b


def test_two_deployments_wanting_one_server_get_one_copy_and_the_other_is_told_who_holds_it(
        make_sup, tmp_path):
    clock, a, b = both_want_the_server(make_sup, tmp_path)
    assert any('shared scale: claims in' in t for _, t in a.logs)
    assert a.step().wanted == {'amcl'}
    out = b.step()
    assert out.wanted == set() and 'amcl' not in b.sup.pids()
    share = out.report.share
    assert 'robot_a/amcl (60 CPU' in share.refused['amcl']
    assert share.claims == {'robot_a/amcl': p.ShareClaim(60.0, 70.0, 0, True)}
    assert any(level == 'warn' and 'amcl: not started or activated here' in text
               for level, text in b.logs)
    # Said once, not at every step.
    before = len(b.logs)
    b.step()
    assert len(b.logs) == before
    # a's copy goes (the layout takes it home): its claim is released once the process is
    # gone, and b's copy starts.
    a.turn.on_layout(layout(2, amcl='robot'), clock[0])
    end = time.monotonic() + 15
    while 'amcl' not in b.sup.pids():
        clock[0] += 0.1
        a.step()
        b.step()
        assert time.monotonic() < end, 'b never started its copy'
        time.sleep(0.02)
    assert 'amcl' not in a.sup.pids()
    assert any('its claim released' in t for _, t in a.logs)
    assert b.turn.report(0.0).share.refused == {}


def test_a_killed_agents_claims_expire_with_their_lease(make_sup, tmp_path):
    clock, a, b = both_want_the_server(make_sup, tmp_path)
    a.step()
    assert b.step().wanted == set()
    # a is not stepped any more (dead): its lease ends, and b may start then, not before.
    lease = lease_s(fleet_member('robot_a'))
    clock[0] += lease - 0.5
    assert b.step().wanted == set()
    clock[0] += 1.0
    assert b.step().wanted == {'amcl'}


def test_a_losing_scale_keeps_its_copy_while_the_gaining_shared_scale_refuses_it():
    d = fleet_member('robot_a')
    robot = Reconciler(d, 'robot', ['amcl'], readiness_timeout_s=2.0, agent_timeout_s=3.0)
    robot.apply_layout(layout(1, amcl='robot'), 0.0)
    robot.apply_layout(layout(2, amcl='server'), 1.0)
    refusal = p.HostShare(100.0, 0.0, {}, {'amcl': 'no room: robot_b/amcl holds 60'}, {}, {})
    report = dataclasses.replace(
        p.AgentState(scale='server', generation=2, stamp=0.0, nodes={}), share=refusal)
    robot.peer_state(report, 1.5)
    # Long past readiness_timeout_s: still kept, and said why.
    assert robot.desired(2.5, {'amcl'}) == {'amcl'}
    robot.peer_state(report, 4.9)
    assert robot.desired(5.0, {'amcl'}) == {'amcl'}
    assert robot.waiting['amcl'].startswith('kept: server does not take it (no room')
    # Without the refusal the timeout lets it go as before.
    robot.peer_state(dataclasses.replace(report, share=None), 5.1)
    assert robot.desired(5.2, {'amcl'}) == set()


def test_an_agent_shutting_down_gives_its_room_back_before_it_exits(make_sup, tmp_path):
    clock, a, b = both_want_the_server(make_sup, tmp_path)
    assert a.step().wanted == {'amcl'}
    a.turn.request_shutdown(clock[0])
    end = time.monotonic() + 15
    while not a.turn.finished:
        clock[0] += 0.05
        a.step()
        assert time.monotonic() < end, 'the agent never finished'
        time.sleep(0.02)
    # Finished (it would exit now): its claim is gone already, not after a lease.
    assert b.step().wanted == {'amcl'}


def test_a_copy_being_deactivated_keeps_its_room_until_it_is_inactive(tmp_path):
    """A layout stands robot_a's active copy down (its goal inactive): while its lifecycle
    state is still active the agent's claim stays active, so robot_b (waiting with a higher
    priority) cannot be handed the room while both would serve; once inactive, the claim
    shrinks to a standby one and robot_b's is granted."""
    low = HostClaims(Ledger(str(tmp_path), 'robot_a', 10.0), fleet_member('robot_a'), 'server')
    high = HostClaims(Ledger(str(tmp_path), 'robot_b', 10.0), fleet_member('robot_b', 1),
                      'server')
    low.begin(0.0)
    high.begin(0.0)
    live = {'amcl'}
    low.gate(1.0, {'amcl'}, {'amcl': lc.ACTIVE}, live.__contains__)
    assert low.held['amcl'].active
    goals = {'amcl': lc.ACTIVE}
    high.gate(2.0, {'amcl'}, goals, lambda n: False)
    assert goals['amcl'] == lc.FINALIZED and 'amcl' in high.waiting
    serving = {'amcl'}
    low.gate(3.0, {'amcl'}, {'amcl': lc.INACTIVE}, live.__contains__, serving.__contains__)
    assert low.held['amcl'].active                 # still serving: its room stays held
    goals = {'amcl': lc.ACTIVE}
    high.gate(3.1, {'amcl'}, goals, lambda n: False)
    assert 'amcl' in high.waiting
    serving.clear()                                # its deactivation done
    low.gate(4.0, {'amcl'}, {'amcl': lc.INACTIVE}, live.__contains__, serving.__contains__)
    assert not low.held['amcl'].active
    goals = {'amcl': lc.ACTIVE}
    high.gate(4.1, {'amcl'}, goals, lambda n: False)
    assert high.held['amcl'].active and goals['amcl'] == lc.ACTIVE


def test_before_any_layout_a_standby_copy_claims_no_cpu_and_an_unknown_one_its_room(tmp_path):
    """Before the first layout a live copy keeps its state (goal None): a standby copy the
    agent has just started claims memory only (it asks no one to leave), one adopted in an
    unknown state (it may serve) claims its CPU."""
    d = fleet_member('robot_a', 1)
    claims = HostClaims(Ledger(str(tmp_path), 'robot_a', 10.0), d, 'server')
    claims.begin(0.0)
    claims.gate(1.0, {'amcl'}, {'amcl': None}, lambda n: True, lambda n: False)
    assert not claims.held['amcl'].active and claims.held['amcl'].memory_mb == 70.0
    claims.gate(2.0, {'amcl'}, {'amcl': None}, lambda n: True, lambda n: True)
    assert claims.held['amcl'].active and claims.held['amcl'].cpu == 60.0


def test_a_wait_given_up_by_the_layout_reserves_nothing_more(tmp_path):
    """robot_b (priority 1) waits for room robot_a holds; its layout then keeps its copy a
    standby (its node placed elsewhere): the reservation goes with the wait, so robot_a's next
    claim and robot_b's own other claims are not held back by room nobody waits for."""
    low = HostClaims(Ledger(str(tmp_path), 'robot_a', 10.0), fleet_member('robot_a'), 'server')
    high = HostClaims(Ledger(str(tmp_path), 'robot_b', 10.0), fleet_member('robot_b', 1),
                      'server')
    low.begin(0.0)
    high.begin(0.0)
    low.gate(1.0, {'amcl'}, {'amcl': lc.ACTIVE}, lambda n: True)
    high.gate(1.5, {'amcl'}, {'amcl': lc.INACTIVE}, lambda n: True)    # its standby copy
    goals = {'amcl': lc.ACTIVE}
    high.gate(2.0, {'amcl'}, goals, lambda n: True)
    assert 'amcl' in high.waiting and low.ledger.share(2.0).asked == {'amcl': 'robot_b/amcl'}
    high.gate(3.0, {'amcl'}, {'amcl': lc.INACTIVE}, lambda n: True)   # placed elsewhere
    assert high.waiting == {} and low.ledger.share(3.0).reserved == ()
    assert low.ledger.share(3.0).asked == {}


def amcl_held_by_the_lower(tmp_path):
    """robot_a (priority 0) holding amcl on the shared server, robot_b (priority 1) joined."""
    low = HostClaims(Ledger(str(tmp_path), 'robot_a', 10.0), fleet_member('robot_a'), 'server')
    high = HostClaims(Ledger(str(tmp_path), 'robot_b', 10.0), fleet_member('robot_b', 1),
                      'server')
    low.begin(0.0)
    high.begin(0.0)
    low.gate(1.0, {'amcl'}, {}, lambda n: True)
    return low, high


def test_a_wait_for_a_node_without_a_claim_here_is_withdrawn_once_not_wanted(tmp_path):
    """A plain node (no standby claim) waits for room; the layout then places it elsewhere (it
    leaves ``want``): its wait and asks go all the same."""
    low, high = amcl_held_by_the_lower(tmp_path)
    want = {'amcl'}
    high.gate(2.0, want, {}, lambda n: False)
    assert 'amcl' in high.waiting and 'amcl' not in want
    high.gate(3.0, set(), {}, lambda n: False)
    assert high.waiting == {} and low.ledger.share(3.0).reserved == ()
    assert low.ledger.share(3.0).asked == {}


def test_a_restarted_agent_drops_the_waits_of_the_one_before_it(tmp_path):
    """An agent that waited for room and died: its successor, which adopts its claims, does not
    know those waits, and its renewals would keep them (and their asks) for as long as it
    lives: they go when it joins, and it waits anew if its layout still wants the node."""
    low, high = amcl_held_by_the_lower(tmp_path)
    high.gate(2.0, {'amcl'}, {}, lambda n: False)
    assert 'amcl' in high.waiting and low.ledger.share(2.0).asked
    successor = HostClaims(Ledger(str(tmp_path), 'robot_b', 10.0), fleet_member('robot_b', 1),
                           'server')
    successor.begin(3.0)
    successor.ledger.renew(4.0)
    assert low.ledger.share(4.0).reserved == () and low.ledger.share(4.0).asked == {}
    successor.gate(5.0, {'amcl'}, {}, lambda n: False)
    assert 'amcl' in successor.waiting and low.ledger.share(5.0).asked
