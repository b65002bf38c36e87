#!/usr/bin/env python3
"""End-to-end figures on the ICAR test-bed (needs root for namespaces, tc and cgroups).

    sudo python bench/bench_e2e.py [--cuts 20] [--stay 30] [--throttles 5]
                                   [--levels 20000,10000,5000:20,2000,500] [--duration 60]
                                   [--out FILE]

1. Reaction: the link is cut after AMCL and AR have served from the laptop for ``--stay``
   seconds (their robot copies inactive all that time); the time until both serve (active,
   ready) on the robot again, p50/p95 over ``--cuts`` cuts, and the Δ violations during each:
   judged on what the harness's observer heard at the robot (a reader no agent started) for
   every connection into the robot, and, apart, the robot's own probes reporting a connection
   past its tolerance.
   Then ``--throttles`` times at each of ``--levels`` (kbit/s; ``LEVEL:COUNT`` sets a level's
   own count): with both on the laptop, the link is throttled; below what AR's connections
   put on the link (12.3 Mbit/s: 6.1 Mbit/s of images to AR and to the laptop agent's probe)
   the time until the link monitor reports it congested and until AR runs on the robot
   again, at or above it that nothing moves; AMCL
   (0.24 Mbit/s twice) must stay where its inputs fit what the link has left after the DDS
   discovery traffic (measured first, bench_link_traffic.py) with the decider's bandwidth
   margin, and come back where they do not. Each throttle's Δ violations: on the
   observer (connections into the robot) and on every scale's probes. Every congestion the
   monitor reported outside a throttle is counted as a false alarm, and every move back for
   bandwidth outside a throttle as a wrong decision.
2. The paper's headline: the same link schedule (paper_schedule) with migration and with
   ``decider.migration false``, one after the other in this run; the decider's time-integrated
   performance, AMCL's mean output rate at the robot and where AMCL and AR ran.
3. CPU used by the decider and by each agent (their own processes, not their nodes) during the
   migration run, in % of one core of this machine and in reference-core percent.

Part 1 runs with the decider's hysteresis T set by ``--hysteresis`` (8 s by default instead of the
deployment's 20 s) so that ten cuts take minutes, not ten; part 2 uses the deployment unchanged.
"""

import argparse
import json
import os
import statistics
import sys
import time

from anyscale_manager.testbed import harness, netns
from anyscale_manager.testbed import schedule as sched
from anyscale_manager.testbed.report import placement_shares

import bench_link_traffic as link_traffic     # this folder's capture of the link

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')


def percentile(values, q):
    values = sorted(values)
    if not values:
        return float('nan')
    k = (len(values) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(values) - 1)
    return values[lo] + (values[hi] - values[lo]) * (k - lo)


def fmt(value) -> str:
    return '-' if value is None or value != value else f'{value:.2f}'


def on(node, scale):
    return lambda r: r.where(node) == (scale,)


def reaction(args):
    if args.keep:
        os.makedirs(args.keep, exist_ok=True)
    options = harness.Options(args.config, args.domain_id, mode='netns',
                              decider_parameters={'decider.hysteresis_s': str(args.hysteresis)},
                              link_up_at_start=False, run_dir=args.keep or '',
                              keep_run_dir=bool(args.keep))
    tb = harness.Testbed(options).start()
    d = tb.deployment
    migratable = set(d.migratable_nodes)
    conns = [c for c in d.connections if c.publisher in migratable or c.subscriber in migratable]
    window = d.monitoring.probe_window_s
    results = []
    try:
        tb.restore()
        for i in range(args.cuts):
            tb.restore()
            tb.wait_for(on('amcl', 'laptop'), 90.0, 'amcl on the laptop')
            tb.wait_for(on('ar', 'laptop'), 90.0, 'ar on the laptop')
            t_out = tb.now()
            # Both connections healthy at the robot before the cut, so what follows is the cut's.
            # Also settled: no move for 5 s and the robot's probes report both within limits,
            # so a gap left by the move out is not counted as the cut's.
            tb.wait_for(lambda r: (r.topic_rate('/amcl_pose', tb.now()) >= 4.0 and
                                   r.topic_rate('/markers', tb.now()) >= 10.0 and
                                   r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), 'robot',
                                             5.0)), 30.0,
                        'amcl_ekf and ar_navigation healthy and settled')
            # The stay on the laptop is the experiment's parameter, not a wait for a state.
            tb.sleep(max(0.0, args.stay - (tb.now() - t_out)))
            stayed = tb.now() - t_out
            t_cut = tb.now()
            tb.cut()
            # Back = the robot's agent reports both running and ready on the robot. (The cut-off
            # laptop is not heard from until the link returns; its reports only age out.)
            tb.wait_for(lambda r: {'amcl', 'ar'} <= set(r.running_on('robot', ready_only=True)),
                        30.0, 'amcl and ar running on the robot')
            # When the report that said so arrived (the wait above polls; this is exact).
            with tb.lock:
                t_back = tb.record.serving_since('robot', ('amcl', 'ar'), t_cut) or tb.now()
            tb.sleep(max(c.tolerance_s or 0 for c in conns) + window + 1.0)
            end = tb.now()
            tb.wait_heard(end)
            with tb.lock:
                r = tb.record
                observed = r.delta_violations(t_cut, end, 'robot')
                reported = [v for v in r.reported_violations(t_cut, end, [c.name for c in conns])
                            if v.source == 'robot']
                timeline = r.timeline(t_cut, end)
            # A standby copy that had to be restarted shows as a backoff in the robot's reports.
            cold = sorted({rep[1] for rep in timeline['reports'] if rep[2] == 'backoff'})
            row = {'cut': i + 1, 'stay_s': round(stayed, 1), 'back_s': round(t_back - t_cut, 3),
                   'restarted_cold': cold,
                   'observed_violations': [(v.connection, round(v.end - v.start, 2))
                                           for v in observed],
                   'reported_violations': [(v.connection, round(v.end - v.start, 2))
                                           for v in reported],
                   'timeline': timeline}
            print(f'cut {i + 1} after {stayed:.0f} s on the laptop: back on the robot after '
                  f'{row["back_s"]:.2f} s; violations '
                  f'observed {row["observed_violations"]} reported {row["reported_violations"]}'
                  + (f'; restarted cold: {cold}' if cold else ''), flush=True)
            if observed or reported:
                print(f'  timeline of cut {i + 1}: {json.dumps(row["timeline"])}', flush=True)
            results.append(row)
        throttles, throttled = throttle_reaction(args, tb)
        with tb.lock:
            onsets = tb.record.congestion_onsets(tb.t0, tb.now())
            backs = [(t, e) for t, e in tb.record.moves() if e.kind == 'migrate_back'
                     and 'usable' in e.reason]
        outside = [t for t in onsets if not any(a <= t <= b for a, b in throttled)]
        false_onsets = [round(t - tb.t0, 1) for t in outside]
        false_backs = [(round(t - tb.t0, 1), e.node, e.reason) for t, e in backs
                       if not any(a <= t <= b for a, b in throttled)]
        moved_out = tb.record.handovers(tb.t0, tb.now(), 'robot')
    finally:
        notes = tb.stop()
    backs = [r['back_s'] for r in results]
    seen = [r['congested_s'] for r in throttles if r['congested_s'] is not None]
    ar_back = [r['ar_back_s'] for r in throttles if r['ar_back_s'] is not None]
    return {'throttles': throttles,
            'throttle_congested_p50_s': percentile(seen, 0.5),
            'throttle_congested_max_s': max(seen) if seen else None,
            'throttle_ar_back_p50_s': percentile(ar_back, 0.5),
            'throttle_ar_back_p95_s': percentile(ar_back, 0.95),
            'throttle_ar_back_max_s': max(ar_back) if ar_back else None,
            'throttles_amcl_moved': sum(1 for r in throttles if r['amcl_moves']),
            'throttles_wrong': sum(1 for r in throttles if not r['right']),
            'throttle_violations': sum(len(r['violations']) for r in throttles),
            'false_congestion_onsets': false_onsets,
            'bandwidth_moves_back_outside_throttles': false_backs,
            'cuts': results, 'p50_s': percentile(backs, 0.5), 'p95_s': percentile(backs, 0.95),
            'max_s': max(backs) if backs else None,
            'cuts_with_cold_restarts': sum(1 for r in results if r['restarted_cold']),
            'cuts_with_violations': sum(1 for r in results
                                        if r['observed_violations'] or r['reported_violations']),
            'violations': sum(len(r['observed_violations']) + len(r['reported_violations'])
                              for r in results),
            'observed': sum(len(r['observed_violations']) for r in results),
            'reported': sum(len(r['reported_violations']) for r in results),
            'stay_s': args.stay,
            'handovers': moved_out,
            'handovers_below_freq_min': sum(1 for h in moved_out if h['below_s'] > 0),
            'handover_kept_past_ready_p50_s': percentile(
                [h['left_s'] - h['ready_s'] for h in moved_out
                 if h['left_s'] is not None and h['ready_s'] is not None], 0.5),
            'handover_kept_past_ready_max_s': max(
                [h['left_s'] - h['ready_s'] for h in moved_out
                 if h['left_s'] is not None and h['ready_s'] is not None], default=None),
            'handover_min_rate_p50_hz': {n: percentile([h['min_rate_hz'] for h in moved_out
                                                        if h['node'] == n], 0.5)
                                         for n in sorted({h['node'] for h in moved_out})},
            'hysteresis_s': args.hysteresis, 'teardown_notes': notes}


def throttle_reaction(args, tb):
    """Throttles at each level with both on the laptop; returns the rows and the intervals
    (throttle to its end + 5 s) in which a congestion report is the throttle's."""
    rows, throttled = [], []
    # What AR's connections put on the link: each twice, once to its subscriber and once to
    # the probe of the subscriber's agent, a reader in another process (docs/monitoring.md).
    need = 2 * sum(c.bandwidth_kbps for c in tb.deployment.connections
                   if 'ar' in (c.publisher, c.subscriber) and c.publisher != c.subscriber)
    # AMCL's inputs cross the link the same way; they fit what the link has left after the DDS
    # discovery traffic, which no connection declares (docs/monitoring.md, known limits):
    # measured here, with both on the laptop, before the first throttle.
    amcl_need = 2 * sum(c.bandwidth_kbps for c in tb.deployment.connections
                        if 'amcl' in (c.publisher, c.subscriber) and c.publisher != c.subscriber
                        and c.subscriber == 'amcl')
    margin = tb.deployment.decider.bandwidth_margin
    if args.throttles <= 0:
        return rows, throttled
    tb.restore()
    tb.wait_for(on('amcl', 'laptop'), 120.0, 'amcl on the laptop')
    tb.wait_for(on('ar', 'laptop'), 120.0, 'ar on the laptop')
    by_kind, _, _ = link_traffic.measure(tb, 10.0)
    discovery = by_kind['discovery'] * 8 / 10.0 / 1000
    print(f'DDS discovery robot -> laptop: {discovery:.0f} kbit/s; AMCL must come back where '
          f'{margin:g} x (level - {discovery:.0f}) < {amcl_need:.0f} kbit/s (its inputs, twice)',
          flush=True)
    tolerance = max(c.tolerance_s or 0.0 for c in tb.deployment.connections)
    for level, count in throttle_plan(args.levels, args.throttles):
        for i in range(count):
            tb.throttle(netns.DEFAULT_RATE_KBPS)
            tb.restore()
            # The figure a throttle left stands until the next probe (every 30 s) measures the
            # full rate again; only then may AR go out.
            tb.wait_for(on('amcl', 'laptop'), 120.0, 'amcl on the laptop')
            tb.wait_for(on('ar', 'laptop'), 120.0, 'ar on the laptop')
            tb.wait_for(lambda r: r.settled(tb.now(), ('amcl_ekf', 'ar_navigation'), 'robot',
                                            5.0), 30.0, 'a settled layout')
            t0 = tb.now()
            tb.throttle(level)
            back_expected = level < need
            amcl_back_expected = margin * (level - discovery) < amcl_need
            t_back = None
            if back_expected:
                tb.wait_for(lambda r: r.where('ar') == ('robot',), 30.0, 'ar back on the robot')
                with tb.lock:
                    t_back = tb.record.serving_since('robot', ('ar',), t0) or tb.now()
            # Long enough for every Δ to run out and a probe to follow the congestion.
            tb.sleep(tolerance + 4.0)
            end = tb.now()
            tb.wait_heard(end)
            with tb.lock:
                r = tb.record
                onsets = r.congestion_onsets(t0, end)
                amcl_moves = r.moves(since=t0, node='amcl')
                ar_moves = r.moves(since=t0, node='ar')
                reasons = [e.reason for _, e in ar_moves][:1]
                observed = r.delta_violations(t0, end, 'robot')
                reported = r.reported_violations(t0, end, serving_only=True)
                timeline = r.timeline(t0, min(end, t0 + 4.0), nodes=('ar',))
            throttled.append((t0, end + 5.0))
            seen = sorted({(v.connection, round(v.end - v.start, 2))
                           for v in list(observed) + list(reported)})
            violations = list(seen)
            amcl_back = any(e.kind != 'migrate' for _, e in amcl_moves)
            right = amcl_back == amcl_back_expected and bool(ar_moves) == back_expected
            row = {'level_kbps': level, 'throttle': i + 1,
                   'congested_s': round(onsets[0] - t0, 3) if onsets else None,
                   'ar_back_s': round(t_back - t0, 3) if t_back is not None else None,
                   'amcl_moves': len(amcl_moves), 'amcl_back_expected': amcl_back_expected,
                   'ar_moves': len(ar_moves),
                   'ar_reason': reasons[0] if reasons else '', 'right': right,
                   'violations': violations}
            print(f'throttle {level:.0f} kbit/s #{i + 1}: congested after {row["congested_s"]} s, '
                  f'ar back after {row["ar_back_s"]} s, ar moves {row["ar_moves"]}, amcl moves '
                  f'{row["amcl_moves"]}, Δ violations {violations} '
                  f'({row["ar_reason"]})',
                  flush=True)
            if back_expected or not right or violations:
                print(f'  link {timeline["link"]}\n  layouts {timeline["layouts"]}\n'
                      f'  robot reports {timeline["reports"]}', flush=True)
            for t, e in amcl_moves:
                print(f'  amcl {e.kind} at +{t - t0:.2f} s: {e.reason[:300]}', flush=True)
            with tb.lock:
                for v in observed:
                    print(f'  observed {v.connection} below {v.end - v.start:.2f} s from '
                          f'{v.start:.3f}: {tb.record.silence(v)}', flush=True)
            rows.append(row)
    tb.throttle(netns.DEFAULT_RATE_KBPS)
    return rows, throttled


def throttle_plan(levels, per_level):
    """[(kbit/s, throttles)] from ``--levels``: ``LEVEL`` or ``LEVEL:COUNT``, comma-separated
    (a level without a count is throttled ``per_level`` times)."""
    plan = []
    for item in levels.split(','):
        if not item.strip():
            continue
        level, _, count = item.partition(':')
        try:
            plan.append((float(level), int(count) if count.strip() else per_level))
        except ValueError:
            raise SystemExit(f'--levels: {item.strip()!r} is not LEVEL or LEVEL:COUNT '
                             '(kbit/s, throttles)')
    return plan


# The paper's robot drove at 0.4 m/s only while AMCL ran on the laptop, 0.2 m/s otherwise.
SPEED_AMCL_REMOTE, SPEED_AMCL_ROBOT = 0.4, 0.2


def mean_speed(shares):
    """Mean driving speed from the time shares of the Fig. 5 layouts."""
    remote = sum(v for k, v in shares.items() if k in ('only AMCL on the laptop',
                                                       'AMCL and AR on the laptop'))
    return SPEED_AMCL_REMOTE * remote + SPEED_AMCL_ROBOT * (1.0 - remote)


def scheduled_run(args, migration):
    parameters = {} if migration else {'decider.migration': 'false'}
    options = harness.Options(args.config, args.domain_id, mode='netns',
                              decider_parameters=parameters, link_up_at_start=False)
    steps = sched.paper_schedule(args.duration)
    tb = harness.Testbed(options).start()
    try:
        cpu0 = tb.cpu_seconds()
        t0 = tb.now()
        tb.restore()
        pending = list(steps)
        while tb.now() - t0 < args.duration:
            while pending and tb.now() - t0 >= pending[0].at_s:
                tb.apply(pending.pop(0))
            time.sleep(0.05)
        t1 = tb.now()
        cpu1 = tb.cpu_seconds()
        with tb.lock:
            r = tb.record
            objective = [o for t, o in r.objectives if t0 <= t <= t1]
            amcl = [t for t in r.arrivals.get('/amcl_pose', []) if t0 <= t <= t1]
            shares = placement_shares(r, t0, t1)
            moves = len(r.moves(t0, t1))
    finally:
        notes = tb.stop()
    wall = t1 - t0
    ref = tb.options.reference_core
    cpu = {name: {'percent_of_one_core': round(100.0 * (cpu1[name] - cpu0[name]) / wall, 2),
                  'reference_core_percent': round(100.0 * (cpu1[name] - cpu0[name]) / wall / ref,
                                                  1)}
           for name in cpu1 if name in cpu0}
    return {'migration': migration, 'duration_s': round(wall, 2),
            'schedule': [str(s) for s in steps],
            'link_up_fraction': sched.up_fraction(steps, args.duration),
            'objective_integral': (objective[-1].integral - objective[0].integral
                                   if len(objective) > 1 else None),
            'mean_perf_map': (statistics.fmean(o.perf_map for o in objective)
                              if objective else None),
            'amcl_mean_rate_hz': len(amcl) / wall, 'moves': moves,
            'placement_shares': shares, 'cpu': cpu, 'teardown_notes': notes}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=CONFIG)
    parser.add_argument('--cuts', type=int, default=20)
    parser.add_argument('--stay', type=float, default=30.0,
                        help='seconds AMCL and AR serve from the laptop before each cut')
    parser.add_argument('--duration', type=float, default=60.0)
    parser.add_argument('--throttles', type=int, default=5, help='throttles per level')
    parser.add_argument('--levels', default='20000,10000,5000,2000,500',
                        help='throttle levels in kbit/s, comma-separated; LEVEL:COUNT throttles '
                             'that level COUNT times instead of --throttles')
    parser.add_argument('--hysteresis', type=float, default=8.0)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '0') or 0))
    parser.add_argument('--skip-reaction', action='store_true')
    parser.add_argument('--skip-headline', action='store_true')
    parser.add_argument('--out', default='')
    parser.add_argument('--keep', metavar='DIR', default='',
                        help="keep the reaction part's run folder (every process's log) in DIR")
    args = parser.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_e2e: needs the test-bed: {why}', file=sys.stderr)
        return 2
    out = {'reference_core': harness.REFERENCE_CORE, 'machine_cores': os.cpu_count()}
    if not args.skip_reaction:
        out['reaction'] = reaction(args)
        r = out['reaction']
        write(args, out)
        if r['cuts']:
            print(f'\nreaction to a link cut over {len(r["cuts"])} cuts: p50 {r["p50_s"]:.2f} s, '
                  f'p95 {r["p95_s"]:.2f} s, max {r["max_s"]:.2f} s; Δ violations: '
                  f'{r["violations"]} (in {r["cuts_with_violations"]} cuts; observer '
                  f'{r["observed"]}, robot probes {r["reported"]}); standby copies restarted '
                  f'in {r["cuts_with_cold_restarts"]} cuts', flush=True)
        if r['throttles']:
            print(f'{len(r["throttles"])} throttles at {args.levels} kbit/s: congestion '
                  f'seen p50 {fmt(r["throttle_congested_p50_s"])} s (max '
                  f'{fmt(r["throttle_congested_max_s"])} s); below what AR puts on the link, AR '
                  f'back p50 {fmt(r["throttle_ar_back_p50_s"])} s, p95 '
                  f'{fmt(r["throttle_ar_back_p95_s"])} s (max {fmt(r["throttle_ar_back_max_s"])} '
                  f's); AMCL moved in {r["throttles_amcl_moved"]}; other than expected in '
                  f'{r["throttles_wrong"]}; Δ violations {r["throttle_violations"]}', flush=True)
        worst = max((h['below_s'] for h in r['handovers']), default=0.0)
        print(f'moves out of the robot: {len(r["handovers"])} outputs judged; below freq_min at '
              f'the robot in {r["handovers_below_freq_min"]} (longest {worst:.2f} s); least rate '
              f'p50 by node {r["handover_min_rate_p50_hz"]}; the robot kept its copy past the '
              f'ready report p50 {r["handover_kept_past_ready_p50_s"]} s, max '
              f'{r["handover_kept_past_ready_max_s"]} s', flush=True)
        print(f'link looked congested outside a throttle: '
              f'{len(r["false_congestion_onsets"])} times, at {r["false_congestion_onsets"]} s; '
              f'moves back for bandwidth outside a throttle: '
              f'{r["bandwidth_moves_back_outside_throttles"]}', flush=True)
    if not args.skip_headline:
        on_ = scheduled_run(args, True)
        off = scheduled_run(args, False)
        out['headline'] = {'with_migration': on_, 'without_migration': off}
        gain = None
        if on_['objective_integral'] and off['objective_integral']:
            gain = on_['objective_integral'] / off['objective_integral'] - 1.0
        out['headline']['objective_gain'] = gain
        print(f'\nsame schedule ({on_["link_up_fraction"]:.0%} link up, {args.duration:g} s):')
        for run in (on_, off):
            label = 'with migration   ' if run['migration'] else 'without migration'
            print(f'  {label}: objective integral {run["objective_integral"]:.1f}, mean '
                  f'Perf_map {run["mean_perf_map"]:.3f}, AMCL at the robot '
                  f'{run["amcl_mean_rate_hz"]:.2f} Hz, {run["moves"]} moves')
        if gain is not None:
            print(f'  time-integrated performance (decider objective) with migration: '
                  f'{gain:+.1%}')
        v_on, v_off = mean_speed(on_['placement_shares']), mean_speed(off['placement_shares'])
        out['headline']['path_time_reduction'] = 1.0 - v_off / v_on
        print(f"  path time at the paper's speeds (0.4 m/s with AMCL on the laptop, else 0.2): "
              f'{1.0 - v_off / v_on:.0%} shorter with migration (paper: 28 %)')
        print('CPU during the migration run (own process, not its nodes):')
        for name, v in sorted(on_['cpu'].items()):
            print(f'  {name:14} {v["percent_of_one_core"]:6.2f} % of one core '
                  f'({v["reference_core_percent"]:.1f} reference-core %)')
    write(args, out)
    return 0


def write(args, out) -> None:
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(out, f, indent=2, sort_keys=True, default=str)
        print(f'written: {args.out}', flush=True)


if __name__ == '__main__':
    sys.exit(main())
