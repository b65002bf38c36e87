"""anyscale-manager validate FILE...: check deployments and print a readable summary."""

import sys
import textwrap
from typing import List, Tuple

from .advice import single_machine, warnings
from .loader import DeploymentError, did_you_mean, load_deployment
from .types import Deployment
from ..protocol_auth import KeyFileError, load_key


def add_arguments(parser) -> None:
    parser.add_argument('files', nargs='+', metavar='FILE', help='deployment YAML files')
    parser.add_argument('--quiet', action='store_true', help='print only errors and warnings')
    parser.add_argument('--scale', metavar='NAME',
                        help='validate for the scale this machine is: a node that may run on it '
                             'and cannot be started here is an error (without it, a warning); '
                             'the launches of nodes that never run on it are not checked')


def _fmt(x) -> str:
    return '-' if x is None else f'{x:g}'


def _crosses(d: Deployment, publisher: str, subscriber: str) -> str:
    """', may cross wifi, backhaul': the links a placement the file allows can make the
    connection cross (none: both ends always share a scale)."""
    if publisher not in d.node_names or subscriber not in d.node_names:
        return ''
    ends = {frozenset((a, b)) for a in d.allowed_scales(publisher)
            for b in d.allowed_scales(subscriber) if a != b}
    links = [link.name for link in d.links if frozenset(link.ends) in ends]
    return f', may cross {", ".join(links)}' if links else ''


def summary(d: Deployment) -> str:
    about = f' ({d.description})' if d.description else ''
    lines = [f'{d.source}: deployment {d.name!r}{about}']
    lines.append(f'  scales ({len(d.scales)}):')
    for s in d.scales:
        lines.append(f'    {s.name:<14} {s.role:<6} {s.kind:<6} capacity {s.capacity_cpu:g} '
                     f'({s.cores} x {s.clock_ghz:g} GHz, gain {s.gain:g}) host {s.host} '
                     f'port {d.scale_port(s.name)}')
    if d.links:
        lines.append(f'  links ({len(d.links)}; each watched by the agent of one end):')
        for link in d.links:
            lines.append(f'    {link.name:<14} {link.ends[0]} <-> {link.ends[1]} '
                         f'{link.bandwidth_kbps:g} kbit/s {link.medium}, watched by '
                         f'{d.link_monitor(link)}')
    names = d.scale_names
    unlinked = [f'{a} <-> {b}' for i, a in enumerate(names) for b in names[i + 1:]
                if d.link_between(a, b) is None]
    if unlinked and len(names) > 1:
        lines.append(f'  no link: {", ".join(unlinked)} (a connection between nodes placed '
                     'there is a bandwidth violation: nothing routes)')
    critical = set(d.critical_nodes)
    providers = set(d.data_providers)
    migratable = set(d.migratable_nodes)
    # A file for planning only has no launch anywhere: no node of it migrates, nothing to say.
    runnable = any(n.launch.startable for n in d.nodes)
    lines.append(f'  nodes ({len(d.nodes)}; migratable: {", ".join(d.migratable_nodes) or "none"}'
                 f'; critical: {", ".join(d.critical_nodes) or "none"}):')
    for n in d.nodes:
        tags = []
        if n.name in migratable:
            tags.append('migratable')
        if n.name in critical:
            tags.append(f'critical ({d.why_critical(n.name)})')
        if n.name in providers:
            tags.append(f'data provider ({d.why_data_provider(n.name)})')
        if not n.managed:
            tags.append('not managed')
        elif n.name not in migratable and n.name not in critical and runnable \
                and not (n.name in providers and not n.residence):
            tags.append(f'not migratable ({d.why_not_migratable(n.name)})')
        if n.lifecycle:
            standby = d.standby_scales(n.name)
            tags.append(f'lifecycle, standby on {", ".join(standby)}' if standby else 'lifecycle')
        if n.configurable:
            tags.append(f'configurable {n.settings.parameter}')
        allowed = d.allowed_scales(n.name)
        where = 'any scale' if len(allowed) == len(d.scales) else ', '.join(allowed)
        lines.append(f'    {n.name:<14} cpu {n.cpu:<6g} on {where:<16} {", ".join(tags)}'.rstrip())
    if d.connections:
        lines.append(f'  connections ({len(d.connections)}):')
        for c in d.connections:
            lines.append(f'    {c.name:<20} {c.publisher} -> {c.subscriber} on {c.topic}: '
                         f'min {_fmt(c.freq_min_hz)} Hz, opt {_fmt(c.freq_opt_hz)} Hz, '
                         f'tolerance {_fmt(c.tolerance_s)} s, {c.bandwidth_kbps:g} kbit/s'
                         + _crosses(d, c.publisher, c.subscriber))
    shared = single_machine(d)
    if shared:
        lines += textwrap.wrap(shared, 99, initial_indent='  ', subsequent_indent='    ')
    return '\n'.join(lines)


def machine_check(d: Deployment, scale: str = '') -> Tuple[List[str], List[str]]:
    """(errors, warnings) about launches this machine cannot start; with ``scale``, the file is
    validated for that scale: its nodes' launches are errors, other nodes' are not looked at."""
    # The command asks how an agent here would resolve each launch; the model itself knows
    # nothing of agents.
    from ..agent.launch_check import launch_problems
    errors, notes = [], []
    for node, problem in launch_problems(d).items():
        if not scale:
            notes.append(f'{d.source}: nodes.{node}.launch: {problem}: an agent on this machine '
                         'cannot start it (validate --scale NAME makes this an error)')
        elif scale in d.allowed_scales(node):
            errors.append(f'{d.source}: nodes.{node}.launch: {problem}: the agent of scale '
                          f'{scale}, on this machine, cannot start it')
    return errors, notes


def run(args) -> int:
    failed = False
    scale = args.scale or ''
    for path in args.files:
        try:
            d = load_deployment(path)
        except DeploymentError as e:
            failed = True
            _print_problems(path, [str(p) for p in e.problems])
            continue
        problems = []
        if scale and scale not in d.scale_names:
            problems.append(f'{path}: --scale: unknown scale {scale!r}'
                            f'{did_you_mean(scale, d.scale_names)}; the scales of this file '
                            f'are {", ".join(d.scale_names)}')
        if d.security.key_file:
            try:
                load_key(d.security.key_file)
            except KeyFileError as e:
                problems.append(f'{path}: {e}')
        errors, notes = machine_check(d, scale if scale in d.scale_names else '')
        problems += errors
        if problems:
            failed = True
            _print_problems(path, problems)
            continue
        if not args.quiet:
            # Flushed before the warnings (stderr): on one terminal or pipe they follow it on
            # lines of their own, never inside it.
            print(summary(d), flush=True)
        for w in warnings(d) + notes:
            print(f'warning: {w}', file=sys.stderr)
    return 2 if failed else 0


def _print_problems(path: str, problems: List[str]) -> None:
    print(f'{path}: {len(problems)} problem(s):', file=sys.stderr)
    for p in problems:
        print(f'  {p}', file=sys.stderr)
