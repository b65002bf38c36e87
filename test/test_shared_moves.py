"""The decider's answers to a shared host (runtime/moves/shared.py, moves/pending.py): a refused
move is undone at once, a node asked to leave comes home, and a move that waits for a
preemption is given the lease of the claims it waits on. Pure, hand-written observations."""

from anyscale_manager import protocol as p
from anyscale_manager.model.capacity import claim_lease_s
from anyscale_manager.model.loader import load_mapping
from anyscale_manager.runtime.moves.pending import pending_timeout_s, settle_pending
from anyscale_manager.runtime.moves.shared import shared_answers
from anyscale_manager.runtime.moves.state import Memory, Step
from anyscale_manager.runtime.observations import MIGRATE_BACK, Observations, YIELD


def deployment():
    return load_mapping({'/**': {'ros__parameters': {
        'deployment': {'name': 'robot_a'},
        'scales': {'names': ['robot', 'server'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                   'server': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100.0,
                              'shared': True}},
        'nodes': {'names': ['amcl', 'ar'], 'amcl': {'cpu': 60.0}, 'ar': {'cpu': 30.0}},
    }}})


def share(refused=None, waiting=None, asked=None):
    return p.HostShare(100.0, 0.0, {'robot_b/amcl': p.ShareClaim(60.0, 0.0, 0, True)},
                       refused or {}, waiting or {}, asked or {})


def step(d, now, running, shares, pending):
    memory = Memory(pending=dict(pending), migrated=[(n, s) for n, (s, _) in pending.items()])
    obs = Observations(now=now, running=running, shares=shares)
    return Step(d, d.decider, obs, dict(running), memory)


def test_a_refused_move_is_undone_at_once_to_where_the_node_still_serves():
    d = deployment()
    s = step(d, 10.0, {'amcl': 'robot', 'ar': 'robot'},
             {'server': share(refused={'amcl': 'robot_b/amcl holds 60 of 100'})},
             {'amcl': ('server', 9.5)})
    decisions = shared_answers(s)
    assert [(x.kind, x.node, x.from_scale, x.to_scale) for x in decisions] == [
        (YIELD, 'amcl', 'server', 'robot')]
    assert decisions[0].reason == 'server has no room for amcl: robot_b/amcl holds 60 of 100'
    assert 'amcl' not in s.memory.pending


def test_a_node_asked_to_leave_comes_home_once_and_only_from_where_it_runs():
    d = deployment()
    shares = {'server': share(asked={'amcl': 'robot_b/amcl', 'ar': 'robot_b/amcl'})}
    s = step(d, 10.0, {'amcl': 'server', 'ar': 'robot'}, shares, {})
    decisions = shared_answers(s)
    assert [(x.kind, x.node, x.to_scale) for x in decisions] == [
        (YIELD, 'amcl', 'robot')]
    assert 'robot_b/amcl of a higher priority asks server' in decisions[0].reason
    # Already on its way home (pending): not asked for again.
    s = step(d, 10.5, {'amcl': 'server', 'ar': 'robot'}, shares, {'amcl': ('robot', 10.0)})
    assert shared_answers(s) == []


def test_a_move_waiting_for_a_preemption_is_given_the_claims_lease_before_it_is_undone():
    d = deployment()
    timeout = pending_timeout_s(d, d.decider)
    running = {'amcl': 'robot', 'ar': 'robot'}
    waiting = {'server': share(waiting={'amcl': 'waits for robot_c/amcl to leave'})}
    late = 1.0 + timeout + 1.0
    assert settle_pending(step(d, late, running, waiting, {'amcl': ('server', 1.0)})) == []
    later = 1.0 + timeout + claim_lease_s(d) + 1.0
    undone = settle_pending(step(d, later, running, waiting, {'amcl': ('server', 1.0)}))
    assert [(x.kind, x.node) for x in undone] == [(MIGRATE_BACK, 'amcl')]
    # Without a preemption under way, the usual timeout.
    assert settle_pending(step(d, late, running, {}, {'amcl': ('server', 1.0)}))


def test_a_yield_holds_nothing_back_from_the_host_once_it_has_room():
    """A refused move is a race for room, not a flapping link: no hysteresis after it."""
    from anyscale_manager.runtime.policy import MigrationPolicy
    d = deployment()
    policy = MigrationPolicy(d)
    policy.reset({'amcl': 'server', 'ar': 'robot'}, 0.0, {'amcl': 'robot', 'ar': 'robot'})
    refused = share(refused={'amcl': 'no room'})
    obs = Observations(now=1.0, running={'amcl': 'robot', 'ar': 'robot'},
                       shares={'server': refused})
    assert [x.kind for x in policy.step(obs)] == [YIELD]
    assert ('amcl', 'server') not in policy.memory.last_back
