"""The whole system on the ICAR test-bed: namespaces, a shaped link, CPU quotas, real processes.

One test-bed is shared by the tests of this module (starting it takes ~15 s); they run in file
order, each waiting for the state it needs. The decider runs with a hysteresis T of 8 s instead
of the deployment's 20 s so the scenarios fit in a few minutes; every rule is the same.
Skipped, with the reason printed, when namespaces, tc or cgroups are not available (not root).
"""

import os
import signal

import pytest

from anyscale_manager.testbed import netns
from anyscale_manager.testbed import harness

HYSTERESIS_S = 8.0
OK, WHY = netns.available()
# Opt-in: about two minutes of real namespaces, quotas and a shaped link. Test 5 failed in two
# of eight full-suite runs on a fault not yet found (a thawed standby AMCL that works but is not
# heard), in none of thirteen since the workload's timer change (docs/testbed.md).
OPTED_IN = os.environ.get('ANYSCALE_E2E') == '1'
pytestmark = [
    pytest.mark.skipif(not OPTED_IN, reason='end-to-end test-bed tests are opt-in: run '
                                            '`sudo env ANYSCALE_E2E=1 ./run.sh test` (about '
                                            '2 minutes more)'),
    pytest.mark.skipif(not OK, reason=f'no test-bed here: {WHY}'),
]

ROBOT, LAPTOP = 'robot', 'laptop'


TESTBED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'config',
                       'icar2015_testbed.yaml')


@pytest.fixture(scope='module')
def bed():
    options = harness.Options(TESTBED, int(os.environ['ROS_DOMAIN_ID']), mode='netns',
                              decider_parameters={'decider.hysteresis_s': str(HYSTERESIS_S)},
                              link_up_at_start=False)
    tb = harness.Testbed(options).start()
    try:
        yield tb
    finally:
        notes = tb.stop()
        assert notes == [], f'teardown had to clean up: {notes}'
        assert not [n for n in netns.list_namespaces() if n.startswith(tb_tag(tb))]


def tb_tag(tb):
    return f'{netns.NAME_PREFIX}-{os.getpid()}-'


def on(tb, node, scale):
    return lambda r: r.where(node) == (scale,)


def wait_both_on_laptop(tb, timeout_s=60.0):
    tb.restore()
    tb.throttle(netns.DEFAULT_RATE_KBPS)
    tb.wait_for(on(tb, 'amcl', LAPTOP), timeout_s, 'amcl running on the laptop (only)')
    tb.wait_for(on(tb, 'ar', LAPTOP), timeout_s, 'ar running on the laptop (only)')


def rate_over(record, topic, start, end):
    times = [t for t in record.arrivals.get(topic, []) if start <= t <= end]
    if len(times) < 2:
        return 0.0
    return (len(times) - 1) / (times[-1] - times[0])


def test_1_link_up_amcl_moves_first_then_ar_and_amcl_ekf_reaches_its_optimal_rate(bed):
    # The test-bed booted with the link cut: everything runs on the robot.
    with bed.lock:
        assert all(bed.record.where(n) == (ROBOT,) for n in ('amcl', 'ar'))
    bed.sleep(8.0)      # under the robot's quota (lifted while booting)
    t_up = bed.now()
    with bed.lock:
        robot_rate = rate_over(bed.record, '/amcl_pose', t_up - 5.0, t_up)
    bed.restore()
    bed.wait_for(on(bed, 'amcl', LAPTOP), 60.0, 'amcl on the laptop')
    t_amcl = bed.now()
    bed.wait_for(on(bed, 'ar', LAPTOP), 60.0, 'ar on the laptop')
    with bed.lock:
        firsts = {}
        for t, e in bed.record.moves():
            if e.kind == 'migrate':
                firsts.setdefault(e.node, t)
        events = [(round(t - bed.t0, 1), e.kind, e.node, e.reason[:60]) for t, e in
                  bed.record.events if e.kind not in ('note', 'warning')]
        # What the decider said while deciding, and what the scales measured: on a failure
        # this says why the order came out as it did.
        said = [(round(t - bed.t0, 1), e.kind, e.reason[:160]) for t, e in bed.record.events
                if e.kind in ('note', 'warning') and t >= t_up - 2.0][:12]
        cpu = [(round(t - bed.t0, 1), {n: round(v) for n, v in s.cpu_by_node.items()
                                       if n in ('amcl', 'ar')})
               for t, s in bed.record.scale_status.get(ROBOT, []) if t_up - 3.0 <= t <= t_amcl]
        states = [(round(t - bed.t0, 1), {n: r.state for n, r in a.nodes.items()
                                          if n in ('amcl', 'ar')})
                  for t, a in bed.record.agent_states.get(ROBOT, []) if t_up - 3.0 <= t <= t_amcl]
    why = f'events {events}\nnotes {said}\nrobot CPU {cpu}\nrobot agent {states}'
    assert 'amcl' in firsts and 'ar' in firsts, f'no migrate events: {why}'
    assert firsts['amcl'] < firsts['ar'], f'AR moved before AMCL: {why}'
    # AMCL -> EKF at the robot (the observer sits there): the optimal 5 Hz, with slack.
    t = bed.wait_for(lambda r: r.topic_rate('/amcl_pose', bed.now(), 3.0) >= 4.3, 20.0,
                     'amcl_ekf near its optimal 5 Hz')
    bed.sleep(3.0)
    with bed.lock:
        rate = rate_over(bed.record, '/amcl_pose', t, bed.now())
    print(f'amcl on the laptop {t_amcl - t_up:.1f} s after the link came up; /amcl_pose at '
          f'the robot {robot_rate:.2f} Hz with AMCL on the robot, {rate:.2f} Hz on the laptop')
    assert 4.3 <= rate <= 5.5
    # The robot kept its copies until it heard the laptop's: its own probes never read a moved
    # node's output below freq_min for as long as Δ after the move (the decider would not see
    # it, being in its grace period, but EKF and the navigation would).
    with bed.lock:
        handovers = bed.record.handovers(t_up, bed.now(), ROBOT)
    tolerance = {c.name: c.tolerance_s for c in bed.deployment.connections}
    assert {h['node'] for h in handovers} >= {'amcl', 'ar'}, handovers
    assert all(h['below_s'] < tolerance[h['connection']] for h in handovers), handovers
    # CPU-bound on the weak robot: 2.4-3.5 Hz in most runs, once 4.09 Hz (the paper: about 2);
    # always visibly below the laptop's rate.
    assert 1.5 <= robot_rate <= rate - 0.5, (robot_rate, rate)


def test_2_throttled_below_ar_need_ar_comes_back_amcl_stays(bed):
    wait_both_on_laptop(bed)
    t_throttle = bed.now()
    bed.throttle(5000.0)          # AR's images need 6 Mbit/s; AMCL's 0.2 Mbit/s still fit
    try:
        bed.wait_for(on(bed, 'ar', ROBOT), 30.0, 'ar back on the robot after the throttle')
        t_back = bed.now()
        bed.sleep(6.0)
        with bed.lock:
            amcl_moves = bed.record.moves(since=t_throttle, node='amcl')
            where = bed.record.where('amcl')
            ar_back = [e for _, e in bed.record.moves(since=t_throttle, node='ar')][:1]
            congested = [t - t_throttle for t, s in bed.record.link_status
                         if t >= t_throttle and s.congested][:1]
            timeline = bed.record.timeline(t_throttle - 1.0, bed.now())
        why = f'AR back: {ar_back}; congested after {congested} s\n{timeline}'
        assert amcl_moves == [], f'AMCL moved although it fits: {amcl_moves}\n{why}'
        assert where == (LAPTOP,)
        # The link's queue gave the throttle away (not AR's rate past its Δ, seconds later),
        # and AR came back under the bandwidth rule.
        assert congested, f'the throttle was never seen as congestion: {why}'
        assert 'usable' in ar_back[0].reason, why
        print(f'link congested {congested[0]:.1f} s and ar back on the robot '
              f'{t_back - t_throttle:.1f} s after the throttle ({ar_back[0].reason})')
    finally:
        bed.throttle(netns.DEFAULT_RATE_KBPS)


def _pids(record):
    out = {}
    for scale in (ROBOT, LAPTOP):
        for node, report in record.running_on(scale).items():
            out.setdefault(node, []).append((scale, report.pid, report.restarts))
    return out


def healthy(tb):
    """AMCL -> EKF and AR -> Navigation near their optimal rates at the robot, measured by the
    harness and reported within limits by the robot's own probes, and no move for 5 s."""
    return lambda r: (r.topic_rate('/amcl_pose', tb.now()) >= 4.0
                      and r.topic_rate('/markers', tb.now()) >= 10.0
                      and r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), ROBOT, 5.0))


def test_3_decider_killed_and_restarted_restarts_or_duplicates_nothing(bed):
    # Both migratable nodes out and a quiet moment (no move for 3 s): nothing is left that the
    # policy would legitimately move while the decider is away.
    wait_both_on_laptop(bed, timeout_s=90.0)
    bed.wait_for(lambda r: not r.moves(since=bed.now() - 3.0) and
                 all(len(v) == 1 for v in _pids(r).values()), 30.0, 'a quiet layout')
    with bed.lock:
        before = _pids(bed.record)
        generation = bed.record.layout_at().generation
    assert bed.kill('decider', signal.SIGKILL) == -signal.SIGKILL
    bed.sleep(2.0)
    bed.start_decider()
    bed.wait_for(lambda r: any(t > bed.procs['decider'].started for t, _ in r.layouts), 30.0,
                 'a layout from the new decider')
    bed.sleep(5.0)
    with bed.lock:
        after = _pids(bed.record)
        new = bed.record.layout_at()
        moves = [(e.kind, e.node, e.reason) for _, e in
                 bed.record.moves(since=bed.procs['decider'].started)]
    assert new.generation > generation
    assert moves == [], f'the new decider moved nodes: {moves}'
    assert after == before, f'running nodes changed across the decider restart:\n{before}\n{after}'


def test_4_laptop_agent_killed_its_nodes_run_on_the_robot_again(bed):
    wait_both_on_laptop(bed)
    with bed.lock:
        orphans = {n: r.pid for n, r in bed.record.running_on(LAPTOP).items()}
    t_kill = bed.now()
    bed.kill('agent_laptop', signal.SIGKILL)
    timeout = bed.deployment.decider.agent_timeout_s + 20.0
    bed.wait_for(lambda r: 'robot' in r.where('amcl') and 'robot' in r.where('ar'), timeout,
                 'amcl and ar running on the robot after the laptop agent died')
    print(f'laptop nodes on the robot {bed.now() - t_kill:.1f} s after the agent was killed')
    # The agent comes back: what its predecessor left running must not stay duplicated.
    bed.start_agent(LAPTOP)
    bed.wait_for(lambda r: r.agent_state_at(LAPTOP, bed.now(), 2.0) is not None, 30.0,
                 'the new laptop agent reporting')

    def orphans_gone(_r):
        alive = [pid for pid in orphans.values() if _alive(pid)]
        return not alive
    bed.wait_for(orphans_gone, 30.0, f'the orphaned laptop nodes {orphans} stopped or adopted '
                 'and stopped')


def _process_state(pid):
    """A process's scheduler state, per thread ('R', 'S', 'T' = stopped, ...), and where its
    main thread waits: what a failure needs to tell a stuck node from a stopped one."""
    states = {}
    try:
        for tid in os.listdir(f'/proc/{pid}/task'):
            with open(f'/proc/{pid}/task/{tid}/stat') as f:
                state = f.read().rsplit(') ', 1)[1][:1]
            states[state] = states.get(state, 0) + 1
        with open(f'/proc/{pid}/wchan') as f:
            wchan = f.read()
    except OSError as e:
        return f'pid {pid}: {e}'
    return f'pid {pid}: threads by state {states}, main thread waits in {wchan or "-"}'


def _stacks(tb, pids):
    """Each node's Python stacks, which it writes to its log on SIGUSR1 (faulthandler)."""
    logs = {n: os.path.join(tb.run_dir, 'nodes', tb.deployment.name, ROBOT, f'{n}.log')
            for n in pids}
    sizes = {n: os.path.getsize(p) if os.path.exists(p) else 0 for n, p in logs.items()}
    for pid in pids.values():
        try:
            os.kill(pid, signal.SIGUSR1)
        except OSError:
            pass
    tb.sleep(1.0)
    out = {}
    for n, path in logs.items():
        try:
            with open(path, 'rb') as f:
                f.seek(sizes[n])
                out[n] = f.read()[-4000:].decode('utf-8', 'replace')
        except OSError as e:
            out[n] = str(e)
    return out


def _alive(pid):
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().split(') ')[-1][:1] != 'Z'
    except OSError:
        return False


def test_5_link_cut_every_migrated_node_back_before_its_delta_runs_out(bed):
    wait_both_on_laptop(bed, timeout_s=90.0)
    bed.wait_for(healthy(bed), 30.0, 'amcl_ekf and ar_navigation healthy before the cut')
    with bed.lock:
        cut_off = {n: rep.pid for n, rep in bed.record.running_on(LAPTOP).items()
                   if n in ('amcl', 'ar')}
        standby = {n: rep.pid for n, rep in bed.record.agent_states[ROBOT][-1][1].nodes.items()
                   if n in ('amcl', 'ar') and rep.state == 'standby'}
    t_cut = bed.now()
    bed.cut()
    try:
        bed.wait_for(lambda r: r.where('amcl') == (ROBOT,) and r.where('ar') == (ROBOT,), 20.0,
                     'amcl and ar back on the robot after the cut')
        t_back = bed.now()
        window = bed.deployment.monitoring.probe_window_s
        end = t_back + max(c.tolerance_s or 0 for c in bed.deployment.connections) + window + 1
        bed.wait_for(lambda r: bed.now() >= end, 30.0, 'the tolerance after the return')
        with bed.lock:
            r = bed.record
            migratable = set(bed.deployment.migratable_nodes)
            conns = [c for c in bed.deployment.connections
                     if c.publisher in migratable or c.subscriber in migratable]
            observed = [v for c in conns if c.subscriber not in migratable
                        for v in r.observed_violations(c, t_cut, end, window_s=window)]
            reported = [v for v in r.reported_violations(t_cut, end, [c.name for c in conns])
                        if v.source == ROBOT]
            timeline = r.timeline(t_cut, end)
            pids = {n: rep.pid for n, rep in r.running_on(ROBOT).items() if n in ('amcl', 'ar')}
        if observed or reported:
            timeline['processes'] = {n: _process_state(pid) for n, pid in pids.items()}
            timeline['stacks'] = _stacks(bed, pids)
        print(f'back on the robot {t_back - t_cut:.2f} s after the cut; observed {observed}; '
              f'reported {reported}')
        assert observed == [], f'past Δ at the robot: {observed}; after the cut: {timeline}'
        assert reported == [], (f'probes on the robot reported connections past Δ: {reported}; '
                                f'after the cut: {timeline}')
        # The frozen copies served: none was found unheard and restarted cold.
        assert pids == standby, f'standby pids {standby}, serving pids {pids}: {timeline}'
        # The laptop's copies, cut off from the master, stop by themselves: nothing stale is
        # left to publish beside the robot's copies when the link comes back.
        settings = bed.deployment.agent
        limit = (bed.deployment.decider.agent_timeout_s + settings.sigint_grace_s
                 + settings.sigterm_grace_s + 5.0)
        bed.wait_for(lambda r: not any(_alive(pid) for pid in cut_off.values()), limit,
                     f'the cut-off laptop copies {cut_off} stopped')
        print(f'cut-off laptop copies gone when checked, {bed.now() - t_cut:.1f} s after the '
              'cut')
    finally:
        bed.restore()


def test_6_flapping_link_moves_are_bounded_by_the_hysteresis(bed):
    bed.restore()
    start = bed.now()
    flaps = 0
    while bed.now() - start < 30.0:
        bed.cut()
        bed.sleep(2.5)
        bed.restore()
        bed.sleep(2.5)
        flaps += 1
    end = bed.now()
    with bed.lock:
        moves = bed.record.moves(since=start, until=end)
    by_node = {}
    for t, e in moves:
        by_node.setdefault(e.node, []).append((t, e.kind))
    span = end - start
    for node, seq in by_node.items():
        outs = [t for t, kind in seq if kind == 'migrate']
        backs = [t for t, kind in seq if kind == 'migrate_back']
        # The rule: a node migrated back is not moved out again within T.
        for tb_ in backs:
            later = [t for t in outs if t > tb_]
            assert not later or later[0] - tb_ >= HYSTERESIS_S - 0.6, \
                f'{node} moved out {later[0] - tb_:.1f} s after coming back (T = {HYSTERESIS_S})'
        assert len(outs) <= 1 + span / HYSTERESIS_S, \
            f'{node}: {len(outs)} moves out in {span:.0f} s'
    print(f'{flaps} flaps in {span:.0f} s: {len(moves)} moves ({by_node})')
    # Without the hysteresis every flap could move both nodes out and back.
    assert len(moves) < 2 * len(bed.deployment.migratable_nodes) * flaps
