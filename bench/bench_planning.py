"""Benchmark of the offline planners: quality and time on the IROS 2016 instances, and scale.

Usage: python bench/bench_planning.py [--repeat N] [--sizes 100x5,250x12,...]
Prints markdown tables. Times are wall-clock seconds of ``planning.solve`` (best of N runs).
"""

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from anyscale_manager.model import load_deployment  # noqa: E402
from anyscale_manager.planning import solve  # noqa: E402
from anyscale_manager.planning.generate import generate_deployment  # noqa: E402

CONFIG = os.path.join(os.path.dirname(HERE), 'config', 'iros2016')
SOLVERS = ('greedy', 'paper-greedy', 'exact')


def best_of(repeat, fn):
    best, plan = None, None
    for _ in range(repeat):
        start = time.perf_counter()
        plan = fn()
        took = time.perf_counter() - start
        best = took if best is None else min(best, took)
    return plan, best


def gap(problem, value, optimum):
    """How far a solution is from the optimum, in percent (0 = optimal)."""
    if optimum == 0:
        return 0.0 if value == 0 else float('inf')
    return 100.0 * ((optimum - value) if problem == 1 else (value - optimum)) / abs(optimum)


def iros_table(repeat, settings):
    print(f'\n### IROS 2016 instances, {settings} settings\n')
    print('| problem | instance | greedy | gap % | time s | paper-greedy | gap % | time s '
          '| exact (optimal) | proven | time s |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    worst = {1: 0.0, 2: 0.0}
    worst_paper = {1: 0.0, 2: 0.0}
    exact_total = 0.0
    all_proven = True
    for problem in (1, 2):
        for i in range(1, 11):
            d = load_deployment(os.path.join(CONFIG, f'instance_{i}.yaml'))
            row = {}
            for s in SOLVERS:
                row[s] = best_of(repeat, lambda: solve(d, problem, s, settings=settings))
            opt = row['exact'][0].objective
            exact_total += row['exact'][1]
            all_proven &= row['exact'][0].optimal
            g = gap(problem, row['greedy'][0].objective, opt)
            pg = gap(problem, row['paper-greedy'][0].objective, opt)
            worst[problem] = max(worst[problem], g)
            worst_paper[problem] = max(worst_paper[problem], pg)
            print(f'| {problem} | {i} | {row["greedy"][0].objective:.3f} | {g:.2f} | '
                  f'{row["greedy"][1]:.3f} | {row["paper-greedy"][0].objective:.3f} | '
                  f'{pg:.2f} | {row["paper-greedy"][1]:.3f} | {opt:.3f} | '
                  f'{"yes" if row["exact"][0].optimal else "no"} | {row["exact"][1]:.3f} |')
    print(f'\n- exact: {"all 20 proven optimal" if all_proven else "NOT all proven"}, '
          f'{exact_total:.2f} s in total (target < 5 s: '
          f'{"met" if all_proven and exact_total < 5 else "missed"})')
    print(f'- greedy, worst gap: problem 1 {worst[1]:.2f}% (target <= 1%: '
          f'{"met" if worst[1] <= 1 else "missed"}), problem 2 {worst[2]:.2f}% '
          f'(target <= 0.5%: {"met" if worst[2] <= 0.5 else "missed"})')
    print(f'- paper-greedy, worst gap: problem 1 {worst_paper[1]:.2f}%, '
          f'problem 2 {worst_paper[2]:.2f}%')


def scale_table(repeat, sizes):
    print('\n### Generated deployments (planning.generate.generate_deployment, seed 0)\n')
    print('| nodes | computers | connections | P1 greedy s | P1 paper-greedy s | P1 gain over '
          'paper % | P1 local search | P2 greedy s | P2 paper-greedy s | P2 saving over '
          'paper % | P2 local search |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for n, c in sizes:
        d = generate_deployment(n, c, seed=0)
        cells = []
        for problem in (1, 2):
            g, tg = best_of(repeat, lambda: solve(d, problem, 'greedy'))
            p, tp = best_of(repeat, lambda: solve(d, problem, 'paper-greedy'))
            if not (g.feasible and p.feasible):
                cells += [f'{tg:.3f}', f'{tp:.3f}', 'infeasible', '-']
                continue
            change = (100 * (g.objective - p.objective) / p.objective if problem == 1 else
                      100 * (p.objective - g.objective) / p.objective)
            done = 'converged' if g.status == 'local optimum' else 'time budget'
            cells += [f'{tg:.3f}', f'{tp:.3f}', f'{change:.2f}', done]
        print(f'| {n} | {c} | {len(d.connections)} | ' + ' | '.join(cells) + ' |')


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=3, help='runs per figure (best kept)')
    parser.add_argument('--sizes', default='100x5,250x12,500x25,1000x50,2000x100',
                        help='generated sizes as NODESxCOMPUTERS, comma separated')
    parser.add_argument('--skip-discrete', action='store_true')
    args = parser.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split('x')) for s in args.sizes.split(',') if s]
    print(f'## Planning benchmark (python {sys.version.split()[0]}, {os.cpu_count()} cores, '
          f'best of {args.repeat})')
    iros_table(args.repeat, 'continuous')
    if not args.skip_discrete:
        iros_table(args.repeat, 'discrete')
    scale_table(args.repeat, sizes)
    return 0


if __name__ == '__main__':
    sys.exit(main())
