"""Laps and experiments: drive a policy around the path, compare with no migration and the oracle.

A lap runs the live decider's turn (``runtime.turn.DeciderTurn``) around the policy: every
period the turn gets the world's observations and the world's clock, and the world applies the
moves it returns. The first layout, the events, the plan check and the cost integral (Eq. 2)
are the turn's, as in the live decider.

Improvement of a lap = (1 - T_lap / T_no_migration) x 100: the share of the path time saved, as
the paper reports the test-bed's 28 %. Distance from the oracle = (1 - T_oracle / T_lap) x 100:
the share of the optimum's performance (1 / time) the policy gives up.

Runs use common random numbers: run r draws its link schedules from ``(seed, r)`` for the remote
scales in ladder order, so the laptop's coverage in run r is the same in every system and the
comparison across K and across policies is not blurred by different draws.
"""

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable, Dict, List, Mapping, Optional, Protocol, Sequence, Tuple

import numpy as np

from ..model.types import DeciderSettings
from ..runtime.policy import MigrationPolicy
from ..runtime.turn import DeciderTurn, EventTuple, TurnPolicy
from .model import PathModel, SimSystem, node_rate, robot_speed
from .oracle import Assignment, LinkBudget
from .path import LinkSchedule, best_case_schedules, draw_schedules
from .planner_policy import PlannerPolicy
from .systems import REMOTE_LADDER
from .world import World

HEURISTIC = 'heuristic'
PLANNER = 'planner'
POLICIES = (HEURISTIC, PLANNER)
ORACLE_KBPS_STEP = 100.0   # the oracle sees available bandwidth rounded down to this


class SimPolicy(TurnPolicy, Protocol):
    """A policy the simulator drives: what the turn asks of it, and the settings it runs on
    (the turn runs on the same)."""

    @property
    def settings(self) -> DeciderSettings: ...


def make_policy(name: str, system: SimSystem, migration: bool = True,
                overrides: Optional[Mapping[str, Any]] = None) -> SimPolicy:
    """The real runtime policy (``heuristic``) or the planner-backed one, fresh for one lap.

    ``overrides`` changes decider settings (e.g. ``hysteresis_s``) for a sensitivity study.
    """
    settings = replace(system.deployment.decider, migration=migration, **dict(overrides or {}))
    if name == HEURISTIC:
        return MigrationPolicy(system.deployment, settings)
    if name == PLANNER:
        return PlannerPolicy(system.deployment, settings)
    raise ValueError(f'unknown policy {name!r}: expected one of {", ".join(POLICIES)}')


@dataclass(frozen=True)
class Lap:
    time_s: float
    finished: bool
    migrations: int = 0
    perf_map_mean: float = 0.0       # the paper's cost function, time-averaged over the lap
    steps: int = 0
    delta_violations: int = 0        # stretches below freq_min past Δ (World.delta_violations)


def peak_kbps(system: SimSystem, path: PathModel) -> Dict[str, float]:
    d = system.deployment
    out = {}
    for s in d.remote_scales:
        link = d.link_between(d.master.name, s.name)
        out[s.name] = (link.bandwidth_kbps if link else 0.0) * path.throughput_fraction
    return out


def drive(system: SimSystem, schedules: Mapping[str, LinkSchedule], path: PathModel,
          policy: SimPolicy, max_time_s: Optional[float] = None,
          trace: Optional[List[Tuple[float, float, float, Dict[str, str]]]] = None,
          said: Optional[List[EventTuple]] = None) -> Lap:
    """One lap: the decider's turn around ``policy`` every period, on the world's observations
    and clock. ``trace`` collects (t, s, v, layout), ``said`` every event the turn said."""
    world = World(system, schedules, path)
    turn = DeciderTurn(system.deployment, policy.settings, world.t, policy)
    dt = policy.settings.period_s
    limit = max_time_s if max_time_s is not None else 20.0 * path.length_m / path.speed_min_mps
    steps = 0
    while world.finish_time_s is None and world.t < limit:
        out = turn.turn(world.t, world.observe())
        world.apply(out.decisions)
        if said is not None:
            said.extend(out.events)
        if trace is not None:
            trace.append((world.t, world.s, world.speed_mps(), dict(world.placement)))
        world.advance(dt)
        steps += 1
    end = world.finish_time_s if world.finish_time_s is not None else world.t
    # The integral closes at the lap's end, with the layout that held until then.
    turn.cost.update(end, dict(world.placement))
    return Lap(time_s=end if world.finished else math.inf, finished=world.finished,
               migrations=world.migrations, perf_map_mean=turn.cost.mean, steps=steps,
               delta_violations=len(world.delta_violations))


def oracle_lap(system: SimSystem, schedules: Mapping[str, LinkSchedule],
               path: PathModel) -> Lap:
    """An upper bound: at every step the best layout for the link state, at once, for free."""
    d = system.deployment
    weights = {n: p.speed_weight for n, p in system.profiles.items()}
    assignment = Assignment(d, system.profiles, weights)
    gain = {s.name: d.worth(s.name) / d.worth(d.master.name) for s in d.scales}
    speed_nodes = system.speed_nodes
    cache: Dict[Tuple, float] = {}
    dt = d.decider.period_s
    t = s = 0.0
    while True:
        usable = {}
        for r, sched in schedules.items():
            if sched.up(s):
                kbps = math.floor(sched.available_kbps(s) / ORACLE_KBPS_STEP) * ORACLE_KBPS_STEP
                usable[r] = LinkBudget(available_kbps=kbps)
        key = tuple(sorted((r, b.available_kbps) for r, b in usable.items()))
        v = cache.get(key)
        if v is None:
            layout = assignment.solve(usable)
            delivered = {n: node_rate(system.profiles[n], gain[layout.get(n, d.master.name)])
                         for n in speed_nodes}
            v = cache[key] = robot_speed(path, system.profiles, delivered)
        if s + v * dt >= path.length_m:
            return Lap(time_s=t + (path.length_m - s) / v, finished=True)
        s += v * dt
        t += dt


@dataclass(frozen=True)
class RunRecord:
    run: int
    availability: Tuple[float, ...]    # per remote scale, in ladder order
    time_s: float
    improvement_pct: float
    oracle_time_s: float
    oracle_improvement_pct: float
    gap_to_oracle_pct: float
    migrations: int
    perf_map_gain_pct: float           # time-averaged Perf_map over the no-migration one


@dataclass(frozen=True)
class SystemResult:
    label: str
    n: int
    m: int
    k: int
    policy: str
    baseline_time_s: float
    best_case_time_s: float
    best_case_improvement_pct: float
    improvement_pct: float
    improvement_std_pct: float
    oracle_improvement_pct: float
    gap_to_oracle_pct: float
    perf_map_gain_pct: float
    runs: Tuple[RunRecord, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        out = asdict(self)
        out['runs'] = [asdict(r) for r in self.runs]
        return out


@dataclass(frozen=True)
class Experiment:
    policy: str
    runs: int
    seed: int
    path: PathModel
    systems: Tuple[SystemResult, ...]
    wall_s: float = 0.0
    simulated_s: float = 0.0
    overrides: Tuple[Tuple[str, object], ...] = ()

    def mean(self, figure: str) -> float:
        """A figure of every system (a SystemResult field), averaged over the systems."""
        return float(np.mean([getattr(s, figure) for s in self.systems]))

    def to_dict(self) -> dict:
        return {
            'policy': self.policy,
            'runs': self.runs,
            'seed': self.seed,
            'systems': [s.to_dict() for s in self.systems],
            'average_improvement_pct': self.mean('improvement_pct'),
            'best_case_improvement_pct': self.mean('best_case_improvement_pct'),
            'average_oracle_improvement_pct': self.mean('oracle_improvement_pct'),
            'average_gap_to_oracle_pct': self.mean('gap_to_oracle_pct'),
            'model': asdict(self.path),
            'decider_overrides': dict(self.overrides),
            'simulated_s': self.simulated_s,
            'wall_s': self.wall_s,
        }


def run_schedules(system: SimSystem, path: PathModel, seed: int,
                  run: int) -> Dict[str, LinkSchedule]:
    """Run ``run``'s link schedules for the system's remote scales (common random numbers)."""
    rng = np.random.default_rng([seed, run])
    remotes = [s.name for s in system.deployment.remote_scales]
    ladder = [name for name, _, _ in REMOTE_LADDER]
    order = ladder + [r for r in remotes if r not in ladder]
    full = draw_schedules(rng, path, order, {r: 1.0 for r in order})
    peaks = peak_kbps(system, path)
    return {r: LinkSchedule(full[r].length_m, full[r].outages, peaks[r], full[r].ramp_m)
            for r in remotes}


def _pct(t: float, base: float) -> float:
    if math.isnan(t):
        return math.nan
    return (1.0 - t / base) * 100.0 if math.isfinite(t) else -math.inf


def run_system(system: SimSystem, runs: int, seed: int, policy: str = HEURISTIC,
               path: PathModel = PathModel(), oracle: bool = True,
               overrides: Optional[Mapping[str, object]] = None) -> Tuple[SystemResult, float]:
    """All runs of one system; returns its result and the simulated seconds it took."""
    if runs < 1:
        raise ValueError(f'runs must be >= 1, got {runs}')
    remotes = [s.name for s in system.deployment.remote_scales]
    simulated = 0.0
    first = run_schedules(system, path, seed, 0)
    # The baseline is the runtime policy's own switch: migration off, everything on the master.
    base = drive(system, first, path, make_policy(HEURISTIC, system, migration=False))
    if not base.finished:
        raise RuntimeError(f'{system.label}: the no-migration lap did not finish')
    simulated += base.time_s
    best = drive(system, best_case_schedules(path, remotes, peak_kbps(system, path)), path,
                 make_policy(policy, system, overrides=overrides))
    simulated += best.time_s if best.finished else 0.0
    records = []
    for r in range(runs):
        schedules = run_schedules(system, path, seed, r)
        lap = drive(system, schedules, path, make_policy(policy, system, overrides=overrides))
        simulated += lap.time_s if lap.finished else 0.0
        if oracle:
            bound = oracle_lap(system, schedules, path)
            o_time = bound.time_s
        else:
            o_time = math.nan
        records.append(RunRecord(
            run=r, availability=tuple(round(schedules[x].availability, 4) for x in remotes),
            time_s=lap.time_s, improvement_pct=_pct(lap.time_s, base.time_s),
            oracle_time_s=o_time, oracle_improvement_pct=_pct(o_time, base.time_s),
            gap_to_oracle_pct=(1.0 - o_time / lap.time_s) * 100.0,
            migrations=lap.migrations,
            perf_map_gain_pct=(lap.perf_map_mean / base.perf_map_mean - 1.0) * 100.0))
    imp = [x.improvement_pct for x in records]
    result = SystemResult(
        label=system.label, n=system.n, m=system.m, k=system.k, policy=policy,
        baseline_time_s=base.time_s, best_case_time_s=best.time_s,
        best_case_improvement_pct=_pct(best.time_s, base.time_s),
        improvement_pct=float(np.mean(imp)), improvement_std_pct=float(np.std(imp)),
        oracle_improvement_pct=float(np.mean([x.oracle_improvement_pct for x in records])),
        gap_to_oracle_pct=float(np.mean([x.gap_to_oracle_pct for x in records])),
        perf_map_gain_pct=float(np.mean([x.perf_map_gain_pct for x in records])),
        runs=tuple(records))
    return result, simulated


def run_experiment(systems: Sequence[SimSystem], runs: int = 10, seed: int = 0,
                   policy: str = HEURISTIC, path: PathModel = PathModel(), oracle: bool = True,
                   progress: Optional[Callable[[SystemResult], None]] = None,
                   overrides: Optional[Mapping[str, object]] = None) -> Experiment:
    start = time.perf_counter()
    results, simulated = [], 0.0
    for system in systems:
        result, sim_s = run_system(system, runs, seed, policy, path, oracle, overrides)
        simulated += sim_s
        results.append(result)
        if progress is not None:
            progress(result)
    return Experiment(policy=policy, runs=runs, seed=seed, path=path, systems=tuple(results),
                      wall_s=time.perf_counter() - start, simulated_s=simulated,
                      overrides=tuple(sorted(dict(overrides or {}).items())))
