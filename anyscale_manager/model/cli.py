"""anyscale-manager validate FILE...: check deployments and print a readable summary."""

import sys

from .advice import warnings
from .loader import DeploymentError, load_deployment
from .types import Deployment
from ..protocol_auth import KeyFileError, load_key


def add_arguments(parser) -> None:
    parser.add_argument('files', nargs='+', metavar='FILE', help='deployment YAML files')
    parser.add_argument('--quiet', action='store_true', help='print only errors and warnings')


def _fmt(x) -> str:
    return '-' if x is None else f'{x:g}'


def summary(d: Deployment) -> str:
    about = f' ({d.description})' if d.description else ''
    lines = [f'{d.source}: deployment {d.name!r}{about}']
    lines.append(f'  scales ({len(d.scales)}):')
    for s in d.scales:
        lines.append(f'    {s.name:<14} {s.role:<6} {s.kind:<6} capacity {s.capacity_cpu:g} '
                     f'({s.cores} x {s.clock_ghz:g} GHz, gain {s.gain:g}) host {s.host}')
    if d.links:
        lines.append(f'  links ({len(d.links)}):')
        for link in d.links:
            lines.append(f'    {link.name:<14} {link.ends[0]} <-> {link.ends[1]} '
                         f'{link.bandwidth_kbps:g} kbit/s {link.medium}')
    critical = set(d.critical_nodes)
    providers = set(d.data_providers)
    migratable = set(d.migratable_nodes)
    lines.append(f'  nodes ({len(d.nodes)}; migratable: {", ".join(d.migratable_nodes) or "none"}'
                 f'; critical: {", ".join(d.critical_nodes) or "none"}):')
    for n in d.nodes:
        tags = []
        if n.name in migratable:
            tags.append('migratable')
        if n.name in critical:
            tags.append('critical')
        if n.name in providers:
            tags.append('data provider')
        if not n.managed:
            tags.append('not managed')
        if n.lifecycle:
            standby = d.standby_scales(n.name)
            tags.append(f'lifecycle, standby on {", ".join(standby)}' if standby else 'lifecycle')
        if n.configurable:
            tags.append(f'configurable {n.settings.parameter}')
        allowed = d.allowed_scales(n.name)
        where = 'any scale' if len(allowed) == len(d.scales) else ', '.join(allowed)
        lines.append(f'    {n.name:<14} cpu {n.cpu:<6g} on {where:<16} {", ".join(tags)}')
    if d.connections:
        lines.append(f'  connections ({len(d.connections)}):')
        for c in d.connections:
            lines.append(f'    {c.name:<20} {c.publisher} -> {c.subscriber} on {c.topic}: '
                         f'min {_fmt(c.freq_min_hz)} Hz, opt {_fmt(c.freq_opt_hz)} Hz, '
                         f'tolerance {_fmt(c.tolerance_s)} s, {c.bandwidth_kbps:g} kbit/s')
    return '\n'.join(lines)


def run(args) -> int:
    failed = False
    for path in args.files:
        try:
            d = load_deployment(path)
        except DeploymentError as e:
            failed = True
            print(f'{path}: {len(e.problems)} problem(s):', file=sys.stderr)
            for p in e.problems:
                print(f'  {p}', file=sys.stderr)
            continue
        if d.security.key_file:
            try:
                load_key(d.security.key_file)
            except KeyFileError as e:
                failed = True
                print(f'{path}: 1 problem(s):\n  {path}: {e}', file=sys.stderr)
                continue
        if not args.quiet:
            print(summary(d))
        for w in warnings(d):
            print(f'warning: {w}', file=sys.stderr)
    return 2 if failed else 0
