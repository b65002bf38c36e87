"""Who decides (pure, clocks by hand): a decider leads after listening, a standby takes over
from a silent leader at a higher term, the first started of several standbys goes first, a
leader steps down before a higher term and after a stall, and two leaders never command at once
under delays and stalls. Real deciders over DDS: test_standby_decider.py."""

import random

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.runtime.leadership import LEADER, STANDBY, Leadership, older, outranks

BEAT, TAKEOVER, DISCOVERY, LEASE = 0.05, 0.3, 5.0, 3.0


def ident(name, started=100.0):
    return p.DeciderIdentity(id=name, host='robot', pid=1, started=started)


def decider(name, started=100.0, at=0.0):
    return Leadership(ident(name, started), beat_s=BEAT, takeover_s=TAKEOVER,
                      discovery_s=DISCOVERY, lease_s=LEASE, started=at)


def test_a_lone_decider_leads_after_listening_above_every_term_heard():
    d = decider('a')
    assert d.check(4.9) is None and d.role == STANDBY and d.due_in(4.9) == pytest.approx(0.1)
    d.heard_term(6)                     # an agent follows a decider of term 6, gone now
    change = d.check(5.0)
    assert change.role == LEADER and change.term == 7 and change.previous is None
    assert 'no leading decider heard in 5.0 s' in change.reason
    assert d.may_command(5.0) and d.takeovers == 0


def test_a_standby_takes_over_from_a_silent_leader_at_a_higher_term():
    d = decider('b', started=200.0)
    leader = ident('a')
    for t in (0.0, 0.05, 0.1):
        assert d.heard_beat(leader, LEADER, 3, 12, t) is None
    assert d.check(0.35) is None and d.role == STANDBY          # 0.25 s of silence
    assert not d.may_command(0.35)
    change = d.check(0.4)                                        # 0.3 s: taken over
    assert change.role == LEADER and change.term == 4
    assert change.previous.identity == leader and change.previous.generation == 12
    assert 'a (host robot, pid 1) (term 3) silent for 0.30 s' in change.reason
    assert d.takeovers == 1 and d.may_command(0.4)
    # Hearing the leader again (a late beat of its old term) changes nothing.
    assert d.heard_beat(leader, LEADER, 3, 12, 0.45) is None and d.role == LEADER


def test_of_two_standbys_the_first_started_takes_over_and_the_other_stands_by():
    first, second = decider('f', started=100.0), decider('s', started=105.0)
    leader = ident('l', started=50.0)
    for d in (first, second):
        d.heard_beat(leader, LEADER, 1, 3, 0.0)
    first.heard_beat(second.me, STANDBY, 0, 0, 0.2)
    second.heard_beat(first.me, STANDBY, 0, 0, 0.2)
    assert first.due_in(0.2) is None                  # the leader is live still
    assert first.due_in(0.31) == pytest.approx(-0.01)
    assert second.due_in(0.31) == pytest.approx(-0.01 + 2 * BEAT)
    change = first.check(0.31)
    assert change.role == LEADER and change.term == 2
    assert second.check(0.31) is None
    # The first one's beat as leader reaches the second before its turn comes.
    assert second.heard_beat(first.me, LEADER, 2, 4, 0.32) is None
    assert second.check(0.45) is None and second.role == STANDBY
    assert second.live_leader(0.45).identity == first.me


def test_a_starting_decider_that_heard_only_a_layout_waits_out_its_discovery():
    d = decider('new', started=300.0, at=0.0)
    d.heard_beat(ident('l', started=50.0), LEADER, 2, 7, 0.2, layout=True)   # latched
    assert d.check(0.6) is None and d.check(4.9) is None and d.role == STANDBY
    change = d.check(5.0)
    assert change.role == LEADER and change.term == 3 and change.previous.identity.id == 'l'


def test_a_starting_decider_that_heard_the_leaders_beats_may_take_over_at_once():
    d = decider('new', started=300.0, at=0.0)
    d.heard_beat(ident('l', started=50.0), LEADER, 2, 7, 0.2, layout=True)
    d.heard_beat(ident('l', started=50.0), LEADER, 2, 7, 0.5)             # a beat
    assert d.check(0.75) is None
    change = d.check(0.8)
    assert change.role == LEADER and change.term == 3 and change.previous.identity.id == 'l'


def test_a_leader_steps_down_before_a_higher_term_or_an_older_one_of_its_term():
    d = decider('a', started=100.0)
    d.check(5.0)
    assert d.role == LEADER and d.term == 1
    # A younger decider at the same term: this one keeps the lead.
    assert d.heard_beat(ident('y', started=300.0), LEADER, 1, 1, 5.1) is None
    assert d.role == LEADER
    # One that took over while this one was cut off: a higher term.
    change = d.heard_beat(ident('n', started=300.0), LEADER, 2, 9, 5.2)
    assert change.role == STANDBY and d.role == STANDBY and not d.may_command(5.2)
    assert 'n (host robot, pid 1) leads at term 2 (this one at term 1): standing by' \
        in change.reason
    other = decider('b', started=200.0)
    other.check(5.0)
    assert other.heard_beat(ident('o', started=50.0), LEADER, 1, 1, 5.1).role == STANDBY
    assert outranks((1, ident('o', 50.0)), (1, ident('b', 200.0)))
    assert older(ident('a', 100.0), ident('b', 100.0))            # a tie: by id


def test_a_stalled_leader_commands_nothing_until_it_has_listened_again():
    d = decider('a')
    d.check(5.0)
    d.beaten(5.0)
    d.heard_beat(ident('s', started=300.0), STANDBY, 0, 0, 5.0)   # a standby is known
    assert d.may_command(5.19) and not d.may_command(5.21)  # takeover_s less the delivery
    # SIGSTOP for 1 s: on resuming it may not command, and its first check steps it down.
    assert not d.may_command(6.3)
    change = d.check(6.3)
    assert change.role == STANDBY and 'could not beat for 1.30 s' in change.reason
    # Nobody took over (the standby was stopped too): it leads again after takeover_s and
    # the time any standby would have taken to go first (two beats, twice the delivery).
    assert d.check(6.85) is None
    change = d.check(6.91)
    assert change.role == LEADER and change.term == 2 and change.previous is None


def test_a_lone_leader_that_stalled_briefly_keeps_leading():
    d = decider('a')
    d.check(5.0)
    d.beaten(5.0)
    assert d.check(6.0) is None and d.role == LEADER       # nobody else heard; 1 s < discovery
    d.beaten(6.0)
    assert d.check(11.5).role == STANDBY                   # 5.5 s: a newcomer may lead now


def test_a_leader_nobody_listens_to_commands_between_its_looks_but_not_after_a_stop():
    """Alone (no other decider reads its beats), a leader looks every alone_wait_s: that
    quiet time is no stall. Stopped longer while alone, a standby started meanwhile may have
    found no beat and taken over: resumed, it commands nothing and its check steps it down."""
    d = Leadership(ident('a'), beat_s=BEAT, takeover_s=TAKEOVER, discovery_s=DISCOVERY,
                   lease_s=LEASE, started=0.0, alone_wait_s=0.5)
    d.check(5.0)
    d.beaten(5.0)
    t = 5.0
    for _ in range(10):                      # its beat thread's turns, each a look
        assert d.check(t) is None
        d.listened(False, t)
        assert d.may_command(t) and d.may_command(t + 0.5 + d.stall_s - 0.01)
        t += 0.5
    # SIGSTOP for 3 s, alone when it stopped: no command before its beat thread has looked
    # again (nobody known and less than discovery_s: it then leads on).
    t += 3.0
    assert not d.may_command(t)
    assert d.check(t) is None
    d.listened(False, t)
    assert d.may_command(t)
    # A standby started meanwhile is heard: a stop past the stall steps it down at once.
    d.heard_beat(ident('s', started=300.0), STANDBY, 0, 0, t)
    assert not d.may_command(t + 1.0)
    change = d.check(t + 1.0)
    assert change is not None and change.role == STANDBY and 'could not beat' in change.reason


def test_a_leader_that_hears_a_higher_term_stands_by_then_leads_above_it():
    d = decider('a')
    d.check(5.0)
    d.beaten(5.0)
    d.heard_term(8)             # an agent follows a decider of term 8 (gone, or not heard yet)
    change = d.check(5.05)
    assert change.role == STANDBY and 'term 8 heard above' in change.reason
    assert not d.may_command(5.05)
    assert d.check(5.6) is None          # takeover_s, and any standby's turn before its own
    change = d.check(5.66)
    assert change.role == LEADER and change.term == 9


def test_a_leader_stalled_longer_than_the_lease_still_knows_its_standby():
    d = decider('a')
    d.check(5.0)
    d.heard_beat(ident('b', started=200.0), STANDBY, 0, 0, 5.0)
    d.beaten(5.0)
    change = d.check(8.5)       # 3.5 s stopped: > lease_s, < discovery_s; b may lead now
    assert change is not None and change.role == STANDBY and 'could not beat' in change.reason


def test_a_stale_layout_does_not_end_a_stepped_down_leaders_wait():
    d = decider('a')
    d.check(5.0)
    d.beaten(5.0)
    d.heard_beat(ident('s', started=300.0), STANDBY, 0, 0, 5.0)
    # Stopped 0.5 s; on resuming it hears the standby's queued beat, then a gone leader's
    # latched layout (term 1) turns up. The standby may have taken over at 5.3, its beats
    # still on their way: this one goes after it, as if no layout had come.
    d.heard_beat(ident('s', started=300.0), STANDBY, 0, 0, 5.5)
    assert d.check(5.5).role == STANDBY
    d.heard_beat(ident('z', started=50.0), LEADER, 1, 7, 5.51, layout=True)
    assert d.check(5.9) is None and d.check(6.1) is None
    assert d.check(6.12).role == LEADER


@pytest.mark.parametrize('seed', range(40))
def test_two_leaders_never_command_at_once_under_delays_and_stalls(seed):
    """Two deciders beat every 50 ms over a channel delaying each beat 0-80 ms; the leader
    is stopped for a random stretch (some shorter than takeover_s, some longer), then resumes.
    Every moment at which each may command is recorded: the stretches never overlap."""
    rng = random.Random(seed)
    a, b = decider('a', started=100.0), decider('b', started=200.0)
    stall_from = rng.uniform(6.0, 8.0)
    stall_to = stall_from + rng.choice([0.1, 0.25, 0.35, 0.6, 2.0, 3.5, 7.0]) \
        + rng.uniform(0, 0.05)
    in_flight = []              # (arrival, receiver, sender, role, term)
    commands = {'a': [], 'b': []}
    t, dt = 0.0, 0.005
    next_beat = {'a': 0.0, 'b': 0.013}
    while t < 20.0:
        for arrival, receiver, sender, role, term in [m for m in in_flight if m[0] <= t]:
            in_flight.remove((arrival, receiver, sender, role, term))
            if receiver is a and stall_from <= t < stall_to:
                # read on resume, some after a's first checks
                in_flight.append((stall_to + rng.uniform(0.0, 0.2), receiver, sender, role,
                                  term))
                continue
            if sender is None:
                receiver.heard_term(term)             # an agent's report of the term it follows
            else:
                receiver.heard_beat(sender.me, role, term, 0, t)
        for name, d, other in (('a', a, b), ('b', b, a)):
            if name == 'a' and stall_from <= t < stall_to:
                continue
            d.check(t)
            if d.may_command(t):
                commands[name].append((t, d.term))
            if t >= next_beat[name]:
                d.beaten(t)
                in_flight.append((t + rng.uniform(0.0, 0.08), other, d, d.role, d.term))
                if d.may_command(t):
                    # the agents follow it; their reports reach the other sooner or later
                    in_flight.append((t + rng.uniform(0.0, 0.3), other, None, LEADER, d.term))
                next_beat[name] = t + BEAT
        t += dt
    assert commands['a'], 'a never led'
    for ta, term_a in commands['a']:
        for tb, term_b in commands['b']:
            assert abs(ta - tb) > 1e-9, (seed, ta, term_a, tb, term_b)
    # A later command is always of a higher-or-equal term than every earlier one of the other.
    merged = sorted([(t_, term, n) for n, c in commands.items() for t_, term in c])
    for (t1, term1, n1), (t2, term2, n2) in zip(merged, merged[1:]):
        if n1 != n2:
            assert term2 > term1, (seed, t1, term1, n1, t2, term2, n2)


def test_layouts_and_beats_carry_and_bound_the_term():
    lay = p.Layout(generation=3, deployment='d', assignments={'x': 'robot'}, reason='r',
                   stamp=1.0, decider=ident('a'), seq=1, term=7)
    assert p.Layout.from_json(lay.to_json()).term == 7
    older_layout = p.Layout(generation=3, deployment='d', assignments={}, reason='r', stamp=1.0)
    assert 'term' not in older_layout.to_json() and p.Layout.from_json(
        older_layout.to_json()).term is None
    with pytest.raises(p.ProtocolError, match=r'Layout.term: must be in \[0, 2\*\*53\]'):
        p.Layout.from_dict(dict(lay.to_dict(), term=-1))
    beat = p.DeciderBeat(stamp=1.0, deployment='d', decider=ident('a'), role='standby', term=2,
                         generation=5)
    assert p.DeciderBeat.from_json(beat.to_json()) == beat
    with pytest.raises(p.ProtocolError, match='DeciderBeat.role: expected one of leader'):
        p.DeciderBeat.from_dict(dict(beat.to_dict(), role='king'))
    state = p.AgentState(scale='robot', generation=1, stamp=1.0, nodes={}, term=3)
    assert p.AgentState.from_json(state.to_json()).term == 3
