"""anyscale-manager simulate --fleet N: the switches of a fleet (sim/fleet.py), and its runs as
a table or as the JSON object the command prints."""

import argparse
import math
import re
from dataclasses import asdict
from typing import Mapping, Sequence

from .fleet import MAX_ROBOTS, MAX_SERVERS, SERVER_CAPACITY_CPU, FleetSpec
from .fleet_figures import FleetRun, FleetSummary, percentile_ms
from .model import PathModel
from .runner import HEURISTIC

BASE_RE = re.compile(r'^\s*(\d+)\s*[nN]?\s*[xX]\s*(\d+)\s*[mM]?\s*$')
# The switches of a fleet, None unless given (they mean nothing without --fleet).
FLEET_ONLY = ('servers', 'capacity', 'priorities', 'duration', 'base')
# Fig. 7's switches, which mean nothing with --fleet.
FIG7_ONLY = ('compare', 'systems', 'no_oracle', 'out')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        'a fleet', 'N robots, each its own deployment and decider, sharing K servers through '
                   "the servers' claims ledgers (agent/ledger.py), instead of Fig. 7")
    group.add_argument('--fleet', type=int, metavar='N',
                       help=f'simulate N robots (1-{MAX_ROBOTS}); --runs defaults to 1')
    group.add_argument('--servers', type=int, metavar='K',
                       help=f'shared servers (1-{MAX_SERVERS}, default 1)')
    group.add_argument('--capacity', type=float, metavar='CPU',
                       help='capacity_cpu of each server (default '
                            f"{SERVER_CAPACITY_CPU:g}: the test-bed laptop's)")
    group.add_argument('--priorities', type=int, metavar='L',
                       help='robot i has deployment.priority i mod L (default 1: all equal)')
    group.add_argument('--duration', type=float, metavar='S',
                       help=f'seconds of each run (default {FleetSpec.duration_s:g}; the '
                            'robots drive lap after lap)')
    group.add_argument('--base', metavar='NxM',
                       help='the system each robot is (default 6x2: the test-bed)')


def fleet_spec(args: argparse.Namespace) -> FleetSpec:
    """The fleet the switches describe; a ValueError names the switch at fault."""
    for name in FIG7_ONLY:
        if getattr(args, name) not in (None, False):
            raise ValueError(f'--{name.replace("_", "-")} does not apply to --fleet')
    if args.policy != HEURISTIC:
        raise ValueError('--fleet runs the runtime policy only (--policy heuristic): the '
                         "planner-backed policy does not read a shared host's claims")
    checks = (
        (1 <= args.fleet <= MAX_ROBOTS, f'--fleet must be in 1..{MAX_ROBOTS}, got {args.fleet}'),
        (args.servers is None or 1 <= args.servers <= MAX_SERVERS,
         f'--servers must be in 1..{MAX_SERVERS}, got {args.servers}'),
        (args.capacity is None or (math.isfinite(args.capacity) and args.capacity > 0),
         f'--capacity must be > 0, got {args.capacity}'),
        (args.priorities is None or args.priorities >= 1,
         f'--priorities must be >= 1, got {args.priorities}'),
        (args.duration is None or (math.isfinite(args.duration) and 0 < args.duration <= 86400),
         f'--duration must be in (0, 86400] s, got {args.duration}'),
    )
    for ok, message in checks:
        if not ok:
            raise ValueError(message)
    n, m = FleetSpec.n, FleetSpec.m
    if args.base is not None:
        match = BASE_RE.match(args.base)
        if not match:
            raise ValueError(f'--base: {args.base.strip()!r} is not NxM (for example 12x6)')
        n, m = (int(g) for g in match.groups())
    given = {'servers': args.servers, 'capacity_cpu': args.capacity,
             'priority_levels': args.priorities, 'duration_s': args.duration}
    return FleetSpec(robots=args.fleet, n=n, m=m, seed=args.seed,
                     **{k: v for k, v in given.items() if v is not None})


def _f(x: float, digits: int = 1) -> str:
    return f'{x:.{digits}f}' if math.isfinite(x) else '-'


def _row(*cells: str) -> str:
    widths = (-5, 16, 13, 7, 8, 8, 12, 13, 9, 8, 13)
    return ' '.join(f'{c:<{-w}}' if w < 0 else f'{c:>{w}}' for c, w in zip(cells, widths))


def table(spec: FleetSpec, runs: Sequence[FleetRun]) -> str:
    """One row per run and their mean, then the servers and the robots of each run."""
    levels = ('all 0' if spec.priority_levels == 1
              else f'robot i: i mod {spec.priority_levels}')
    lines = [
        f'A fleet in simulation: {spec.robots} robot(s) of {spec.n}N x {spec.m}M sharing '
        f'{spec.servers} server(s) of {spec.capacity_cpu:g} CPU each, priorities {levels}; '
        f'{spec.duration_s:g} s per run, {len(runs)} run(s), seed {spec.seed}',
        _row('run', 'utilisation %', 'over-commit s', 'claims', 'refused', 'waiting',
             'preemptions', 'Δ violations', 'fairness', 'saved %', 'claim p50/p95'),
    ]
    for r in runs:
        lines.append(_row(str(r.run), '/'.join(_f(s.utilisation * 100) for s in r.servers),
                          _f(r.overcommit_s), str(r.claims), str(r.refused), str(r.waiting),
                          str(r.preemptions), str(r.delta_violations), _f(r.fairness, 3),
                          _f(r.improvement_pct), f'{percentile_ms(r.claim_s, 50):.2f}/'
                                                 f'{percentile_ms(r.claim_s, 95):.2f}'))
    if len(runs) > 1:
        s = FleetSummary.of(runs)
        lines.append(_row('mean', _f(s.utilisation * 100), _f(s.overcommit_s), _f(s.claims),
                          _f(s.refused), _f(s.waiting), _f(s.preemptions),
                          _f(s.delta_violations), _f(s.fairness, 3), _f(s.improvement_pct),
                          f'{s.claim_p50_ms:.2f}/{s.claim_p95_ms:.2f}'))
    for r in runs:
        servers = ', '.join(f'{s.name} peak {s.peak_claimed_cpu:g} CPU claimed, '
                            f'{s.peak_running_cpu:g} running' for s in r.servers)
        saved = sorted(x.improvement_pct for x in r.robots)
        on = sorted(x.server_time_s for x in r.robots)
        violated = ', '.join(f'{x.name} {x.delta_violations}' for x in r.robots
                             if x.delta_violations) or 'none'
        lines.append(f'run {r.run}: {servers}; saved % min {_f(saved[0])} median '
                     f'{_f(saved[len(saved) // 2])} max {_f(saved[-1])}; time on a server min '
                     f'{on[0]:.0f} median {on[len(on) // 2]:.0f} max {on[-1]:.0f} s; '
                     f'Δ violations: {violated}')
    lines.append('utilisation: CPU claimed over capacity, time-averaged, per server; fairness: '
                 "Jain's index over the robots' time with a node serving on a server; saved: "
                 'path time saved against no migration, mean over the robots; claim: one '
                 'ledger decision, ms')
    return '\n'.join(lines)


def summary(spec: FleetSpec, path: PathModel, runs: Sequence[FleetRun],
            overrides: Mapping[str, object]) -> dict:
    """The JSON object: the fleet, the model, every run and their mean."""
    return {'fleet': asdict(spec), 'model': asdict(path), 'decider_overrides': dict(overrides),
            'runs': [r.to_dict() for r in runs], 'mean': asdict(FleetSummary.of(runs))}
