"""Two robots, each its own copy of the ICAR 2015 graph (eleven nodes, AMCL and AR migratable
lifecycle nodes, the Δ 0 chain at real-time priority), its own decider, agents, ROS domain
and network namespace, share one server with room for one robot's AMCL and AR (50 + 33 of
capacity 100, 90 usable), not two (testbed/fleet_graphs.py, testbed/fleet_netns.py).

Judged from outside: the copies serving under each agent (psutil: an active lifecycle copy is
the one busy on its CPU), the server's claims by robot, sampled throughout, and every
connection with a minimum frequency as the robot's users hear it, by an observer in the
robot's own namespace, by the Δ rule (the critical chain's Δ is 0). One fleet, brought up once:

(a) robot_a starts: its AMCL and AR go to the server; then robot_b starts: they stay home (the
    room left, 17, holds neither);
(b) robot_a's link is cut: robot_a's AMCL and AR serve at home within every connection's Δ, its
    copies on the server stop serving and its claims are released, and only then do robot_b's
    serve there, within T + 2 s of the room freed;
(c) robot_a's link restored, robot_a is stopped and started anew with priority 1: robot_b is
    told to leave and takes its AMCL and AR home within every Δ, and robot_a's serve there as
    the room is handed over (robot_a's AMCL may join robot_b's AR while they fit);
(d) robot_a's server agent is SIGKILLed: robot_a serves at home within every Δ, and robot_b
    moves in only once robot_a's claims ran out with their lease;
never more on the server than its capacity (its claims at any sample; the CPU its serving copies
declare for half a second: fleet_record.over_capacity), and never a connection of either
robot past its Δ while it runs.

About 80 s of wall time. Part of the default suite; skipped, with the reason printed, without
namespaces (not root).
"""

import os
import signal
import time

import pytest

from anyscale_manager.model.capacity import claim_lease_s
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.testbed import netns
from anyscale_manager.testbed.fleet import (FleetShape, other_domain, SERVER,
                                            stretches_past_delta)
from anyscale_manager.testbed.fleet_netns import FleetBed
from anyscale_manager.testbed.fleet_record import over_capacity

OK, WHY = netns.available()
pytestmark = pytest.mark.skipif(not OK, reason=f'no test-bed here: {WHY}')

HYSTERESIS_S = 6.0
SHAPE = FleetShape(graph='icar', hysteresis_s=HYSTERESIS_S)
ROBOTS = ('robot_a', 'robot_b')
PAIR = ('amcl', 'ar')
# Long enough for both deciders to judge the server several times once a pair is there.
WATCH_S = 6.0


def away(s, robot):
    """``robot``'s AMCL and AR both serve on the server."""
    return s.all_away(robot, PAIR)


def home(s, robot):
    """Neither of ``robot``'s AMCL and AR serves on the server: they serve at home, which its
    users' observer judges (AMCL's and AR's outputs, amcl_ekf and ar_navigation, each within
    its Δ). A copy at home is not judged by its CPU: under the robot's saturated quota AR may
    get too little of it to look busy."""
    return s.none_away(robot)


def past_delta(bed, robot, start, end):
    """The connections of ``robot`` whose users heard them below freq_min past their Δ within
    [start, end], with the longest stretch below; and the longest stretch of each."""
    rec, past, longest = bed.record, {}, {}
    for j in bed.graph.judged(robot):
        n, worst = stretches_past_delta(rec.heard(robot, j.topic), start, end, j)
        longest[j.name] = round(worst, 2)
        if n:
            past[j.name] = round(worst, 2)
    return past, longest


def heard_through(bed, robot, t, what, but=()):
    bed.until(lambda s: bed.record.judged_until(robot) >= t, 10.0,
              f"{robot}'s observer's lines past {what}", but=but)


def test_two_icar_robots_share_one_server_through_a_cut_and_a_preemption(tmp_path):
    mine = int(os.environ['ROS_DOMAIN_ID'])
    domains = {'robot_a': mine, 'robot_b': other_domain(mine)}
    a, b = ROBOTS
    began = time.monotonic()
    with FleetBed(str(tmp_path), ROBOTS, SHAPE) as bed:
        rec = bed.record
        room = SHAPE.capacity_cpu

        # (a) robot_a first: its pair to the server; then robot_b, whose pair stays home.
        bed.start(a, domains[a])
        a_booted = time.monotonic()
        first = bed.until(lambda s: away(s, a), 60.0, f"{a}'s AMCL and AR on the server")
        bed.start(b, domains[b])
        b_booted = time.monotonic()
        settled = bed.until(lambda s: s.t - b_booted >= WATCH_S, WATCH_S + 10.0,
                            f'{b} watched beside {a}')
        assert away(settled, a) and home(settled, b), bed.describe()
        assert all(not s.on_server_nodes.get(b) for s in rec.between(b_booted)), bed.describe()
        heard_through(bed, a, settled.t, 'the start')
        past, longest = past_delta(bed, a, first.t, settled.t)
        assert past == {}, f'{a} past Δ with its pair on the server: {past}\n{bed.describe()}'
        past, _ = past_delta(bed, b, b_booted + 1.0, settled.t)
        assert past == {}, f'{b} past Δ at home: {past}\n{bed.describe()}'

        # (b) robot_a's link is cut: its pair home within Δ, then robot_b's moves in.
        cut = bed.cut(a)
        done = bed.until(lambda s: home(s, a) and away(s, b) and not s.claims_cpu.get(a),
                         60.0, f"{a}'s pair home, its claims gone, {b}'s on the server")
        a_home = rec.first(lambda s: home(s, a), since=cut)
        freed = rec.first(lambda s: not s.on_server_nodes.get(a) and not s.claims_cpu.get(a),
                          since=cut)
        b_first = rec.first(lambda s: bool(s.on_server_nodes.get(b)), since=cut)
        b_there = rec.first(lambda s: away(s, b), since=cut)
        heard_through(bed, a, done.t, 'the hand-over')
        past, longest = past_delta(bed, a, cut - 2.0, done.t)
        print(f'\n[fleet icar] {a} cut: its pair home {a_home - cut:.2f} s (longest below '
              f'freq_min {longest}), the room freed {freed - cut:.2f} s; {b} serving there '
              f'{b_there - cut:.2f} s')
        assert past == {}, f'{a} past Δ after its cut: {past}\n{bed.describe()}'
        assert b_first >= freed, bed.describe()
        assert b_there - freed <= HYSTERESIS_S + 2.0, bed.describe()
        past, _ = past_delta(bed, b, cut - 2.0, done.t)
        assert past == {}, f'{b} past Δ moving in: {past}\n{bed.describe()}'

        # (c) robot_a back with a higher priority: robot_b is told first and goes home.
        bed.restore(a)
        bed.stop(a)
        arrived = time.monotonic()
        bed.start(a, domains[a], priority=1)
        took = bed.until(lambda s: away(s, a) and home(s, b), 90.0,
                         f'{a} (priority 1) on the server, {b} home')
        b_left = rec.first(lambda s: not s.on_server_nodes.get(b), since=arrived)
        a_first = rec.first(lambda s: bool(s.on_server_nodes.get(a)), since=arrived)
        bed.until(lambda s: s.t >= took.t + 3.0, 10.0, 'the watch after the preemption')
        heard_through(bed, b, took.t + 3.0, 'the preemption')
        past, longest = past_delta(bed, b, arrived - 2.0, took.t + 3.0)
        print(f'[fleet icar] {a} back with priority 1: {b} home {b_left - arrived:.2f} s after '
              f'(longest below freq_min {longest}), {a} serving there '
              f'{a_first - arrived:.2f} s after')
        assert past == {}, f'{b} past Δ, preempted: {past}\n{bed.describe()}'
        assert 'of a higher priority asks away for the room' in bed.fleet.text(b, 'decider')

        # (d) robot_a's server agent is SIGKILLed: its warden stops its copies there, robot_a
        # serves at home within every Δ, its claims run out with their lease, and only then
        # does robot_b move in.
        agent = bed.fleet.procs[a][SERVER]
        lease = claim_lease_s(load_deployment(bed.fleet.paths[a]))
        agent.send_signal(signal.SIGKILL)
        agent.wait(10)
        killed = time.monotonic()
        bed.mark(f"{a}'s server agent SIGKILLed")
        moved = bed.until(lambda s: away(s, b) and home(s, a), lease + 40.0,
                          f"{b}'s pair on the server after {a}'s server agent died",
                          but=((a, SERVER),))
        a_home = rec.first(lambda s: home(s, a), since=killed)
        b_first = rec.first(lambda s: bool(s.on_server_nodes.get(b)), since=killed)
        heard_through(bed, a, moved.t, "the server agent's death", but=((a, SERVER),))
        past, longest = past_delta(bed, a, killed - 2.0, moved.t)
        print(f"[fleet icar] {a}'s server agent killed: its copies there stopped serving "
              f'{a_home - killed:.2f} s after (longest below freq_min at home {longest}); '
              f'{b} serving there '
              f'{b_first - killed:.2f} s after (lease {lease:g} s)')
        assert past == {}, f'{a} past Δ, its server agent dead: {past}\n{bed.describe()}'
        assert b_first - killed >= 0.75 * lease - 0.5, (b_first - killed, lease)
        assert b_first >= a_home, bed.describe()      # never beside robot_a's orphans

        over = [(round(s.t - rec.t0, 2), dict(s.on_server_nodes), dict(s.claims_cpu))
                for s in over_capacity(rec.samples, room, lifecycle=True)]
        assert over == [], f'copies serving on the server past its capacity: {over}\n' \
                           f'{bed.describe()}'
        assert rec.most_claimed() <= room, bed.describe()
        print(f'[fleet icar] boot {a} {a_booted - began:.1f} s, {b} '
              f'{b_booted - a_booted:.1f} s; whole test {time.monotonic() - began:.1f} s')
        notes = bed.close()
    assert notes == [], f'teardown had to clean up: {notes}'
