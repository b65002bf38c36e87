"""The whole system on the ICAR test-bed: namespaces, a shaped link, CPU quotas, real processes.

One test-bed is shared by the tests of this module (starting it takes ~15 s); they run in file
order, each waiting for the state it needs. The decider runs with a hysteresis T of 8 s instead
of the deployment's 20 s so the scenarios fit in a few minutes; every rule is the same.
Part of the default suite; skipped, with the reason printed, when namespaces, tc or cgroups are
not available (not root).

Every Δ judgement here is made on what the harness's observer heard (a reader in the robot's
namespace that no agent started), not on what the agents' own probes say; where the probes'
reports are also checked, that is said.
"""

import os
import signal

import pytest

from carried_pose import assert_pose_never_jumped

from anyscale_manager.testbed import netns
from anyscale_manager.testbed import harness

HYSTERESIS_S = 8.0
# Longer than two of Fast DDS's default 20 s leases: a copy idle (inactive) that long on the
# robot must still serve at once when the link goes.
REMOTE_STAY_S = 45.0
OK, WHY = netns.available()
pytestmark = pytest.mark.skipif(not OK, reason=f'no test-bed here: {WHY}')

ROBOT, LAPTOP = 'robot', 'laptop'
MOVING = ('amcl', 'ar')


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


def link_log(tb, lines=6):
    """The robot link monitor's last verdicts (a down one says what it rests on)."""
    try:
        with open(os.path.join(tb.run_dir, 'logs', 'agent_robot.log'), errors='replace') as f:
            said = [line.strip() for line in f if 'link to laptop is' in line]
    except OSError as e:
        return f'(no agent log: {e})'
    return '\n'.join(said[-lines:])


def tb_tag(tb):
    return f'{netns.NAME_PREFIX}-{os.getpid()}-'


def on(tb, node, scale):
    return lambda r: r.where(node) == (scale,)


def wait_both_on_laptop(tb, timeout_s=60.0):
    tb.restore()
    tb.throttle(netns.DEFAULT_RATE_KBPS)
    tb.wait_for(on(tb, 'amcl', LAPTOP), timeout_s, 'amcl running on the laptop (only)')
    tb.wait_for(on(tb, 'ar', LAPTOP), timeout_s, 'ar running on the laptop (only)')


def settled_on_laptop(tb, timeout_s=60.0):
    """The link up at its full rate, then AMCL and AR serving on the laptop (only) with no
    move for 3 s, judged together: a scenario that starts from there starts from there (a link
    blip while waiting brings them home, and they go out again after T)."""
    wait_both_on_laptop(tb, timeout_s)
    both = (on(tb, 'amcl', LAPTOP), on(tb, 'ar', LAPTOP), quiet(tb))
    tb.wait_for(lambda r: all(check(r) for check in both), 30.0 + HYSTERESIS_S,
                'a quiet layout with amcl and ar on the laptop')


def wait_both_on_robot(tb, timeout_s=20.0):
    tb.wait_for(lambda r: r.where('amcl') == (ROBOT,) and r.where('ar') == (ROBOT,),
                timeout_s, 'amcl and ar running on the robot (only)')


def rate_over(record, topic, start, end):
    times = [t for t in record.arrivals.get(topic, []) if start <= t <= end]
    if len(times) < 2:
        return 0.0
    return (len(times) - 1) / (times[-1] - times[0])


def copies(record):
    """(node, scale) -> (pid, restarts) of every live copy the agents report, serving or not:
    a restarted or duplicated node changes it."""
    return {(n, s): (rep.pid, rep.restarts) for s in (ROBOT, LAPTOP)
            for n, rep in record.copies(s).items()}


def serving_pids(record, scale):
    return {n: rep.pid for n, rep in record.running_on(scale, ready_only=True).items()
            if n in MOVING}


def standby_pids(record, scale):
    return {n: rep.pid for n, rep in record.standby_on(scale).items() if n in MOVING}


def quiet(tb, quiet_s=3.0):
    """No move for quiet_s; AMCL and AR each serve on one scale and are standby on the other."""
    def check(r):
        if r.moves(since=tb.now() - quiet_s):
            return False
        serving = [serving_pids(r, s) for s in (ROBOT, LAPTOP)]
        standby = [standby_pids(r, s) for s in (ROBOT, LAPTOP)]
        return all(sorted([n in serving[0], n in serving[1]]) == [False, True]
                   and (n in standby[0]) == (n in serving[1])
                   and (n in standby[1]) == (n in serving[0]) for n in MOVING)
    return check


def healthy(tb):
    """AMCL -> EKF and AR -> Navigation near their optimal rates at the robot, measured by the
    harness and reported within limits by the robot's own probes, and no move for 5 s."""
    return lambda r: (r.topic_rate('/amcl_pose', tb.now()) >= 4.0
                      and r.topic_rate('/markers', tb.now()) >= 10.0
                      and r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), ROBOT, 5.0))


def moves_since(tb, t0):
    """(seconds from t0, kind, node, reason) of every move since t0, for failure messages."""
    return [(round(t - t0, 1), e.kind, e.node, e.reason[:100])
            for t, e in tb.record.moves(since=t0)]


def delta_check(tb, start, end):
    """The Δ judgement, on the observer's arrivals: every monitored connection into the robot
    that stayed below its freq_min for longer than Δ in [start, end] (none is the pass), and
    the longest time each was read below (for the log)."""
    tb.wait_heard(end)
    with tb.lock:
        found = tb.record.delta_violations(start, end, ROBOT)
        longest = tb.record.longest_below(start, end, ROBOT)
    return found, {k: v for k, v in longest.items() if v > 0}


def assert_within_delta(tb, start, end, what):
    found, longest = delta_check(tb, start, end)
    if found:
        with tb.lock:
            r = tb.record
            timeline = r.timeline(start, end)
            moves = moves_since(tb, start)
            laptop = r.timeline(start, end, scale=LAPTOP)['reports']
            inputs = {name: [(round(t - start, 2), round(x.rate_hz, 1), round(x.below_for_s, 1))
                             for t, src, x in r.readings.get(name, [])
                             if src == LAPTOP and start <= t <= end][::2]
                      for name in ('laser_amcl', 'camera_ar')}
            silences = {v.connection: r.silence(v) for v in found}
        raise AssertionError(f'{what}: connections into the robot past their Δ (observer): '
                             f'{found}; their longest silences {silences}; longest below '
                             f'{longest}; moves {moves}; laptop reports '
                             f'{laptop}; laptop probes {inputs}; at the robot {timeline}')
    return longest


def test_1_link_up_amcl_moves_first_then_ar_and_amcl_ekf_reaches_its_optimal_rate(bed):
    # The test-bed booted with the link cut: everything runs on the robot.
    with bed.lock:
        assert all(bed.record.where(n) == (ROBOT,) for n in MOVING)
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
                                       if n in MOVING})
               for t, s in bed.record.scale_status.get(ROBOT, []) if t_up - 3.0 <= t <= t_amcl]
        states = [(round(t - bed.t0, 1), {n: r.state for n, r in a.nodes.items()
                                          if n in MOVING})
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
    # The robot kept its copies until it heard the laptop's: neither the observer nor the
    # robot's own probes read a moved node's output below freq_min for as long as Δ after the
    # move (the decider would not see it, being in its grace period, but EKF and the
    # navigation would).
    assert_within_delta(bed, t_up, bed.now(), 'AMCL and AR moving out')
    with bed.lock:
        handovers = bed.record.handovers(t_up, bed.now(), ROBOT)
    tolerance = {c.name: c.tolerance_s for c in bed.deployment.connections}
    assert {h['node'] for h in handovers} >= set(MOVING), handovers
    assert all(h['below_s'] < tolerance[h['connection']] for h in handovers), handovers
    # CPU-bound on the weak robot, below the laptop's rate: the reason to move it (the paper:
    # about 2 Hz on the robot). How far below depends on what else the robot's quota runs:
    # 3.5-3.8 Hz (docs/measurements.md, AMCL's calibration).
    assert 1.5 <= robot_rate < rate, (robot_rate, rate)


def test_2_throttled_below_ar_need_ar_comes_back_amcl_stays(bed):
    settled_on_laptop(bed)
    t_throttle = bed.now()
    bed.throttle(5000.0)          # AR's images need 6 Mbit/s; AMCL's 0.2 Mbit/s still fit
    try:
        bed.wait_for(on(bed, 'ar', ROBOT), 30.0, 'ar back on the robot after the throttle')
        t_back = bed.now()
        bed.wait_for(lambda r: 'ar' in standby_pids(r, LAPTOP), 20.0,
                     "the laptop's AR copy inactive")
        bed.sleep(6.0)
        with bed.lock:
            amcl_moves = bed.record.moves(since=t_throttle, node='amcl')
            where = bed.record.where('amcl')
            ar_back = [e for _, e in bed.record.moves(since=t_throttle, node='ar')][:1]
            congested = [t - t_throttle for t, s in bed.record.link_status
                         if t >= t_throttle and s.congested][:1]
            timeline = bed.record.timeline(t_throttle - 1.0, bed.now())
            # When the laptop reported its AR inactive, and its agent's last reading of AR's
            # input (camera_ar) after the throttle.
            inactive = next(t for t, st in bed.record.agent_states[LAPTOP] if t >= t_throttle
                            and st.nodes.get('ar') and st.nodes['ar'].state == 'standby')
            # When the laptop published it (a status repaired by DDS after a loss on the
            # throttled link arrives late, but says when the probe still ran).
            probed = max([t for t, src in bed.record.readings_sent.get('camera_ar', [])
                          if src == LAPTOP and t >= t_throttle], default=t_throttle)
        why = (f'AR back: {ar_back}; congested after {congested} s; the laptop reported AR '
               f'inactive {inactive - t_throttle:.2f} s and still probed its input '
               f'{probed - t_throttle:.2f} s after the throttle\n{timeline}')
        # An inactive copy's inputs no longer cross the link: nor may the laptop agent's probe
        # of them (one probe report period, 0.25 s, and some slack), or AR's 6 Mbit/s go on
        # filling the throttled link after AR has left, starving AMCL's laser input.
        assert probed - inactive <= 1.0, \
            f"the laptop's agent kept probing the input of its inactive AR: {why}"
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


def test_3_decider_killed_and_restarted_restarts_or_duplicates_nothing(bed):
    # Both migratable nodes out and a quiet moment (no move for 3 s): nothing is left that the
    # policy would legitimately move while the decider is away.
    settled_on_laptop(bed, timeout_s=90.0)
    with bed.lock:
        before = copies(bed.record)
        generation = bed.record.layout_at().generation
    assert bed.kill('decider', signal.SIGKILL) == -signal.SIGKILL
    bed.sleep(2.0)
    bed.start_decider()
    bed.wait_for(lambda r: any(t > bed.procs['decider'].started for t, _ in r.layouts), 30.0,
                 'a layout from the new decider')
    bed.sleep(5.0)
    with bed.lock:
        after = copies(bed.record)
        new = bed.record.layout_at()
        moves = [(e.kind, e.node, e.reason) for _, e in
                 bed.record.moves(since=bed.procs['decider'].started)]
    assert new.generation > generation
    assert moves == [], f'the new decider moved nodes: {moves}'
    assert after == before, f'live copies changed across the decider restart:\n{before}\n{after}'


def test_4_laptop_agent_killed_its_nodes_run_on_the_robot_again(bed):
    settled_on_laptop(bed)
    with bed.lock:
        orphans = {n: r.pid for n, r in bed.record.copies(LAPTOP).items()}
    assert set(orphans) == set(MOVING), orphans
    t_kill = bed.now()
    bed.kill('agent_laptop', signal.SIGKILL)
    timeout = bed.deployment.decider.agent_timeout_s + 20.0
    bed.wait_for(lambda r: 'robot' in r.where('amcl') and 'robot' in r.where('ar'), timeout,
                 'amcl and ar running on the robot after the laptop agent died')
    print(f'laptop nodes on the robot {bed.now() - t_kill:.1f} s after the agent was killed')
    # The laptop's warden stopped what the dead agent left running before the robot's copies
    # were activated: never two copies serving.
    for n in orphans:
        assert bed.node_pids(n, LAPTOP) == [], f'{n}: a laptop copy outlived its agent'
    with bed.lock:
        fenced = [t for t, s in bed.record.link_status if s.peer_agent == 'fenced' and t > t_kill]
        back = bed.record.serving_since(ROBOT, MOVING, t_kill)
    assert fenced and back is not None and fenced[0] <= back, (fenced[:1], back)
    # The agent comes back and starts its standby copies afresh.
    agent = bed.start_agent(LAPTOP)

    def standby_again(r):
        state = r.agent_state_at(LAPTOP, bed.now(), 2.0)
        if state is None or r.agent_states[LAPTOP][-1][0] < agent.started:
            return False
        reps = {n: state.nodes.get(n) for n in orphans}
        return all(rep is not None and rep.state == 'standby' and rep.pid != orphans[n]
                   and rep.lifecycle == 'inactive' for n, rep in reps.items())
    bed.wait_for(standby_again, 60.0, 'the new laptop agent keeping fresh inactive copies')
    assert_within_delta(bed, t_kill, bed.now(), 'the laptop agent killed')


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


def cut_and_judge(tb, what):
    """Cut the link while AMCL and AR serve on the laptop, and check the return: both serve on
    the robot again through its standby copies (same pids: activated, not started), no
    connection into the robot stays below freq_min past its Δ (the observer; the robot's own
    probes must not report one either), and the laptop's agent, cut off from the master,
    deactivates its copies (standby, same pids; heard on the laptop). The link stays cut."""
    with tb.lock:
        standby = standby_pids(tb.record, ROBOT)
        cut_off = serving_pids(tb.record, LAPTOP)
    assert set(standby) == set(MOVING) and set(cut_off) == set(MOVING), (standby, cut_off)
    t_cut = tb.now()
    tb.cut()
    wait_both_on_robot(tb, 20.0)
    t_back = tb.now()
    window = tb.deployment.monitoring.probe_window_s
    end = t_back + max(c.tolerance_s or 0 for c in tb.deployment.connections) + window + 1
    tb.wait_for(lambda r: r.heard_until >= end, 30.0, 'the tolerance after the return')
    found, longest = delta_check(tb, t_cut, end)
    with tb.lock:
        r = tb.record
        names = [c.name for c in tb.deployment.connections if r.into(c, ROBOT, end)]
        reported = [v for v in r.reported_violations(t_cut, end, names) if v.source == ROBOT]
        timeline = r.timeline(t_cut, end)
        pids = serving_pids(r, ROBOT)
        serving = r.serving_since(ROBOT, MOVING, t_cut)
    if found or reported:
        timeline['processes'] = {n: _process_state(pid) for n, pid in pids.items()}
        timeline['stacks'] = _stacks(tb, pids)
    print(f'{what}: AMCL and AR serving on the robot {serving - t_cut:.2f} s after the cut '
          f'(the laptop reports stale after {t_back - t_cut:.2f} s); longest below '
          f'freq_min at the robot (observer) {longest}; reported past Δ {reported}')
    assert found == [], (f'{what}: past Δ at the robot (observer): {found}; after the cut: '
                         f'{timeline}')
    assert reported == [], (f'{what}: probes on the robot reported connections past Δ: '
                            f'{reported}; after the cut: {timeline}')
    # The standby copies served: none was restarted to do it.
    assert pids == standby, f'standby pids {standby}, serving pids {pids}: {timeline}'
    # The laptop's copies, cut off from the master, are deactivated by their agent: nothing
    # stale publishes beside the robot's copies when the link comes back.
    d = tb.deployment
    limit = d.decider.agent_timeout_s + d.agent.lifecycle_timeout_s + 5.0
    tb.wait_for(lambda _r: standby_pids(tb.laptop_view, LAPTOP) == cut_off, limit,
                f'the cut-off laptop copies {cut_off} inactive (heard on the laptop)')
    print(f'{what}: cut-off laptop copies inactive when checked, {tb.now() - t_cut:.1f} s '
          'after the cut')
    return t_cut


def test_5_link_cut_every_migrated_node_back_before_its_delta_runs_out(bed):
    wait_both_on_laptop(bed, timeout_s=90.0)
    bed.wait_for(healthy(bed), 30.0, 'amcl_ekf and ar_navigation healthy before the cut')
    try:
        cut_and_judge(bed, 'the cut')
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


def test_7_a_remote_stay_longer_than_two_dds_leases_then_a_cut(bed):
    settled_on_laptop(bed, timeout_s=90.0)
    t_out = bed.now()
    with bed.lock:
        before = copies(bed.record)
    # The stay itself (a scenario's length, not a wait for a state): the robot's inactive copies
    # sit idle for longer than two 20 s leases.
    bed.sleep(REMOTE_STAY_S)
    bed.wait_for(healthy(bed), 30.0, 'amcl_ekf and ar_navigation healthy before the cut')
    t_end = bed.now()
    with bed.lock:
        moves = [(round(t - t_out, 1), e.kind, e.node, e.reason[:80])
                 for t, e in bed.record.moves(since=t_out)]
        after = copies(bed.record)
    assert moves == [], f'moves during the remote stay: {moves}; robot link monitor: ' \
        f'{link_log(bed)}'
    assert after == before, f'live copies changed during the stay:\n{before}\n{after}'
    assert_within_delta(bed, t_out, t_end, f'{REMOTE_STAY_S:g} s on the laptop')
    try:
        t_cut = cut_and_judge(bed, f'the cut after {t_end - t_out:.0f} s on the laptop')
        with bed.lock:
            after = copies(bed.record)
        # The robot's copies are the ones it held all along, none restarted (the laptop's
        # reports are out of date behind the cut and left out).
        robot = {k: v for k, v in before.items() if k[1] == ROBOT}
        assert {k: v for k, v in after.items() if k[1] == ROBOT} == robot
        assert t_cut - t_out >= REMOTE_STAY_S
    finally:
        bed.restore()


def test_8_b_moves_out_and_back_keep_a_standby_copy_on_both_scales(bed):
    settled_on_laptop(bed, timeout_s=90.0)
    with bed.lock:
        start_copies = copies(bed.record)
        robot = standby_pids(bed.record, ROBOT)
        laptop = serving_pids(bed.record, LAPTOP)
    t_start = bed.now()
    settle = bed.deployment.agent.readiness_timeout_s + 5.0

    def kept(scale, view=None):
        """The scale keeps its inactive copies, the same processes as at the start."""
        want = robot if scale == ROBOT else laptop
        return lambda r: {n: p for n, p in standby_pids(view or r, scale).items()
                          if n in names} == {n: want[n] for n in names}
    # AR back under the bandwidth rule, the link up: the laptop deactivates its copy once the
    # robot's serves, and keeps it.
    names = ('ar',)
    bed.throttle(5000.0)
    try:
        bed.wait_for(on(bed, 'ar', ROBOT), 30.0, 'ar back on the robot after the throttle')
        bed.wait_for(kept(LAPTOP), settle, 'the laptop keeping its AR copy, inactive')
        with bed.lock:
            serving = {s: serving_pids(bed.record, s) for s in (ROBOT, LAPTOP)}
            why = (f'moves {moves_since(bed, t_start)}\n'
                   f'{bed.record.timeline(t_start, bed.now(), topic="/markers")}')
        assert serving == {ROBOT: {'ar': robot['ar']}, LAPTOP: {'amcl': laptop['amcl']}}, \
            f'{serving}\n{why}'
    finally:
        bed.throttle(netns.DEFAULT_RATE_KBPS)
    # AR out again once T has run out and the link monitor's next throughput probe (every
    # bandwidth_probe_interval_s) has measured the link whole again: the robot keeps its copy,
    # inactive.
    probe_s = bed.deployment.monitoring.bandwidth_probe_interval_s
    bed.wait_for(on(bed, 'ar', LAPTOP), HYSTERESIS_S + probe_s + 20.0, 'ar on the laptop again')
    bed.wait_for(kept(ROBOT), settle, 'the robot keeping its AR copy, inactive')
    # Both back through a cut (the laptop deactivates its copies itself, heard there), then
    # both out again when the link returns.
    names = MOVING
    bed.wait_for(quiet(bed), 30.0, 'a quiet layout before the cut')
    bed.cut()
    try:
        wait_both_on_robot(bed)
        with bed.lock:
            assert serving_pids(bed.record, ROBOT) == robot
        d = bed.deployment
        bed.wait_for(kept(LAPTOP, bed.laptop_view),
                     d.decider.agent_timeout_s + d.agent.lifecycle_timeout_s + 5.0,
                     'the cut-off laptop keeping its copies, inactive')
    finally:
        bed.restore()
    wait_both_on_laptop(bed, timeout_s=HYSTERESIS_S + 60.0)
    bed.wait_for(kept(ROBOT), settle, 'the robot keeping its copies, inactive')
    bed.wait_for(quiet(bed), 30.0, 'a quiet layout at the end')
    with bed.lock:
        end_copies = copies(bed.record)
        moves = [(round(t - t_start, 1), e.kind, e.node) for t, e in
                 bed.record.moves(since=t_start)]
    assert end_copies == start_copies, \
        f'a copy was restarted or duplicated:\n{start_copies}\n{end_copies}'
    longest = assert_within_delta(bed, t_start, bed.now(), f'the moves {moves}')
    print(f'moves {moves}; longest below freq_min at the robot (observer) {longest}')


def test_9_c_a_standby_copy_killed_comes_back_inactive_and_nothing_else_moves(bed):
    settled_on_laptop(bed, timeout_s=90.0)
    with bed.lock:
        before = copies(bed.record)
        victim = bed.record.copies(ROBOT)['amcl']
    assert victim.state == 'standby', victim
    t_kill = bed.now()
    pid = bed.kill_node('amcl', ROBOT, signal.SIGKILL)
    s = bed.deployment.agent
    limit = s.restart_backoff_s + s.readiness_timeout_s + s.lifecycle_timeout_s + 10.0

    def back_inactive(r):
        rep = r.copies(ROBOT).get('amcl')
        return (rep is not None and rep.pid != pid and rep.state == 'standby'
                and rep.lifecycle == 'inactive')
    bed.wait_for(back_inactive, limit, "the robot's AMCL copy started again, inactive")
    t_back = bed.now()
    # A measurement period: a move or a restart the kill set off would show in it.
    bed.sleep(bed.deployment.monitoring.probe_window_s + 1.0)
    with bed.lock:
        after = copies(bed.record)
        new = bed.record.copies(ROBOT)['amcl']
        moves = [(e.kind, e.node, e.reason[:80]) for _, e in bed.record.moves(since=t_kill)]
        where = {n: bed.record.where(n) for n in MOVING}
    changed = {k: (before.get(k), after.get(k)) for k in set(before) | set(after)
               if before.get(k) != after.get(k)}
    print(f'robot AMCL copy {pid} killed; {new.pid} inactive {t_back - t_kill:.1f} s later')
    assert moves == [], f'moves after the kill: {moves}; robot link monitor: {link_log(bed)}'
    assert where == {n: (LAPTOP,) for n in MOVING}, where
    assert set(changed) == {('amcl', ROBOT)}, f'copies changed: {changed}'
    assert new.pid != pid and new.restarts > victim.restarts, (victim, new)
    assert bed.node_pids('amcl', ROBOT) == [new.pid]
    assert_within_delta(bed, t_kill, bed.now(), "the robot's standby AMCL killed")


def test_10_d_robot_agent_restarted_while_its_copies_are_inactive_adopts_them(bed):
    settled_on_laptop(bed, timeout_s=90.0)
    with bed.lock:
        before = copies(bed.record)
        inactive = standby_pids(bed.record, ROBOT)
    robot = {n: pid for (n, s), (pid, _) in before.items() if s == ROBOT}
    assert set(inactive) == set(MOVING), inactive
    t_kill = bed.now()
    agent = bed.restart_agent(ROBOT, signal.SIGKILL)

    def new_reports(r):
        return [st for t, st in r.agent_states.get(ROBOT, []) if t > agent.started]

    def adopted(r):
        reports = new_reports(r)
        if not reports:
            return False
        last = reports[-1].nodes
        return (all(n in last and last[n].pid == pid for n, pid in robot.items())
                and all(last[n].lifecycle in ('inactive', 'active') for n in MOVING))
    bed.wait_for(adopted, 30.0, 'the new robot agent reporting its copies adopted, their '
                 'lifecycle states read')
    t_adopted = bed.now()
    # Whatever the decider did while the robot's monitors were silent, it settles.
    bed.wait_for(quiet(bed, 5.0), HYSTERESIS_S + 60.0, 'a quiet layout after the restart')
    with bed.lock:
        seen = {}
        for st in new_reports(bed.record):
            for n, rep in st.nodes.items():
                if rep.pid > 0:
                    seen.setdefault(n, set()).add(rep.pid)
        after = copies(bed.record)
        moves = [(round(t - t_kill, 1), e.kind, e.node, e.reason[:80])
                 for t, e in bed.record.moves(since=t_kill)]
    print(f'robot agent restarted: copies adopted {t_adopted - t_kill:.1f} s after the kill; '
          f'moves meanwhile {moves}')
    assert seen == {n: {pid} for n, pid in robot.items()}, \
        f'the new robot agent reported other processes: {seen} (before: {robot})'
    assert after == before, f'a copy was restarted or duplicated:\n{before}\n{after}'
    for n, pid in robot.items():
        live = bed.node_pids(n, ROBOT)
        assert live == [pid], f'{n}: robot processes {live}, adopted {pid}'
    assert_within_delta(bed, t_kill, bed.now(), 'the robot agent restarted')


def test_11_the_robot_pose_never_jumped_at_any_change_of_serving_copy(bed):
    """AMCL's state is the robot's pose: at every move, failover, relocation and restart of
    the tests above, the copy that took over continued from the last pose (handed over by the
    agents), judged on the poses the harness's own observer heard on /amcl_pose."""
    assert_pose_never_jumped(bed)
