"""Fig. 7 as a table, CSV files and a PNG."""

import csv
import math
import os
from typing import List, Optional, Sequence, Tuple

from .runner import Experiment

PAPER_TESTBED_PCT = 28.0
PAPER_AVERAGE_PCT = 39.0
PAPER_BEST_CASE_PCT = 50.0


def _f(x: float, digits: int = 1) -> str:
    return '-' if x is None or (isinstance(x, float) and math.isnan(x)) else f'{x:.{digits}f}'


def _row(*cells: str) -> str:
    """One line of the table: system, improvement, std, best case, oracle, gap, moves/lap, and
    the other policy's improvement when there is one."""
    widths = (-14, 13, 5, 11, 8, 15, 9, 13)
    return ' '.join(f'{c:<{-w}}' if w < 0 else f'{c:>{w}}' for c, w in zip(cells, widths))


def table(exp: Experiment, other: Optional[Experiment] = None) -> str:
    p = exp.path
    lines = [
        f'ICAR 2015 Fig. 7 in simulation: policy {exp.policy}, {exp.runs} run(s) per system, '
        f'seed {exp.seed}, links {p.links}, availability U({p.availability_low:g}, '
        f'{p.availability_high:g}), {p.outages_min}-{p.outages_max} hole(s) per lap and link',
        _row('system', 'improvement %', 'std', 'best case %', 'oracle %', 'gap to oracle %',
             'moves/lap', *([other.policy + ' %'] if other else [])),
    ]
    others = {s.label: s for s in other.systems} if other else {}
    for s in exp.systems:
        moves = sum(r.migrations for r in s.runs) / max(1, len(s.runs))
        lines.append(_row(s.label, _f(s.improvement_pct), _f(s.improvement_std_pct),
                          _f(s.best_case_improvement_pct), _f(s.oracle_improvement_pct),
                          _f(s.gap_to_oracle_pct), f'{moves:.1f}',
                          *([_f(others[s.label].improvement_pct)] if other else [])))
    lines.append(_row('average', _f(exp.mean('improvement_pct')), '',
                      _f(exp.mean('best_case_improvement_pct')),
                      _f(exp.mean('oracle_improvement_pct')), _f(exp.mean('gap_to_oracle_pct')),
                      '', *([_f(other.mean('improvement_pct'))] if other else [])))
    lines.append(f'paper: 6N x 2M x 2K {PAPER_TESTBED_PCT:g} %, average {PAPER_AVERAGE_PCT:g} %, '
                 f'best case {PAPER_BEST_CASE_PCT:g} %; heuristic estimated 10-15 % from the '
                 'optimum')
    return '\n'.join(lines)


SYSTEM_FIELDS = ('label', 'n', 'm', 'k', 'policy', 'runs', 'improvement_pct',
                 'improvement_std_pct', 'best_case_improvement_pct', 'oracle_improvement_pct',
                 'gap_to_oracle_pct', 'perf_map_gain_pct', 'baseline_time_s',
                 'best_case_time_s', 'mean_time_s', 'mean_migrations')
RUN_FIELDS = ('label', 'n', 'm', 'k', 'policy', 'run', 'availability', 'time_s',
              'improvement_pct', 'oracle_time_s', 'oracle_improvement_pct', 'gap_to_oracle_pct',
              'migrations', 'perf_map_gain_pct')


def write_csv(exps: Sequence[Experiment], directory: str) -> List[str]:
    """fig7.csv (one row per system and policy) and runs.csv (one row per lap)."""
    os.makedirs(directory, exist_ok=True)
    systems_path = os.path.join(directory, 'fig7.csv')
    runs_path = os.path.join(directory, 'runs.csv')
    with open(systems_path, 'w', newline='', encoding='utf-8') as f:
        w = csv.writer(f)
        w.writerow(SYSTEM_FIELDS)
        for exp in exps:
            for s in exp.systems:
                n = max(1, len(s.runs))
                w.writerow([s.label, s.n, s.m, s.k, s.policy, len(s.runs),
                            f'{s.improvement_pct:.3f}', f'{s.improvement_std_pct:.3f}',
                            f'{s.best_case_improvement_pct:.3f}',
                            f'{s.oracle_improvement_pct:.3f}', f'{s.gap_to_oracle_pct:.3f}',
                            f'{s.perf_map_gain_pct:.3f}', f'{s.baseline_time_s:.2f}',
                            f'{s.best_case_time_s:.2f}',
                            f'{sum(r.time_s for r in s.runs) / n:.2f}',
                            f'{sum(r.migrations for r in s.runs) / n:.2f}'])
    with open(runs_path, 'w', newline='', encoding='utf-8') as f:
        w = csv.writer(f)
        w.writerow(RUN_FIELDS)
        for exp in exps:
            for s in exp.systems:
                for r in s.runs:
                    w.writerow([s.label, s.n, s.m, s.k, s.policy, r.run,
                                ' '.join(f'{a:.4f}' for a in r.availability), f'{r.time_s:.2f}',
                                f'{r.improvement_pct:.3f}', f'{r.oracle_time_s:.2f}',
                                f'{r.oracle_improvement_pct:.3f}', f'{r.gap_to_oracle_pct:.3f}',
                                r.migrations, f'{r.perf_map_gain_pct:.3f}'])
    return [systems_path, runs_path]


def write_figure(exp: Experiment, directory: str, other: Optional[Experiment] = None) -> str:
    """fig7.png: improvement per system (typical and best case), the oracle, the paper's values."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, 'fig7.png')
    labels = [s.label.replace(' x ', '\n') for s in exp.systems]
    x = list(range(len(exp.systems)))
    # (label, values, error bars or None, colour)
    series: List[Tuple[str, List[float], Optional[List[float]], str]] = [
        (f'{exp.policy} (link 45-65 %)', [s.improvement_pct for s in exp.systems],
         [s.improvement_std_pct for s in exp.systems], '#4c72b0')]
    if other is not None:
        series.append((f'{other.policy} (link 45-65 %)',
                       [s.improvement_pct for s in other.systems],
                       [s.improvement_std_pct for s in other.systems], '#55a868'))
    series.append((f'{exp.policy}, best case (link always up)',
                   [s.best_case_improvement_pct for s in exp.systems], None, '#c44e52'))
    width = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(11, 5.6))
    for i, (name, values, err, colour) in enumerate(series):
        offs = [xi - 0.4 + width * (i + 0.5) for xi in x]
        ax.bar(offs, values, width, yerr=err, label=name, color=colour, capsize=2)
    ax.scatter(x, [s.oracle_improvement_pct for s in exp.systems], marker='_', s=400,
               color='black', zorder=3, label='oracle (best layout per link state, no delays)')
    ax.axhline(PAPER_AVERAGE_PCT, color='#4c72b0', ls='--', lw=0.8,
               label=f'paper: average {PAPER_AVERAGE_PCT:g} %')
    ax.axhline(PAPER_BEST_CASE_PCT, color='#c44e52', ls='--', lw=0.8,
               label=f'paper: best case {PAPER_BEST_CASE_PCT:g} %')
    testbed = [i for i, s in enumerate(exp.systems) if (s.n, s.m, s.k) == (6, 2, 2)]
    if testbed:
        ax.plot(testbed, [PAPER_TESTBED_PCT], marker='*', ms=12, color='orange', ls='none',
                label=f'paper: test-bed {PAPER_TESTBED_PCT:g} %')
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylabel('path time saved vs no migration (%)')
    ax.set_ylim(0, 60)
    average, best = exp.mean('improvement_pct'), exp.mean('best_case_improvement_pct')
    title = (f'Fig. 7 reproduced: {exp.runs} run(s) per system, seed {exp.seed}; {exp.policy} '
             f'average {average:.1f} %')
    if other is not None:
        theirs = other.mean('improvement_pct')
        title += f', {other.policy} average {theirs:.1f} %'
    title += f'; best case {best:.1f} %'
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.16), ncol=4)
    ax.grid(axis='y', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
