#!/usr/bin/env python3
"""The chaos soak on the ICAR test-bed (needs root: namespaces, tc, cgroups).

    sudo python bench/soak.py [--minutes 10] [--seed N] [--hysteresis 8] [--kinds cut,flap,...]
                              [--each] [--out FILE] [--keep]

Ten minutes (by default) of faults drawn from a seeded schedule, one after the other: link
cuts, throttles and flaps; SIGKILL of the laptop's agent, the robot's agent, the leading
decider (two run, one stands by) and managed nodes (serving and standby copies), each
restarted after 1 s as systemd would; SIGSTOP of the leading decider; a hostile publisher
(forged, replayed and malformed layouts, states and reports); a third decider started. The
deployment is signed (a key made for the run). Prints each fault with the system's reaction
time, p50/p95 per kind, the counts that must all be 0 (two copies publishing at once beyond
the move overlap, a connection past its Δ at the robot not excused by a kill, AMCL's pose
jumping, a node running nowhere longer than a cold move, forged layouts followed, a third
decider leading or followed, a resumed leader publishing or followed, unexpected exits, missed
reactions, leftovers after the teardown, tracebacks in any log) and the CPU and RSS of the
decider and the agents at the start and the end. Exit 0 when every count is 0, 1 otherwise, 2
on bad arguments or no test-bed. The rules: docs/testbed.md, the chaos soak.
"""

import argparse
import json
import os
import random
import sys

from anyscale_manager.testbed import chaos, netns, soak

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'icar2015_testbed.yaml')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=CONFIG)
    parser.add_argument('--minutes', type=float, default=10.0)
    parser.add_argument('--seed', type=int, default=None,
                        help='schedule seed (default: drawn, and printed)')
    parser.add_argument('--hysteresis', type=float, default=8.0,
                        help="the decider's T (the e2e tests' 8 s; the file says 20 s)")
    parser.add_argument('--kinds', default=','.join(chaos.KINDS),
                        help='fault kinds to draw from, comma-separated')
    parser.add_argument('--each', action='store_true',
                        help='begin with one fault of every kind')
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '0') or 0))
    parser.add_argument('--out', default='', help='write the report as JSON here')
    parser.add_argument('--keep', action='store_true',
                        help='keep the run folder (logs, report) even when every count is 0')
    args = parser.parse_args()
    kinds = tuple(k.strip() for k in args.kinds.split(',') if k.strip())
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1 << 20)
    try:
        chaos.generate(seed, args.minutes * 60.0, kinds=kinds)
    except ValueError as e:
        print(f'soak: {e}', file=sys.stderr)
        return 2
    ok, why = netns.available()
    if not ok:
        print(f'soak: needs the test-bed: {why}', file=sys.stderr)
        return 2
    print(f'seed {seed}', flush=True)
    report = soak.run(soak.SoakOptions(
        args.config, args.domain_id, seed, duration_s=args.minutes * 60.0,
        hysteresis_s=args.hysteresis, kinds=kinds, ensure_each=args.each,
        keep_run_dir=args.keep, log=lambda text: print(text, flush=True)))
    print()
    print(soak.format_report(report), flush=True)
    if report.get('run_dir'):
        print(f'run folder kept: {report["run_dir"]}')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(report, f, indent=2, sort_keys=True, default=str)
        print(f'written: {args.out}')
    return 0 if report['ok'] else 1


if __name__ == '__main__':
    sys.exit(main())
