#!/usr/bin/env python3
"""A fleet in simulation: 10, 25 and 50 robots sharing 1, 2 and 3 servers through the claims
ledger (sim/fleet.py), and what each costs.

Each robot is the test-bed (6N x 2M: AMCL CPU 50 and AR CPU 33 migratable) with the servers as
its remote scales, each server of the test-bed laptop's power and capacity (700 CPU) unless
``--capacity`` says otherwise; robot i has priority i mod ``--priorities``. Per fleet: each
server's utilisation (CPU claimed over capacity, time-averaged), the over-commit seconds, the
ledger's claim decisions (refused, waiting), the preemptions (asks to leave), the Δ violations,
Jain's index over the robots' time with a node serving on a server, the path time saved against
no migration (mean over the robots), and a claim decision's wall time (p50, p95 over every
decision of the fleet's runs). The reference row of each fleet size is the same robots and
links with one server of room for all of them: what sharing costs.

    python bench/bench_sim_fleet.py [--runs 1] [--duration 600] [--seed 0] [--priorities 2]
"""

import argparse
import os
import time

from anyscale_manager.sim.fleet import FleetSpec, run_fleet_runs
from anyscale_manager.sim.fleet_figures import FleetSummary

ROBOTS = (10, 25, 50)
SERVERS = (1, 2, 3)
# Every robot's AMCL and AR at once (83 CPU each), with room to spare.
UNCONTENDED_CPU_PER_ROBOT = 100.0


def _row(*cells) -> str:
    widths = (6, 7, 16, 13, 7, 8, 8, 11, 12, 8, 7, 14, 7)
    return ' '.join(f'{c:>{w}}' for c, w in zip(cells, widths))


def _line(robots: int, servers: str, runs: list, per_server: bool = True) -> str:
    s = FleetSummary.of(runs)
    if per_server:
        util = '/'.join(f'{sum(r.servers[i].utilisation for r in runs) / len(runs) * 100:.0f}'
                        for i in range(len(runs[0].servers)))
    else:
        util = '-'
    return _row(robots, servers, util, f'{s.overcommit_s:.1f}', f'{s.claims:.0f}',
                f'{s.refused:.0f}', f'{s.waiting:.0f}', f'{s.preemptions:.0f}',
                f'{s.delta_violations:.0f}', f'{s.fairness:.3f}', f'{s.improvement_pct:.1f}',
                f'{s.claim_p50_ms:.2f}/{s.claim_p95_ms:.2f}', f'{s.wall_s:.0f}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=1, help='runs per fleet (default 1)')
    parser.add_argument('--duration', type=float, default=600.0, help='seconds per run')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--priorities', type=int, default=2,
                        help='robot i has priority i mod this (default 2)')
    parser.add_argument('--capacity', type=float, default=FleetSpec.capacity_cpu,
                        help='capacity_cpu of each server (default 700)')
    parser.add_argument('--no-reference', action='store_true',
                        help='skip the uncontended reference of each fleet size')
    args = parser.parse_args()
    start = time.perf_counter()
    print(f'load average before: {" ".join(f"{x:.2f}" for x in os.getloadavg())} '
          f'({os.cpu_count()} CPUs)')
    print(f'{args.runs} run(s) of {args.duration:g} s per fleet, seed {args.seed}, priorities '
          f'i mod {args.priorities}, servers of {args.capacity:g} CPU')
    print(_row('robots', 'servers', 'utilisation %', 'over-commit s', 'claims', 'refused',
               'waiting', 'preemptions', 'Δ violations', 'fairness', 'saved %',
               'claim p50/p95', 'wall s'))
    for robots in ROBOTS:
        for servers in SERVERS:
            spec = FleetSpec(robots=robots, servers=servers, capacity_cpu=args.capacity,
                             duration_s=args.duration, priority_levels=args.priorities,
                             seed=args.seed)
            print(_line(robots, str(servers), run_fleet_runs(spec, args.runs)), flush=True)
        if not args.no_reference:
            spec = FleetSpec(robots=robots, servers=1,
                             capacity_cpu=robots * UNCONTENDED_CPU_PER_ROBOT,
                             duration_s=args.duration, priority_levels=args.priorities,
                             seed=args.seed)
            print(_line(robots, 'room', run_fleet_runs(spec, args.runs), per_server=False),
                  flush=True)
    print('utilisation: per server; claims, refused, waiting, preemptions, Δ violations: per '
          "run; fairness: Jain's index over the robots' time with a node serving on a server; "
          'saved: path time saved against no migration, mean over the robots; claim: ms; '
          "room: one server with room for every robot's nodes")
    print(f'load average after: {" ".join(f"{x:.2f}" for x in os.getloadavg())}; '
          f'{time.perf_counter() - start:.0f} s in all')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
