"""The claims ledger of a shared host (agent/ledger.py) on a real SQLite file: fit, refusal with
who holds what, standby memory, preemption by priority, leases, the host's figure, and agents
in separate processes claiming at once never over-committing."""

import multiprocessing
import sqlite3

import pytest

from anyscale_manager.agent.ledger import Claim, Ledger, LedgerError

LEASE = 10.0


def ledger(tmp_path, deployment, capacity=100.0, memory=0.0, priority=0, now=0.0):
    book = Ledger(str(tmp_path), deployment, LEASE)
    book.join(capacity, memory, priority, now)
    return book


def test_a_claim_that_fits_is_granted_and_one_that_does_not_is_refused_naming_the_holder(
        tmp_path):
    a, b = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b')
    assert a.claim(Claim('robot_a', 'amcl', 60, 0), 1.0).granted
    answer = b.claim(Claim('robot_b', 'amcl', 60, 0), 1.0)
    assert not answer.granted and not answer.waiting
    assert 'robot_a/amcl (60 CPU' in answer.reason and 'capacity 100' in answer.reason
    assert b.claim(Claim('robot_b', 'ar', 40, 0), 1.0).granted
    share = b.share(1.0)
    assert share.others_cpu() == 60 and [c.node for c in share.others] == ['amcl']


def test_a_standby_copy_claims_memory_only(tmp_path):
    a = ledger(tmp_path, 'robot_a', capacity=100, memory=200)
    b = ledger(tmp_path, 'robot_b', capacity=100, memory=200)
    assert a.claim(Claim('robot_a', 'amcl', 0, 70, active=False), 1.0).granted
    assert b.claim(Claim('robot_b', 'amcl', 90, 70), 1.0).granted
    # Its activation asks for CPU too: b holds 90 of 100.
    assert not a.claim(Claim('robot_a', 'amcl', 60, 70), 1.0).granted
    answer = a.claim(Claim('robot_a', 'ar', 0, 70, active=False), 1.0)
    assert not answer.granted and 'memory 140 MiB held + 70 > 200 MiB' in answer.reason


def test_released_capacity_is_there_for_the_next(tmp_path):
    a, b = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b')
    assert a.claim(Claim('robot_a', 'amcl', 60, 0), 1.0).granted
    assert not b.claim(Claim('robot_b', 'amcl', 60, 0), 1.0).granted
    a.release('amcl', 2.0)
    assert b.claim(Claim('robot_b', 'amcl', 60, 0), 2.0).granted


def test_a_claim_not_renewed_within_its_lease_expires_and_renewed_ones_stay(tmp_path):
    a, b = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b')
    assert a.claim(Claim('robot_a', 'amcl', 60, 0), 0.0).granted
    b.renew(LEASE - 1)
    a.renew(LEASE - 1)            # a renews once, then dies
    assert not b.claim(Claim('robot_b', 'amcl', 60, 0), 2 * LEASE - 2).granted
    assert b.claim(Claim('robot_b', 'amcl', 60, 0), 2 * LEASE).granted


def test_a_higher_priority_claim_asks_the_lower_to_leave_and_is_granted_only_after(tmp_path):
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=1)
    assert low.claim(Claim('robot_a', 'amcl', 60, 0, priority=0), 1.0).granted
    assert low.claim(Claim('robot_a', 'ar', 30, 0, priority=0), 1.0).granted
    answer = high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 2.0)
    assert not answer.granted and answer.waiting
    assert 'robot_a/amcl' in answer.reason and 'robot_a/ar' not in answer.reason
    assert low.share(2.0).asked == {'amcl': 'robot_b/amcl'}
    # Still not granted while the lower copy holds it.
    assert not high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 3.0).granted
    low.release('amcl', 4.0)
    assert low.share(4.0).asked == {}
    assert high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 4.0).granted


def test_equal_priority_never_preempts(tmp_path):
    a, b = ledger(tmp_path, 'robot_a', priority=1), ledger(tmp_path, 'robot_b', priority=1)
    assert a.claim(Claim('robot_a', 'amcl', 60, 0, priority=1), 1.0).granted
    answer = b.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 1.0)
    assert not answer.granted and not answer.waiting and a.share(1.0).asked == {}


def test_a_preemption_that_would_not_make_room_asks_no_one(tmp_path):
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=2)
    assert low.claim(Claim('robot_a', 'ar', 30, 0), 1.0).granted
    other = ledger(tmp_path, 'robot_c', priority=5)
    assert other.claim(Claim('robot_c', 'amcl', 60, 0, priority=5), 1.0).granted
    answer = high.claim(Claim('robot_b', 'amcl', 60, 0, priority=2), 1.0)
    assert not answer.granted and not answer.waiting and low.share(1.0).asked == {}


def test_the_first_figure_of_the_host_rules_and_a_disagreeing_one_is_told(tmp_path):
    a = Ledger(str(tmp_path), 'robot_a', LEASE)
    assert a.join(100, 0, 0, 0.0).disagreement == ''
    b = Ledger(str(tmp_path), 'robot_b', LEASE)
    figure = b.join(400, 0, 0, 0.0)
    assert figure.capacity_cpu == 100 and 'robot_a' in figure.disagreement
    assert '400' in figure.disagreement
    assert not b.claim(Claim('robot_b', 'amcl', 150, 0), 1.0).granted
    # robot_a gone for good: the next to join alone sets the figure.
    a.leave()
    b.leave()
    assert Ledger(str(tmp_path), 'robot_c', LEASE).join(400, 0, 0, 2.0).capacity_cpu == 400


def test_an_unusable_state_dir_is_an_error_naming_the_file(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    with pytest.raises(LedgerError, match='claims ledger'):
        Ledger(str(blocker / 'sub'), 'robot_a', LEASE)
    (tmp_path / 'bad').mkdir()
    (tmp_path / 'bad' / 'claims.sqlite3').write_text('garbage' * 200)
    with pytest.raises(LedgerError, match='claims.sqlite3'):
        Ledger(str(tmp_path / 'bad'), 'robot_a', LEASE)


def _claimer(path, deployment, rounds, queue):
    book = Ledger(path, deployment, 1e6)
    book.join(100, 0, 0, 0.0)
    granted = 0
    for i in range(rounds):
        if book.claim(Claim(deployment, 'amcl', 60, 0), float(i)).granted:
            granted += 1
            con = sqlite3.connect(book.path)
            total = con.execute('SELECT SUM(cpu) FROM claims WHERE active = 1').fetchone()[0]
            con.close()
            queue.put(total)
            book.release('amcl', float(i))
    queue.put(('done', granted))


def test_agents_in_separate_processes_claiming_at_once_never_over_commit(tmp_path):
    context = multiprocessing.get_context('spawn')
    queue = context.Queue()
    workers = [context.Process(target=_claimer, args=(str(tmp_path), f'robot_{i}', 150, queue))
               for i in range(4)]
    for w in workers:
        w.start()
    totals, done = [], []
    while len(done) < len(workers):
        item = queue.get(timeout=60)
        (done if isinstance(item, tuple) else totals).append(item)
    for w in workers:
        w.join(timeout=30)
    assert totals and max(totals) <= 100
    assert sum(granted for _, granted in done) == len(totals)


def test_the_room_a_waiting_claim_waits_for_is_not_taken_by_a_lower_one_meanwhile(tmp_path):
    """robot_a (priority 0) is asked to leave for robot_b (1); once robot_a has gone, robot_a's
    next claim (its node coming straight back, say) does not take the room robot_b waits for."""
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=1)
    assert low.claim(Claim('robot_a', 'amcl', 60, 0), 1.0).granted
    assert high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 2.0).waiting
    # robot_a's decider sees the room reserved.
    assert [c.deployment for c in low.share(2.0).reserved] == ['robot_b']
    low.release('amcl', 3.0)
    answer = low.claim(Claim('robot_a', 'amcl', 60, 0), 3.1)
    assert not answer.granted and not answer.waiting and 'robot_b/amcl' in answer.reason
    assert high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 3.2).granted
    # Granted, it waits no more: nothing is reserved twice.
    assert [c.node for c in low.share(3.2).others] == ['amcl'] and low.share(3.2).reserved == ()


def test_a_waiting_claim_given_up_reserves_nothing_more(tmp_path):
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=1)
    assert low.claim(Claim('robot_a', 'amcl', 60, 0), 1.0).granted
    assert high.claim(Claim('robot_b', 'amcl', 60, 0, priority=1), 2.0).waiting
    assert not low.claim(Claim('robot_a', 'ar', 40, 0), 2.1).granted   # 60 + 60 reserved
    high.release('amcl', 2.2)              # robot_b placed its node elsewhere
    assert low.share(2.2).asked == {} and low.share(2.2).reserved == ()
    assert low.claim(Claim('robot_a', 'ar', 40, 0), 2.3).granted


def test_a_robot_that_waits_for_two_nodes_asks_room_for_both(tmp_path):
    """robot_b (priority 1) wants its AMCL and AR where robot_a (0) holds both: each of
    robot_b's claims counts the room its other one waits for, so robot_a is asked for as much
    as both need, not only for what each would need alone (which left robot_b's second node
    waiting for an ask that had been answered)."""
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=1)
    assert low.claim(Claim('robot_a', 'amcl', 50, 0), 1.0).granted
    assert low.claim(Claim('robot_a', 'ar', 33, 0), 1.0).granted
    assert high.claim(Claim('robot_b', 'amcl', 50, 0, priority=1), 2.0).waiting
    answer = high.claim(Claim('robot_b', 'ar', 33, 0, priority=1), 2.0)
    assert answer.waiting and 'robot_a/amcl' in answer.reason and 'robot_a/ar' in answer.reason
    low.release('amcl', 3.0)
    # AMCL alone would fit beside robot_a's AR now; with robot_b's AR waiting it does not, and
    # robot_a's AR stays asked.
    assert high.claim(Claim('robot_b', 'amcl', 50, 0, priority=1), 3.1).waiting
    assert low.share(3.1).asked == {'ar': 'robot_b/ar'}
    low.release('ar', 4.0)
    assert high.claim(Claim('robot_b', 'amcl', 50, 0, priority=1), 4.1).granted
    assert high.claim(Claim('robot_b', 'ar', 33, 0, priority=1), 4.1).granted


def test_a_copy_deactivated_while_others_wait_for_room_gets_its_smaller_claim(tmp_path):
    """robot_a (0) holds AMCL and AR; robot_b (1) waits for room for both. robot_a yields
    AMCL first (its copy deactivated: a standby claim of no CPU): held and waited-for room add
    up past the capacity meanwhile, and the smaller claim must still be granted, or robot_a's
    active claim would stay and robot_b would wait for ever."""
    low, high = ledger(tmp_path, 'robot_a'), ledger(tmp_path, 'robot_b', priority=1)
    assert low.claim(Claim('robot_a', 'amcl', 50, 0), 1.0).granted
    assert low.claim(Claim('robot_a', 'ar', 33, 0), 1.0).granted
    assert high.claim(Claim('robot_b', 'amcl', 50, 0, priority=1), 2.0).waiting
    assert high.claim(Claim('robot_b', 'ar', 33, 0, priority=1), 2.0).waiting
    assert low.claim(Claim('robot_a', 'amcl', 50, 0, active=False), 3.0).granted
    assert low.claim(Claim('robot_a', 'ar', 33, 0, active=False), 3.0).granted
    # A claim growing back is not let through that way.
    assert not low.claim(Claim('robot_a', 'ar', 33, 0), 3.1).granted
    assert high.claim(Claim('robot_b', 'amcl', 50, 0, priority=1), 4.0).granted
    assert high.claim(Claim('robot_b', 'ar', 33, 0, priority=1), 4.0).granted
