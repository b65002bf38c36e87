"""The IROS 2016 greedy planners (Algorithms 1-3) and the local search that improves them.

``paper_problem1`` and ``paper_problem2`` follow the published pseudo-code; where it is loose
the reading taken is noted next to the code. ``improve_problem1`` and ``improve_problem2`` start
from a greedy layout and apply moves, swaps and exact re-upgrades (a knapsack per scale) while
any of them improves the objective, re-checking every constraint on each change.
"""

import heapq
from dataclasses import dataclass
from typing import Callable, Dict, FrozenSet, List, Optional, Sequence, Tuple

from .feasibility import TOLERANCE, Loads
from .instance import Instance
from .knapsack import best_fill, best_settings

Clock = Callable[[], float]
# Local search considers every scale as a move target up to this many scales, then only the
# scales of a unit's neighbours and the ones with the most free CPU.
ALL_TARGETS_UP_TO = 12
NEAR_TARGETS = 6
# Swaps are tried between every pair of units up to this many units.
ALL_SWAPS_UP_TO = 80

# A scale's best weighted performance from its configurable nodes, and the option of each.
ScaleValue = Tuple[float, Dict[int, int]]


@dataclass
class Outcome:
    """A solver's working result: the loads of a full layout, or why there is none."""

    loads: Optional[Loads]
    reason: Tuple[str, ...] = ()


def _label(inst: Instance, u: int) -> str:
    names = [inst.nodes[n] for n in inst.units[u]]
    return names[0] if len(names) == 1 else ' + '.join(names)


def _why_not(inst: Instance, loads: Loads, u: int, shown: int = 4) -> str:
    cpu, links = [], []
    for s in inst.unit_allowed[u]:
        if loads.unit_cpu(u) > loads.free(s) + TOLERANCE:
            cpu.append(f'{inst.scales[s]} ({max(loads.free(s), 0.0):g} free)')
        else:
            links.append(inst.scales[s])
    parts = []
    for what, names in (('too little CPU on', cpu), ('a missing or full link to', links)):
        if names:
            more = f' and {len(names) - shown} more' if len(names) > shown else ''
            parts.append(f'{what} {", ".join(names[:shown])}{more}')
    where = '; '.join(parts) or 'no scale allowed by residence'
    return f'{_label(inst, u)} (CPU {loads.unit_cpu(u):g}) fits nowhere: {where}'


def _has_residence(inst: Instance, u: int) -> bool:
    return len(inst.unit_allowed[u]) < len(inst.scales)


# --- Problem 1 ------------------------------------------------------------------------------
def _initial_allocation(inst: Instance, loads: Loads, paper: bool) -> Tuple[str, ...]:
    """Algorithm 1, lines 1-6: residence units, then coresidence units, then the rest, each
    by CPU (at the lowest settings) from the largest, on the scale with most free CPU.

    ``paper=False`` orders by the number of allowed scales first: a fallback that places the
    most constrained units while there is still room for them.
    """
    units = range(len(inst.units))
    if paper:
        def rank(u):
            return (0 if _has_residence(inst, u) else 1 if len(inst.units[u]) > 1 else 2,
                    -loads.unit_cpu(u), u)
    else:
        def rank(u):
            return (len(inst.unit_allowed[u]), -loads.unit_cpu(u), u)
    for u in sorted(units, key=rank):
        targets = sorted(inst.unit_allowed[u], key=lambda s: (-loads.free(s), s))
        for s in targets:
            if loads.fits(u, s):
                loads.place(u, s)
                break
        else:
            return (_why_not(inst, loads, u),)
    return ()


def _gradient(inst: Instance, loads: Loads, n: int) -> float:
    """Weighted performance gained per CPU unit by the node's next setting."""
    opts = inst.options[n]
    k = loads.choice[n]
    if k + 1 >= len(opts):
        return float('-inf')
    return (inst.value(n, k + 1) - inst.value(n, k)) / (opts[k + 1].cpu - opts[k].cpu)


def _upgrade(inst: Instance, loads: Loads) -> None:
    """Algorithm 2: raise the node with the best performance gradient by one step while its
    scale has the CPU for it. Link loads do not depend on settings in this model, so an
    upgrade can only break the CPU constraint, which is checked before each step."""
    heap = [(-_gradient(inst, loads, n), n) for n in inst.configurable
            if loads.choice[n] + 1 < len(inst.options[n])]
    heapq.heapify(heap)
    while heap:
        neg, n = heapq.heappop(heap)
        if -neg <= 0:
            break          # no setting left that adds performance
        k = loads.choice[n]
        step = inst.options[n][k + 1].cpu - inst.options[n][k].cpu
        if step <= loads.free(loads.scale_of[n]) + TOLERANCE:
            loads.set_choice(n, k + 1)
            if k + 2 < len(inst.options[n]):
                heapq.heappush(heap, (-_gradient(inst, loads, n), n))


def _min_step(inst: Instance) -> float:
    steps = [o.cpu - inst.options[n][k].cpu for n in inst.configurable
             for k, o in enumerate(inst.options[n][1:])]
    return min((s for s in steps if s > 0), default=1.0)


def _full_scales(inst: Instance, loads: Loads, step: float) -> List[int]:
    return [s for s in range(len(inst.scales)) if loads.free(s) < step - TOLERANCE]


def _relocate(inst: Instance, loads: Loads, full: List[int], upgradeable_only: bool) -> None:
    """Algorithm 1, lines 9-11 and 14-15: move one node (its coresidence unit) off each full
    scale to the not-full scale with the most free CPU that takes it. Nodes are tried by
    gradient, best first; with ``upgradeable_only`` only nodes below their top setting."""
    full_set = set(full)
    for s in full:
        def key(u):
            grads = [_gradient(inst, loads, n) for n in inst.units[u] if n in inst.configurable]
            return (-max(grads, default=float('-inf')), -loads.unit_cpu(u), u)
        candidates = sorted(loads.members[s], key=key)
        if upgradeable_only:
            candidates = [u for u in candidates
                          if any(loads.choice[n] + 1 < len(inst.options[n])
                                 for n in inst.units[u])]
        for u in candidates:
            targets = sorted((t for t in inst.unit_allowed[u] if t != s and t not in full_set),
                             key=lambda t: (-loads.free(t), t))
            if any(loads.try_moves([(u, t)]) for t in targets):
                break      # the scale is no longer full: one move per full scale


def paper_problem1(inst: Instance) -> Outcome:
    """Algorithm 1 of the paper (with Algorithm 2 as its upgrade step)."""
    loads = Loads(inst, [0] * len(inst.nodes))
    reason = _initial_allocation(inst, loads, paper=True)
    if reason:
        return Outcome(None, reason)
    if not inst.configurable:
        return Outcome(loads)
    step = _min_step(inst)
    _upgrade(inst, loads)
    _relocate(inst, loads, _full_scales(inst, loads, step), upgradeable_only=True)
    _upgrade(inst, loads)
    _relocate(inst, loads, _full_scales(inst, loads, step), upgradeable_only=False)
    _upgrade(inst, loads)
    return Outcome(loads)


class _ScaleValues:
    """Best settings per (scale, set of units on it), memoised."""

    def __init__(self, inst: Instance):
        self.inst = inst
        self.cache: Dict[Tuple[int, FrozenSet[int]], Optional[Tuple[float, Dict[int, int]]]] = {}

    def __call__(self, s: int, units: FrozenSet[int]) -> Optional[ScaleValue]:
        key = (s, units)
        if key not in self.cache:
            inst = self.inst
            fixed = 0.0
            conf = []
            for u in units:
                for n in inst.units[u]:
                    if len(inst.options[n]) > 1:
                        conf.append(n)
                    else:
                        fixed += inst.options[n][0].cpu
            conf.sort()
            self.cache[key] = best_settings(inst, conf, inst.capacity[s] - fixed)
        return self.cache[key]


def _targets(inst: Instance, loads: Loads, u: int, s: int) -> List[int]:
    allowed = [t for t in inst.unit_allowed[u] if t != s]
    if len(inst.scales) <= ALL_TARGETS_UP_TO:
        return allowed
    near = {loads.scale_of[m] for n in inst.units[u] for m, _ in inst.neighbours[n]}
    roomy = sorted(allowed, key=lambda t: -loads.free(t))[:NEAR_TARGETS]
    return [t for t in allowed if t in near or t in roomy]


def improve_problem1(inst: Instance, loads: Loads, clock: Clock, deadline: float
                     ) -> Tuple[Loads, bool]:
    """Local search: re-upgrade every scale exactly, then move and swap units while the total
    weighted performance rises, each candidate re-checked for links and CPU. Returns the loads
    and whether a local optimum was reached (False: the deadline came first)."""
    values = _ScaleValues(inst)
    members = [frozenset(m) for m in loads.members]

    def apply(s: int, result: ScaleValue) -> None:
        for n, k in result[1].items():
            loads.set_choice(n, k)

    # Exact re-upgrade of the current layout (settings only).
    current = []
    for s in range(len(inst.scales)):
        result = values(s, members[s])
        if result is None:        # cannot happen for a feasible layout; keep it as it is
            current.append(sum(inst.value(n, loads.choice[n]) for u in members[s]
                               for n in inst.units[u] if len(inst.options[n]) > 1))
            continue
        for u in members[s]:
            for n in inst.units[u]:
                loads.set_choice(n, 0)
        apply(s, result)
        current.append(result[0])
    if not inst.configurable:
        return loads, True
    swaps = len(inst.units) <= ALL_SWAPS_UP_TO
    improved = True
    while improved and clock() < deadline:
        improved = False
        for u in range(len(inst.units)):
            if clock() >= deadline:
                break
            s = loads.unit_scale(u)
            best_gain, best = TOLERANCE, None
            candidates: List[Tuple[Tuple[int, int], ...]] = [
                ((u, t),) for t in _targets(inst, loads, u, s)]
            if swaps:
                candidates += [((u, loads.unit_scale(v)), (v, s)) for v in range(len(inst.units))
                               if v != u and loads.unit_scale(v) != s
                               and loads.unit_scale(v) in inst.unit_allowed[u]
                               and s in inst.unit_allowed[v]]
            for moves in candidates:
                t = moves[0][1]
                new_s, new_t = set(members[s]), set(members[t])
                new_s.discard(u)
                new_t.add(u)
                if len(moves) == 2:
                    v = moves[1][0]
                    new_t.discard(v)
                    new_s.add(v)
                vs = values(s, frozenset(new_s))
                if vs is None:
                    continue
                vt = values(t, frozenset(new_t))
                if vt is None:
                    continue
                gain = vs[0] + vt[0] - current[s] - current[t]
                if gain > best_gain and _links_allow(loads, moves):
                    best_gain = gain
                    best = (moves, t, vs, vt, frozenset(new_s), frozenset(new_t))
            if best is None:
                continue
            moves, t, vs, vt, chosen_s, chosen_t = best
            for moved, _ in moves:
                loads.unplace(moved)
            for moved, target in moves:
                loads.place(moved, target)
            for scale in (s, t):
                for w in (chosen_s if scale == s else chosen_t):
                    for n in inst.units[w]:
                        loads.set_choice(n, 0)
            apply(s, vs)
            apply(t, vt)
            members[s], members[t] = chosen_s, chosen_t
            current[s], current[t] = vs[0], vt[0]
            improved = True
    return loads, not improved


def _links_allow(loads: Loads, moves: Sequence[Tuple[int, int]]) -> bool:
    """Whether the moves keep every link present and within bandwidth (CPU not judged)."""
    origins = [(u, loads.unit_scale(u)) for u, _ in moves]
    before = loads.no_link
    touched: List[int] = []
    for u, _ in moves:
        touched += loads.unplace(u)
    for u, s in moves:
        touched += loads.place(u, s)
    ok = loads.no_link <= before and all(loads.link_ok(li) for li in touched)
    for u, _ in moves:
        loads.unplace(u)
    for u, s in origins:
        loads.place(u, s)
    return ok


def construct_problem1(inst: Instance) -> Outcome:
    """The paper's greedy, or (when its allocation order finds no room) the most-constrained-
    first allocation followed by the same upgrades."""
    first = paper_problem1(inst)
    if first.loads is not None:
        return first
    loads = Loads(inst, [0] * len(inst.nodes))
    if _initial_allocation(inst, loads, paper=False):
        return first
    _upgrade(inst, loads)
    return Outcome(loads)


# --- Problem 2 ------------------------------------------------------------------------------
def paper_problem2(inst: Instance) -> Outcome:
    """Algorithm 3: nodes by CPU from the largest, residence nodes first, each on the first
    computer in increasing capacity order that holds it; a server that cannot grows to fit.

    Servers start at 0 and so come first in the order, but a server has no free capacity until
    it grows; the reading taken is that a node goes to the first fixed computer with room and
    otherwise to the first server it may use, which grows by exactly the node's CPU. A
    coresidence group is placed as one unit (the paper's CoRes check).
    """
    loads = Loads(inst, [0] * len(inst.nodes))
    order = sorted(range(len(inst.scales)),
                   key=lambda s: (0.0 if inst.growable[s] else inst.capacity[s], s))
    units = sorted(range(len(inst.units)),
                   key=lambda u: (0 if _has_residence(inst, u) else 1, -loads.unit_cpu(u), u))
    for u in units:
        allowed = set(inst.unit_allowed[u])
        fixed = [s for s in order if s in allowed and not inst.growable[s]]
        grow = [s for s in order if s in allowed and inst.growable[s]]
        for s in fixed + grow:
            if loads.fits(u, s):
                loads.place(u, s)
                break
        else:
            return Outcome(None, (_why_not(inst, loads, u),))
    return Outcome(loads)


def improve_problem2(inst: Instance, loads: Loads, clock: Clock, deadline: float
                     ) -> Tuple[Loads, bool]:
    """Local search that moves CPU from growable servers onto fixed computers: single moves,
    swaps, and an exact refill (subset sum) of each fixed computer, every change re-checked."""
    fixed = [s for s in range(len(inst.scales)) if not inst.growable[s]]
    if not fixed or not any(inst.growable):
        return loads, True
    cpu = [loads.unit_cpu(u) for u in range(len(inst.units))]
    q = _grid_of(cpu)

    def growable_for(u: int) -> List[int]:
        return [s for s in inst.unit_allowed[u] if inst.growable[s]]

    improved = True
    while improved and clock() < deadline:
        improved = False
        for f in fixed:
            if clock() >= deadline:
                break
            stay: List[int] = []
            pool: List[int] = []
            for u in range(len(inst.units)):
                s = loads.unit_scale(u)
                if s == f:
                    (pool if growable_for(u) else stay).append(u)
                elif inst.growable[s] and f in inst.unit_allowed[u]:
                    pool.append(u)
            room = inst.capacity[f] - sum(cpu[u] for u in stay)
            before = sum(cpu[u] for u in pool if loads.unit_scale(u) == f)
            chosen = set(pool[i] for i in best_fill([cpu[u] for u in pool], room, q))
            if sum(cpu[u] for u in chosen) <= before + TOLERANCE:
                continue
            moves = [(u, f) for u in pool if u in chosen and loads.unit_scale(u) != f]
            leaving = [u for u in pool if u not in chosen and loads.unit_scale(u) == f]
            if _try_with_growable(loads, moves, leaving, growable_for):
                improved = True
        # Swaps between a fixed computer and a server whose exact refill missed a link limit.
        for u in range(len(inst.units)):
            s = loads.unit_scale(u)
            if not inst.growable[s]:
                continue
            for f in inst.unit_allowed[u]:
                if inst.growable[f]:
                    continue
                if loads.try_moves([(u, f)]):
                    improved = True
                    break
    return loads, not improved


def _try_with_growable(loads: Loads, moves, leaving, growable_for) -> bool:
    """Apply moves onto a fixed computer, sending the units leaving it to a server they may
    use (the first whose links take them)."""
    options = [growable_for(u) for u in leaving]
    plan = list(moves) + [(u, opts[0]) for u, opts in zip(leaving, options)]
    if loads.try_moves(plan):
        return True
    # Links refused the first choice of server: try each leaving unit's other servers.
    for i, (u, opts) in enumerate(zip(leaving, options)):
        for alt in opts[1:]:
            trial = list(plan)
            trial[len(moves) + i] = (u, alt)
            if loads.try_moves(trial):
                return True
    return False


def _grid_of(values: Sequence[float]) -> float:
    for q in (1.0, 0.5, 0.25, 0.2, 0.1, 0.05, 0.02, 0.01):
        if all(abs(v / q - round(v / q)) < 1e-9 for v in values):
            return q
    return 0.01
