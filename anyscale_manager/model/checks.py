"""The whole-deployment checks: how the sections of a file fit together.

Each check takes the deployment as read and what the reading found (which values were not read
as written, the names each collection declares) and returns its problems. They run in the order
of CHECKS, on whatever was read, so that a typo in one key does not hide a contradiction
elsewhere in the same file; each problem marks its path damaged before the next check runs, and
a check that depends on a damaged value stays quiet rather than repeat a problem.
"""

from dataclasses import replace
from typing import Callable, Collection, Dict, FrozenSet, List, Set, Tuple

from . import types as t
from .placement import allowed
from .reader import Context, Problem, did_you_mean

# A check: the deployment as read and what the reading found -> its problems.
Check = Callable[[t.Deployment, Context], List[Problem]]

LOOPBACK_HOSTS = ('localhost', '127.0.0.1', '::1', '', '0.0.0.0')

# A tolerance-0 connection pins both ends; how to pin only one of them.
PIN_ONE_END = ('to pin only the other end, mark that node critical: true and give the '
               'connection a tolerance_s above 0')


def _unknown(d: t.Deployment, read: Context, path: str, kind: str, name: str,
             known: Collection[str]) -> List[Problem]:
    """A reference to a name the file never declares. A name it declares badly (invalid, listed
    without a section, a section not listed) was reported where it is declared: not again."""
    collection = f'{kind}s'
    if collection in read.broken or str(name) in read.declared.get(collection, ()):
        return []
    return [Problem(d.source, path, f'unknown {kind} {name!r}{did_you_mean(name, known)}')]


def one_master(d: t.Deployment, read: Context) -> List[Problem]:
    masters = [s.name for s in d.scales if s.is_master]
    if len(masters) == 1 or not read.all_read('scales', 'role'):
        return []
    return [Problem(d.source, 'scales', f'expected exactly one scale with role master, got '
                                        f'{len(masters)}'
                    + (f' ({", ".join(masters)})' if masters else ''))]


def shared_scales(d: t.Deployment, read: Context) -> List[Problem]:
    """A shared scale is another machine this deployment uses beside others: never its master,
    which is the robot's own and runs its decider."""
    return [Problem(d.source, f'scales.{s.name}.shared',
                    f"the master scale {s.name!r} cannot be shared: it runs this deployment's "
                    'decider; share the servers, each robot keeps its own master')
            for s in d.scales if s.shared and s.is_master]


def ports(d: t.Deployment, read: Context) -> List[Problem]:
    """Each scale's warden and probe server take one port on its host: two scales of one host
    must not share it."""
    if not read.all_read('scales', 'port', 'host') \
            or read.damaged('monitoring.bandwidth_probe_port'):
        return []
    out = []
    taken: Dict[Tuple[str, int], str] = {}
    for s in d.scales:
        port = d.scale_port(s.name)
        where = f'scales.{s.name}.port'
        if port > 65535:
            out.append(Problem(d.source, where, f'no port of its own, and '
                                                f'monitoring.bandwidth_probe_port + 1 + '
                                                f'{d.scale_names.index(s.name)} = {port} is past '
                                                '65535: give it a port or lower the base'))
            continue
        host = 'localhost' if s.host.lower() in LOOPBACK_HOSTS else s.host.lower()
        other = taken.setdefault((host, port), s.name)
        if other != s.name:
            out.append(Problem(d.source, where, f'port {port} on host {s.host!r} is also the port '
                                                f'of scale {other!r}: the warden and probe server '
                                                'of each scale need their own (set port, or '
                                                'leave it out on both to derive one per scale)'))
    return out


def links(d: t.Deployment, read: Context) -> List[Problem]:
    """Each link joins two different scales the file declares, and no two join the same."""
    out = []
    for link in d.links:
        for end in link.ends:
            if end and end not in d.scale_names:
                out += _unknown(d, read, f'links.{link.name}.ends', 'scale', end, d.scale_names)
        if link.ends[0] and link.ends[0] == link.ends[1]:
            out.append(Problem(d.source, f'links.{link.name}.ends',
                               'a link joins two different scales'))
    pairs: Dict[FrozenSet[str], str] = {}
    for link in d.links:
        key = frozenset(link.ends)
        if key in pairs and all(link.ends):
            out.append(Problem(d.source, f'links.{link.name}',
                               f'scales {" and ".join(link.ends)} are already joined by link '
                               f'{pairs[key]!r}'))
        pairs.setdefault(key, link.name)
    return out


def node_fields(d: t.Deployment, read: Context) -> List[Problem]:
    """What a node's own fields contradict, and the scales and nodes they name; said whatever
    else is wrong in the file."""
    out = []
    for n in d.nodes:
        here = f'nodes.{n.name}'
        if n.standby and not n.lifecycle and not read.damaged(f'{here}.lifecycle'):
            out.append(Problem(d.source, f'{here}.standby',
                               'a standby copy is an inactive lifecycle node: set lifecycle: '
                               'true (and make the node a lifecycle node, docs/lifecycle.md)'))
        if n.lifecycle and not n.managed:
            out.append(Problem(d.source, f'{here}.lifecycle',
                               'only a node the agents start (managed) is driven through its '
                               'lifecycle'))
        for s in n.residence:
            if s not in d.scale_names:
                out += _unknown(d, read, f'{here}.residence', 'scale', s, d.scale_names)
        for other in n.coresidence:
            if other == n.name:
                out.append(Problem(d.source, f'{here}.coresidence',
                                   'a node is always on its own scale'))
            elif other not in d.node_names:
                out += _unknown(d, read, f'{here}.coresidence', 'node', other, d.node_names)
    return out


def node_state(d: t.Deployment, read: Context) -> List[Problem]:
    """A node's ``state`` names one of its outputs (or declares its type), and the node is one
    the agents start: only they can hand a copy its state."""
    out = []
    for n in d.nodes:
        if n.state is None:
            continue
        here = f'nodes.{n.name}.state'
        if not n.managed and not read.damaged(f'nodes.{n.name}.managed'):
            out.append(Problem(d.source, here, 'only a node the agents start (managed) is '
                                               'handed its state: they start its copies'))
        topic = n.state.topic
        if not topic or read.damaged(f'{here}.topic'):
            continue
        outputs = [c for c in d.connections if c.publisher == n.name]
        if n.state.msg_type or any(c.topic == topic for c in outputs) \
                or not read.all_read('connections', 'topic', 'publisher'):
            continue
        known = sorted({c.topic for c in outputs})
        out.append(Problem(d.source, f'{here}.topic',
                           f'{topic!r} is not an output of {n.name!r}'
                           f'{did_you_mean(topic, known)}: its connections publish '
                           f'{", ".join(repr(x) for x in known) or "nothing"}; name one of '
                           'them, or give state.msg_type for a topic no connection declares'))
    return out


def connection_ends(d: t.Deployment, read: Context) -> List[Problem]:
    out = []
    for c in d.connections:
        for role in ('publisher', 'subscriber'):
            ref = getattr(c, role)
            if ref and ref not in d.node_names:
                out += _unknown(d, read, f'connections.{c.name}.{role}', 'node', ref,
                                d.node_names)
        if c.publisher and c.publisher == c.subscriber:
            out.append(Problem(d.source, f'connections.{c.name}',
                               'publisher and subscriber are the same node'))
    return out


def first_layout(d: t.Deployment, read: Context) -> List[Problem]:
    """decider.layout names nodes and scales of the file, and is given when it is used."""
    out = []
    layout = d.decider.layout
    for node, scale in layout.items():
        if node not in d.node_names:
            out += _unknown(d, read, f'decider.layout.{node}', 'node', node, d.node_names)
        if scale not in d.scale_names:
            out += _unknown(d, read, f'decider.layout.{node}', 'scale', scale, d.scale_names)
    if d.decider.initial_layout == 'explicit' and not layout:
        out.append(Problem(d.source, 'decider.layout',
                           'initial_layout is explicit but no layout is given'))
    return out


def beats(d: t.Deployment, read: Context) -> List[Problem]:
    beat, takeover = d.decider.beat_s, d.decider.takeover_s
    if takeover >= 3 * beat or any(read.damaged(f'decider.{k}')
                                   for k in ('beat_s', 'takeover_s')):
        return []
    return [Problem(d.source, 'decider.takeover_s',
                    f'{takeover:g} s is under three beats ({beat:g} s each): one late beat would '
                    'pass for a dead leader')]


def _placement_read(d: t.Deployment, read: Context) -> bool:
    """Whether the derived sets mean something. Every rule they give is relative to the master
    and to every scale; a node whose input could not be read would pass for a data provider.
    Missing parts make for looser rules (fewer constraints, no false alarm) except these, whose
    problems are reported already. Connections none of which could be read make none of these
    mistakes; some of them do."""
    connections_read = read.all_read('connections', 'subscriber') \
        or 'connections' in read.broken and not d.connections
    return sum(s.is_master for s in d.scales) == 1 and read.all_read('scales', 'role') \
        and connections_read


def _known_references(d: t.Deployment) -> t.Deployment:
    """``d`` without the residence and coresidence entries that name no scale or node (the
    checks above reported them): the derived sets are computed on the rest."""
    scales, names = set(d.scale_names), set(d.node_names)
    return replace(d, nodes=tuple(
        replace(n, residence=tuple(s for s in n.residence if s in scales),
                coresidence=tuple(o for o in n.coresidence if o in names and o != n.name))
        for n in d.nodes))


def placement(d: t.Deployment, read: Context) -> List[Problem]:
    """What each node declares about where it runs, against the sets the file derives: critical
    nodes, coresidence groups, migratable nodes, standby copies."""
    if not _placement_read(d, read):
        return []
    d = _known_references(d)
    out = []
    critical = set(d.critical_nodes)
    master = d.master.name
    reported_groups: Set[Tuple[str, ...]] = set()
    for n in d.nodes:
        here = f'nodes.{n.name}'
        why = d.why_critical(n.name)
        zero = d.pinning_connections(n.name)
        # Values replaced by a default when they could not be read: the checks that depend on
        # them would only repeat that problem.
        unread = any(read.damaged(f'{here}.{k}') for k in ('launch', 'lifecycle'))
        if n.name in critical and n.migratable is True:
            out.append(Problem(d.source, f'{here}.migratable',
                               f'declared migratable, but the node is critical ({why}), pinned '
                               f'to the master scale {master!r}'
                               + (f'; {PIN_ONE_END}' if zero else '')))
        if n.critical is False and zero:
            out.append(Problem(d.source, f'{here}.critical',
                               f'declared critical: false, but {why}: a connection that '
                               'tolerates no outage never crosses a link, so both its ends stay '
                               f'on the master; {PIN_ONE_END}'))
        if n.name in critical and n.residence and master not in n.residence:
            out.append(Problem(d.source, f'{here}.residence',
                               f'critical node must run on the master scale {master!r} ({why}), '
                               f'but residence allows only {", ".join(n.residence)}'))
        group = d.coresidence_group(n.name)
        allowed = d.allowed_scales(n.name)
        if not allowed:
            # One line per group, at its first node that declares a coresidence.
            if group not in reported_groups:
                reported_groups.add(group)
                at = next((m for m in group if d.node(m).coresidence), n.name)
                each = '; '.join(f'{m} {d.why_own_scales(m)}' for m in group
                                 if d.why_own_scales(m))
                out.append(Problem(d.source, f'nodes.{at}.coresidence',
                                   f'no scale satisfies every node that must share a scale '
                                   f'({", ".join(group)}): {each}'))
            continue        # nothing below means anything for a node with nowhere to run
        if n.standby and n.name not in d.migratable_nodes and not unread:
            out.append(Problem(d.source, f'{here}.standby',
                               'a standby copy is kept only for a migratable node, and this '
                               f'node cannot migrate: {d.why_not_migratable(n.name)}'))
        for i, scale in enumerate(n.standby_on):
            if scale not in d.scale_names:
                out.append(Problem(d.source, f'{here}.standby[{i}]',
                                   f'unknown scale {scale!r}'
                                   f'{did_you_mean(scale, d.scale_names)}'))
            elif scale not in allowed:
                out.append(Problem(d.source, f'{here}.standby[{i}]',
                                   f'{scale!r} is not a scale the node may run on (allowed: '
                                   f'{", ".join(allowed)})'))
        if n.migratable is True and n.name not in d.migratable_nodes \
                and n.name not in critical and not unread:
            out.append(Problem(d.source, f'{here}.migratable',
                               f'declared migratable, but {d.why_not_migratable(n.name)}'))
    return out


def layout_allowed(d: t.Deployment, read: Context) -> List[Problem]:
    """decider.layout puts each node on a scale it may run on."""
    if not _placement_read(d, read):
        return []
    d = _known_references(d)
    out = []
    for node, scale in d.decider.layout.items():
        if node in d.node_names and scale in d.scale_names and d.allowed_scales(node) \
                and not allowed(d, node, scale).passed:
            out.append(Problem(d.source, f'decider.layout.{node}',
                               f'node {node!r} may not run on {scale!r} (allowed: '
                               f'{", ".join(d.allowed_scales(node))})'))
    return out


# In this order: a check may stay quiet about what an earlier one reported.
CHECKS: Tuple[Check, ...] = (one_master, shared_scales, ports, links, node_fields, node_state,
                             connection_ends, first_layout, beats, placement, layout_allowed)
