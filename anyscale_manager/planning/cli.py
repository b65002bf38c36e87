"""anyscale-manager plan FILE: choose node settings and the first layout (IROS 2016 P1/P2).

``plan --fleet A.yaml B.yaml ...`` plans Problem 1 over several robots' deployments that share
servers (planning/fleet.py) and writes each robot's part as ``plan --write`` would.
"""

import copy
import json
import math
import os
import sys
from typing import Any, Dict, List, Optional, Sequence, Tuple

import yaml

from ..model.capacity import usable_cpu
from ..model.iros2016 import split_fleet
from ..model.loader import DeploymentError, load_deployment, load_mapping
from ..model.reader import Problem
from ..model.types import Deployment
from ..model.yaml_io import read_yaml
from .fleet import FleetError, FleetPlan, merge, solve_fleet
from .instance import SETTINGS
from .plan import SOLVERS, Plan, solve

# Why a fleet may score below the same system planned as one deployment (docs/planning.md).
FLEET_BELOW_SINGLE = (
    "a fleet's plan may score below the instance planned as one deployment: there one robot's "
    "master decides for every robot, so a robot's node may run on another robot; in a fleet a "
    "robot's nodes run only on that robot and the shared servers")


def add_arguments(parser) -> None:
    parser.add_argument('file', metavar='FILE', nargs='+',
                        help='deployment YAML file (with --fleet: one per robot)')
    parser.add_argument('--fleet', action='store_true',
                        help='plan the files together as one fleet (Problem 1): each keeps its '
                             'own scales and nodes; a scale marked shared with the same name and '
                             'host in several files is one server, whose capacity their nodes '
                             'divide')
    parser.add_argument('--split-iros', action='store_true',
                        help='FILE is an IROS 2016 instance (config/iros2016/instance_N.yaml): '
                             'split it into one deployment per robot (robot 1 also takes the '
                             'experiment and the trackers), plan them as a fleet and print the '
                             'instance planned as one deployment beside it; implies --fleet')
    parser.add_argument('--write-dir', metavar='DIR', default=None,
                        help='with --fleet: write each deployment configured by the fleet plan '
                             'to DIR/<its file name>.planned.yaml (as --write does, and each '
                             "node's cpu and performance set to the planned ones, which a shared "
                             "host's claims count); with --split-iros each robot's deployment "
                             'too, DIR/<instance>_robot_<r>.yaml')
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


def _outcome(plan: Plan) -> Dict[str, Any]:
    """How a solve went, as plain JSON-ready data (a deployment's plan, a fleet's)."""
    return {
        'problem': plan.problem,
        'solver': plan.solver,
        'settings': plan.settings,
        'feasible': plan.feasible,
        'objective': None if math.isnan(plan.objective) else plan.objective,
        'optimal': plan.optimal,
        'gap': plan.gap,
        'status': plan.status,
        'solve_time_s': plan.solve_time_s,
        'violations': list(plan.violations),
    }


def plan_to_dict(d: Deployment, plan: Plan) -> Dict[str, Any]:
    """The plan as plain JSON-ready data."""
    return {
        'deployment': d.name,
        **_outcome(plan),
        'layout': {n: {'scale': p.scale, 'cpu': p.cpu, 'performance': p.performance,
                       'parameter': p.parameter or None, 'parameter_value': p.parameter_value}
                   for n, p in plan.layout.items()},
        'server_capacity': dict(plan.server_capacity),
        'scale_load': dict(plan.scale_load),
        'link_load': dict(plan.link_load),
    }


def _parameter_value(d: Deployment, node: str, value: float) -> Any:
    """The value as the node's parameter type: an integer when every profiled value is one."""
    settings = d.node(node).settings
    if settings and settings.values and all(float(v).is_integer() for v in settings.values):
        return int(round(value))
    return float(value)


def configured(source: Dict[str, Any], d: Deployment, plan: Plan,
               planned_cpu: bool = False) -> Dict[str, Any]:
    """A copy of the deployment file's data with the plan's settings and layout written in;
    ``planned_cpu``: each configured node's ``cpu`` and ``performance`` become the planned ones
    (what it uses at its setting, and what its claim on a shared host counts)."""
    out = copy.deepcopy(source)
    params = out['/**']['ros__parameters']
    for name, placement in plan.layout.items():
        if not placement.parameter or placement.parameter_value is None:
            continue
        node = params['nodes'][name]
        launch = node.setdefault('launch', {})
        launch.setdefault('parameters', {})[placement.parameter] = _parameter_value(
            d, name, placement.parameter_value)
        if planned_cpu:
            node['cpu'] = float(placement.cpu)
            node['performance'] = round(float(placement.performance), 6)
    decider = params.setdefault('decider', {})
    decider['initial_layout'] = 'explicit'
    managed = {n.name for n in d.nodes if n.managed}
    decider['layout'] = {n: p.scale for n, p in plan.layout.items() if n in managed}
    return out


def write_configured(path: str, out_path: str, d: Deployment, plan: Plan) -> None:
    """Write the configured deployment and check it loads; raises DeploymentError or OSError."""
    with open(path, encoding='utf-8') as f:
        source = yaml.safe_load(f)
    write_yaml(out_path, configured(source, d, plan),
               f'{os.path.basename(path)} configured by anyscale-manager plan --problem '
               f'{plan.problem} --solver {plan.solver} --settings {plan.settings}')


def write_yaml(out_path: str, data: Dict[str, Any], header: str) -> None:
    """Write a deployment file after checking it loads (never one the agents would refuse);
    raises DeploymentError or OSError."""
    load_mapping(data, out_path)
    tmp = f'{out_path}.tmp'
    with open(tmp, 'w', encoding='utf-8') as f:
        f.write(f'# {header}\n')
        yaml.safe_dump(data, f, sort_keys=False, default_flow_style=None, width=99)
    os.replace(tmp, out_path)


def _node_table(plan: Plan) -> List[str]:
    """One line per node: scale, CPU, the parameter value to set, performance."""
    lines = []
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
    return lines


def _proof(plan: Plan) -> str:
    return ('proven optimal' if plan.optimal else
            f'not proven optimal (gap {100 * plan.gap:.3g}%)' if plan.gap is not None else
            'not proven optimal')


def render(d: Deployment, plan: Plan) -> str:
    """A readable report: the node table, objective, per-computer and per-link loads."""
    what = ('maximise performance' if plan.problem == 1 else 'minimise server capacity')
    lines = [f'{d.name}: problem {plan.problem} ({what}), solver {plan.solver}, '
             f'settings {plan.settings}', '']
    lines += _node_table(plan)
    lines.append('')
    unit = 'weighted performance' if plan.problem == 1 else 'total server capacity'
    lines.append(f'objective: {plan.objective:.4f} ({unit}); {_proof(plan)}; '
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


def _say_problems(source: str, problems: Sequence[Any]) -> None:
    print(f'{source}: {len(problems)} problem(s):', file=sys.stderr)
    for p in problems:
        print(f'  {p}', file=sys.stderr)


def _usage_error(args) -> str:
    """What is wrong with the command line's combination of options ('' when nothing)."""
    fleet = args.fleet or args.split_iros
    if not (args.time_limit > 0 and math.isfinite(args.time_limit)):
        return f'--time-limit must be a positive number of seconds, got {args.time_limit}'
    if not fleet:
        if len(args.file) > 1:
            return (f'{len(args.file)} files given: plan takes one deployment, or several '
                    "robots' deployments with --fleet")
        if args.write_dir:
            return '--write-dir goes with --fleet (one deployment: --write OUT)'
        return ''
    if args.problem != 1:
        return '--fleet plans Problem 1 (maximise performance) only'
    if args.write:
        return '--fleet writes one file per deployment: --write-dir DIR, not --write'
    if args.split_iros and len(args.file) != 1:
        return f'--split-iros takes one IROS 2016 instance file, got {len(args.file)}'
    return ''


def run(args) -> int:
    wrong = _usage_error(args)
    if wrong:
        print(f'anyscale-manager plan: {wrong}', file=sys.stderr)
        return 2
    if args.fleet or args.split_iros:
        return run_fleet(args)
    path = args.file[0]
    try:
        d = load_deployment(path)
    except DeploymentError as e:
        _say_problems(path, e.problems)
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
        print(f'{path}: no feasible layout for problem {args.problem} '
              f'(solver {args.solver}); constraints that cannot be met:', file=sys.stderr)
        for v in plan.violations:
            print(f'  - {v}', file=sys.stderr)
        return 1
    if not args.json:
        print(render(d, plan))
    if args.write:
        try:
            write_configured(path, args.write, d, plan)
        except (OSError, DeploymentError) as e:
            print(f'anyscale-manager plan: cannot write {args.write}: {e}', file=sys.stderr)
            return 2
        print(f'configured deployment written to {args.write}', file=sys.stderr)
    return 0


# --- a fleet ----------------------------------------------------------------------------------
def _stem(path: str) -> str:
    base = os.path.basename(path)
    for ext in ('.yaml', '.yml'):
        if base.endswith(ext):
            return base[:-len(ext)]
    return base


def fleet_to_dict(fp: FleetPlan) -> Dict[str, Any]:
    """The fleet's plan as plain JSON-ready data: the whole, each deployment's part, and each
    shared scale's use by deployment."""
    plan = fp.plan
    use = fp.shared_use()
    return {
        'fleet': [d.name for d in fp.fleet.members],
        **_outcome(plan),
        'deployments': {d.name: dict(plan_to_dict(d, fp.members[d.name]), file=d.source)
                        for d in fp.fleet.members},
        'shared': {name: {'host': s.host, 'capacity_cpu': s.capacity_cpu,
                          'usable_cpu': s.usable_cpu, 'use': use[name],
                          'total_cpu': sum(use[name].values())}
                   for name, s in fp.fleet.shared.items()},
    }


def _percent(part: float, whole: float) -> str:
    return f'{100 * part / whole:.0f}%' if whole else '-'


def render_fleet(fp: FleetPlan) -> str:
    """Per deployment its node table and computers; each shared scale's use by deployment
    against its capacity; the fleet's objective."""
    plan = fp.plan
    members = fp.fleet.members
    lines = [f'fleet of {len(members)} deployment(s): problem 1 (maximise performance), '
             f'solver {plan.solver}, settings {plan.settings}']
    for d in members:
        part = fp.members[d.name]
        lines += ['', f'{d.name} ({d.source}): weighted performance {part.objective:.4f}']
        lines += _node_table(part)
        lines.append('computers:')
        for s in d.scales:
            load = part.scale_load.get(s.name, 0.0)
            if s.shared:
                lines.append(f'  {s.name:<10} {s.kind:<7} CPU {_num(load):>7}  its share of '
                             f'the shared {fp.fleet.scale_names[d.name, s.name]} (below)')
            else:
                cap = usable_cpu(s.capacity_cpu, d.decider)
                lines.append(f'  {s.name:<10} {s.kind:<7} CPU {_num(load):>7} of {_num(cap):>7}'
                             f'  {_percent(load, cap)} used')
        if d.links:
            lines.append('links (both directions summed):')
            for link in d.links:
                lines.append(f'  {link.name:<14} {link.ends[0]} <-> {link.ends[1]}  '
                             f'{_num(part.link_load.get(link.name, 0.0))} of '
                             f'{_num(link.bandwidth_kbps)} kbit/s')
    use = fp.shared_use()
    if fp.fleet.shared:
        lines += ['', 'shared scales (one machine each: its capacity counted once):']
        width = max(len('together'), *(len(d.name) for d in members))
        for name, share in fp.fleet.shared.items():
            lines.append(f'  {name} (host {share.host}): capacity {_num(share.capacity_cpu)}, '
                         f'usable {_num(share.usable_cpu)}')
            for user, cpu in use[name].items():
                lines.append(f'    {user:<{width}}  CPU {_num(cpu):>7}')
            total = sum(use[name].values())
            lines.append(f'    {"together":<{width}}  CPU {_num(total):>7} of '
                         f'{_num(share.usable_cpu):>7}  {_percent(total, share.usable_cpu)} '
                         'used')
    lines += ['', f'fleet objective: {plan.objective:.4f} (weighted performance of every '
                  f'robot); {_proof(plan)}; solved in {plan.solve_time_s:.3f} s']
    return '\n'.join(lines)


def _fleet_sources(args) -> Tuple[List[Tuple[str, Dict[str, Any]]], List[Problem],
                                  Optional[Tuple[str, Deployment, Tuple[str, ...]]]]:
    """(where each deployment is read from or will be written, its data), the problems of
    reading them, and with --split-iros (the instance file, its deployment, the connections
    between two robots' nodes)."""
    problems: List[Problem] = []
    sources: List[Tuple[str, Dict[str, Any]]] = []
    if not args.split_iros:
        for path in args.file:
            try:
                sources.append((path, read_yaml(path)))
            except DeploymentError as e:
                problems += e.problems
        return sources, problems, None
    path = args.file[0]
    try:
        original = load_deployment(path)
        split = split_fleet(read_yaml(path))
    except DeploymentError as e:
        return [], e.problems, None
    except (KeyError, TypeError, ValueError) as e:
        return [], [Problem(path, '', f'not an IROS 2016 instance to split by robot ({e})')], None
    for r, (robot, data) in enumerate(split.members, start=1):
        where = (os.path.join(args.write_dir, f'{_stem(path)}_robot_{r}.yaml')
                 if args.write_dir else f'{path} (robot {r}: {robot})')
        sources.append((where, data))
    return sources, problems, (path, original, split.crossing)


def run_fleet(args) -> int:
    sources, problems, iros = _fleet_sources(args)
    members: List[Deployment] = []
    for where, data in sources:
        try:
            members.append(load_mapping(data, where))
        except DeploymentError as e:
            problems += e.problems
    if problems:
        _say_problems(', '.join(args.file), problems)
        return 2
    outputs: Dict[str, str] = {}
    if args.write_dir:
        for (where, _), d in zip(sources, members):
            out = os.path.join(args.write_dir, f'{_stem(where)}.planned.yaml')
            if out in outputs:
                print(f'anyscale-manager plan: {where} and {outputs[out]} would both be '
                      f'written to {out}: give the files different names', file=sys.stderr)
                return 2
            outputs[out] = where
    try:
        fleet = merge(members)
    except FleetError as e:
        _say_problems(f'the fleet of {", ".join(d.source for d in members)}', e.problems)
        return 2
    for note in fleet.notes:
        print(f'anyscale-manager plan: note: {note}', file=sys.stderr)
    try:
        fp = solve_fleet(members, solver=args.solver, settings=args.settings,
                         time_limit_s=args.time_limit, fleet=fleet)
        single = None
        if iros is not None:
            single = solve(iros[1], problem=1, solver=args.solver, settings=args.settings,
                           time_limit_s=args.time_limit)
    except ImportError as e:
        print(f'anyscale-manager plan: {e}', file=sys.stderr)
        return 2
    if args.json:
        report = fleet_to_dict(fp)
        if iros is not None and single is not None:
            report['single_deployment'] = {
                'file': iros[0], 'feasible': single.feasible, 'optimal': single.optimal,
                'objective': None if math.isnan(single.objective) else single.objective}
            report['crossing_connections'] = list(iros[2])
        print(json.dumps(report, indent=2))
    if not fp.feasible:
        print(f'the fleet of {", ".join(d.source for d in members)}: no feasible layout '
              f'(solver {args.solver}); constraints that cannot be met (names are '
              '<deployment>/<name>):', file=sys.stderr)
        for v in fp.plan.violations:
            print(f'  - {v}', file=sys.stderr)
        return 1
    if not args.json:
        print(render_fleet(fp))
        if iros is not None and single is not None:
            print(_compare_single(fp, iros[0], single, iros[2]))
    if args.write_dir:
        return _write_fleet(args, sources, members, fp, iros is not None)
    return 0


def _compare_single(fp: FleetPlan, path: str, single: Plan, crossing: Sequence[str]) -> str:
    """The fleet's objective beside the instance planned as one deployment, and why they may
    differ."""
    lines = ['']
    if single.feasible:
        ratio = (f' ({100 * fp.plan.objective / single.objective:.2f}% of it)'
                 if single.objective > 0 else '')
        lines.append(f'the instance as one deployment ({path}): {single.objective:.4f}, '
                     f'{_proof(single)}; the fleet: {fp.plan.objective:.4f}{ratio}')
    else:
        lines.append(f'the instance as one deployment ({path}): no feasible layout')
    lines.append(f'({FLEET_BELOW_SINGLE})')
    if crossing:
        lines.append("connections between two robots' nodes, in no deployment (each robot is "
                     f'a ROS domain of its own): {", ".join(crossing)}')
    return '\n'.join(lines)


def _write_fleet(args, sources: Sequence[Tuple[str, Dict[str, Any]]],
                 members: Sequence[Deployment], fp: FleetPlan, split: bool) -> int:
    """Each robot's deployment (with --split-iros) and its configured copy, into --write-dir."""
    names = ', '.join(d.name for d in members)
    try:
        os.makedirs(args.write_dir, exist_ok=True)
        for (where, data), d in zip(sources, members):
            if split:
                write_yaml(where, data, f'{d.name}: one robot of {args.file[0]}, split by '
                                        'anyscale-manager plan --split-iros')
            out = os.path.join(args.write_dir, f'{_stem(where)}.planned.yaml')
            write_yaml(out, configured(data, d, fp.members[d.name], planned_cpu=True),
                       f'{os.path.basename(where)} configured by anyscale-manager plan --fleet '
                       f'(with {names}) --solver {args.solver} --settings {args.settings}')
            print(f'{d.name}: configured deployment written to {out}', file=sys.stderr)
    except (OSError, DeploymentError) as e:
        print(f'anyscale-manager plan: cannot write into {args.write_dir}: {e}', file=sys.stderr)
        return 2
    return 0
