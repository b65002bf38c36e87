"""Two robots sharing one server in network namespaces (testbed/fleet_netns.py FleetBed, as
test/test_fleet_netns.py; root), preemption after preemption, or the holder's link cut after
cut: the time from capacity freed to the other robot's node there, the longest stretch below
freq_min of the robot that gave the room up, and over-commit.

    sudo python bench/bench_fleet.py [--preemptions 20] [--graph worker|icar] [--hysteresis 5]
                                     [--domain-id N] [--keep DIR]
    sudo python bench/bench_fleet.py --cuts 10 [--hysteresis 6] [--domain-id N] [--keep DIR]

robot_a and robot_b, each its own deployment, decider, agents, ROS domain and namespace, share
one server (capacity 100) with room for one worker (CPU 60), a plain node, moved cold, Δ 5 s;
or, ``--graph icar`` (preemptions only), each its own copy of the ICAR graph, the server with
room for one robot's AMCL and AR (testbed/fleet_graphs.py), every connection judged.
Each robot's users are an observer in its own namespace; the bed samples at 5 Hz the worker
processes under each agent and the active claims in the host's database.

Preemptions: robot_a (priority 0) starts and its worker goes to the server; then,
--preemptions times, once robot_a's every judged connection has been heard for 4 s and none is
below freq_min: robot_b starts with priority 1 and preempts it (robot_a takes its worker
home, then robot_b's starts there), and robot_b stops, after which robot_a's worker goes back
once its hysteresis (--hysteresis s) has passed. Measured each cycle: from the room freed
(robot_a's server copy gone and its claim released, the later) to robot_b's worker started
there; robot_a's longest stretch below freq_min from 2 s before robot_b's start until 2 s after
the hand-over, judged by the Δ rule (runtime/delta.py); from robot_b stopped to robot_a's
worker back there.

``--cuts N``: both robots of priority 0, brought up once. N times: once one robot's worker
serves from the server and the other's from home, the layout quiet, the holder's link is cut.
Measured from the bed's samples: the holder's worker home, its server copy gone and its claim
released (the room freed: the later of the two), the other robot's worker started there and
serving there (its home copy let go); the holder's longest stretch below freq_min, judged by
the Δ rule on what its namespace heard from 2 s before the cut. Then the link is restored and
the next round waits for the layout to be quiet again: the other robot holds the server, the
first one's agent judged its link up, past the first one's hysteresis since its move home (so
room, not T, decides the next hand-over), and nothing moved for 5 s; the next round cuts the
new holder.

Over-commit, in both: claims above the server's capacity, or the CPU its serving copies declare
above it for half a second (testbed/fleet_record.over_capacity).
"""

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from anyscale_manager.runtime.delta import DEFAULT_WINDOW_S, rate_below  # noqa: E402
from anyscale_manager.testbed import netns  # noqa: E402
from anyscale_manager.testbed.fleet import (FleetShape, HOME, other_domain,  # noqa: E402
                                            SERVER, stretches_past_delta)
from anyscale_manager.testbed.fleet_netns import FleetBed  # noqa: E402
from anyscale_manager.testbed.fleet_record import over_capacity  # noqa: E402


def _pct(values, q):
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))]


def _line(label, values, unit='s'):
    return (f'  {label:<46} p50 {statistics.median(values):.2f} {unit}  p95 '
            f'{_pct(values, 0.95):.2f} {unit}  max {max(values):.2f} {unit}  (n={len(values)})')


def _table(rows):
    """One ``_line`` per (label, values), none when nothing was measured."""
    for label, values in rows:
        if values:
            print(_line(label, values))


ROBOTS = ('robot_a', 'robot_b')
# How long the layout must stay as it is before a cut: several turns of both deciders.
QUIET_S = 5.0
# A preemption's judged window opens this long before the higher robot starts; a round starts
# only once the lower robot's every connection has been heard for STEADY_S (a window and the
# Δ rule's 2 s of intervals): its first round began 1-2 s after the chain's first messages,
# and their start-up read as stretches below freq_min.
JUDGED_BEFORE_S = 2.0
STEADY_S = JUDGED_BEFORE_S + DEFAULT_WINDOW_S


def heard_rate(record, robot, now, topic=None, window_s=1.0):
    """Messages a second ``robot``'s users heard (of ``topic``; None: any) over the
    ``window_s`` before ``now``."""
    return sum(1 for t in record.heard(robot, topic) if now - window_s <= t <= now) / window_s


def steady(record, robot, judged, now):
    """Every connection of ``judged`` heard by ``robot``'s users since STEADY_S before ``now``
    at least, and none below freq_min over the last JUDGED_BEFORE_S: a round's judged window
    (from JUDGED_BEFORE_S before its start) then holds nothing of the robot's boot."""
    for j in judged:
        heard = record.heard(robot, j.topic)
        if not heard or heard[0] > now - STEADY_S:
            return False
        if stretches_past_delta(heard, now - JUDGED_BEFORE_S, now, j)[1] > 0.0:
            return False
    return True


def link_judged_up(bed, robot):
    """``robot``'s home agent has not said its link to the server is DOWN since it last said
    it is up."""
    said = bed.fleet.text(robot, HOME)
    return said.rfind('link to away is up') >= said.rfind('link to away is DOWN')


def over_commit(samples, shape):
    """(samples with the server over its capacity (fleet_record.over_capacity), their seconds:
    each such sample counted until the next one)."""
    over = {id(s) for s in over_capacity(samples, shape.capacity_cpu, shape.lifecycle)}
    seconds = sum(b.t - a.t for a, b in zip(samples, samples[1:]) if id(a) in over)
    for s in samples:
        if id(s) in over:
            print(f'  over capacity at {s.t - samples[0].t:.2f} s: serving '
                  f'{dict(s.on_server_nodes)}, claims {dict(s.claims_cpu)}')
    return len(over), seconds


def quiet(bed, shape, not_before, what):
    """Wait until one robot's worker serves from the server and is heard at freq_min or more,
    the other's is home, each link up and judged up, at or after ``not_before``, and the layout
    has not changed for QUIET_S; return (holder, other)."""
    since = {'t': None, 'layout': None}

    def holds(s):
        layout = tuple(s.where(r) for r in ROBOTS)
        if sorted(layout) != [SERVER, HOME] or s.on_server != 1:
            since['t'] = None
            return False
        holder = ROBOTS[layout.index(SERVER)]
        if not (all(s.links_up.values()) and all(link_judged_up(bed, r) for r in ROBOTS)
                and {r for r, cpu in s.claims_cpu.items() if cpu} <= {holder}):
            since['t'] = None
            return False
        if since['t'] is None or layout != since['layout']:
            since['t'], since['layout'] = s.t, layout
        return (s.t >= not_before and s.t - since['t'] >= QUIET_S
                and not rate_below(shape.freq_min_hz,
                                   heard_rate(bed.record, holder, s.t - 0.6)))
    s = bed.until(holds, 120.0, what)
    holder = next(r for r in ROBOTS if s.where(r) == SERVER)
    return holder, next(r for r in ROBOTS if r != holder)


def cuts(a, run_dir: str) -> int:
    """The holder's link cut, ``a.cuts`` times, in namespaces (the module's docstring)."""
    shape = FleetShape(hysteresis_s=a.hysteresis)
    domains = {'robot_a': a.domain_id, 'robot_b': other_domain(a.domain_id)}
    rows = {k: [] for k in ('home', 'freed', 'serving', 'gap')}
    violations, early, notes = 0, 0, []
    bed = FleetBed(run_dir, ROBOTS, shape)
    try:
        bed.setup()
        for robot in ROBOTS:
            bed.start(robot, domains[robot])
        not_before = 0.0
        for i in range(a.cuts):
            holder, other = quiet(bed, shape, not_before, f'round {i + 1}: the layout quiet')
            cut = bed.cut(holder)
            done = bed.until(lambda s: s.where(holder) == HOME and s.where(other) == SERVER
                             and not s.claims_cpu.get(holder), 60.0,
                             f"round {i + 1}: {holder}'s worker home, its claim gone, "
                             f"{other}'s on the server")
            rec = bed.record
            h = rec.hand_over(holder, other, cut)
            home, fenced, released, started, serving, freed = \
                h.home, h.fenced, h.released, h.started, h.serving, h.freed
            bed.until(lambda s: rec.judged_until(holder) >= done.t, 10.0,
                      f"{holder}'s observer's lines past the move")
            past, longest = stretches_past_delta(rec.heard(holder), cut - 2.0, done.t, shape)
            violations += past > 0
            early += started < freed
            rows['home'].append(home - cut)
            rows['freed'].append(freed - cut)
            rows['serving'].append(serving - freed)
            rows['gap'].append(longest)
            bed.restore(holder)
            not_before = home + shape.hysteresis_s + 1.0
            print(f'[{i + 1}/{a.cuts}] {holder} cut: home {home - cut:.2f} s, server copy gone '
                  f'{fenced - cut:.2f} s, claim released {released - cut:.2f} s; {other} '
                  f'started there {started - cut:.2f} s, serving {serving - cut:.2f} s '
                  f'(freed -> serving {serving - freed:.2f} s); {holder} below freq_min '
                  f'{longest:.2f} s at most{", PAST Δ" if past else ""}', flush=True)
    finally:
        notes = bed.close()
    over_n, over_s = over_commit(bed.record.samples, shape)
    print(f'fleet, link cuts: 2 robots in namespaces, one server (capacity '
          f'{shape.capacity_cpu:g}, worker {shape.worker_cpu:g}), {len(rows["home"])} cuts, '
          f'hysteresis {shape.hysteresis_s:g} s, Δ {shape.tolerance_s:g} s{kept(a, run_dir)}')
    _table([("cut -> the holder's worker home", rows['home']),
            ('cut -> room freed (copy gone, claim released)', rows['freed']),
            ("room freed -> the other's worker serving there", rows['serving']),
            ("the holder's longest stretch below freq_min", rows['gap'])])
    print(f'  Δ violations on the cut robot: {violations} of {len(rows["home"])}; started '
          f'before the room was freed: {early}; over-commit: {over_n} samples of '
          f'{len(bed.record.samples)}, {over_s:.1f} s; teardown cleaned: {notes or "nothing"}')
    return 1 if violations or early or over_n else 0


def preemptions(a, run_dir: str) -> int:
    """robot_b (priority 1) preempts robot_a ``a.preemptions`` times (the module's docstring)."""
    shape = FleetShape(hysteresis_s=a.hysteresis, graph=a.graph)
    low, high = ROBOTS
    domains = {low: a.domain_id, high: other_domain(a.domain_id)}
    rows = {k: [] for k in ('there', 'gap', 'back')}
    violations, notes = 0, []
    bed = FleetBed(run_dir, ROBOTS, shape)
    graph, rec = bed.graph, bed.record
    moving, shown = graph.moving, graph.shown(low)
    try:
        bed.setup()
        bed.start(low, domains[low], priority=0)
        for i in range(a.preemptions):
            bed.until(lambda s: s.all_away(low, moving) and not rate_below(
                shown.freq_min_hz, heard_rate(rec, low, s.t - 0.6, shown.topic))
                and steady(rec, low, graph.judged(low), s.t),
                shape.hysteresis_s + 120.0,
                f"round {i + 1}: {low}'s {graph.what} serving from the server, every "
                f'connection heard for {STEADY_S:g} s and none below freq_min')
            start = time.monotonic()
            bed.start(high, domains[high], priority=1)
            took = bed.until(lambda s: s.all_away(high, moving) and s.none_away(low), 90.0,
                             f'round {i + 1}: {high} on the server, {low} home')
            freed = rec.first(lambda s: s.none_away(low) and not s.claims_cpu.get(low),
                              since=start)
            there = rec.first(lambda s: s.all_away(high, moving), since=start)
            bed.until(lambda s: s.t >= took.t + 2.0 and rec.judged_until(low) >= s.t - 0.5,
                      20.0, f"round {i + 1}: {low}'s observer's lines past the hand-over")
            past, longest, which = 0, 0.0, []
            for j in graph.judged(low):
                n, worst = stretches_past_delta(rec.heard(low, j.topic),
                                                start - JUDGED_BEFORE_S, took.t + 2.0, j)
                past, longest = past + n, max(longest, worst)
                if n:
                    which.append(f'{j.name} {worst:.2f} s below (Δ {j.tolerance_s:g} s)')
            violations += past > 0
            gone = bed.stop(high)
            back = bed.until(lambda s: s.all_away(low, moving), shape.hysteresis_s + 60.0,
                             f"round {i + 1}: {low}'s {graph.what} back on the server")
            rows['there'].append(there - freed)
            rows['gap'].append(longest)
            rows['back'].append(back.t - gone)
            print(f'[{i + 1}/{a.preemptions}] freed -> {high} there {there - freed:.2f} s; '
                  f'{low} below freq_min {longest:.2f} s at most'
                  f'{", PAST Δ: " + ", ".join(which) if past else ""}; '
                  f'{high} gone -> {low} back {back.t - gone:.2f} s', flush=True)
    finally:
        notes = bed.close()
    over_n, over_s = over_commit(rec.samples, shape)
    print(f'fleet, preemptions: 2 robots in namespaces, graph {shape.graph}, one server '
          f'(capacity {shape.capacity_cpu:g}; {graph.needs()}), {len(rows["there"])} '
          f'preemptions, hysteresis {shape.hysteresis_s:g} s{kept(a, run_dir)}')
    _table([('room freed -> the higher robot all there', rows['there']),
            ("the lower robot's longest stretch below freq_min", rows['gap']),
            ('the higher robot gone -> the lower one back', rows['back'])])
    print(f'  Δ violations on the preempted robot (every connection judged): {violations} of '
          f'{len(rows["there"])}; over-commit: {over_n} samples of {len(rec.samples)}, '
          f'{over_s:.1f} s; teardown cleaned: {notes or "nothing"}')
    return 1 if violations or over_n else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preemptions', type=int, default=20)
    ap.add_argument('--cuts', type=int, default=0,
                    help="instead of preemptions, this many cuts of the holder's link")
    ap.add_argument('--graph', choices=('worker', 'icar'), default='worker',
                    help="each robot's graph, with --preemptions (testbed/fleet_graphs.py)")
    ap.add_argument('--hysteresis', type=float, default=None,
                    help='seconds (default 5, with --cuts 6)')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 57)))
    ap.add_argument('--keep', default='',
                    help='keep the run folder (logs, the host ledger) here; else it is removed')
    a = ap.parse_args(argv)
    if a.cuts < 0 or a.preemptions < 0:
        ap.error('--cuts and --preemptions take a count of 0 or more')
    if a.cuts and a.graph != 'worker':
        ap.error('--cuts runs the worker graph only')
    if a.hysteresis is None:
        a.hysteresis = 6.0 if a.cuts else 5.0
    ok, why = netns.available()
    if not ok:
        print(f'the fleet in namespaces needs the test-bed: {why}', file=sys.stderr)
        return 2
    # The run's folder (logs, the host's ledger): --keep's, else a temporary one removed at the
    # end of a run that passed, kept and named after one that did not.
    run_dir = a.keep or tempfile.mkdtemp(prefix=f'fleet_{"cuts" if a.cuts else "preemptions"}_')
    os.makedirs(run_dir, exist_ok=True)
    code = 1
    try:
        code = cuts(a, run_dir) if a.cuts else preemptions(a, run_dir)
    finally:
        if not a.keep and code == 0:
            shutil.rmtree(run_dir, ignore_errors=True)
        elif not a.keep:
            print(f'bench_fleet: the run folder is kept for its logs: {run_dir}', file=sys.stderr)
    return code


def kept(a, run_dir: str) -> str:
    """The summary's mention of the run folder, named only when --keep keeps it."""
    return f'; run folder {run_dir}' if a.keep else ''


if __name__ == '__main__':
    sys.exit(main())
