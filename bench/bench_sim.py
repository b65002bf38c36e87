#!/usr/bin/env python3
"""Simulator speed: simulated seconds of robot time per wall-clock second.

Drives laps of the three system sizes with each policy (the runtime heuristic and the
planner-backed policy) and the oracle, and prints the rate per lap kind. Every lap runs the
decider's turn around the policy once per decider period (0.5 s), as the live decider does.

    python bench/bench_sim.py [--laps 5] [--seed 0]
"""

import argparse
import os
import time

from anyscale_manager.sim.model import PathModel
from anyscale_manager.sim.runner import HEURISTIC, PLANNER, drive, make_policy, oracle_lap, \
    run_schedules
from anyscale_manager.sim.systems import build_system


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--laps', type=int, default=5, help='laps per system and policy')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    path = PathModel()
    print(f'load average before: {" ".join(f"{x:.2f}" for x in os.getloadavg())} '
          f'({os.cpu_count()} CPUs)')
    print(f'{"system":<14} {"lap kind":<10} {"laps":>4} {"simulated s":>11} {"wall s":>7} '
          f'{"sim s / wall s":>14} {"steps / wall s":>14}')
    totals = {}
    for n, m, k in ((6, 2, 2), (12, 6, 3), (18, 9, 4)):
        system = build_system(n, m, k, args.seed)
        schedules = [run_schedules(system, path, args.seed, r) for r in range(args.laps)]
        for kind in (HEURISTIC, PLANNER, 'oracle'):
            simulated = wall = steps = 0.0
            for sched in schedules:
                start = time.perf_counter()
                if kind == 'oracle':
                    lap = oracle_lap(system, sched, path)
                else:
                    lap = drive(system, sched, path, make_policy(kind, system))
                wall += time.perf_counter() - start
                simulated += lap.time_s
                steps += lap.steps
            sim_t, wall_t = totals.get(kind, (0.0, 0.0))
            totals[kind] = (sim_t + simulated, wall_t + wall)
            rate = f'{steps / wall:>14.0f}' if kind != 'oracle' else f'{"-":>14}'
            print(f'{system.label:<14} {kind:<10} {args.laps:>4} {simulated:>11.0f} '
                  f'{wall:>7.2f} {simulated / wall:>14.0f} {rate}')
    for kind, (sim_t, wall_t) in totals.items():
        print(f'overall {kind:<10}: {sim_t / wall_t:.0f} simulated s per wall s')
    print(f'load average after: {" ".join(f"{x:.2f}" for x in os.getloadavg())}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
