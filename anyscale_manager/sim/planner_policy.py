"""A planner-backed policy: each period, the exact best layout for what is observed, and the
moves that reach it. Same ``step(obs)`` API as ``runtime.policy.MigrationPolicy``.

Where Algorithm 1 moves one node per step, only from the master, and keeps a migrated-back node
home for the hysteresis time T, this policy solves the assignment problem (``oracle.Assignment``)
over the scales whose links are up (and have stayed up for ``settle_s``) with the observed CPU and
bandwidth, and moves every node whose place differs, directly from one remote scale to another
when that is better. Its objective uses only the deployment: each migratable node's weight times
the quality its rate reaches on a scale (freq_min on the master, scaled by the gain alpha, up to
freq_opt), with the paper's cost function breaking ties. It judges constraints with the same
``runtime.constraints.evaluate`` as the heuristic; a node whose connections break their Δ on a
remote scale for another reason than the link is kept off that scale for T. It runs under the
decider's turn (``runtime.turn.DeciderTurn``) as the heuristic does: ``reset`` gives it the
first layout, ``layout`` and ``migrated`` say where it wants the nodes.
"""

import math
from typing import Dict, List, Mapping, Optional, Tuple

from ..model.types import DeciderSettings, Deployment, frozen_map
from ..runtime.constraints import CPU, FREQUENCY, ConstraintReport, evaluate, link_capacity, \
    node_cpu, scale_cpu
from ..runtime.delta import DeltaTracker
from ..runtime.observations import MIGRATE, MIGRATE_BACK, MOVE_AWAY, RELOCATE, Decision, \
    Observations
from .model import profiles_from_deployment
from .oracle import Assignment, LinkBudget

STICKY = 0.02        # a node moves only for at least this much more value (no churn)
KBPS_STEP = 100.0    # bandwidth is planned rounded down to this
BARRED = -1e6


class PlannerPolicy:
    """Plan-and-move policy; time comes only from ``obs.now``."""

    def __init__(self, deployment: Deployment, settings: Optional[DeciderSettings] = None,
                 weights: Optional[Mapping[str, float]] = None,
                 settle_s: Optional[float] = None):
        self.deployment = deployment
        self.settings = settings or deployment.decider
        self.master = deployment.master.name
        self.nodes = deployment.migratable_nodes
        if weights is None:
            weights = {n: deployment.node(n).weight for n in self.nodes}
        self.assignment = Assignment(deployment, profiles_from_deployment(deployment, {}),
                                     weights, self.settings.cpu_headroom,
                                     self.settings.bandwidth_margin)
        self.settle_s = self.settings.period_s if settle_s is None else settle_s
        self.pending: Dict[str, Tuple[str, float]] = {}
        self.last_move: Dict[str, float] = {}
        self.barred: Dict[Tuple[str, str], float] = {}
        self.up_since: Dict[str, float] = {}
        self.started: Optional[float] = None
        self.history: List[Tuple[float, Decision]] = []
        self.desired: Dict[str, str] = {}
        self.last_report: Optional[ConstraintReport] = None
        self.notes: Tuple[str, ...] = ()            # it always finds a layout: nothing to say
        self.unplaceable: Mapping[str, str] = frozen_map()
        self._delta = DeltaTracker(deployment)

    def update_settings(self, settings: DeciderSettings) -> None:
        """New thresholds; the assignment keeps the headroom and margin it was built with."""
        self.settings = settings

    def reset(self, layout: Mapping[str, str], now: float,
              running: Optional[Mapping[str, str]] = None, *, settled: bool = False) -> None:
        """Start from ``layout``: nodes not yet running where it places them are pending and get
        a grace period (without ``settled``, so do the nodes it places off the master)."""
        self.desired = {n: s for n, s in layout.items() if n in self.deployment.node_names}
        self.pending = {n: (s, now) for n, s in self.desired.items()
                        if n in self.nodes and running is not None and running.get(n) != s}
        self.last_move = {n: now for n, s in self.desired.items() if n in self.nodes
                          and (n in self.pending or s != self.master and not settled)}
        if self.started is None:
            self.started = now

    def heard(self, kind: str, node: str, from_scale: str, now: float) -> None:
        """Another decider's move back from a scale keeps the node off it for T, as its own."""
        if node in self.nodes and kind in (MIGRATE_BACK, MOVE_AWAY, RELOCATE):
            self.barred[(node, from_scale)] = now + self.settings.hysteresis_s

    @property
    def layout(self) -> Mapping[str, str]:
        return frozen_map(self.desired)

    @property
    def migrated(self) -> List[Tuple[str, str]]:
        return [(n, s) for n, s in self.desired.items() if n in self.nodes and s != self.master]

    @property
    def grace_until(self) -> Mapping[str, float]:
        return {n: t + self.settings.grace_s for n, t in self.last_move.items()}

    def step(self, obs: Observations) -> List[Decision]:
        now = obs.now
        if self.started is None:
            self.started = now
        d, s = self.deployment, self.settings
        running = dict(obs.running)
        timeout = d.agent.readiness_timeout_s + s.agent_timeout_s
        if not self.desired:
            self.desired = {n: running.get(n, self.master) for n in self.nodes}
        for node, (scale, asked) in list(self.pending.items()):
            if running.get(node) == scale:
                del self.pending[node]
            elif now - asked > timeout:
                del self.pending[node]
                self.desired[node] = running.get(node, self.master)   # never applied
        report = evaluate(d, s, obs, self.grace_until, below_for=self._delta.update(obs, s),
                          since=self.started)
        self.last_report = report
        for v in report.of_kind(FREQUENCY, CPU):
            for n in v.nodes:
                if n in self.nodes and running.get(n, self.master) != self.master:
                    self.barred[(n, running[n])] = now + s.hysteresis_s
        usable = self._usable(obs, running)
        bonus = {(n, running[n]): STICKY for n in self.nodes if n in running}
        for key, until in list(self.barred.items()):
            if until <= now:
                del self.barred[key]
            else:
                bonus[key] = BARRED
        if not s.migration:
            plan = {n: self.master for n in self.nodes}
        else:
            plan = self.assignment.solve(usable, bonus)
            plan = {n: (self.master if bonus.get((n, x), 0.0) <= BARRED else x)
                    for n, x in plan.items()}
        decisions = []
        for n in self.nodes:
            want, here = plan.get(n, self.master), running.get(n, self.master)
            if n in self.pending:
                if self.pending[n][0] == want:
                    continue
            elif here == want:
                continue
            decisions.append(self._decision(obs, n, here, want, usable))
        for dec in decisions:
            self.desired[dec.node] = dec.to_scale
            self.pending[dec.node] = (dec.to_scale, now)
            self.last_move[dec.node] = now
            self.history.append((now, dec))
        return decisions

    def _usable(self, obs: Observations, running: Mapping[str, str]) -> Dict[str, LinkBudget]:
        """Remote scales whose link is observed up (for ``settle_s``), with their budgets."""
        d, s, now = self.deployment, self.settings, obs.now
        out = {}
        for scale in d.remote_scales:
            name = scale.name
            link = d.link_between(self.master, name)
            if link is None or name in obs.lost_scales:
                self.up_since.pop(name, None)
                continue
            up, observed, available, _ = link_capacity(d, s, obs, link, self.started)
            if not (up and observed):
                self.up_since.pop(name, None)
                continue
            since = self.up_since.setdefault(name, now)
            hosting = any(running.get(n) == name for n in self.nodes)
            if now - since < self.settle_s and not hosting:
                continue
            used, _ = scale_cpu(d, s, obs, name)
            ours = sum(node_cpu(d, s, obs, n) for n in self.nodes if running.get(n) == name)
            out[name] = LinkBudget(available_kbps=math.floor(available / KBPS_STEP) * KBPS_STEP,
                                   background_cpu=round(max(0.0, used - ours), 1))
        return out

    def _decision(self, obs: Observations, node: str, here: str, want: str,
                  usable: Mapping[str, LinkBudget]) -> Decision:
        a = self.assignment
        gain = a.value[(node, want)] - a.value[(node, here)]
        if here in obs.lost_scales:
            return Decision(RELOCATE, node, here, want,
                            f'scale {here} lost; the plan places {node} on {want}')
        if want == self.master:
            why = 'its scale is unreachable' if here not in usable else \
                'the planned layout needs its place (CPU or bandwidth) for a better node'
            return Decision(MIGRATE_BACK, node, here, want, f'{node} back to {want}: {why}')
        budget = usable[want]
        return Decision(MIGRATE, node, here, want,
                        f'{node} to {want}: planned best layout (value {gain:+.3f}; link '
                        f'{budget.available_kbps:.0f} kbit/s available)'
                        if math.isfinite(gain) else f'{node} to {want}: planned best layout')
