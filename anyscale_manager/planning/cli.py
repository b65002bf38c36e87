"""anyscale-manager plan FILE: choose node settings and the first layout (IROS 2016 P1/P2)."""

import copy
import json
import math
import os
import sys
from typing import Any, Dict

import yaml

from ..model.capacity import usable_cpu
from ..model.loader import DeploymentError, load_deployment, load_mapping
from ..model.types import Deployment
from .instance import SETTINGS
from .plan import SOLVERS, Plan, solve


def add_arguments(parser) -> None:
    parser.add_argument('file', metavar='FILE', help='deployment YAML file')
    parser.add_argument('--problem', type=int, choices=(1, 2), default=1,
                        help='1: maximise performance (default); 2: minimise server capacity')
    parser.add_argument('--solver', choices=SOLVERS, default='greedy',
                        help='greedy: the paper greedy plus local search (default); '
                             'paper-greedy: Algorithms 1-3 as published; exact: MILP (HiGHS)')
    parser.add_argument('--settings', choices=SETTINGS, default='continuous',
                        help='continuous: any integer CPU share between the samples (default); '
                             'discrete: one of the profiled samples')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('--time-limit', type=float, default=10.0, metavar='S',
                        help='time limit in seconds (exact solver; local search)')
    parser.add_argument('--write', metavar='OUT', default=None,
                        help='write a copy of FILE configured by the plan: each configurable '
                             "node's chosen parameter value in launch.parameters (named by "
                             'settings.parameter) and the layout as decider.layout with '
                             'initial_layout explicit, for the agents and the decider to run')


def _num(x: float) -> str:
    return f'{x:.6g}'


def plan_to_dict(d: Deployment, plan: Plan) -> Dict[str, Any]:
    """The plan as plain JSON-ready data."""
    return {
        'deployment': d.name,
        'problem': plan.problem,
        'solver': plan.solver,
        'settings': plan.settings,
        'feasible': plan.feasible,
        'objective': None if math.isnan(plan.objective) else plan.objective,
        'optimal': plan.optimal,
        'gap': plan.gap,
        'status': plan.status,
        'solve_time_s': plan.solve_time_s,
        'layout': {n: {'scale': p.scale, 'cpu': p.cpu, 'performance': p.performance,
                       'parameter': p.parameter or None, 'parameter_value': p.parameter_value}
                   for n, p in plan.layout.items()},
        'server_capacity': dict(plan.server_capacity),
        'scale_load': dict(plan.scale_load),
        'link_load': dict(plan.link_load),
        'violations': list(plan.violations),
    }


def _parameter_value(d: Deployment, node: str, value: float) -> Any:
    """The value as the node's parameter type: an integer when every profiled value is one."""
    settings = d.node(node).settings
    if settings and settings.values and all(float(v).is_integer() for v in settings.values):
        return int(round(value))
    return float(value)


def configured(source: Dict[str, Any], d: Deployment, plan: Plan) -> Dict[str, Any]:
    """A copy of the deployment file's data with the plan's settings and layout written in."""
    out = copy.deepcopy(source)
    params = out['/**']['ros__parameters']
    for name, placement in plan.layout.items():
        if not placement.parameter or placement.parameter_value is None:
            continue
        node = params['nodes'][name]
        launch = node.setdefault('launch', {})
        launch.setdefault('parameters', {})[placement.parameter] = _parameter_value(
            d, name, placement.parameter_value)
    decider = params.setdefault('decider', {})
    decider['initial_layout'] = 'explicit'
    managed = {n.name for n in d.nodes if n.managed}
    decider['layout'] = {n: p.scale for n, p in plan.layout.items() if n in managed}
    return out


def write_configured(path: str, out_path: str, d: Deployment, plan: Plan) -> None:
    """Write the configured deployment and check it loads; raises DeploymentError or OSError."""
    with open(path, encoding='utf-8') as f:
        source = yaml.safe_load(f)
    data = configured(source, d, plan)
    load_mapping(data, out_path)   # never write a file the agents would refuse
    tmp = f'{out_path}.tmp'
    with open(tmp, 'w', encoding='utf-8') as f:
        f.write(f'# {os.path.basename(path)} configured by anyscale-manager plan '
                f'--problem {plan.problem} --solver {plan.solver} --settings {plan.settings}\n')
        yaml.safe_dump(data, f, sort_keys=False, default_flow_style=None, width=99)
    os.replace(tmp, out_path)


def render(d: Deployment, plan: Plan) -> str:
    """A readable report: the node table, objective, per-computer and per-link loads."""
    what = ('maximise performance' if plan.problem == 1 else 'minimise server capacity')
    lines = [f'{d.name}: problem {plan.problem} ({what}), solver {plan.solver}, '
             f'settings {plan.settings}', '']
    width = max([len('node')] + [len(n) for n in plan.layout])
    lines.append(f'{"node":<{width}}  {"scale":<10} {"CPU":>7}  {"parameter value":<32} '
                 f'{"performance":>11}')
    for name, p in plan.layout.items():
        param = '-'
        if p.parameter:
            value = '?' if p.parameter_value is None else _num(p.parameter_value)
            param = f'{p.parameter}={value}'
        lines.append(f'{name:<{width}}  {p.scale:<10} {_num(p.cpu):>7}  {param:<32} '
                     f'{p.performance:>11.2f}')
    lines.append('')
    unit = 'weighted performance' if plan.problem == 1 else 'total server capacity'
    proof = ('proven optimal' if plan.optimal else
             f'not proven optimal (gap {100 * plan.gap:.3g}%)' if plan.gap is not None else
             'not proven optimal')
    lines.append(f'objective: {plan.objective:.4f} ({unit}); {proof}; '
                 f'solved in {plan.solve_time_s:.3f} s')
    lines.append('computers:')
    for s in d.scales:
        load = plan.scale_load.get(s.name, 0.0)
        if s.name in plan.server_capacity:
            cap = plan.server_capacity[s.name]
            note = 'capacity grown to its load'
        else:
            cap = usable_cpu(s.capacity_cpu, d.decider)
            note = f'{100 * load / cap:.0f}% used' if cap else ''
            note += (f' (usable: capacity {_num(s.capacity_cpu)} x cpu_headroom '
                     f'{d.decider.cpu_headroom:g})')
        lines.append(f'  {s.name:<10} {s.kind:<7} CPU {_num(load):>7} of {_num(cap):>7}  {note}')
    if d.links:
        lines.append('links (both directions summed):')
        for link in d.links:
            load = plan.link_load.get(link.name, 0.0)
            lines.append(f'  {link.name:<14} {link.ends[0]} <-> {link.ends[1]}  '
                         f'{_num(load)} of {_num(link.bandwidth_kbps)} kbit/s')
    return '\n'.join(lines)


def run(args) -> int:
    try:
        d = load_deployment(args.file)
    except DeploymentError as e:
        print(f'{args.file}: {len(e.problems)} problem(s):', file=sys.stderr)
        for p in e.problems:
            print(f'  {p}', file=sys.stderr)
        return 2
    if not (args.time_limit > 0 and math.isfinite(args.time_limit)):
        print(f'--time-limit must be a positive number of seconds, got {args.time_limit}',
              file=sys.stderr)
        return 2
    try:
        plan = solve(d, problem=args.problem, solver=args.solver, settings=args.settings,
                     time_limit_s=args.time_limit)
    except ImportError as e:
        print(f'anyscale-manager plan: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(plan_to_dict(d, plan), indent=2))
    if not plan.feasible:
        print(f'{args.file}: no feasible layout for problem {args.problem} '
              f'(solver {args.solver}); constraints that cannot be met:', file=sys.stderr)
        for v in plan.violations:
            print(f'  - {v}', file=sys.stderr)
        return 1
    if not args.json:
        print(render(d, plan))
    if args.write:
        try:
            write_configured(args.file, args.write, d, plan)
        except (OSError, DeploymentError) as e:
            print(f'anyscale-manager plan: cannot write {args.write}: {e}', file=sys.stderr)
            return 2
        print(f'configured deployment written to {args.write}', file=sys.stderr)
    return 0
