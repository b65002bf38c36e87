"""``solve``: one entry to every planner, returning a frozen ``Plan``."""

import math
import time
from dataclasses import dataclass, field
from typing import Callable, List, Mapping, Optional, Sequence, Tuple

from ..model.types import Deployment, frozen_map
from .exact import solve_exact
from .feasibility import check_layout, explain_infeasible
from .greedy import (construct_problem1, improve_problem1, improve_problem2, paper_problem1,
                     paper_problem2)
from .instance import PROBLEMS, SETTINGS, Instance

SOLVERS = ('greedy', 'paper-greedy', 'exact')
# Our greedy's local search stops at a local optimum or after this long, whichever is first
# (never later than the caller's time limit).
IMPROVE_BUDGET_S = 1.2


@dataclass(frozen=True)
class Placement:
    """Where one node runs and how it is set."""

    scale: str
    cpu: float
    performance: float
    parameter_value: Optional[float] = None   # the parameter to set for that CPU share
    parameter: str = ''                       # its name ('' for a node without settings)


@dataclass(frozen=True)
class Plan:
    """A planner's answer. ``feasible`` False: ``layout`` is empty and ``violations`` say why."""

    problem: int
    solver: str
    objective: float              # Problem 1: weighted performance; Problem 2: server capacity
    layout: Mapping[str, Placement]
    server_capacity: Mapping[str, float]   # Problem 2: each server's grown capacity
    optimal: bool                 # proven optimal (exact solver only)
    gap: Optional[float]          # relative optimality gap when the exact solver knows it
    solve_time_s: float
    feasible: bool
    violations: Tuple[str, ...] = ()
    settings: str = 'continuous'
    scale_load: Mapping[str, float] = field(default_factory=frozen_map)   # CPU per scale
    link_load: Mapping[str, float] = field(default_factory=frozen_map)    # kbit/s per link
    status: str = ''              # the exact solver's model status, or the greedy's outcome

    def scale_of(self, node: str) -> str:
        return self.layout[node].scale

    def assignment(self) -> Mapping[str, str]:
        """node -> scale."""
        return frozen_map({n: p.scale for n, p in self.layout.items()})


def _plan(inst: Instance, solver: str, placement: Sequence[int], choice: Sequence[int],
          elapsed: float, optimal: bool = False, gap: Optional[float] = None,
          status: str = '') -> Plan:
    d = inst.deployment
    layout = {}
    for n, name in enumerate(inst.nodes):
        o = inst.options[n][choice[n]]
        profile = inst.profiles[n]
        layout[name] = Placement(inst.scales[placement[n]], o.cpu, o.performance,
                                 inst.parameter_value(n, choice[n]),
                                 profile.parameter if profile else '')
    capacity = {}
    if inst.problem == 2:
        load = inst.loads(placement, choice)
        capacity = {inst.scales[s]: load[s] for s in range(len(inst.scales))
                    if inst.growable[s]}
    cpu = {name: p.cpu for name, p in layout.items()}
    violations = check_layout(d, {n: p.scale for n, p in layout.items()}, cpu, capacity)
    scale_load = dict.fromkeys(inst.scales, 0.0)
    for p in layout.values():
        scale_load[p.scale] += p.cpu
    link_load = dict.fromkeys(inst.link_names, 0.0)
    for c in d.connections:
        a, b = inst.scale_index[layout[c.publisher].scale], \
            inst.scale_index[layout[c.subscriber].scale]
        li = inst.link_of[a][b] if a != b else -1
        if li >= 0:
            link_load[inst.link_names[li]] += c.bandwidth_kbps
    return Plan(problem=inst.problem, solver=solver,
                objective=inst.objective(placement, choice), layout=frozen_map(layout),
                server_capacity=frozen_map(capacity), optimal=optimal and not violations,
                gap=gap, solve_time_s=elapsed, feasible=not violations,
                violations=tuple(str(v) for v in violations), settings=inst.settings,
                scale_load=frozen_map(scale_load), link_load=frozen_map(link_load),
                status=status)


def _infeasible(inst: Instance, solver: str, elapsed: float, found: Sequence[str],
                status: str, proven: bool) -> Plan:
    reasons: List[str] = list(explain_infeasible(inst))
    proven = proven or bool(reasons)
    for r in found:
        if r not in reasons:
            reasons.append(r)
    if not reasons:
        reasons.append('no layout meets CPU, bandwidth, residence and coresidence together')
    if not proven and solver != 'exact':
        reasons.append(f'the {solver} solver found no feasible layout; the exact solver '
                       f'(--solver exact) decides whether one exists')
    return Plan(problem=inst.problem, solver=solver, objective=math.nan,
                layout=frozen_map(), server_capacity=frozen_map(), optimal=False, gap=None,
                solve_time_s=elapsed, feasible=False, violations=tuple(reasons),
                settings=inst.settings, status=status)


def solve(deployment: Deployment, problem: int = 1, solver: str = 'greedy',
          settings: str = 'continuous', time_limit_s: float = 10.0, *,
          clock: Callable[[], float] = time.perf_counter) -> Plan:
    """Plan node settings and placement for IROS 2016 Problem 1 (maximise the weighted sum of
    node performance) or Problem 2 (minimise the capacity of the servers, which grow from 0,
    with every node at its nominal setting).

    solver: ``greedy`` (the paper's greedy plus local search; the default), ``paper-greedy``
    (Algorithms 1-3 as published) or ``exact`` (MILP through HiGHS, within ``time_limit_s``).
    settings: ``continuous`` (any integer CPU share between a node's smallest and largest
    sample, performance from its fitted curve) or ``discrete`` (one of its samples). Nodes
    without settings (or with one sample) keep their ``cpu`` and ``performance``.

    A deployment with no feasible layout gives a Plan with ``feasible`` False whose
    ``violations`` name the constraints that cannot be met. Bad arguments raise ValueError.
    """
    if problem not in PROBLEMS:
        raise ValueError(f'problem must be 1 or 2, got {problem!r}')
    if solver not in SOLVERS:
        raise ValueError(f'solver must be one of {", ".join(SOLVERS)}, got {solver!r}')
    if settings not in SETTINGS:
        raise ValueError(f'settings must be one of {", ".join(SETTINGS)}, got {settings!r}')
    if not (isinstance(time_limit_s, (int, float)) and time_limit_s > 0
            and math.isfinite(time_limit_s)):
        raise ValueError(f'time_limit_s must be a positive number, got {time_limit_s!r}')
    start = clock()
    inst = Instance(deployment, problem, settings)
    if solver == 'exact':
        r = solve_exact(inst, time_limit_s)
        elapsed = clock() - start
        if r.placement is None or r.choice is None:
            found: Tuple[str, ...] = ()
            if not r.infeasible:
                found = (f'the exact solver stopped ({r.status}) before finding a feasible '
                         f'layout',)
            return _infeasible(inst, solver, elapsed, found, r.status, r.infeasible)
        return _plan(inst, solver, r.placement, r.choice, elapsed, r.optimal, r.gap, r.status)
    if problem == 1:
        outcome = paper_problem1(inst) if solver == 'paper-greedy' else construct_problem1(inst)
    else:
        outcome = paper_problem2(inst)
    if outcome.loads is None:
        return _infeasible(inst, solver, clock() - start, outcome.reason, 'no layout', False)
    loads = outcome.loads
    status = 'greedy'
    if solver == 'greedy':
        deadline = start + min(time_limit_s, IMPROVE_BUDGET_S)
        improve = improve_problem1 if problem == 1 else improve_problem2
        loads, converged = improve(inst, loads, clock, deadline)
        status = 'local optimum' if converged else 'local search stopped at its time budget'
    return _plan(inst, solver, loads.placement(), loads.choice, clock() - start, status=status)
