"""The chaos soak's report: the counts that must all be 0, and the report as data and as text.

``build`` puts together the runner's tally and samples, the verdict (``verdict.judge``) and what
the teardown found; ``format_report`` prints it. Pure: the runner writes the file.
"""

import json
from typing import Dict, Sequence

from . import chaos
from .samples import Samples
from .verdict import Tally


def resource_window_s(duration_s: float) -> float:
    """The window at the start and at the end of a soak of ``duration_s`` whose CPU and RSS are
    reported."""
    return min(60.0, max(15.0, duration_s / 5.0))


def counts(tally: Tally, samples: Samples, verdict: Dict[str, object],
           teardown: Dict[str, object]) -> Dict[str, int]:
    """What must never happen, counted: every one must be 0."""
    return {
        'duplicate_publishers': len(verdict['duplicates']),
        'duplicate_publishers_reported': len(verdict['duplicates_reported']),
        'duplicate_processes': len(samples.duplicates),
        'delta_violations': len(verdict['delta_violations']),
        'state_jumps': len(verdict['state_jumps']),
        'nowhere': len(verdict['nowhere']),
        'unneeded_moves_back': len(verdict['unneeded_moves_back']),
        'forged_applied': verdict['forged_applied_count'],
        'rival_followed': verdict['rival_followed_count'],
        'rival_misbehaved': tally.rival_misbehaved,
        'stale_leader': tally.stale_leader,
        'restart_harm': tally.restart_harm,
        'unfenced': tally.unfenced,
        'unexpected_exits': len([e for e in tally.exits if not e['intended']]),
        'missed_reactions': tally.missed,
        'leftovers': len(teardown['leftovers']),
        'tracebacks': len(teardown['tracebacks']),
    }


def build(*, seed: int, planned_s: float, hysteresis_s: float, kinds: Sequence[str],
          bounds: Dict[str, float], t0: float, t_end: float, schedule: Sequence[chaos.Fault],
          system: Sequence[str], tally: Tally, samples: Samples, verdict: Dict[str, object],
          teardown: Dict[str, object], run_dir: str) -> Dict[str, object]:
    """The report of a soak planned for ``planned_s`` that ran from ``t0`` to ``t_end``:
    ``system`` names the processes whose resources are reported; ``teardown`` holds
    ``leftovers``, ``tracebacks`` and ``resources_end`` (each process's end window)."""
    found = counts(tally, samples, verdict, teardown)
    edge = resource_window_s(planned_s)
    resources = {name: {'start': samples.resources.window(name, t0, t0 + edge),
                        'end': teardown['resources_end'][name],
                        'growth': samples.resources.growth(name, 0.5 * planned_s)}
                 for name in system}
    out = {
        'seed': seed, 'duration_s': round(t_end - t0, 1),
        'hysteresis_s': hysteresis_s, 'kinds': list(kinds),
        'bounds': dict(bounds),
        'counts': found, 'ok': not any(found.values()),
        'faults': tally.results, 'reactions': chaos.reaction_summary(tally.results),
        'schedule': [f.describe() for f in schedule],
        'exits': tally.exits, 'restarts': tally.restarts,
        'duplicate_processes': samples.duplicates,
        'resources': resources, 'resource_window_s': edge,
        **verdict, **teardown, 'run_dir': run_dir,
    }
    out.pop('resources_end', None)
    return out


def format_report(report: Dict[str, object]) -> str:
    """The report as text: every fault with its reaction, the reaction times per kind, the
    counts, and the CPU and memory of the decider and the agents."""
    lines = [f'chaos soak: seed {report["seed"]}, {report["duration_s"]:g} s, '
             f'{len(report["faults"])} faults (T = {report["hysteresis_s"]:g} s)', '',
             f'{"#":>3} {"at s":>7}  {"fault":44} {"reaction":>9}  what / outcome']
    for r in report['faults']:
        took = '-' if r['reaction_s'] is None else f'{r["reaction_s"]:.2f} s'
        lines.append(f'{r["index"]:>3} {r["at_s"]:>7.1f}  {r["what"][:44]:44} {took:>9}  '
                     f'{r["reaction"]} {r["outcome"]}'.rstrip())
    lines += ['', f'{"fault kind":20} {"faults":>6} {"timed":>6} {"p50 s":>7} {"p95 s":>7} '
                  f'{"max s":>7}']
    for kind, row in sorted(report['reactions'].items()):
        cells = ['-' if row[k] is None else f'{row[k]:.2f}' for k in ('p50_s', 'p95_s', 'max_s')]
        lines.append(f'{kind:20} {row["faults"]:>6} {row["timed"]:>6} {cells[0]:>7} '
                     f'{cells[1]:>7} {cells[2]:>7}')
    b = report['bounds']
    lines += ['', f'counts (each must be 0; overlap bound {b["overlap_s"]:g} s, nowhere bound '
                  f'{b["nowhere_s"]:g} s):']
    for name, n in report['counts'].items():
        lines.append(f'  {name:22} {n}')
    lines += ['', f'{"process":14} {"CPU % start":>11} {"CPU % end":>10} {"RSS MiB start":>14} '
                  f'{"RSS MiB end":>12} {"RSS growth (same process)":>26}']
    for name, row in report['resources'].items():
        s, e, g = row['start'] or {}, row['end'] or {}, row['growth']
        growth = '-' if not g else f'{g["growth_mib"]:+.2f} MiB over {g["over_s"]:.0f} s'
        lines.append(f'{name:14} {s.get("cpu_percent", "-"):>11} {e.get("cpu_percent", "-"):>10} '
                     f'{s.get("rss_mib", "-"):>14} {e.get("rss_mib", "-"):>12} {growth:>26}')
    for key in ('duplicates', 'duplicates_reported', 'delta_violations', 'nowhere',
                'unneeded_moves_back',
                'forged_applied', 'rival_followed', 'leftovers', 'tracebacks',
                'duplicate_processes', 'moves_back_noted'):
        if report.get(key):
            lines += ['', f'{key}:'] + [f'  {json.dumps(x, default=str)[:300]}'
                                        for x in report[key]]
    unintended = [e for e in report['exits'] if not e['intended']]
    if unintended:
        lines += ['', 'unexpected exits:'] + [f'  {x}' for x in unintended]
    if report.get('delta_excused'):
        lines += ['', f'Δ spans excused (a serving copy killed): {len(report["delta_excused"])}']
    if report.get('state_jumps'):
        lines += ['', "state_jumps (AMCL's pose jumped: the state judge):"] + [
            f'  {x["topic"]}: {x["jump"]}, {x["at_s"]} s into the soak'
            for x in report['state_jumps']]
    lines.append('')
    lines.append('PASS: every count is 0' if report['ok'] else 'FAIL: see the counts above')
    return '\n'.join(lines)


__all__ = ['build', 'counts', 'format_report', 'resource_window_s']
