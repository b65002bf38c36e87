#!/usr/bin/env python3
"""Figures of the three-scale test-bed (config/three_scales_testbed.yaml; needs root).

    sudo python bench/bench_three_scales.py [--cuts 20] [--stay 10] [--backhaul-cuts 5]
                                            [--quiet-minutes 10] [--out FILE]

1. Server link cut -> next-best: with AMCL and AR serving on the server (their copies on the
   robot and the laptop inactive) for ``--stay`` seconds, the WiFi to the server is cut; the
   time until the laptop's agent reports both serving (active, ready), p50/p95 over ``--cuts``
   cuts, whether anything went home first, and the Δ violations of the cut judged on what every
   scale's observer heard (readers no agent started). Then the WiFi is restored: the time until
   both serve on the server again, from the restore and from the end of the hysteresis T (a
   node that left a scale is not moved back to it within T of leaving).
2. Laptop-server link (backhaul) cut, ``--backhaul-cuts`` times: the time until its watcher
   (the laptop) reports it down, heard at the robot; and the moves it caused (nothing of this
   deployment crosses that link while AMCL and AR are on the server: none is right).
3. Needless moves: ``--quiet-minutes`` with nothing changing but a CPU noise process on the
   server (a busy loop whose duty changes at random every 2-6 s between 0 and 60 % of a core):
   every move is needless.

Runs with the decider's hysteresis T set by ``--hysteresis`` (8 s by default instead of the
file's 20 s) so that twenty cuts take minutes.
"""

import argparse
import json
import os
import sys

from anyscale_manager.testbed import harness, netns

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'three_scales_testbed.yaml')
MOVING = ('amcl', 'ar')
NOISE = '''
import random, time
random.seed(7)
while True:
    duty, until = random.uniform(0.0, 0.6), time.time() + random.uniform(2.0, 6.0)
    while time.time() < until:
        t = time.time()
        while time.time() - t < duty * 0.05:
            pass
        time.sleep((1.0 - duty) * 0.05)
'''


def percentile(values, q):
    values = sorted(values)
    if not values:
        return float('nan')
    k = (len(values) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(values) - 1)
    return values[lo] + (values[hi] - values[lo]) * (k - lo)


def serving(tb, scale):
    return {n for n in tb.views[scale].running_on(scale, ready_only=True) if n in MOVING}


def only_on(tb, scale):
    others = [s for s in tb.deployment.scale_names if s != scale]
    return lambda _r: serving(tb, scale) == set(MOVING) and not any(serving(tb, s)
                                                                    for s in others)


def out_to_server(tb):
    for link in tb.deployment.links:
        if not tb.link_state(link.name)[0]:
            tb.restore(link.name)
    tb.wait_for(only_on(tb, 'server'), 90.0, 'amcl and ar serving on the server only')
    tb.wait_for(lambda r: not r.moves(since=tb.now() - 3.0), 30.0, 'no move for 3 s')


def violations(tb, start, end):
    """(scale, connection, seconds below, what its longest silence says) past Δ at every
    observer."""
    tb.wait_heard(end)
    found = []
    with tb.lock:
        for scale in tb.deployment.scale_names:
            view = tb.views[scale]
            found += [(scale, v.connection, round(v.end - v.start, 2),
                       view.silence(v))
                      for v in view.delta_violations(start, end, scale)]
    return found


def moves(tb, since, until=float('inf')):
    with tb.lock:
        return [(round(t - since, 2), e.kind, e.node, e.from_scale, e.to_scale,
                 e.reason[:240]) for t, e in tb.record.moves(since=since, until=until)]


def server_cuts(tb, args):
    rows = []
    for i in range(args.cuts):
        out_to_server(tb)
        tb.sleep(args.stay)
        t_cut = tb.now()
        tb.cut('wifi')
        tb.wait_for(lambda _r: serving(tb, 'laptop') == set(MOVING), 30.0,
                    'amcl and ar serving on the laptop')
        with tb.lock:
            t_serving = tb.views['laptop'].serving_since('laptop', MOVING, t_cut) or tb.now()
        tb.sleep(3.0)
        t_restore = tb.now()
        bad = violations(tb, t_cut, t_restore)
        cut_moves = moves(tb, t_cut, t_restore)
        left_at = max((t_cut + m[0] for m in cut_moves if m[3] == 'server'), default=t_cut)
        tb.restore('wifi')
        tb.wait_for(only_on(tb, 'server'), 90.0, 'amcl and ar back on the server')
        with tb.lock:
            # Back = the server serves both again after the last of the moves that returned
            # them (its own copies stood down during the cut).
            returned = [t for t, e in tb.record.moves(since=t_restore) if e.to_scale == 'server']
            t_back = tb.views['server'].serving_since(
                'server', MOVING, max(returned, default=t_restore)) or tb.now()
            t_down = next((t for t, state in tb.views['server'].agent_states.get('server', [])
                           if t >= t_cut and not any(
                               state.nodes.get(n) is not None and state.nodes[n].ready
                               and state.nodes[n].state == 'running' for n in MOVING)), None)
        row = {'cut': i + 1, 'serving_s': round(t_serving - t_cut, 3),
               'server_stood_down_s': None if t_down is None else round(t_down - t_cut, 2),
               'home_first': [m for m in cut_moves if m[4] == 'robot'],
               'violations': bad,
               'return_s': round(t_back - t_restore, 2),
               'return_after_hysteresis_s': round(
                   t_back - max(t_restore, left_at + args.hysteresis), 2),
               'moves': cut_moves}
        print(f'server cut {i + 1}: serving on the laptop after {row["serving_s"]:.2f} s, the '
              f'server stood down after {row["server_stood_down_s"]} s; home first '
              f'{row["home_first"]}; Δ violations {bad}; back on '
              f'the server {row["return_s"]:.1f} s after the restore, '
              f'{row["return_after_hysteresis_s"]:.1f} s after T', flush=True)
        rows.append(row)
    served = [r['serving_s'] for r in rows]
    return {'cuts': rows, 'p50_s': percentile(served, 0.5), 'p95_s': percentile(served, 0.95),
            'max_s': max(served, default=float('nan')),
            'violations': sum(len(r['violations']) for r in rows),
            'home_first': sum(bool(r['home_first']) for r in rows),
            'server_stood_down_max_s': max((r['server_stood_down_s'] or float('inf')
                                            for r in rows), default=float('nan')),
            'return_after_hysteresis_p50_s': percentile(
                [r['return_after_hysteresis_s'] for r in rows], 0.5),
            'return_after_hysteresis_p95_s': percentile(
                [r['return_after_hysteresis_s'] for r in rows], 0.95)}


def backhaul_cuts(tb, args):
    rows = []
    for i in range(args.backhaul_cuts):
        out_to_server(tb)
        # The previous restore reported: a late "down" of the last cut is not this one's.
        tb.wait_for(lambda r: bool(r.link_reports('backhaul'))
                    and r.link_reports('backhaul')[-1][1].up, 20.0, 'the backhaul reported up')
        t_cut = tb.now()
        tb.cut('backhaul')

        def seen(r):
            return any(t >= t_cut and not s.up for t, s in r.link_reports('backhaul'))
        tb.wait_for(seen, 10.0, 'the backhaul reported down')
        with tb.lock:
            t_seen = next(t for t, s in tb.record.link_reports('backhaul')
                          if t >= t_cut and not s.up)
        tb.sleep(4.0)
        caused = moves(tb, t_cut)
        bad = violations(tb, t_cut, tb.now())
        tb.restore('backhaul')
        rows.append({'cut': i + 1, 'seen_s': round(t_seen - t_cut, 3), 'moves': caused,
                     'violations': bad})
        print(f'backhaul cut {i + 1}: reported down after {t_seen - t_cut:.2f} s; moves '
              f'{caused}; Δ violations {bad}', flush=True)
    seen_s = [r['seen_s'] for r in rows]
    return {'cuts': rows, 'seen_p50_s': percentile(seen_s, 0.5),
            'seen_max_s': max(seen_s, default=float('nan')),
            'moves': sum(len(r['moves']) for r in rows)}


def quiet_run(tb, args):
    out_to_server(tb)
    noise = tb.start_tool('cpu_noise', 'server', [tb.options.python, '-c', NOISE], quota=True)
    try:
        t0 = tb.now()
        tb.sleep(args.quiet_minutes * 60.0)
        t1 = tb.now()
    finally:
        noise.popen.kill()
        noise.popen.wait()
    with tb.lock:
        cpu = [s.cpu_total for t, s in tb.record.scale_status.get('server', []) if t0 <= t <= t1]
    found = moves(tb, t0, t1)
    bad = violations(tb, t0, t1)
    print(f'{args.quiet_minutes:g} min with CPU noise on the server (its CPU read '
          f'{min(cpu, default=0):.0f}-{max(cpu, default=0):.0f}): {len(found)} moves {found}; '
          f'Δ violations {bad}', flush=True)
    return {'minutes': args.quiet_minutes, 'moves': found, 'violations': bad,
            'server_cpu_min': min(cpu, default=None),
            'server_cpu_max': max(cpu, default=None)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=CONFIG)
    parser.add_argument('--cuts', type=int, default=20)
    parser.add_argument('--stay', type=float, default=10.0,
                        help='seconds AMCL and AR serve on the server before each cut')
    parser.add_argument('--backhaul-cuts', type=int, default=5)
    parser.add_argument('--quiet-minutes', type=float, default=10.0)
    parser.add_argument('--hysteresis', type=float, default=8.0)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '0') or 0))
    parser.add_argument('--out', default='')
    parser.add_argument('--keep', default='', metavar='DIR',
                        help="keep the test-bed's logs in DIR (the agents', the deciders')")
    args = parser.parse_args()
    ok, why = netns.available()
    if not ok:
        print(f'bench_three_scales: needs the test-bed: {why}', file=sys.stderr)
        return 2
    options = harness.Options(args.config, args.domain_id, mode='netns',
                              decider_parameters={'decider.hysteresis_s': str(args.hysteresis)},
                              link_up_at_start=False, run_dir=args.keep,
                              keep_run_dir=bool(args.keep))
    tb = harness.Testbed(options).start()
    out = {'machine_cores': os.cpu_count(), 'hysteresis_s': args.hysteresis}
    try:
        out['server_cuts'] = server_cuts(tb, args)
        out['backhaul_cuts'] = backhaul_cuts(tb, args)
        if args.quiet_minutes > 0:
            out['quiet'] = quiet_run(tb, args)
    finally:
        out['teardown_notes'] = tb.stop()
    s, b = out['server_cuts'], out['backhaul_cuts']
    print(f'\nserver link cut -> amcl and ar serving on the laptop over {len(s["cuts"])} cuts: '
          f'p50 {s["p50_s"]:.2f} s, p95 {s["p95_s"]:.2f} s, max {s["max_s"]:.2f} s; the cut-off '
          f'server stood down within {s["server_stood_down_max_s"]:.2f} s; home first '
          f'in {s["home_first"]} cuts; Δ violations {s["violations"]}; back on the server '
          f'after T: p50 {s["return_after_hysteresis_p50_s"]:.2f} s, p95 '
          f'{s["return_after_hysteresis_p95_s"]:.2f} s')
    print(f'backhaul cut seen by its watcher: p50 {b["seen_p50_s"]:.2f} s, max '
          f'{b["seen_max_s"]:.2f} s; moves caused {b["moves"]}')
    if 'quiet' in out:
        print(f'needless moves in {args.quiet_minutes:g} min of CPU noise: '
              f'{len(out["quiet"]["moves"])}')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(out, f, indent=2, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
