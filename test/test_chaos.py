"""The chaos soak's pure parts: the seeded fault schedule, the fault registry, the judges, the
samples' census, the verdict and the report, the hostile forger, and the record's signature
check. No ROS, no processes (the soak itself: test_e2e_soak.py)."""

import json
import random

import pytest

from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.testbed import chaos, faults, samples, soak_report, verdict
from anyscale_manager.testbed.hostile import LABELS, Forger
from anyscale_manager.testbed.record import DeltaBreach, Record

from conftest import TESTBED

KEY = bytes(range(32))


# --- the schedule -------------------------------------------------------------------------------

def test_the_same_seed_gives_the_same_schedule_and_another_seed_another():
    assert chaos.generate(11, 600.0) == chaos.generate(11, 600.0)
    assert chaos.generate(11, 600.0) != chaos.generate(12, 600.0)


@pytest.mark.parametrize('seed', range(8))
@pytest.mark.parametrize('duration_s', [60.0, 120.0, 600.0])
def test_faults_fit_the_duration_and_never_overlap(seed, duration_s):
    gap = (6.0, 12.0)
    faults = chaos.generate(seed, duration_s, gap_s=gap)
    assert [f.index for f in faults] == list(range(len(faults)))
    for f in faults:
        assert f.kind in chaos.KINDS
        assert f.at_s + f.length_s <= duration_s
    for a, b in zip(faults, faults[1:]):
        assert b.at_s >= a.at_s + a.length_s + gap[0] - 0.1
    if duration_s == 600.0:
        assert len(faults) >= 20


def test_a_long_soak_draws_every_kind_with_its_parameters_in_range():
    faults = [f for seed in range(5) for f in chaos.generate(seed, 600.0)]
    assert {f.kind for f in faults} == set(chaos.KINDS)
    for f in faults:
        if f.kind == 'cut':
            assert 3.0 <= f.hold_s <= 12.0
        elif f.kind == 'throttle':
            assert f.rate_kbps in chaos.THROTTLE_KBPS and 8.0 <= f.hold_s <= 15.0
        elif f.kind == 'flap':
            assert 3 <= len(f.flaps) <= 6
            assert all(0.3 <= d <= 1.5 and 0.5 <= u <= 2.0 for d, u in f.flaps)
        elif f.kind == 'kill_node':
            assert (f.node, f.copy) in {(n, c) for n in ('amcl', 'ar')
                                        for c in ('active', 'standby')} | {
                (n, 'active') for n in ('odometry', 'ekf', 'navigation')}
        elif f.kind == 'hostile':
            assert 4.0 <= f.hold_s <= 8.0
        elif f.kind == 'stop_decider':
            assert 1.0 <= f.hold_s <= 4.0
        elif f.kind == 'lose_agent_laptop':
            assert f.hold_s == chaos.LOSE_AGENT_S
        elif f.kind == 'crash_loop':
            assert f.node in ('amcl', 'ar', 'odometry', 'ekf', 'navigation')
            assert f.node in f.describe()
        assert f.describe()


def test_the_short_soak_of_the_e2e_module_has_one_fault_of_every_kind():
    # The seed and bounds of test_e2e_soak.py.
    from test_e2e_soak import DURATION_S, SEED
    faults = chaos.generate(SEED, DURATION_S, ensure_each=True, gap_s=(3.0, 5.0))
    assert sorted(f.kind for f in faults) == sorted(chaos.KINDS)


def test_kinds_can_be_restricted_and_bad_arguments_are_refused():
    faults = chaos.generate(1, 300.0, kinds=('cut', 'flap'))
    assert faults and {f.kind for f in faults} <= {'cut', 'flap'}
    with pytest.raises(ValueError, match='unknown fault kind'):
        chaos.generate(1, 300.0, kinds=('cut', 'meteor'))
    with pytest.raises(ValueError, match='duration'):
        chaos.generate(1, 0.0)
    with pytest.raises(ValueError, match='no fault kinds'):
        chaos.generate(1, 60.0, kinds=())
    with pytest.raises(ValueError, match='gap_s'):
        chaos.generate(1, 60.0, gap_s=(5.0, 1.0))


def test_reaction_summary_gives_p50_and_p95_per_kind():
    rows = [{'kind': 'cut', 'reaction_s': x} for x in (0.3, 0.4, 0.5, 0.6, 2.0)]
    rows += [{'kind': 'cut', 'reaction_s': None}, {'kind': 'hostile', 'reaction_s': None}]
    summary = chaos.reaction_summary(rows)
    assert summary['cut']['faults'] == 6 and summary['cut']['timed'] == 5
    assert summary['cut']['p50_s'] == 0.5 and summary['cut']['max_s'] == 2.0
    assert summary['cut']['p95_s'] == pytest.approx(1.72)
    assert summary['hostile'] == {'faults': 1, 'timed': 0, 'p50_s': None, 'p95_s': None,
                                  'max_s': None}
    assert chaos.percentile([], 0.5) is None


# --- two writers at once ------------------------------------------------------------------------

def _interleave(a, b):
    return sorted(a + b)


def test_writer_streams_tell_interleaved_writers_and_a_restarted_one_apart():
    old = [(t * 0.2, 1000 + t) for t in range(50)]                # 5 Hz for 10 s
    new = [(5.1 + t * 0.2, 1 + t) for t in range(50)]             # a copy from 5.1 s
    both = _interleave(old, new)
    streams = chaos.writer_streams([t for t, _ in both], [s for _, s in both])
    assert sorted(len(s) for s in streams) == [50, 50]
    # One writer after another (a restart): the new one starts from 1 after the old ended.
    seq = [(t * 0.2, 500 + t) for t in range(10)] + [(3.0 + t * 0.2, 1 + t) for t in range(10)]
    streams = chaos.writer_streams([t for t, _ in seq], [s for _, s in seq])
    assert [len(s) for s in streams] == [10, 10]
    assert chaos.concurrent_spans([chaos.active_spans(s, 1.0) for s in streams]) == []
    # Arrivals without a number are left out.
    assert chaos.writer_streams([0.0, 0.1], [-1, -1]) == []


def test_duplicates_count_overlaps_beyond_the_bound_and_report_the_longest():
    old = [(t * 0.2, 1000 + t) for t in range(100)]               # 0 .. 19.8 s
    short = [(3.0 + t * 0.2, 1 + t) for t in range(10)]           # 3 .. 4.8 s: a handover
    long_ = [(10.0 + t * 0.2, 1 + t) for t in range(50)]          # 10 .. 19.8 s
    for extra, found in ((short, 0), (long_, 1)):
        both = _interleave(old, extra)
        dups, longest = chaos.duplicates({'/amcl_pose': [t for t, _ in both]},
                                         {'/amcl_pose': [s for _, s in both]},
                                         {'/amcl_pose': 'amcl'}, 0.0, 30.0, bound_s=6.0)
        assert len(dups) == found
        assert longest['amcl'] == pytest.approx(extra[-1][0] - extra[0][0], abs=0.01)
    assert dups[0].node == 'amcl' and dups[0].length_s == pytest.approx(9.8, abs=0.01)


def test_concurrent_spans_need_two_streams_at_once():
    assert chaos.concurrent_spans([[(0.0, 5.0)], [(3.0, 8.0)], [(10.0, 12.0)]]) == [(3.0, 5.0)]
    two = chaos.concurrent_spans([[(0.0, 5.0), (6.0, 9.0)], [(4.0, 7.0)]])
    assert two == [(4.0, 5.0), (6.0, 7.0)]
    assert chaos.active_spans([0.0, 0.5, 1.0, 3.0, 3.4], 1.0) == [(0.0, 1.0), (3.0, 3.4)]


# --- a node that runs nowhere -------------------------------------------------------------------

def _state(scale, t, **nodes):
    reports = {n: p.NodeReport(state, 100, 0.0, 0, state == 'running', '', life)
               for n, (state, life) in nodes.items()}
    return (t, p.AgentState(scale, 1, t, reports))


def test_nowhere_counts_a_node_served_nowhere_past_the_bound():
    robot = [_state('robot', t * 0.5, ekf=('running', None),
                    amcl=('running', 'active') if t * 0.5 < 10 or t * 0.5 >= 19 else
                    ('standby', 'inactive')) for t in range(60)]
    found = chaos.nowhere(['ekf', 'amcl'], [robot], {}, {}, [], 0.0, 29.5, max_age_s=4.0,
                          bound_s=7.0)
    assert [(x.node, round(x.start, 1), round(x.end, 1)) for x in found] == \
        [('amcl', 10.0, 19.0)]
    # Heard at the robot, or served on another scale, it runs.
    pose = [10.0 + 0.2 * i for i in range(46)]
    assert chaos.nowhere(['amcl'], [robot], {'amcl': '/amcl_pose'}, {'/amcl_pose': pose}, [],
                         0.0, 29.5, 4.0, 7.0) == []
    laptop = [_state('laptop', 12.0 + t * 0.5, amcl=('running', 'active')) for t in range(14)]
    assert chaos.nowhere(['amcl'], [robot, laptop], {}, {}, [], 0.0, 29.5, 4.0, 7.0) == []
    # Stale reports say nothing: a silent agent's node runs nowhere unless heard or seen live.
    silent = [x for x in robot if x[0] < 5.0]
    assert [x.node for x in chaos.nowhere(['ekf'], [silent], {}, {}, [], 0.0, 29.5, 4.0,
                                          7.0)] == ['ekf']
    processes = [(float(t), {'ekf': 1}) for t in range(30)]
    assert chaos.nowhere(['ekf'], [silent], {}, {}, processes, 0.0, 29.5, 4.0, 7.0,
                         process_nodes=['ekf']) == []


def test_a_crash_backoff_does_not_count_towards_the_nowhere_bound():
    """AR crash-looped: the agent waits out its backoff (2 s, then 4 s) before the cold
    restart. That wait is the configured restart policy; the rest is judged as before."""
    def ar(t):
        if t < 10.0 or t >= 17.5:
            return ('running', None)
        return ('backoff', None) if t < 14.0 else ('starting', None)
    robot = [_state('robot', t * 0.25, ar=ar(t * 0.25)) for t in range(120)]
    assert chaos.nowhere(['ar'], [robot], {}, {}, [], 0.0, 29.75, 4.0, 7.0) == []
    (x,) = chaos.nowhere(['ar'], [robot], {}, {}, [], 0.0, 29.75, 4.0, 3.0)
    assert (x.start, x.end, x.backoff_s) == (10.0, 17.5, 4.0)
    # Reported starting the whole time (no backoff): the same span counts.
    cold = [_state('robot', t * 0.25, ar=('starting', None) if 10.0 <= t * 0.25 < 17.5 else
                   ('running', None)) for t in range(120)]
    (y,) = chaos.nowhere(['ar'], [cold], {}, {}, [], 0.0, 29.75, 4.0, 7.0)
    assert (y.start, y.end, y.backoff_s) == (10.0, 17.5, 0.0)
    # The bound already allows for one backoff: only the wait beyond it is set aside.
    assert chaos.nowhere(['ar'], [robot], {}, {}, [], 0.0, 29.75, 4.0, 3.5) == []
    assert chaos.nowhere(['ar'], [robot], {}, {}, [], 0.0, 29.75, 4.0, 3.5,
                         backoff_in_bound_s=1.0)
    # A copy backing off on a scale the layout does not place the node on excuses nothing.
    laptop = [_state('laptop', t * 0.25, ar=('backoff', None)) for t in range(120)]
    on_robot = [(0.0, {'ar': 'robot'})]
    (z,) = chaos.nowhere(['ar'], [cold, laptop], {}, {}, [], 0.0, 29.75, 4.0, 7.0,
                         layouts=on_robot)
    assert (z.start, z.end, z.backoff_s) == (10.0, 17.5, 0.0)
    assert chaos.nowhere(['ar'], [cold, laptop], {}, {}, [], 0.0, 29.75, 4.0, 7.0,
                         layouts=[(0.0, {'ar': 'laptop'})]) == []


# --- Δ excuses ----------------------------------------------------------------------------------

def test_a_killed_serving_copy_excuses_what_it_feeds_until_it_serves_again():
    d = load_deployment(TESTBED)
    conns = [(c.name, c.publisher, c.subscriber) for c in d.connections]
    assert chaos.downstream([(a, b) for _, a, b in conns], 'odometry') == \
        {'odometry', 'ekf', 'navigation'}
    e = chaos.kill_excuse(conns, 'amcl', 100.0, 103.0, 5.0, 'amcl killed')
    assert e.connections == {'amcl_ekf', 'laser_amcl', 'ekf_navigation'}
    assert (e.start, e.end) == (100.0, 108.0)
    assert chaos.excused('amcl_ekf', 104.0, [e]) is e
    assert chaos.excused('amcl_ekf', 108.5, [e]) is None
    assert chaos.excused('camera_ar', 104.0, [e]) is None


# --- after the run ------------------------------------------------------------------------------

def test_tracebacks_are_found_with_their_exception_line():
    text = ('ok\nTraceback (most recent call last):\n  File "x.py", line 1, in <module>\n'
            '    boom()\nZeroDivisionError: division by zero\nmore\n')
    found = chaos.tracebacks({'logs/agent_robot.log': text, 'clean.log': 'fine\n'})
    assert len(found) == 1
    assert found[0]['file'] == 'logs/agent_robot.log' and found[0]['line'] == 2
    assert found[0]['text'].endswith('ZeroDivisionError: division by zero')


def test_resources_give_cpu_and_rss_per_window_and_growth_of_one_process():
    r = chaos.Resources()
    for i in range(40):                      # 200 s of one process, 10 % of a core, growing
        r.add(i * 5.0, 'decider', 7, i * 0.5, (50 << 20) + i * (1 << 16))
    for i in range(5):                       # a restarted agent: the longest stretch counts
        r.add(i * 5.0, 'agent_robot', 8, i * 0.1, 40 << 20)
    for i in range(10):
        r.add(30.0 + i * 5.0, 'agent_robot', 9, i * 0.2, 41 << 20)
    w = r.window('decider', 0.0, 60.0)
    assert w['cpu_percent'] == pytest.approx(10.0) and w['pid'] == 7
    assert r.window('agent_robot', 0.0, 100.0)['pid'] == 9
    g = r.growth('decider', min_life_s=100.0)
    assert g['growth_mib'] == pytest.approx((39 - 12) / 16, abs=0.01)
    assert r.growth('agent_robot', min_life_s=100.0) is None
    # A soak shorter than the start-up skipped (bench/soak.py --minutes 0.4): no growth.
    assert r.growth('decider', min_life_s=12.0, skip_s=300.0) is None


# --- the observer's record checks signatures ----------------------------------------------------

def _layout(seq, generation=1, key=KEY):
    identity = p.DeciderIdentity('abc', 'robot', 42, 1.0)
    lay = p.Layout(generation, 'icar2015_testbed', {'amcl': 'laptop'}, 'r', 5.0, identity, seq=seq)
    return auth.seal(key, lay)


def _line(t, topic, data):
    return json.dumps({'t': t, 'topic': topic, 'data': data})


def test_a_keyed_record_keeps_forged_and_replayed_layouts_apart():
    r = Record(load_deployment(TESTBED), key=KEY)
    r.ingest_line(_line(1.0, p.TOPIC_LAYOUT, _layout(1)))
    r.ingest_line(_line(2.0, p.TOPIC_LAYOUT, _layout(1)))                  # replayed
    r.ingest_line(_line(3.0, p.TOPIC_LAYOUT, _layout(2, 7, key=b'x' * 32)))   # forged
    r.ingest_line(_line(4.0, p.TOPIC_LAYOUT, json.dumps(
        {'generation': 10 ** 15, 'deployment': 'icar2015_testbed', 'assignments': {},
         'reason': 'hostile', 'stamp': 1.0})))                              # unsigned
    r.ingest_line(_line(5.0, p.TOPIC_LAYOUT, _layout(3, 2)))
    assert [(t, lay.generation) for t, lay in r.layouts] == [(1.0, 1), (5.0, 2)]
    assert [why.split(' ')[0] for _, _, why in r.refused] == ['sequence', 'bad', 'not']
    unkeyed = Record(load_deployment(TESTBED))
    unkeyed.ingest_line(_line(1.0, p.TOPIC_LAYOUT, _layout(1, key=b'y' * 32)))
    assert len(unkeyed.layouts) == 1


def test_the_record_keeps_publication_sequence_numbers_beside_arrivals():
    r = Record(load_deployment(TESTBED))
    r.ingest({'t': 1.0, 'arrivals': {'/scan': [0.9, 1.0]}, 'seqs': {'/scan': [5, 6]}})
    r.ingest({'t': 1.2, 'arrivals': {'/scan': [1.1]}})          # an older observer: none
    assert r.arrivals['/scan'] == [0.9, 1.0, 1.1]
    assert r.arrival_seqs['/scan'] == [5, 6, -1]


# --- the hostile publisher's messages -----------------------------------------------------------

def test_every_hostile_message_is_refused_by_a_keyed_receiver():
    d = load_deployment(TESTBED)
    forger = Forger(d, random.Random(3))
    real = _layout(9, 4)
    forger.hear(p.TOPIC_LAYOUT, real)
    labels = set()
    for _ in range(400):
        topic, text, label = forger.draw(10.0)
        labels.add(label)
        assert label in LABELS
        if text == real:                  # a replay: refused by its sequence number
            continue
        try:
            cls = {p.TOPIC_LAYOUT: p.Layout, p.TOPIC_AGENT_STATE: p.AgentState,
                   p.TOPIC_OBJECTIVE: p.Objective}.get(topic)
            if cls is None:
                continue
            cls.from_json(text, topic)
        except p.ProtocolError:
            continue
        # Well-formed: it must fail the signature check, or be for another deployment.
        data = json.loads(text)
        assert auth.check_signature(KEY, text) or data.get('deployment') == 'another_robot', \
            (label, text[:200])
    assert labels == set(LABELS) - {'state_replay'}


# --- the soak: its fault registry, samples, verdict and report ----------------------------------

def test_every_kind_the_schedule_draws_has_a_handler_and_every_handler_a_kind():
    assert set(faults.REGISTRY) == set(chaos.KINDS)
    assert set(chaos.WEIGHTS) == set(chaos.KINDS) == set(chaos.EXTRA_S)
    drawn = {f.kind for seed in range(5) for f in chaos.generate(seed, 600.0, ensure_each=True)}
    assert drawn <= set(faults.REGISTRY)
    assert all(callable(handler) for handler in faults.REGISTRY.values())
    assert set(verdict.NO_MOVE_BACK) | set(verdict.NOTED_MOVE_BACK) <= set(chaos.KINDS)


def test_a_move_back_counts_after_the_faults_that_give_no_reason_for_one():
    def fault(kind, copy=''):
        return chaos.Fault(0, 10.0, kind, node='amcl' if copy else '', copy=copy)
    assert verdict.no_move_back(fault('kill_decider'))
    assert verdict.no_move_back(fault('kill_node', 'standby'))
    assert not verdict.no_move_back(fault('kill_node', 'active'))
    assert not verdict.no_move_back(fault('cut'))
    assert verdict.noted_move_back(fault('rival_decider'))
    assert not verdict.noted_move_back(fault('kill_agent_laptop'))


def test_the_census_counts_a_second_live_copy_on_one_scale_past_its_bound_once():
    said = []
    s = samples.Samples(said.append)
    two = {('amcl', 'robot'): 2, ('ekf', 'robot'): 1}
    s.count(0.0, two)
    s.count(1.0, {('amcl', 'robot'): 1, ('amcl', 'laptop'): 1})    # one per scale: no duplicate
    s.count(2.0, two)
    s.count(2.0 + samples.DUPLICATE_PROCESS_S - 0.5, two)           # not yet past the bound
    assert s.duplicates == []
    for t in (5.5, 6.5):
        s.count(t, two)
    assert s.duplicates == [{'node': 'amcl', 'scale': 'robot', 'since': 2.0, 'count': 2}]
    assert len(said) == 1 and 'amcl' in said[0]
    assert s.processes[1] == (1.0, {'amcl': 2})
    assert s.processes[0] == (0.0, {'amcl': 2, 'ekf': 1})


def _decider(pid, ident):
    return p.DeciderIdentity(ident, 'robot', pid, 1.0)


def _followed(t, scale, ident, generation):
    return (t, p.AgentState(scale, generation, t, {}, decider=ident))


def test_the_verdict_tells_forged_rival_and_real_leaders_apart_and_counts_moves_back():
    d = load_deployment(TESTBED)
    robot, laptop = Record(d), Record(d)
    for t, gen, ident, pid in ((1.0, 1, 'real', 42), (2.0, 1, 'rival', 99)):
        robot.layouts.append((t, p.Layout(gen, 'icar2015_testbed', {}, 'r', t,
                                          _decider(pid, ident))))
    robot.agent_states['robot'] = [_followed(1.5, 'robot', 'real', 1),
                                   _followed(2.5, 'robot', 'rival', 1),
                                   _followed(3.0, 'robot', 'real', 7),        # no such layout
                                   _followed(50.0, 'robot', 'forger', 1)]     # after the soak
    laptop.agent_states['laptop'] = [_followed(4.0, 'laptop', 'forger', 1)]
    robot.events += [(t, p.Event(t, 'migrate_back', 'amcl', 'laptop', 'robot', 'back', 2))
                     for t in (11.0, 30.0)]
    tally = verdict.Tally(decider_pids={42}, rival_pids={99})
    tally.results.append({'index': 0, 'kind': 'kill_decider', 'what': 'x', 'at_s': 10.0,
                          'end_s': 12.0, 'no_move_back': True, 'noted_move_back': False})
    found = verdict.judge(d, robot, laptop, tally, [], 0.0, 40.0)
    assert found['forged_applied'] == [(3.0, 'robot', 'real', 7), (4.0, 'laptop', 'forger', 1)]
    assert found['rival_followed'] == [(2.5, 'robot', 'rival')]
    assert [(x['fault'], x['at_s']) for x in found['unneeded_moves_back']] == [(0, 11.0)]
    assert found['moves_back_noted'] == [] and found['duplicates'] == []
    assert found['duplicates_reported'] == []
    # The decider's own report of two senders counts, within the soak only.
    robot.events += [(t, p.Event(t, 'duplicate', 'amcl', 'laptop', '', '2 senders', 2))
                     for t in (20.0, 45.0)]
    found = verdict.judge(d, robot, laptop, tally, [], 0.0, 40.0)
    assert [(x['at_s'], x['node'], x['scale']) for x in found['duplicates_reported']] == [
        (20.0, 'amcl', 'laptop')]


def _report(jumps=(), **changes):
    tally = verdict.Tally(**changes)
    found = {'duplicates': [], 'duplicates_reported': [], 'delta_violations': [], 'nowhere': [],
             'unneeded_moves_back': [],
             'forged_applied': [], 'forged_applied_count': 0, 'rival_followed': [],
             'rival_followed_count': 0, 'delta_excused': [],
             'state_jumps': list(jumps)}
    teardown = {'leftovers': [], 'tracebacks': [], 'resources_end': {'decider': None}}
    bounds = {'overlap_s': 3.0, 'nowhere_s': 7.0, 'restart_s': 1.0, 'duplicate_process_s': 3.0}
    return soak_report.build(
        seed=7, planned_s=120.0, hysteresis_s=8.0, kinds=chaos.KINDS, bounds=bounds, t0=100.0,
        t_end=220.04, schedule=chaos.generate(7, 120.0), system=('decider',), tally=tally,
        samples=samples.Samples(), verdict=found, teardown=teardown, run_dir='/run')


def test_the_report_passes_only_when_every_count_is_0():
    report = _report()
    assert report['ok'] and set(report['counts'].values()) == {0}
    assert report['duration_s'] == 120.0 and 'resources_end' not in report
    assert report['resource_window_s'] == soak_report.resource_window_s(120.0) == 24.0
    assert soak_report.format_report(report).endswith('PASS: every count is 0')
    exit_ = {'t': 3.0, 'name': 'decider', 'pid': 5, 'code': -9, 'intended': False}
    failed = _report(missed=1, exits=[exit_])
    assert not failed['ok']
    assert failed['counts']['missed_reactions'] == 1 == failed['counts']['unexpected_exits']
    text = soak_report.format_report(failed)
    assert 'unexpected exits:' in text and text.endswith('FAIL: see the counts above')
    # A pose that jumped fails the soak as it fails the e2e modules.
    jumped = _report(jumps=[{'topic': '/amcl_pose', 'at_s': 0.3,
                             'jump': '0.21 m in 0.20 s at t=100.30 (at most 0.09 m)'}])
    assert not jumped['ok'] and jumped['counts']['state_jumps'] == 1
    assert '/amcl_pose: 0.21 m in 0.20 s' in soak_report.format_report(jumped)


def test_a_span_a_kill_excuses_is_excused_and_every_other_is_counted():
    # ekf killed with no standby copy (a crash loop): ekf -> navigation is silent past its Δ of
    # 0 because of the kill; the same connection silent later is counted.
    conns = [('ekf_navigation', 'ekf', 'navigation'), ('laser_amcl', 'laser', 'amcl')]
    excuse = chaos.kill_excuse(conns, 'ekf', 10.0, 12.0, 3.0, 'fault 2: ekf killed')
    violations = [DeltaBreach('ekf_navigation', 10.1, 14.0, 0.0, 'observer'),   # in the excuse
                  DeltaBreach('ekf_navigation', 40.0, 41.0, 0.0, 'observer'),   # counted
                  DeltaBreach('laser_amcl', 40.0, 43.0, 2.0, 'observer')]       # counted
    counted, excused = verdict.sort_violations(violations, [excuse], lambda t: t)
    assert [(x['connection'], x['start_s'], x['excused_by']) for x in excused] == \
        [('ekf_navigation', 10.1, 'fault 2: ekf killed')]
    assert [(x['connection'], x['below_s']) for x in counted] == [
        ('ekf_navigation', 1.0), ('laser_amcl', 3.0)]


def _resumed(pid: int, stamp: float) -> p.Layout:
    return p.Layout(generation=3, deployment='d', assignments={'a': 'robot'}, reason='r',
                    stamp=stamp, decider=p.DeciderIdentity(id='x', host='h', pid=pid,
                                                           started=0.0), term=1)


def test_a_resumed_leaders_layout_counts_by_when_it_was_composed_not_heard():
    # Resumed at monotonic 100.0 = wall 5000.0: a layout stamped before the stop and heard
    # after the resume is the stalled leader's last command delivered late, not a new one.
    layouts = [(99.0, _resumed(7, 4990.0)),          # before the resume: not looked at
               (100.2, _resumed(7, 4996.6)),         # composed before the stop, heard late
               (100.5, _resumed(8, 5000.4)),         # another decider
               (101.0, _resumed(7, 5000.9))]         # composed after the resume
    assert verdict.resumed_layouts(layouts, 7, 100.0, 5000.0) == (1, 1)
    assert verdict.resumed_layouts(layouts[:3], 7, 100.0, 5000.0) == (0, 1)
