"""The exact planner: both problems as one mixed-integer linear program, solved by HiGHS.

The model is the paper's, with its settings made exact rather than approximated:

* ``x[u, s]`` (binary): unit u (a node, or a coresidence group that moves as one) runs on
  scale s, for the scales its residence allows; each unit on exactly one scale.
* Problem 1 settings. A configurable node takes one of its options (every integer CPU share
  between its smallest and largest sample with the fitted performance, or, with discrete
  settings, one sample). When the options are consecutive integers and their performance is
  concave (log fits), an integer CPU variable ``v`` and a performance variable bounded by every
  chord between neighbouring options give exactly the fitted value at every integer (the
  chords of a concave sequence meet above it). Otherwise (the convex AMCL quadratic, discrete
  samples) a binary per option chooses one. No piecewise-linear approximation anywhere: the
  optimum is the optimum of the integer-share model.
* CPU on a scale: ``y[n, s]`` (continuous) carries node n's share on s, with
  ``cpu_min x <= y <= cpu_max x`` and ``sum_s y[n, s]`` = the node's share.
* Links: a connection between scales a and b loads link (a, b); ``f >= x[u_p, a] + x[u_q, b]
  - 1`` per orientation, and the link's load stays within its bandwidth. Links whose bandwidth
  exceeds the sum of all connections cannot bind and are left out. A connection may never
  cross two scales without a link: ``x[u_p, a] + sum x[u_q, b] <= 1`` over those b.
* Problem 2: servers get a capacity variable ``R_s >= load``; minimise ``sum R_s``.

``optimal`` is reported only when HiGHS proves it (relative gap 0, absolute gap 1e-6).
"""

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from .highs import highspy, quiet_highs
from .instance import Instance
from .knapsack import best_settings

ABS_GAP = 1e-6


@dataclass
class ExactResult:
    placement: Optional[List[int]]
    choice: Optional[List[int]]
    optimal: bool
    infeasible: bool
    gap: Optional[float]
    status: str
    bound: Optional[float] = None
    stats: Dict[str, int] = field(default_factory=dict)
    model: str = ''


class _Model:
    def __init__(self):
        self.cost: List[float] = []
        self.lower: List[float] = []
        self.upper: List[float] = []
        self.integer: List[bool] = []
        self.row_lower: List[float] = []
        self.row_upper: List[float] = []
        self.start: List[int] = [0]
        self.index: List[int] = []
        self.value: List[float] = []

    def var(self, low: float, high: float, cost: float = 0.0, integer: bool = False) -> int:
        self.cost.append(cost)
        self.lower.append(low)
        self.upper.append(high)
        self.integer.append(integer)
        return len(self.cost) - 1

    def row(self, terms: Dict[int, float], low: float, high: float) -> None:
        for j, a in terms.items():
            if a != 0.0:
                self.index.append(j)
                self.value.append(a)
        self.start.append(len(self.index))
        self.row_lower.append(low)
        self.row_upper.append(high)

    def lp(self, maximise: bool, offset: float) -> 'highspy.HighsLp':
        lp = highspy.HighsLp()
        lp.num_col_ = len(self.cost)
        lp.num_row_ = len(self.row_lower)
        lp.col_cost_ = np.array(self.cost, dtype=float)
        lp.col_lower_ = np.array(self.lower, dtype=float)
        lp.col_upper_ = np.array(self.upper, dtype=float)
        lp.row_lower_ = np.array(self.row_lower, dtype=float)
        lp.row_upper_ = np.array(self.row_upper, dtype=float)
        lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
        lp.a_matrix_.num_col_ = lp.num_col_
        lp.a_matrix_.num_row_ = lp.num_row_
        lp.a_matrix_.start_ = np.array(self.start, dtype=np.int32)
        lp.a_matrix_.index_ = np.array(self.index, dtype=np.int32)
        lp.a_matrix_.value_ = np.array(self.value, dtype=float)
        lp.integrality_ = [highspy.HighsVarType.kInteger if i else
                           highspy.HighsVarType.kContinuous for i in self.integer]
        lp.sense_ = highspy.ObjSense.kMaximize if maximise else highspy.ObjSense.kMinimize
        lp.offset_ = offset
        return lp


def _concave_integer(opts) -> bool:
    """Options on consecutive integer CPU shares whose performance is concave."""
    cpus = [o.cpu for o in opts]
    if any(abs(c - round(c)) > 1e-9 for c in cpus):
        return False
    if any(abs(b - a - 1.0) > 1e-9 for a, b in zip(cpus, cpus[1:])):
        return False
    slopes = [b.performance - a.performance for a, b in zip(opts, opts[1:])]
    return all(s2 <= s1 + 1e-12 for s1, s2 in zip(slopes, slopes[1:]))


def _connections_inert(inst: Instance) -> bool:
    """No link can bind and every connection's ends have a link wherever they may run."""
    if any(inst.link_may_bind):
        return False
    for p, q, _, _ in inst.connections:
        for a in inst.unit_allowed[inst.unit_of[p]]:
            for b in inst.unit_allowed[inst.unit_of[q]]:
                if a != b and inst.link_of[a][b] < 0:
                    return False
    return True


Extract = Callable[[List[float]], Tuple[List[int], List[int]]]


def _capacity_rows(m: _Model, inst: Instance, cpu_terms: List[Dict[int, float]]) -> None:
    """CPU per scale; Problem 2 servers get a capacity variable (the objective) instead."""
    for s in range(len(inst.scales)):
        if inst.growable[s]:
            r = m.var(0.0, highspy.kHighsInf, cost=1.0)
            row = dict(cpu_terms[s])
            row[r] = -1.0
            m.row(row, -highspy.kHighsInf, 0.0)
        elif cpu_terms[s]:
            m.row(cpu_terms[s], -highspy.kHighsInf, inst.capacity[s])


def _chords(m: _Model, opts, p: int, v: int, count: int) -> None:
    """p <= perf(a) * count + slope * (v - cpu(a) * count) for each pair of neighbouring
    options: with count the 0/1 placement (or the number of nodes) this is the perspective of
    the concave curve through the options, exact at integer shares."""
    for a, b in zip(opts, opts[1:]):
        slope = b.performance - a.performance
        m.row({p: 1.0, v: -slope, count: -(a.performance - slope * a.cpu)},
              -highspy.kHighsInf, 0.0)


def _build_general(m: _Model, inst: Instance) -> Tuple[float, Extract]:
    """One binary per (unit, allowed scale); settings per node; links row by row."""
    INF = highspy.kHighsInf
    S = len(inst.scales)
    x: Dict[Tuple[int, int], int] = {}
    for u, allowed in enumerate(inst.unit_allowed):
        for s in allowed:
            x[u, s] = m.var(0.0, 1.0, integer=True)
        m.row({x[u, s]: 1.0 for s in allowed}, 1.0, 1.0)
    cpu_terms: List[Dict[int, float]] = [dict() for _ in range(S)]
    offset = 0.0
    choice_vars: Dict[int, List[int]] = {}
    level_vars: Dict[int, List[int]] = {}
    for n, opts in enumerate(inst.options):
        u = inst.unit_of[n]
        allowed = inst.unit_allowed[u]
        if len(opts) == 1:
            if inst.problem == 1:
                offset += inst.value(n, 0)
            for s in allowed:
                cpu_terms[s][x[u, s]] = cpu_terms[s].get(x[u, s], 0.0) + opts[0].cpu
            continue
        lo, hi = opts[0].cpu, opts[-1].cpu
        if _concave_integer(opts):
            # Per allowed scale: the share v and performance p there, both 0 unless the node
            # runs there.
            level_vars[n] = []
            for s in allowed:
                v = m.var(0.0, hi, integer=True)
                p = m.var(-INF, INF, cost=inst.weight[n])
                level_vars[n].append(v)
                m.row({v: 1.0, x[u, s]: -hi}, -INF, 0.0)
                m.row({v: 1.0, x[u, s]: -lo}, 0.0, INF)
                _chords(m, opts, p, v, x[u, s])
                cpu_terms[s][v] = 1.0
            continue
        zs = [m.var(0.0, 1.0, cost=inst.value(n, k), integer=True) for k in range(len(opts))]
        choice_vars[n] = zs
        m.row({z: 1.0 for z in zs}, 1.0, 1.0)
        share = {z: o.cpu for z, o in zip(zs, opts)}
        if len(allowed) == 1:
            for j, a in share.items():
                cpu_terms[allowed[0]][j] = a
            continue
        row = {}
        for s in allowed:
            y = m.var(0.0, hi)
            m.row({y: 1.0, x[u, s]: -hi}, -INF, 0.0)
            m.row({y: 1.0, x[u, s]: -lo}, 0.0, INF)
            cpu_terms[s][y] = 1.0
            row[y] = 1.0
        for j, a in share.items():
            row[j] = -a
        m.row(row, 0.0, 0.0)
    _capacity_rows(m, inst, cpu_terms)
    # Links: scales with no link between them never both hold the ends of a connection;
    # links that could bind carry the connections whose ends they join.
    link_rows: Dict[int, Dict[int, float]] = {}
    for p, q, bw, _ in inst.connections:
        up, uq = inst.unit_of[p], inst.unit_of[q]
        for a in inst.unit_allowed[up]:
            unlinked = [b for b in inst.unit_allowed[uq] if b != a and inst.link_of[a][b] < 0]
            if unlinked:
                m.row({x[up, a]: 1.0, **{x[uq, b]: 1.0 for b in unlinked}}, -INF, 1.0)
        for a in inst.unit_allowed[up]:
            for b in inst.unit_allowed[uq]:
                li = inst.link_of[a][b] if a != b else -1
                if li < 0 or not inst.link_may_bind[li]:
                    continue
                f = m.var(0.0, 1.0)
                m.row({f: 1.0, x[up, a]: -1.0, x[uq, b]: -1.0}, -1.0, INF)
                link_rows.setdefault(li, {})[f] = bw
    for li, row in link_rows.items():
        m.row(row, -INF, inst.link_capacity[li])

    def extract(col: List[float]) -> Tuple[List[int], List[int]]:
        placement = [-1] * len(inst.nodes)
        for (u, s), j in x.items():
            if col[j] > 0.5:
                for n in inst.units[u]:
                    placement[n] = s
        choice = [0] * len(inst.nodes)
        for n, zs in choice_vars.items():
            choice[n] = int(np.argmax([col[z] for z in zs]))
        for n, vs in level_vars.items():
            choice[n] = _option_at(inst, n, round(sum(col[v] for v in vs)))
        return placement, choice
    return offset, extract


def _option_at(inst: Instance, n: int, cpu: float) -> int:
    return min(range(len(inst.options[n])), key=lambda k: abs(inst.options[n][k].cpu - cpu))


def _classes(inst: Instance) -> Optional[List[List[int]]]:
    """Units grouped by everything the model sees of them (members' options and weights,
    allowed scales); None when a unit has two configurable members."""
    classes: Dict[tuple, List[int]] = {}
    for u, members in enumerate(inst.units):
        if sum(1 for n in members if len(inst.options[n]) > 1) > 1:
            return None
        sig = (tuple(sorted((tuple((o.cpu, o.performance) for o in inst.options[n]),
                             inst.weight[n]) for n in members)), inst.unit_allowed[u])
        classes.setdefault(sig, []).append(u)
    return list(classes.values())


def _scale_orbits(inst: Instance, classes: List[List[int]]) -> List[List[int]]:
    """Groups of scales any two of which can be swapped without changing the model."""
    signature: Dict[Tuple[object, Tuple[int, ...]], int] = {}
    for units in classes:
        u = units[0]
        sig = tuple(sorted((tuple((o.cpu, o.performance) for o in inst.options[n]),
                            inst.weight[n]) for n in inst.units[u]))
        key = (sig, inst.unit_allowed[u])
        signature[key] = signature.get(key, 0) + len(units)

    def swaps(a: int, b: int) -> bool:
        if (inst.capacity[a], inst.growable[a]) != (inst.capacity[b], inst.growable[b]):
            return False
        image: Dict[tuple, int] = {}
        for (sig, allowed), size in signature.items():
            mapped = tuple(sorted(b if s == a else a if s == b else s for s in allowed))
            image[sig, mapped] = image.get((sig, mapped), 0) + size
        return image == signature

    groups: List[List[int]] = []
    for s in range(len(inst.scales)):
        for g in groups:
            if swaps(g[0], s):
                g.append(s)
                break
        else:
            groups.append([s])
    return [g for g in groups if len(g) > 1]


def _build_aggregated(m: _Model, inst: Instance, classes: List[List[int]]
                      ) -> Tuple[float, Extract]:
    """When links can neither bind nor be missing, units that look alike to the model are
    interchangeable: count how many of each class run on each scale (and at which setting)
    instead of naming them. Same optimum, none of the symmetric copies."""
    INF = highspy.kHighsInf
    S = len(inst.scales)
    cpu_terms: List[Dict[int, float]] = [dict() for _ in range(S)]
    offset = 0.0
    parts = []
    for units in classes:
        size = len(units)
        allowed = inst.unit_allowed[units[0]]
        members = inst.units[units[0]]
        conf = [n for n in members if len(inst.options[n]) > 1]
        fixed_cpu = sum(inst.options[n][0].cpu for n in members if n not in conf)
        if inst.problem == 1:
            offset += size * sum(inst.value(n, 0) for n in members if n not in conf)
        count = {s: m.var(0.0, size, integer=True) for s in allowed}
        m.row({c: 1.0 for c in count.values()}, size, size)
        for s in allowed:
            if fixed_cpu:
                cpu_terms[s][count[s]] = fixed_cpu
        kind = 'fixed'
        level: Dict[int, int] = {}              # concave: scale -> its total-share variable
        picks: Dict[int, List[int]] = {}        # choice: scale -> a count variable per option
        if conf:
            n = conf[0]
            opts = inst.options[n]
            lo, hi = opts[0].cpu, opts[-1].cpu
            if _concave_integer(opts):
                kind = 'concave'
                for s in allowed:
                    v = m.var(0.0, hi * size, integer=True)
                    p = m.var(-INF, INF, cost=inst.weight[n])
                    m.row({v: 1.0, count[s]: -hi}, -INF, 0.0)
                    m.row({v: 1.0, count[s]: -lo}, 0.0, INF)
                    _chords(m, opts, p, v, count[s])
                    cpu_terms[s][v] = cpu_terms[s].get(v, 0.0) + 1.0
                    level[s] = v
            else:
                kind = 'choice'
                for s in allowed:
                    ws = [m.var(0.0, size, cost=inst.value(n, k), integer=True)
                          for k in range(len(opts))]
                    row = {w: 1.0 for w in ws}
                    row[count[s]] = -1.0
                    m.row(row, 0.0, 0.0)
                    for w, o in zip(ws, opts):
                        cpu_terms[s][w] = o.cpu
                    picks[s] = ws
        parts.append((units, count, kind, level, picks, conf))
    _capacity_rows(m, inst, cpu_terms)
    # Interchangeable scales (same capacity, and swapping them maps every class onto a class
    # alike): order them by load, which keeps one of each set of mirror-image layouts.
    for group in _scale_orbits(inst, classes):
        for a, b in zip(group, group[1:]):
            row = dict(cpu_terms[a])
            for j, coef in cpu_terms[b].items():
                row[j] = row.get(j, 0.0) - coef
            m.row(row, 0.0, INF)

    def extract(col: List[float]) -> Tuple[List[int], List[int]]:
        placement = [-1] * len(inst.nodes)
        choice = [0] * len(inst.nodes)
        for units, count, kind, level, picks, conf in parts:
            todo = list(units)
            for s, c in count.items():
                here = [todo.pop(0) for _ in range(min(int(round(col[c])), len(todo)))]
                settings: List[int] = []
                if kind == 'concave' and here:
                    n0 = conf[0]
                    base, more = divmod(int(round(col[level[s]])), len(here))
                    settings = [_option_at(inst, n0, base + (1 if i < more else 0))
                                for i in range(len(here))]
                elif kind == 'choice':
                    for k, w in enumerate(picks[s]):
                        settings += [k] * int(round(col[w]))
                for i, u in enumerate(here):
                    for n in inst.units[u]:
                        placement[n] = s
                        if len(inst.options[n]) > 1 and i < len(settings):
                            choice[n] = settings[i]
        return placement, choice
    return offset, extract


MAX_CONFIGURATIONS = 20_000


def _configurations(inst: Instance, classes: List[List[int]], s: int
                    ) -> Optional[List[Tuple[Tuple[int, ...], float]]]:
    """Every way to fill scale s with so many units of each class, with the best weighted
    performance of its configurable nodes there (a knapsack over their settings, exact on the
    instance's CPU grid); None when there are too many."""
    q = inst.quantum
    size = int(math.floor(inst.capacity[s] / q + 1e-9)) + 1
    here = [i for i, units in enumerate(classes) if s in inst.unit_allowed[units[0]]]
    # Per class here: its fixed CPU, its configurable node's smallest share, and that node's
    # (steps on the grid, values) per option, None when it has none.
    info: List[Tuple[float, float, Optional[Tuple[np.ndarray, np.ndarray]]]] = []
    for i in here:
        members = inst.units[classes[i][0]]
        conf = [n for n in members if len(inst.options[n]) > 1]
        fixed = sum(inst.options[n][0].cpu for n in members if n not in conf)
        if conf:
            n = conf[0]
            opts = inst.options[n]
            steps = np.array([int(round((o.cpu - opts[0].cpu) / q)) for o in opts])
            values = np.array([inst.value(n, k) for k in range(len(opts))])
            info.append((fixed, opts[0].cpu, (steps, values)))
        else:
            info.append((fixed, 0.0, None))
    out: List[Tuple[Tuple[int, ...], float]] = []
    counts = [0] * len(classes)
    grid = np.arange(size)

    def add(dp: np.ndarray, steps: np.ndarray, values: np.ndarray) -> np.ndarray:
        idx = grid[None, :] - steps[:, None]
        cand = np.where(idx >= 0, dp[np.clip(idx, 0, None)] + values[:, None], -np.inf)
        return cand.max(axis=0)

    def walk(j: int, used: float, dp: np.ndarray) -> bool:
        if len(out) > MAX_CONFIGURATIONS:
            return False
        if j == len(here):
            spare = int(math.floor((inst.capacity[s] - used) / q + 1e-9))
            out.append((tuple(counts), float(dp[min(spare, size - 1)])))
            return True
        i = here[j]
        fixed, low, curve = info[j]
        pinned = len(inst.unit_allowed[classes[i][0]]) == 1
        k_min = len(classes[i]) if pinned else 0
        for k in range(0, len(classes[i]) + 1):
            if used > inst.capacity[s] + 1e-6:
                break
            if k >= k_min:
                counts[i] = k
                if not walk(j + 1, used, dp):
                    return False
            used += fixed + low
            if curve is not None:
                dp = add(dp, *curve)
        counts[i] = 0
        return True

    if not walk(0, 0.0, np.zeros(size)):
        return None
    return out


def _build_configurations(m: _Model, inst: Instance, classes: List[List[int]]
                          ) -> Optional[Tuple[float, Extract]]:
    """Problem 1 with inert links as a choice of one configuration per scale (how many units
    of each class it runs, valued by its exact best settings). Its relaxation is far tighter
    than the compact model's, which is what proves the case-study optima in milliseconds."""
    if inst.problem != 1 or any(inst.growable) or inst.quantum not in (1.0, 0.5, 0.25):
        return None
    if any(abs(o.cpu - inst.options[n][0].cpu) / inst.quantum
           - round(abs(o.cpu - inst.options[n][0].cpu) / inst.quantum) > 1e-9
           for n in inst.configurable for o in inst.options[n]):
        return None
    per_scale = []
    total = 0
    for s in range(len(inst.scales)):
        configs = _configurations(inst, classes, s)
        if configs is None:
            return None
        total += len(configs)
        if total > MAX_CONFIGURATIONS:
            return None
        per_scale.append(configs)
    offset = sum(inst.value(n, 0) for n in range(len(inst.nodes)) if len(inst.options[n]) == 1)
    lam: List[List[int]] = []
    class_rows: List[Dict[int, float]] = [dict() for _ in classes]
    for s, configs in enumerate(per_scale):
        cols = [m.var(0.0, 1.0, cost=value, integer=True) for _, value in configs]
        lam.append(cols)
        m.row({c: 1.0 for c in cols}, 1.0, 1.0)
        for c, (counts, _) in zip(cols, configs):
            for i, k in enumerate(counts):
                if k:
                    class_rows[i][c] = float(k)
    for i, row in enumerate(class_rows):
        m.row(row, len(classes[i]), len(classes[i]))

    def extract(col: List[float]) -> Tuple[List[int], List[int]]:
        placement = [-1] * len(inst.nodes)
        todo = [list(units) for units in classes]
        for s, cols in enumerate(lam):
            j = max(range(len(cols)), key=lambda c: col[cols[c]])
            for i, k in enumerate(per_scale[s][j][0]):
                for _ in range(min(k, len(todo[i]))):
                    for n in inst.units[todo[i].pop(0)]:
                        placement[n] = s
        choice = [0] * len(inst.nodes)
        for s in range(len(inst.scales)):
            nodes = [n for n in inst.configurable if placement[n] == s]
            fixed = sum(inst.options[n][0].cpu for n in range(len(inst.nodes))
                        if placement[n] == s and len(inst.options[n]) == 1)
            best = best_settings(inst, nodes, inst.capacity[s] - fixed)
            if best is not None:
                for n, k in best[1].items():
                    choice[n] = k
        return placement, choice
    return offset, extract


def solve_exact(inst: Instance, time_limit_s: float) -> ExactResult:
    if highspy is None:
        raise ImportError('the exact solver needs HiGHS: pip install highspy')
    if any(not a for a in inst.unit_allowed):
        return ExactResult(None, None, False, True, None, 'a node has no allowed scale')
    m = _Model()
    classes = _classes(inst) if _connections_inert(inst) else None
    model = 'general'
    built = None
    if classes is not None:
        built = _build_configurations(m, inst, classes)
        model = 'configurations'
        if built is None:
            m = _Model()
            built = _build_aggregated(m, inst, classes)
            model = 'aggregated'
    if built is None:
        built = _build_general(m, inst)
    offset, extract = built
    h = quiet_highs()
    h.setOptionValue('time_limit', float(time_limit_s))
    h.setOptionValue('mip_rel_gap', 0.0)
    h.setOptionValue('mip_abs_gap', ABS_GAP)
    h.setOptionValue('threads', 1)
    h.setOptionValue('random_seed', 0)
    h.passModel(m.lp(maximise=inst.problem == 1, offset=offset))
    h.run()
    status = h.getModelStatus()
    name = h.modelStatusToString(status)
    stats = {'columns': len(m.cost), 'rows': len(m.row_lower),
             'integer_columns': sum(m.integer)}
    if status == highspy.HighsModelStatus.kInfeasible:
        return ExactResult(None, None, False, True, None, name, stats=stats, model=model)
    info = h.getInfo()
    solution = h.getSolution()
    if not solution.value_valid:
        return ExactResult(None, None, False, False, None, name, stats=stats, model=model)
    placement, choice = extract(list(solution.col_value))
    gap = float(info.mip_gap) if math.isfinite(info.mip_gap) else None
    optimal = status == highspy.HighsModelStatus.kOptimal
    bound = float(info.mip_dual_bound) if math.isfinite(info.mip_dual_bound) else None
    return ExactResult(placement, choice, optimal, False, 0.0 if optimal and gap is None
                       else gap, name, bound, stats, model)
