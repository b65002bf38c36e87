"""The best layout for one link state, exactly: per-node optimum when it fits, else a search.

The placement of the migratable nodes is a generalised assignment problem: each node goes to
the master or to a remote scale whose link is usable; each remote scale has a CPU budget
(headroom x capacity minus what else runs there) and each link a bandwidth budget (margin x
available). A node's bandwidth on a link is the sum of its connections to nodes pinned to the
master; a connection between two migratable nodes is counted as crossing whenever either is
remote (an upper bound; none of the Fig. 7 systems has one).

The objective is a per-(node, scale) value: ``weight x quality(rate on the scale)``, plus a
small multiple of the paper's cost function (CPU x gain alpha) to prefer the more powerful
scale when the quality is the same. Two exact methods: a branch and bound (default; fast for
the Fig. 7 sizes) and a MILP with HiGHS; tests check both against exhaustive enumeration. The
oracle uses the simulator's true speed weights; the
planner-backed policy uses the deployment's node weights, which is all a live decider has.
"""

import itertools
import math
from dataclasses import dataclass
from functools import partial
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from ..model.types import Deployment
from ..planning.highs import highspy, quiet_highs
from .model import NodeProfile, node_rate, quality

# (node, scale) -> its value in the objective, bonus included.
Value = Callable[[str, str], float]
COST_EPSILON = 1e-3     # the cost function only breaks ties between equal qualities
BRANCH_AND_BOUND = 'branch_and_bound'
MILP = 'milp'
METHODS = (BRANCH_AND_BOUND, MILP)
CACHE_MAX = 4096        # solved link states kept per assignment


@dataclass(frozen=True)
class LinkBudget:
    """What a usable remote scale offers right now."""

    available_kbps: float
    background_cpu: float = 0.0


class Assignment:
    """The static data of one deployment's assignment problem; solve() per link state."""

    def __init__(self, deployment: Deployment, profiles: Mapping[str, NodeProfile],
                 weights: Mapping[str, float], cpu_headroom: Optional[float] = None,
                 bandwidth_margin: Optional[float] = None, method: str = BRANCH_AND_BOUND):
        if method not in METHODS:
            raise ValueError(f'unknown method {method!r}: expected one of {", ".join(METHODS)}')
        if method == MILP and highspy is None:
            raise ImportError('the MILP oracle needs HiGHS: pip install highspy')
        d = deployment
        self.method = method
        self.deployment = d
        self.master = d.master.name
        self.nodes: Tuple[str, ...] = d.migratable_nodes
        self.cpu_headroom = d.decider.cpu_headroom if cpu_headroom is None else cpu_headroom
        self.margin = d.decider.bandwidth_margin if bandwidth_margin is None else bandwidth_margin
        self.cpu = {n: d.node(n).cpu for n in self.nodes}
        self.kbps = {n: sum(c.bandwidth_kbps for c in d.connections_of(n)) for n in self.nodes}
        self.capacity = {s.name: s.capacity_cpu for s in d.scales}
        self.allowed = {n: set(d.allowed_scales(n)) for n in self.nodes}
        max_gain = max(d.worth(s.name) for s in d.scales)
        total_cpu = sum(self.cpu.values()) or 1.0
        master_gain = d.worth(d.master.name)
        self.value: Dict[Tuple[str, str], float] = {}
        for n in self.nodes:
            p = profiles[n]
            for s in d.scales:
                q = quality(p, node_rate(p, d.worth(s.name) / master_gain))
                cost = self.cpu[n] * d.worth(s.name) / (total_cpu * max_gain)
                self.value[(n, s.name)] = weights.get(n, 0.0) * q + COST_EPSILON * cost
        self._cache: Dict[Tuple, Dict[str, str]] = {}

    def cpu_budget(self, scale: str, budget: LinkBudget) -> float:
        return self.cpu_headroom * self.capacity[scale] - budget.background_cpu

    def candidates(self, n: str, usable: Mapping[str, LinkBudget]) -> Tuple[str, ...]:
        """The master, and the usable scales that could host the node on its own."""
        out = []
        for s in self.deployment.scale_names:
            if s not in self.allowed[n]:
                continue
            if s == self.master:
                out.append(s)
            elif s in usable and self.cpu[n] <= self.cpu_budget(s, usable[s]) + 1e-9 \
                    and self.kbps[n] <= self.margin * usable[s].available_kbps + 1e-9:
                out.append(s)
        return tuple(out)

    def score(self, layout: Mapping[str, str]) -> float:
        return sum(self.value[(n, layout[n])] for n in self.nodes)

    def feasible(self, layout: Mapping[str, str], usable: Mapping[str, LinkBudget]) -> bool:
        cpu: Dict[str, float] = {}
        kbps: Dict[str, float] = {}
        for n in self.nodes:
            s = layout[n]
            if s == self.master:
                continue
            if s not in usable:
                return False
            cpu[s] = cpu.get(s, 0.0) + self.cpu[n]
            kbps[s] = kbps.get(s, 0.0) + self.kbps[n]
        for s, used in cpu.items():
            if used > self.cpu_budget(s, usable[s]) + 1e-9:
                return False
        for s, used in kbps.items():
            if used > self.margin * usable[s].available_kbps + 1e-9:
                return False
        return True

    def solve(self, usable: Mapping[str, LinkBudget],
              bonus: Optional[Mapping[Tuple[str, str], float]] = None) -> Dict[str, str]:
        """The best layout of the migratable nodes; ``bonus`` adds value to (node, scale)."""
        bonus = bonus or {}
        key = (tuple(sorted((name, b.available_kbps, b.background_cpu)
                            for name, b in usable.items())),
               tuple(sorted(bonus.items())))
        found = self._cache.get(key)
        if found is None:
            if len(self._cache) >= CACHE_MAX:
                self._cache.clear()
            found = self._cache[key] = self._solve(usable, bonus)
        return dict(found)

    def _solve(self, usable: Mapping[str, LinkBudget],
               bonus: Mapping[Tuple[str, str], float]) -> Dict[str, str]:
        cands = {n: self.candidates(n, usable) for n in self.nodes}

        def val(n: str, s: str) -> float:
            return self.value[(n, s)] + bonus.get((n, s), 0.0)

        greedy = {n: max(cands[n], key=partial(val, n)) for n in self.nodes}
        if self.feasible(greedy, usable):
            return greedy
        if self.method == MILP:
            return self._milp(cands, usable, val)
        return self._branch_and_bound(cands, usable, val)

    def _branch_and_bound(self, cands: Mapping[str, Sequence[str]],
                          usable: Mapping[str, LinkBudget], val: Value) -> Dict[str, str]:
        """Depth-first over nodes (widest value range first), best scale first, pruned by the
        sum of the remaining nodes' best values; exact."""
        nodes = sorted(self.nodes, key=lambda n: -(max(val(n, s) for s in cands[n])
                                                   - min(val(n, s) for s in cands[n])))
        options = [sorted(((val(n, s), s) for s in cands[n]), key=lambda o: -o[0])
                   for n in nodes]
        suffix = [0.0] * (len(nodes) + 1)
        for i in range(len(nodes) - 1, -1, -1):
            suffix[i] = suffix[i + 1] + options[i][0][0]
        cpu_left = {s: self.cpu_budget(s, b) for s, b in usable.items()}
        kbps_left = {s: self.margin * b.available_kbps for s, b in usable.items()}
        chosen: List[str] = [self.master] * len(nodes)
        best_value, best = -math.inf, list(chosen)

        def visit(i: int, acc: float) -> None:
            nonlocal best_value, best
            if acc + suffix[i] <= best_value + 1e-12:
                return
            if i == len(nodes):
                best_value, best = acc, list(chosen)
                return
            n = nodes[i]
            for v, s in options[i]:
                if s == self.master:
                    chosen[i] = s
                    visit(i + 1, acc + v)
                    continue
                if cpu_left[s] < self.cpu[n] - 1e-9 or kbps_left[s] < self.kbps[n] - 1e-9:
                    continue
                cpu_left[s] -= self.cpu[n]
                kbps_left[s] -= self.kbps[n]
                chosen[i] = s
                visit(i + 1, acc + v)
                cpu_left[s] += self.cpu[n]
                kbps_left[s] += self.kbps[n]

        visit(0, 0.0)
        return dict(zip(nodes, best))

    def enumerate(self, usable: Mapping[str, LinkBudget],
                  bonus: Optional[Mapping[Tuple[str, str], float]] = None) -> Dict[str, str]:
        """Exhaustive search (exact; exponential in the number of migratable nodes)."""
        bonus = bonus or {}
        cands = [self.candidates(n, usable) for n in self.nodes]
        best, best_value = None, float('-inf')
        for combo in itertools.product(*cands):
            layout = dict(zip(self.nodes, combo))
            if not self.feasible(layout, usable):
                continue
            v = sum(self.value[(n, s)] + bonus.get((n, s), 0.0) for n, s in layout.items())
            if v > best_value + 1e-12:
                best, best_value = layout, v
        return best if best is not None else {n: self.master for n in self.nodes}

    def _milp(self, cands: Mapping[str, Sequence[str]], usable: Mapping[str, LinkBudget],
              val: Value) -> Dict[str, str]:
        h = quiet_highs()
        h.setOptionValue('mip_rel_gap', 0.0)
        x = {}
        for n in self.nodes:
            for s in cands[n]:
                x[(n, s)] = h.addBinary(obj=0.0)
        for n in self.nodes:
            h.addConstr(sum(x[(n, s)] for s in cands[n]) == 1)
        for s in usable:
            members = [n for n in self.nodes if (n, s) in x]
            if not members:
                continue
            h.addConstr(sum(self.cpu[n] * x[(n, s)] for n in members)
                        <= self.cpu_budget(s, usable[s]))
            h.addConstr(sum(self.kbps[n] * x[(n, s)] for n in members)
                        <= self.margin * usable[s].available_kbps)
        h.maximize(sum(val(n, s) * var for (n, s), var in x.items()))
        if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
            return {n: self.master for n in self.nodes}
        values = h.vals(list(x.values()))
        layout = {}
        for (n, s), v in zip(x.keys(), values):
            if v > 0.5:
                layout[n] = s
        return layout
