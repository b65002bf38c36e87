"""The one feasibility checker every planner answers to, and its incremental form for search.

``check_layout`` judges a complete layout by name: one placement per node on a known scale,
residence (and the pinning of critical nodes, data providers and unmanaged nodes to the master),
coresidence, CPU per computer, bandwidth per link with both directions summed, and connections
between two scales that have no link at all. It returns every violation with its reason; an
empty tuple means feasible. ``Loads`` applies the same rules incrementally while a solver moves
units around, and ``explain_infeasible`` names the constraints that cannot all be met.
Residence and coresidence are model/placement.py's filters, as the first layout's check and
the migration policy judge them.
"""

from typing import Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple

from ..model.capacity import usable_cpu
from ..model.placement import apart, residence
from ..model.types import Deployment
from ..model.violation import Violation
from .instance import Instance

TOLERANCE = 1e-6


def _usable(d: Deployment, scale: str, cpu: float, given: bool = False) -> str:
    """A scale's CPU limit in words: given outright, or its capacity less the headroom."""
    if given:
        return f'capacity {cpu:g}'
    return (f'{cpu:g} usable (capacity {d.scale(scale).capacity_cpu:g} x cpu_headroom '
            f'{d.decider.cpu_headroom:g})')


def check_layout(deployment: Deployment, layout: Mapping[str, str],
                 cpu: Optional[Mapping[str, float]] = None,
                 capacity: Optional[Mapping[str, float]] = None,
                 tolerance: float = TOLERANCE) -> Tuple[Violation, ...]:
    """Every violated constraint of ``layout`` (node -> scale); empty when feasible.

    ``cpu`` gives each node's planned CPU share (default: its nominal ``cpu``). A scale's CPU
    limit is what the decider lets nodes use there (``capacity_cpu`` x ``cpu_headroom``), unless
    ``capacity`` gives it (Problem 2's servers, grown to their load).
    """
    d = deployment
    out: List[Violation] = []
    scales = set(d.scale_names)
    node_names = set(d.node_names)
    links = {frozenset(link.ends): link for link in d.links}
    cpu = dict(cpu or {})
    for name in layout:
        if name not in node_names:
            out.append(Violation('placement', name, f'{name!r} is not a node of the deployment'))
    for n in d.nodes:
        scale = layout.get(n.name)
        if scale is None:
            out.append(Violation('placement', n.name, f'node {n.name} has no placement'))
        elif scale not in scales:
            out.append(Violation('placement', n.name,
                                 f'node {n.name} is placed on unknown scale {scale!r}'))
        else:
            alone = residence(d, n.name, scale)
            if not alone.passed:
                out.append(Violation(alone.code.value, n.name,
                                     f'node {n.name} is on {scale} but {alone.reason}'))
        share = cpu.get(n.name, n.cpu)
        profiled = n.settings
        if profiled is not None and profiled.configurable:
            if not (profiled.cpu_min - tolerance <= share <= profiled.cpu_max + tolerance):
                out.append(Violation('setting', n.name,
                                     f'node {n.name} is given CPU {share:g}, outside its '
                                     f'profiled range {profiled.cpu_min:g}-'
                                     f'{profiled.cpu_max:g}'))
        elif abs(share - n.cpu) > tolerance:
            out.append(Violation('setting', n.name, f'node {n.name} has a fixed CPU share of '
                                                    f'{n.cpu:g}, not {share:g}'))
    for n in d.nodes:
        here = layout.get(n.name)
        if here not in scales:
            continue
        # Each pair as declared (a node's own coresidence list), once per declaring node.
        for other in apart(d, n.name, here, layout, among=n.coresidence):
            there = layout[other]
            if there in scales:
                out.append(Violation('coresidence', n.name,
                                     f'node {n.name} must share a scale with {other}, but is '
                                     f'on {here} and {other} on {there}'))
    load: Dict[str, float] = {s: 0.0 for s in d.scale_names}
    for n in d.nodes:
        if layout.get(n.name) in scales:
            load[layout[n.name]] += cpu.get(n.name, n.cpu)
    given = dict(capacity or {})
    for sc in d.scales:
        s = sc.name
        cap = given.get(s, usable_cpu(sc.capacity_cpu, d.decider))
        if load[s] > cap + tolerance:
            on = sorted((n.name for n in d.nodes if layout.get(n.name) == s))
            out.append(Violation('cpu', s, f'scale {s} needs CPU {load[s]:g} but has '
                                           f'{_usable(d, s, cap, s in given)} (nodes: '
                                           f'{", ".join(on)})'))
    link_load: Dict[str, float] = {link.name: 0.0 for link in d.links}
    for c in d.connections:
        a, b = layout.get(c.publisher), layout.get(c.subscriber)
        if a not in scales or b not in scales or a == b:
            continue
        link = links.get(frozenset((a, b)))
        if link is None:
            out.append(Violation('no_link', c.name,
                                 f'connection {c.name} ({c.publisher} on {a} -> {c.subscriber} '
                                 f'on {b}) crosses scales that have no link'))
        else:
            link_load[link.name] += c.bandwidth_kbps
    for link in d.links:
        if link_load[link.name] > link.bandwidth_kbps + tolerance:
            out.append(Violation('bandwidth', link.name,
                                 f'link {link.name} ({link.ends[0]} <-> {link.ends[1]}) carries '
                                 f'{link_load[link.name]:g} kbit/s but has '
                                 f'{link.bandwidth_kbps:g}'))
    return tuple(out)


class Loads:
    """Incremental CPU and link loads of a partial layout, for search.

    The rules are those of ``check_layout``; a solver moves units (coresidence groups) and asks
    whether the scales and links touched are still within their capacities. Growable scales
    (Problem 2 servers) have no CPU limit here.
    """

    def __init__(self, inst: Instance, choice: Sequence[int]):
        self.inst = inst
        self.scale_of: List[int] = [-1] * len(inst.nodes)
        self.cpu: List[float] = [inst.options[n][choice[n]].cpu for n in range(len(inst.nodes))]
        self.choice: List[int] = list(choice)
        self.load: List[float] = [0.0] * len(inst.scales)
        self.link_load: List[float] = [0.0] * len(inst.link_names)
        self.no_link = 0        # connections currently crossing scales without a link
        self.members: List[set] = [set() for _ in inst.scales]   # units per scale

    # --- queries ------------------------------------------------------------------------------
    def unit_scale(self, u: int) -> int:
        return self.scale_of[self.inst.units[u][0]]

    def unit_cpu(self, u: int) -> float:
        return sum(self.cpu[n] for n in self.inst.units[u])

    def free(self, s: int) -> float:
        return float('inf') if self.inst.growable[s] else self.inst.capacity[s] - self.load[s]

    def cpu_ok(self, s: int) -> bool:
        return self.inst.growable[s] or self.load[s] <= self.inst.capacity[s] + TOLERANCE

    def link_ok(self, li: int) -> bool:
        return self.link_load[li] <= self.inst.link_capacity[li] + TOLERANCE

    def fits(self, u: int, s: int) -> bool:
        """Unit u (not placed) fits on s by CPU, links and the existence of links."""
        if self.unit_cpu(u) > self.free(s) + TOLERANCE:
            return False
        return self._links_after(u, s) is not None

    def _crossings(self, u: int, s: int) -> Iterator[Tuple[int, float]]:
        """(link index, bandwidth) of each connection of unit u that would cross from s to a
        placed neighbour on another scale; link index -1 where no link joins the two."""
        inst = self.inst
        scale_of, link_of = self.scale_of, inst.link_of[s]
        for n in inst.units[u]:
            for m, bw in inst.neighbours[n]:
                t = scale_of[m]
                if t >= 0 and t != s:
                    yield link_of[t], bw

    def _links_after(self, u: int, s: int) -> Optional[Dict[int, float]]:
        """Link load changes if unplaced unit u went to s; None if a link is missing/full."""
        delta: Dict[int, float] = {}
        for li, bw in self._crossings(u, s):
            if li < 0:
                return None
            delta[li] = delta.get(li, 0.0) + bw
        capacity = self.inst.link_capacity
        for li, dl in delta.items():
            if self.link_load[li] + dl > capacity[li] + TOLERANCE:
                return None
        return delta

    # --- changes --------------------------------------------------------------------------------
    def _account(self, u: int, s: int, sign: float) -> List[int]:
        touched = []
        for li, bw in self._crossings(u, s):
            if li < 0:
                self.no_link += 1 if sign > 0 else -1
            else:
                self.link_load[li] += sign * bw
                touched.append(li)
        return touched

    def place(self, u: int, s: int) -> List[int]:
        """Put unplaced unit u on s (no check); returns the links touched."""
        touched = self._account(u, s, 1.0)
        for n in self.inst.units[u]:
            self.scale_of[n] = s
        self.load[s] += self.unit_cpu(u)
        self.members[s].add(u)
        return touched

    def unplace(self, u: int) -> List[int]:
        s = self.unit_scale(u)
        for n in self.inst.units[u]:
            self.scale_of[n] = -1
        self.load[s] -= self.unit_cpu(u)
        self.members[s].discard(u)
        return self._account(u, s, -1.0)

    def set_choice(self, n: int, k: int) -> None:
        s = self.scale_of[n]
        new = self.inst.options[n][k].cpu
        if s >= 0:
            self.load[s] += new - self.cpu[n]
        self.cpu[n] = new
        self.choice[n] = k

    def try_moves(self, moves: Iterable[Tuple[int, int]]) -> bool:
        """Apply unit moves together; keep them only if every touched constraint still holds."""
        moves = list(moves)
        origins = [(u, self.unit_scale(u)) for u, _ in moves]
        touched_links: List[int] = []
        touched_scales = set()
        no_link_before = self.no_link
        for u, s in moves:
            touched_scales.add(self.unit_scale(u))
            touched_links += self.unplace(u)
        for u, s in moves:
            touched_scales.add(s)
            touched_links += self.place(u, s)
        ok = (self.no_link <= no_link_before and all(self.cpu_ok(s) for s in touched_scales)
              and all(self.link_ok(li) for li in touched_links))
        if not ok:
            for u, _ in moves:
                self.unplace(u)
            for u, s in origins:
                self.place(u, s)
        return ok

    def placement(self) -> List[int]:
        return list(self.scale_of)


def explain_infeasible(inst: Instance) -> Tuple[str, ...]:
    """Constraints that cannot all be met, found by necessary conditions (may be empty)."""
    d = inst.deployment
    reasons: List[str] = []
    pinned_load = [0.0] * len(inst.scales)
    pinned_units: List[List[str]] = [[] for _ in inst.scales]
    for u, members in enumerate(inst.units):
        names = [inst.nodes[n] for n in members]
        allowed = inst.unit_allowed[u]
        need = inst.min_cpu(u)
        label = names[0] if len(names) == 1 else f'{" + ".join(names)} (coresident)'
        if not allowed:
            reasons.append(f'residence: {label} has no scale it may run on')
            continue
        room = max(float('inf') if inst.growable[s] else inst.capacity[s] for s in allowed)
        if need > room + TOLERANCE:
            reasons.append(f'CPU: {label} needs at least {need:g} but the largest scale it may '
                           f'run on ({", ".join(inst.scales[s] for s in allowed)}) has '
                           f'{room:g} usable')
        if len(allowed) == 1:
            pinned_load[allowed[0]] += need
            pinned_units[allowed[0]].append(label)
    for s, load in enumerate(pinned_load):
        if not inst.growable[s] and load > inst.capacity[s] + TOLERANCE:
            name = inst.scales[s]
            reasons.append(f'CPU: scale {name} has {_usable(d, name, inst.capacity[s])} but '
                           f'the nodes that may run only there need {load:g} '
                           f'({", ".join(pinned_units[s])})')
    if not any(inst.growable):
        total = sum(inst.min_cpu(u) for u in range(len(inst.units)))
        cap = sum(inst.capacity)
        if total > cap + TOLERANCE:
            reasons.append(f'CPU: the nodes need at least {total:g} in total but all scales '
                           f'together have {cap:g} usable')
    link_pinned: Dict[int, float] = {}
    for p, q, bw, name in inst.connections:
        ap, aq = inst.unit_allowed[inst.unit_of[p]], inst.unit_allowed[inst.unit_of[q]]
        if len(ap) == 1 and len(aq) == 1 and ap[0] != aq[0]:
            li = inst.link_of[ap[0]][aq[0]]
            if li < 0:
                reasons.append(f'link: connection {name} joins {inst.nodes[p]} (only on '
                               f'{inst.scales[ap[0]]}) and {inst.nodes[q]} (only on '
                               f'{inst.scales[aq[0]]}), scales with no link')
            else:
                link_pinned[li] = link_pinned.get(li, 0.0) + bw
    for li, load in link_pinned.items():
        if load > inst.link_capacity[li] + TOLERANCE:
            reasons.append(f'bandwidth: link {inst.link_names[li]} must carry at least {load:g} '
                           f'kbit/s between pinned nodes but has {inst.link_capacity[li]:g}')
    return tuple(reasons)
