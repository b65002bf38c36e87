"""A deployment compiled for the planners: indexed scales, nodes, options, units and links.

Every solver works on the same ``Instance``: nodes become integer indices, each node gets its
options (CPU, performance) sorted by CPU, coresidence groups become units that always move
together, and every pair of scales knows its link (or that there is none).
"""

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

from ..model.capacity import usable_cpu
from ..model.types import SERVER, Deployment
from .regression import NodeProfile, fit_profile

PROBLEMS = (1, 2)
SETTINGS = ('continuous', 'discrete')
_QUANTA = (1.0, 0.5, 0.25, 0.2, 0.1, 0.05, 0.02, 0.01)


@dataclass(frozen=True)
class Option:
    """One setting a node may take: its CPU share, performance and parameter value."""

    cpu: float
    performance: float
    parameter_value: Optional[float] = None


def _is_multiple(x: float, q: float) -> bool:
    return abs(x / q - round(x / q)) < 1e-9


def _node_options(node, problem: int, settings: str
                  ) -> Tuple[Tuple[Option, ...], Optional[NodeProfile]]:
    s = node.settings
    profile = fit_profile(s) if node.configurable else None
    if problem == 2 or profile is None:
        value = None
        if profile is not None:
            value = profile.parameter_for_cpu(node.cpu)
        return (Option(node.cpu, node.performance, value),), profile
    if settings == 'discrete':
        best: Dict[float, Option] = {}
        values = s.values or (None,) * len(s.cpu)
        for v, c, p in zip(values, s.cpu, s.performance):
            if c not in best or p > best[c].performance:
                best[c] = Option(float(c), float(p), None if v is None else float(v))
        return tuple(best[c] for c in sorted(best)), profile
    low, high = math.ceil(s.cpu_min - 1e-9), math.floor(s.cpu_max + 1e-9)
    cpus = [float(c) for c in range(low, high + 1)] or [float(s.cpu_min)]
    # Parameter values are found (by inverting the parameter -> CPU fit) only for the options
    # a plan picks: see parameter_value().
    perf = profile.cpu_to_performance.predict(cpus)
    return tuple(Option(c, float(p)) for c, p in zip(cpus, perf)), profile


class Instance:
    """The planning view of one deployment for one problem and settings mode."""

    def __init__(self, deployment: Deployment, problem: int = 1, settings: str = 'continuous'):
        if problem not in PROBLEMS:
            raise ValueError(f'problem must be 1 or 2, got {problem!r}')
        if settings not in SETTINGS:
            raise ValueError(f'settings must be one of {", ".join(SETTINGS)}, got {settings!r}')
        d = deployment
        self.deployment = d
        self.problem = problem
        self.settings = settings
        self.scales: Tuple[str, ...] = d.scale_names
        self.scale_index = {s: i for i, s in enumerate(self.scales)}
        # The CPU the decider lets nodes use on each scale (capacity less its headroom): a
        # layout that filled a scale beyond it would be judged over capacity at its first turn.
        self.capacity: Tuple[float, ...] = tuple(usable_cpu(s.capacity_cpu, d.decider)
                                                 for s in d.scales)
        # Problem 2 grows servers from 0; robots (and any other kind) keep their capacity.
        self.growable: Tuple[bool, ...] = tuple(problem == 2 and s.kind == SERVER
                                                for s in d.scales)
        self.nodes: Tuple[str, ...] = d.node_names
        self.node_index = {n: i for i, n in enumerate(self.nodes)}
        self.weight: Tuple[float, ...] = tuple(n.weight for n in d.nodes)
        options, profiles = [], []
        for n in d.nodes:
            o, p = _node_options(n, problem, settings)
            options.append(o)
            profiles.append(p)
        self.options: Tuple[Tuple[Option, ...], ...] = tuple(options)
        self.profiles: Tuple[Optional[NodeProfile], ...] = tuple(profiles)
        self.configurable: Tuple[int, ...] = tuple(i for i, o in enumerate(self.options)
                                                   if len(o) > 1)
        # Units: coresidence groups, in node order of their first member.
        # (Deployment.coresidence_group per node, computed for all nodes at once.)
        root = list(range(len(self.nodes)))

        def find(i: int) -> int:
            while root[i] != i:
                root[i] = root[root[i]]
                i = root[i]
            return i
        for i, n in enumerate(d.nodes):
            for other in n.coresidence:
                root[find(i)] = find(self.node_index[other])
        groups: Dict[int, List[int]] = {}
        for i in range(len(self.nodes)):
            groups.setdefault(find(i), []).append(i)
        unit_of: List[int] = [-1] * len(self.nodes)
        units: List[Tuple[int, ...]] = []
        for members in sorted(groups.values()):
            for m in members:
                unit_of[m] = len(units)
            units.append(tuple(members))
        self.units: Tuple[Tuple[int, ...], ...] = tuple(units)
        self.unit_of: Tuple[int, ...] = tuple(unit_of)
        allowed_units = []
        for unit in self.units:
            allowed = set(self.scales)
            for m in unit:
                allowed &= set(d.own_scales(self.nodes[m]))
            allowed_units.append(tuple(i for i, s in enumerate(self.scales) if s in allowed))
        self.unit_allowed: Tuple[Tuple[int, ...], ...] = tuple(allowed_units)
        # Links, both orientations; -1 = no link between the two scales.
        self.link_names = tuple(link.name for link in d.links)
        self.link_capacity = tuple(float(link.bandwidth_kbps) for link in d.links)
        S = len(self.scales)
        self.link_of: List[List[int]] = [[-1] * S for _ in range(S)]
        for li, link in enumerate(d.links):
            a, b = (self.scale_index[e] for e in link.ends)
            self.link_of[a][b] = self.link_of[b][a] = li
        # Connections between nodes; those inside one unit never cross a link.
        self.connections: List[Tuple[int, int, float, str]] = []
        self.neighbours: List[List[Tuple[int, float]]] = [[] for _ in self.nodes]
        for c in d.connections:
            pub, sub = self.node_index[c.publisher], self.node_index[c.subscriber]
            if unit_of[pub] == unit_of[sub]:
                continue
            self.connections.append((pub, sub, float(c.bandwidth_kbps), c.name))
            self.neighbours[pub].append((sub, float(c.bandwidth_kbps)))
            self.neighbours[sub].append((pub, float(c.bandwidth_kbps)))
        total_bw = sum(bw for _, _, bw, _ in self.connections)
        # A link that could carry every connection at once never binds: solvers skip it.
        self.link_may_bind = tuple(total_bw > cap + 1e-9 for cap in self.link_capacity)
        self.quantum = self._quantum()

    def _quantum(self) -> float:
        """The CPU grid of the option steps (1 for integer shares)."""
        steps = [o.cpu - self.options[i][0].cpu for i in self.configurable
                 for o in self.options[i]]
        for q in _QUANTA:
            if all(_is_multiple(s, q) for s in steps):
                return q
        return _QUANTA[-1]

    # --- small helpers ----------------------------------------------------------------------
    def parameter_value(self, n: int, k: int) -> Optional[float]:
        """The parameter value that gives node n the CPU share of its option k."""
        o = self.options[n][k]
        profile = self.profiles[n]
        if o.parameter_value is not None or profile is None:
            return o.parameter_value
        return profile.parameter_for_cpu(o.cpu)

    def unit_cpu(self, u: int, choice: Sequence[int]) -> float:
        return sum(self.options[n][choice[n]].cpu for n in self.units[u])

    def min_cpu(self, u: int) -> float:
        return sum(self.options[n][0].cpu for n in self.units[u])

    def value(self, n: int, k: int) -> float:
        """Weighted performance of node n at option k (Problem 1's objective term)."""
        return self.weight[n] * self.options[n][k].performance

    def objective(self, placement: Sequence[int], choice: Sequence[int]) -> float:
        if self.problem == 1:
            return sum(self.value(n, choice[n]) for n in range(len(self.nodes)))
        load = [0.0] * len(self.scales)
        for n, s in enumerate(placement):
            load[s] += self.options[n][choice[n]].cpu
        return sum(load[s] for s in range(len(self.scales)) if self.growable[s])

    def loads(self, placement: Sequence[int], choice: Sequence[int]) -> List[float]:
        load = [0.0] * len(self.scales)
        for n, s in enumerate(placement):
            load[s] += self.options[n][choice[n]].cpu
        return load

    def effective_capacity(self, placement: Sequence[int], choice: Sequence[int]
                           ) -> List[float]:
        """Capacities with each growable scale grown to exactly its load."""
        load = self.loads(placement, choice)
        return [load[s] if self.growable[s] else self.capacity[s]
                for s in range(len(self.scales))]
