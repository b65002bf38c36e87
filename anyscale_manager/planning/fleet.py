"""A fleet planned as one: several deployments (one per robot) that share servers.

Each robot of a fleet keeps its own deployment file, master and decider; a server the robots
share is a scale marked ``shared`` with the same name and host in each file, one machine whose
capacity their nodes divide. Planned one file at a time, each robot would take the whole server.
``merge`` builds one planning deployment of the fleet instead:

* each file's own scales, nodes, links and connections are kept apart, named
  ``<deployment>/<name>``; a node may run only where its own file allows (its residence, and
  the pinning of critical nodes, data providers and unmanaged nodes to its own master), so no
  robot's node lands on another robot;
* a shared scale is one scale of the fleet, with the host's capacity counted once and the
  strictest ``decider.cpu_headroom`` of the files that share it (every decider must accept the
  fleet's layout there); a link between two shared scales is one link too.

``solve_fleet`` plans Problem 1 (the existing solvers, unchanged) over the merged deployment and
splits the answer back into one ``Plan`` per file, in the file's own names. Files that disagree
on a shared scale's capacity, a shared scale that is another file's master (or not marked
shared there), and two files of one deployment name are refused with every file named.
"""

import math
import time
from dataclasses import dataclass, replace
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from ..model.capacity import usable_cpu
from ..model.reader import Problem
from ..model.types import REMOTE, Connection, DeciderSettings, Deployment, Link, Node, Scale, \
    frozen_map
from .plan import Placement, Plan, solve

SEP = '/'


class FleetError(ValueError):
    """Deployment files that cannot be planned together; carries every problem found."""

    def __init__(self, problems: Sequence[Problem]):
        self.problems = list(problems)
        super().__init__('\n'.join(str(p) for p in self.problems))


@dataclass(frozen=True)
class SharedScale:
    """A scale several deployments use: one machine, its capacity counted once."""

    name: str                          # its name in the fleet (and in every file)
    host: str
    capacity_cpu: float
    usable_cpu: float                  # capacity x the strictest cpu_headroom of its users
    users: Tuple[str, ...]             # the deployments that name it, in file order


@dataclass(frozen=True)
class Fleet:
    """The fleet's deployments and the one planning deployment made of them."""

    members: Tuple[Deployment, ...]
    merged: Deployment
    shared: Mapping[str, SharedScale]              # fleet scale name -> the shared scale
    scale_names: Mapping[Tuple[str, str], str]     # (deployment, its scale) -> fleet scale
    link_names: Mapping[Tuple[str, str], str]      # (deployment, its link) -> fleet link
    notes: Tuple[str, ...] = ()                    # what a user may want to know (not errors)

    def node_name(self, deployment: str, node: str) -> str:
        return f'{deployment}{SEP}{node}'


def _own(d: Deployment, name: str) -> str:
    return f'{d.name}{SEP}{name}'


def _check_names(members: Sequence[Deployment]) -> List[Problem]:
    """Deployment names are what a shared host's claims are held under: one per file."""
    out = []
    first: Dict[str, Deployment] = {}
    for d in members:
        if d.name in first:
            out.append(Problem(d.source, 'deployment.name',
                               f'{d.name!r} is also the name of {first[d.name].source}: each '
                               'robot of a fleet is a deployment of its own name (a shared '
                               "host's claims are held under it)"))
        first.setdefault(d.name, d)
    return out


def _shared_keys(members: Sequence[Deployment]
                 ) -> Tuple[Dict[Tuple[str, str], List[Tuple[Deployment, Scale]]], List[Problem]]:
    """Each shared machine (scale name, host) with every file's scale of that name and host,
    and the files that contradict each other about one."""
    machines: Dict[Tuple[str, str], List[Tuple[Deployment, Scale]]] = {}
    for d in members:
        for s in d.scales:
            machines.setdefault((s.name, s.host), []).append((d, s))
    problems: List[Problem] = []
    shared = {}
    for key, uses in machines.items():
        marked = [(d, s) for d, s in uses if s.shared]
        if not marked:
            continue          # each file's own scale, even if two robots name theirs alike
        shared[key] = uses
        first_d, first_s = marked[0]
        name, host = key
        said = f'scale {name!r} (host {host!r}) is shared in {first_d.source}'
        for d, s in uses:
            where = f'scales.{s.name}'
            if s.is_master:
                problems.append(Problem(
                    d.source, f'{where}.role',
                    f"{said}, but is this file's master: a shared scale is a server the robots "
                    "use beside each other; each robot's master is its own (rename one, or "
                    'give it another host)'))
            elif not s.shared:
                problems.append(Problem(
                    d.source, f'{where}.shared',
                    f'{said}, but not here: its agent for this deployment would start copies '
                    "without a claim on the host's capacity (set shared: true, or rename "
                    'one)'))
            for key_name, unit in (('capacity_cpu', ''), ('memory_mb', ' MiB')):
                mine, theirs = getattr(s, key_name), getattr(first_s, key_name)
                if d is not first_d and mine != theirs:
                    problems.append(Problem(
                        d.source, f'{where}.{key_name}',
                        f'{mine:g}{unit} here but {theirs:g}{unit} in {first_d.source}: a '
                        'shared scale is one machine, whose capacity every file must give '
                        'alike'))
    return shared, problems


def merge(members: Sequence[Deployment]) -> Fleet:
    """One planning deployment of a fleet; raises FleetError naming the files and keys."""
    if not members:
        raise ValueError('a fleet needs at least one deployment')
    problems = _check_names(members)
    machines, more = _shared_keys(members)
    problems += more
    if problems:
        raise FleetError(problems)
    # A shared scale keeps its name; two shared machines of one name are told apart by host.
    by_name: Dict[str, List[Tuple[str, str]]] = {}
    for key in machines:
        by_name.setdefault(key[0], []).append(key)
    notes = []
    fleet_name: Dict[Tuple[str, str], str] = {}
    for name, keys in by_name.items():
        for key in keys:
            fleet_name[key] = name if len(keys) == 1 else f'{name}@{key[1]}'
        if len(keys) > 1:
            hosts = ', '.join(f'{k[1]!r} in {machines[k][0][0].source}' for k in keys)
            notes.append(f'shared scale {name!r} names {len(keys)} hosts ({hosts}): planned '
                         'as that many machines')
    headrooms = {d.decider.cpu_headroom for d in members}
    one_headroom = len(headrooms) == 1
    # The usable CPU of every scale is what its own deciders allow: with one cpu_headroom in
    # every file the capacities stay as written; otherwise each is made usable here.
    headroom = headrooms.pop() if one_headroom else 1.0

    def capacity(d: Deployment, s: Scale) -> float:
        return s.capacity_cpu if one_headroom else usable_cpu(s.capacity_cpu, d.decider)

    scales: List[Scale] = []
    names: Dict[Tuple[str, str], str] = {}
    shared: Dict[str, SharedScale] = {}
    for d in members:
        for s in d.scales:
            key = (s.name, s.host)
            if key in machines:
                fleet = fleet_name[key]
                names[d.name, s.name] = fleet
                if fleet not in shared:
                    users = tuple(u.name for u, _ in machines[key])
                    strictest = min(u.decider.cpu_headroom for u, _ in machines[key])
                    usable = s.capacity_cpu * strictest
                    shared[fleet] = SharedScale(fleet, s.host, s.capacity_cpu, usable, users)
                    scales.append(replace(s, name=fleet, role=REMOTE, capacity_cpu=(
                        s.capacity_cpu if one_headroom else usable)))
            else:
                names[d.name, s.name] = _own(d, s.name)
                scales.append(replace(s, name=_own(d, s.name), capacity_cpu=capacity(d, s)))
    links: List[Link] = []
    link_names: Dict[Tuple[str, str], str] = {}
    joint: Dict[frozenset, Tuple[Deployment, Link]] = {}
    problems = []
    for d in members:
        for link in d.links:
            ends = (names[d.name, link.ends[0]], names[d.name, link.ends[1]])
            if all(e in shared for e in ends):
                pair = frozenset(ends)
                if pair in joint:
                    first_d, first = joint[pair]
                    link_names[d.name, link.name] = first.name
                    if first.bandwidth_kbps != link.bandwidth_kbps:
                        problems.append(Problem(
                            d.source, f'links.{link.name}.bandwidth_kbps',
                            f'{link.bandwidth_kbps:g} here but {first.bandwidth_kbps:g} in '
                            f'{first_d.source} (link {first.name}): a link between two shared '
                            'scales is one link, whose bandwidth every file must give alike'))
                    continue
                joint[pair] = (d, link)
                link_names[d.name, link.name] = link.name
                links.append(replace(link, ends=ends))
            else:
                link_names[d.name, link.name] = _own(d, link.name)
                links.append(replace(link, name=_own(d, link.name), ends=ends))
    if problems:
        raise FleetError(problems)
    nodes: List[Node] = []
    connections: List[Connection] = []
    for d in members:
        for n in d.nodes:
            # Where the node may run by its own file, written out: the merged deployment has
            # no master of its own to pin critical nodes and data providers to.
            nodes.append(replace(
                n, name=_own(d, n.name), critical=False,
                residence=tuple(names[d.name, s] for s in d.own_scales(n.name)),
                coresidence=tuple(_own(d, m) for m in n.coresidence)))
        for c in d.connections:
            connections.append(replace(c, name=_own(d, c.name), publisher=_own(d, c.publisher),
                                       subscriber=_own(d, c.subscriber), tolerance_s=None))
    merged = Deployment(name='fleet', source=', '.join(d.source for d in members),
                        scales=tuple(scales), links=tuple(links), nodes=tuple(nodes),
                        connections=tuple(connections),
                        decider=DeciderSettings(cpu_headroom=headroom))
    return Fleet(members=tuple(members), merged=merged, shared=frozen_map(shared),
                 scale_names=frozen_map(names), link_names=frozen_map(link_names),
                 notes=tuple(notes))


@dataclass(frozen=True)
class FleetPlan:
    """The fleet's plan and each deployment's part of it, in that deployment's own names.

    A member's ``objective`` is its own nodes' weighted performance; ``optimal`` and ``gap``
    are the fleet's (a member's part of a fleet optimum is not the best that member could do
    alone: the server is shared). ``scale_load`` of a shared scale is the member's own use.
    """

    fleet: Fleet
    plan: Plan                                  # over fleet.merged
    members: Mapping[str, Plan]                 # deployment name -> its part

    @property
    def feasible(self) -> bool:
        return self.plan.feasible

    def shared_use(self) -> Dict[str, Dict[str, float]]:
        """Shared scale -> deployment -> the CPU its nodes are planned to use there."""
        out: Dict[str, Dict[str, float]] = {}
        for name, s in self.fleet.shared.items():
            out[name] = {}
            for user in s.users:
                local = next(k[1] for k, v in self.fleet.scale_names.items()
                             if k[0] == user and v == name)
                out[name][user] = self.members[user].scale_load.get(local, 0.0)
        return out


def split(fleet: Fleet, plan: Plan) -> Dict[str, Plan]:
    """The fleet's plan as one Plan per deployment, in each deployment's own names."""
    out = {}
    for d in fleet.members:
        local = {v: k[1] for k, v in fleet.scale_names.items() if k[0] == d.name}
        layout: Dict[str, Placement] = {}
        for n in d.nodes:
            p = plan.layout.get(fleet.node_name(d.name, n.name))
            if p is not None:
                layout[n.name] = replace(p, scale=local[p.scale])
        scale_load = dict.fromkeys(d.scale_names, 0.0)
        for p in layout.values():
            scale_load[p.scale] += p.cpu
        link_load = {link.name: plan.link_load.get(fleet.link_names[d.name, link.name], 0.0)
                     for link in d.links}
        objective = (sum(d.node(n).weight * p.performance for n, p in layout.items())
                     if plan.feasible else math.nan)
        out[d.name] = replace(plan, objective=objective, layout=frozen_map(layout),
                              scale_load=frozen_map(scale_load),
                              link_load=frozen_map(link_load))
    return out


def solve_fleet(members: Sequence[Deployment], solver: str = 'greedy',
                settings: str = 'continuous', time_limit_s: float = 10.0, *,
                clock: Callable[[], float] = time.perf_counter,
                fleet: Optional[Fleet] = None) -> FleetPlan:
    """IROS 2016 Problem 1 over a whole fleet: ``merge``, ``solve``, ``split``.

    The plan's layout puts on each shared scale no more than its usable CPU, all robots
    together. ``fleet``: ``merge(members)`` when the caller has it already. Raises FleetError
    for files that cannot be planned together, ValueError for bad arguments (as ``solve``).
    """
    fleet = fleet or merge(members)
    plan = solve(fleet.merged, problem=1, solver=solver, settings=settings,
                 time_limit_s=time_limit_s, clock=clock)
    return FleetPlan(fleet=fleet, plan=plan, members=frozen_map(split(fleet, plan)))
