#!/usr/bin/env python3
"""The demo, run several times in a row: Δ violations, moves and exit code of each run.

    sudo python bench/bench_demo_repeat.py [--runs 5] [--domain-id N] [--out FOLDER]
        [-- DEMO ARGS...]

Each run is ``anyscale-manager demo`` with its default schedule (or the arguments after ``--``)
in its own output folder; its summary.json gives the violations the robot's probes reported
and those judged on what the harness's observer heard (a reader no agent started). Exits 1
when any run had a violation or failed.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--domain-id', type=int,
                        default=int(os.environ.get('ROS_DOMAIN_ID', '57') or 57))
    parser.add_argument('--out', default='', help='folder for the runs (default: a new one)')
    parser.add_argument('demo_args', nargs='*', help='passed on to the demo (after --)')
    args = parser.parse_args()
    if args.runs < 1:
        parser.error('--runs must be >= 1')
    out = args.out or tempfile.mkdtemp(prefix='anyscale_demo_runs_')
    os.makedirs(out, exist_ok=True)
    exe = os.path.join(os.path.dirname(sys.executable), 'anyscale-manager')
    rows = []
    for i in range(args.runs):
        folder = os.path.join(out, f'run{i + 1}')
        t0 = time.monotonic()
        with open(os.path.join(out, f'run{i + 1}.log'), 'w') as log:
            demo = subprocess.Popen([exe, 'demo', '--out', folder, '--domain-id',
                                     str(args.domain_id), *args.demo_args],
                                    stdout=log, stderr=subprocess.STDOUT)
            try:
                code = demo.wait()
            except KeyboardInterrupt:
                # Ctrl-C reached the demo too (same process group): it tears its test-bed down;
                # let it finish (a second signal would cut the teardown short), then stop here.
                demo.wait()
                print(f'interrupted during run {i + 1}; logs in {out}', file=sys.stderr)
                return 130
        try:
            with open(os.path.join(folder, 'summary.json')) as f:
                summary = json.load(f)
        except (OSError, ValueError) as e:
            summary = {'error': f'no summary.json: {e}'}
        row = {'run': i + 1, 'exit': code, 'wall_s': round(time.monotonic() - t0, 1),
               'mode': summary.get('mode'), 'moves': summary.get('moves'),
               'reported': summary.get('violations'),
               'observed': summary.get('observed_violations'),
               'details': summary.get('violation_details', []) +
               summary.get('observed_violation_details', []),
               'error': summary.get('error', '')}
        rows.append(row)
        print(f'run {row["run"]}: exit {code}, {row["mode"]}, {row["moves"]} moves, Δ '
              f'violations reported {row["reported"]} observed {row["observed"]}'
              + (f' {row["details"]}' if row['details'] else '')
              + (f' ({row["error"]})' if row['error'] else ''), flush=True)
    bad = [r for r in rows if r['exit'] != 0 or r['reported'] != 0 or r['observed'] != 0]
    print(f'\n{args.runs} demo runs: {args.runs - len(bad)} with exit 0 and no Δ violation '
          f'(probes or observer); logs in {out}')
    with open(os.path.join(out, 'runs.json'), 'w') as f:
        json.dump(rows, f, indent=2)
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
