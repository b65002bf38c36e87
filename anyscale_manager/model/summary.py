"""A deployment in words: what validate prints for a file it accepts.

Pure: a deployment in, text out; what the file declares and what follows from it (which nodes
may move, which are pinned and why, the links each connection may cross).
"""

import os
import textwrap
from typing import Optional

from .advice import single_machine
from .discovery import ENV_SERVERS, ENV_SUPER_CLIENT, domain_of, server_list, uses_servers
from .types import Deployment, Scale


def _fmt(x: Optional[float]) -> str:
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


def _worth(d: Deployment, s: Scale) -> str:
    if s.gain is not None:
        return f'worth {s.gain:g} (gain)'
    return f'worth {d.worth(s.name):.3g} (from its power)'


def summary(d: Deployment) -> str:
    """The deployment, one line per scale, link, node and connection."""
    about = f' ({d.description})' if d.description else ''
    lines = [f'{d.source}: deployment {d.name!r}{about}']
    lines.append(f'  scales ({len(d.scales)}):')
    for s in d.scales:
        lines.append(f'    {s.name:<14} {s.role:<6} {s.kind:<6} capacity {s.capacity_cpu:g} '
                     f'({s.cores} x {s.clock_ghz:g} GHz, {_worth(d, s)}) host {s.host} '
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
        if n.settings is not None and n.settings.configurable:
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
    if uses_servers(d):
        domain = domain_of(os.environ)
        lines.append(f'  discovery: through a server on each scale (ROS domain {domain}); a '
                     f'shell for ros2 tools (then ros2 daemon stop): export '
                     f'{ENV_SERVERS}="{server_list(d, domain)}" {ENV_SUPER_CLIENT}=TRUE')
    shared = single_machine(d)
    if shared:
        lines += textwrap.wrap(shared, 99, initial_indent='  ', subsequent_indent='    ')
    return '\n'.join(lines)
