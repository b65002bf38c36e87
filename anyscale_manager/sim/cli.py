"""anyscale-manager simulate: the ICAR 2015 evaluation (Fig. 7) in simulation, without ROS; with
--fleet, N robots sharing K servers (sim/fleet.py)."""

import argparse
import json
import math
import re
import sys
from dataclasses import replace
from typing import Dict, List, Optional, Tuple

from ..model.loader import DeploymentError
from ..model.types import HYSTERESIS_SCOPES
from . import fleet_cli, report
from .fleet import run_fleet_runs
from .model import LINK_MODES, PathModel
from .runner import HEURISTIC, PLANNER, POLICIES, Experiment, run_experiment
from .systems import FIG7_SCALES, FIG7_TYPES, build_system

DEFAULT_OUT = 'simulation'
SYSTEM_RE = re.compile(r'^\s*(\d+)\s*[nN]?\s*[xX]\s*(\d+)\s*[mM]?\s*[xX]\s*(\d+)\s*[kK]?\s*$')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--runs', type=int, metavar='N',
                        help='seeded runs per system (default 10; the paper used 3; 1 with '
                             '--fleet)')
    parser.add_argument('--seed', type=int, default=0, metavar='S',
                        help='base seed: same seed, same results (default 0)')
    parser.add_argument('--out', metavar='DIR',
                        help='directory for fig7.png, fig7.csv and runs.csv '
                             f'(default ./{DEFAULT_OUT})')
    parser.add_argument('--json', action='store_true',
                        help='print one JSON object instead of a table')
    parser.add_argument('--policy', choices=POLICIES, default=HEURISTIC,
                        help='heuristic: the runtime policy (Algorithm 1); planner: the '
                             'planner-backed policy (default heuristic)')
    parser.add_argument('--compare', action='store_true',
                        help='also run the other policy and report both')
    parser.add_argument('--systems', metavar='LIST',
                        help='comma-separated NxMxK systems (default: the nine of Fig. 7, '
                             'N/M in 6/2, 12/6, 18/9 and K in 2, 3, 4)')
    parser.add_argument('--links', choices=LINK_MODES, default=PathModel.links,
                        help='independent: each remote scale has its own coverage holes '
                             '(default); shared: one hole pattern for every link')
    parser.add_argument('--availability', nargs=2, type=float, metavar=('LOW', 'HIGH'),
                        default=(PathModel.availability_low, PathModel.availability_high),
                        help='share of the path a link is up, drawn uniformly (default 0.45 0.65)')
    parser.add_argument('--outages', nargs=2, type=int, metavar=('MIN', 'MAX'),
                        default=(PathModel.outages_min, PathModel.outages_max),
                        help='coverage holes per lap and link, drawn uniformly (default 1 3)')
    parser.add_argument('--migration-delay', type=float, default=PathModel.migration_delay_s,
                        metavar='S', help='seconds a moved node needs to start (default 2)')
    parser.add_argument('--standby-resume', type=float, default=PathModel.standby_resume_s,
                        metavar='S', help='seconds a standby copy needs to serve once activated '
                                          f'(default {PathModel.standby_resume_s:g})')
    parser.add_argument('--hysteresis', type=float, metavar='S',
                        help="override the decider's hysteresis T in seconds (default: each "
                             "deployment's own, 20 s for the test-bed)")
    parser.add_argument('--hysteresis-scope', choices=HYSTERESIS_SCOPES,
                        help="override the decider's hysteresis scope: scale (T bars only the "
                             "scale a node came back from) or node (the paper's literal rule: "
                             "any scale); default: each deployment's own")
    parser.add_argument('--testbed', metavar='FILE',
                        help='the test-bed deployment file (default: the installed '
                             'icar2015_testbed.yaml)')
    parser.add_argument('--no-oracle', action='store_true', help='skip the oracle bound')
    fleet_cli.add_arguments(parser)


def parse_systems(text: Optional[str]) -> List[Tuple[int, int, int]]:
    if not text:
        return [(n, m, k) for n, m in FIG7_TYPES for k in FIG7_SCALES]
    out = []
    for part in text.split(','):
        match = SYSTEM_RE.match(part)
        if not match:
            raise ValueError(f'--systems: {part.strip()!r} is not NxMxK (for example 6x2x2)')
        n, m, k = (int(g) for g in match.groups())
        out.append((n, m, k))
    return out


def _path_model(args) -> PathModel:
    return replace(PathModel(), links=args.links, availability_low=args.availability[0],
                   availability_high=args.availability[1], outages_min=args.outages[0],
                   outages_max=args.outages[1], migration_delay_s=args.migration_delay,
                   standby_resume_s=args.standby_resume)


def _finite(x):
    """JSON has no inf or NaN: a lap that never finished, or no oracle, becomes null."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _summary(exp: Experiment) -> dict:
    return _finite(exp.to_dict())


def _settings(args) -> Tuple[Dict[str, object], PathModel]:
    """The decider overrides and the path model the switches ask for (shared by both modes)."""
    if args.runs is not None and args.runs < 1:
        raise ValueError(f'--runs must be >= 1, got {args.runs}')
    if args.seed < 0:
        raise ValueError(f'--seed must be >= 0, got {args.seed}')
    if args.hysteresis is not None and not 0 <= args.hysteresis <= 86400:
        raise ValueError(f'--hysteresis must be in [0, 86400] s, got {args.hysteresis:g}')
    overrides: Dict[str, object] = {}
    if args.hysteresis is not None:
        overrides['hysteresis_s'] = args.hysteresis
    if args.hysteresis_scope is not None:
        overrides['hysteresis_scope'] = args.hysteresis_scope
    return overrides, _path_model(args)


def run(args) -> int:
    if args.fleet is not None:
        return run_fleet(args)
    try:
        given = [n for n in fleet_cli.FLEET_ONLY if getattr(args, n) is not None]
        if given:
            raise ValueError(f'--{given[0]} needs --fleet N')
        overrides, path = _settings(args)
        runs = 10 if args.runs is None else args.runs
        out_dir = args.out or DEFAULT_OUT
        systems = [build_system(n, m, k, args.seed, args.testbed)
                   for n, m, k in parse_systems(args.systems)]
    except (ValueError, OSError, DeploymentError) as e:
        print(f'anyscale-manager simulate: {e}', file=sys.stderr)
        return 2

    def progress(s) -> None:
        if not args.json:
            print(f'  {s.policy}: {s.label} done', file=sys.stderr, flush=True)

    exp = run_experiment(systems, runs, args.seed, args.policy, path,
                         oracle=not args.no_oracle, progress=progress, overrides=overrides)
    other = None
    if args.compare:
        name = PLANNER if args.policy == HEURISTIC else HEURISTIC
        other = run_experiment(systems, runs, args.seed, name, path,
                               oracle=not args.no_oracle, progress=progress, overrides=overrides)
    try:
        files = report.write_csv([exp] + ([other] if other else []), out_dir)
        files.append(report.write_figure(exp, out_dir, other))
    except OSError as e:
        print(f'anyscale-manager simulate: cannot write to {out_dir}: {e}', file=sys.stderr)
        return 1
    wall = exp.wall_s + (other.wall_s if other else 0.0)
    simulated = exp.simulated_s + (other.simulated_s if other else 0.0)
    if args.json:
        out = _summary(exp)
        if other:
            out['comparison'] = _summary(other)
        out['files'] = files
        print(json.dumps(out, allow_nan=False))
    else:
        print(report.table(exp, other))
        print('wrote ' + ', '.join(files))
        rate = simulated / wall if wall > 0 else math.inf
        print(f'simulated {simulated:.0f} s of robot time in {wall:.1f} s of wall time '
              f'({rate:.0f} simulated s per wall s)')
    return 0


def run_fleet(args) -> int:
    """--fleet N: N robots sharing K servers; writes no file."""
    try:
        overrides, path = _settings(args)
        spec = fleet_cli.fleet_spec(args)
        runs = 1 if args.runs is None else args.runs
    except ValueError as e:
        print(f'anyscale-manager simulate: {e}', file=sys.stderr)
        return 2

    def progress(r) -> None:
        if not args.json:
            print(f'  fleet run {r.run} done ({r.wall_s:.1f} s)', file=sys.stderr, flush=True)

    try:
        done = run_fleet_runs(spec, runs, path, args.testbed, overrides, progress)
    except (ValueError, OSError, DeploymentError) as e:
        print(f'anyscale-manager simulate: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(_finite(fleet_cli.summary(spec, path, done, overrides)),
                         allow_nan=False))
    else:
        print(fleet_cli.table(spec, done))
        wall = sum(r.wall_s for r in done)
        robot_s = sum(r.duration_s for r in done) * spec.robots
        print(f'simulated {robot_s:.0f} s of robot time in {wall:.1f} s of wall time')
    return 0
