"""The dynamic migration policy: the ICAR 2015 paper's Algorithm 1, plus what a real system needs.

Each ``step(obs)`` is one turn of the paper's loop, taken once per decider period:

- if a constraint is violated (bandwidth required > available, a link down or silent, a
  connection below freq_min for longer than its Δ, a remote scale over its CPU), move the nodes
  of the migrated list that cause it to the next-best scale (the most powerful remote one that
  can host them now, else back to the master), and keep doing so while some link's required
  bandwidth exceeds what it has (the paper's do ... while);
- otherwise sort the migratable nodes on the master by CPU usage and the remote scales by power,
  and migrate the first node not migrated back within the hysteresis time T to the first scale
  that can host it (allowed there, CPU headroom, link up with the bandwidth available); when
  none moves, rebalance: a node on a remote scale moves to a more powerful one when the cost
  function gains enough (beyond the paper).

Additions a live system needs (documented in docs/decider.md): a grace period after each move
during which the moved node's connections are not judged; at most one move out per step, and
none while an earlier move is not yet running, nor before the scales it weighs have been
observed (link and CPU; a scale a node moved to: CPU measured after that node started there);
a move the agents do not apply in time is undone; nodes of a lost scale are relocated;
``migration: false`` never moves out (the paper's no-migration baseline). Every decision
carries its reason.

A silent agent is not a silent link: nothing is placed on a scale whose agent is silent
(``Observations.silent_agents``), the master included. When the master's agent is silent the
layout is kept as it is: no move back to the master (its agent could not start the node), no
move out of it (its agent could not stop the old copy). A node that no scale with a live agent
and a reachable link may host is reported in ``unplaceable`` with the reason, and stays where
the layout has it.

The policy decides the desired layout; it judges by what actually runs (``obs.running``).
"""

from dataclasses import replace
from typing import List, Mapping, Optional, Tuple

from ..model.placement import allowed
from ..model.types import DeciderSettings, Deployment, frozen_map
from .constraints import ConstraintReport, evaluate
from .delta import DeltaTracker
from .layout import adopt, default_scale, master_layout
from .moves.back import migrate_back
from .moves.failover import failover
from .moves.out import migrate_out
from .moves.pending import pending_timeout_s, settle_pending
from .moves.relocate import relocate_lost
from .moves.shared import shared_answers
from .moves.state import Memory, Step
from .observations import (FAILOVER, MIGRATE, MIGRATE_BACK, MOVE_AWAY, REBALANCE, RELOCATE,
                           YIELD, Decision, Observations)
from .upstream import UpstreamWatch


class MigrationPolicy:
    """Algorithm 1 with its state: the migrated list, migrate-back and move times, pending moves.

    Time comes only from ``obs.now``. The same object runs in the live decider, the simulator
    and the unit tests. Each step runs the moves of runtime/moves/ in turn over one
    observation snapshot; they read and change its ``Memory``.
    """

    def __init__(self, deployment: Deployment, settings: Optional[DeciderSettings] = None):
        self.deployment = deployment
        self.settings = settings or deployment.decider
        self.master = deployment.master.name
        self.memory = Memory()
        self.last_report: Optional[ConstraintReport] = None
        self.below_for: Mapping[str, float] = frozen_map()
        self.notes: Tuple[str, ...] = ()               # why nothing (more) moved this step
        # node -> why no scale with a live agent may host it (this step)
        self.unplaceable: Mapping[str, str] = frozen_map()
        self._delta = DeltaTracker(deployment)
        self._upstream = UpstreamWatch(deployment, self.settings)
        self._seeded = False

    # --- what the turn and the simulator read of any policy (PlannerPolicy has them too) ----
    @property
    def migrated(self) -> List[Tuple[str, str]]:
        """(node, scale) of each node migrated off the master, in migration order."""
        return self.memory.migrated

    @property
    def history(self) -> List[Tuple[float, Decision]]:
        return self.memory.history

    # --- configuration ----------------------------------------------------------------------
    def update_settings(self, settings: DeciderSettings) -> None:
        """New thresholds (changed at run time); state is kept."""
        self.settings = settings
        self._upstream.settings = settings

    def reset(self, layout: Mapping[str, str], now: float,
              running: Optional[Mapping[str, str]] = None, *, settled: bool = False) -> None:
        """Start from a given layout (the first layout the decider published).

        Nodes it places off the master enter the migrated list (in deployment order); they and
        the nodes it places elsewhere than they run (pending) get a grace period from ``now``
        (with ``settled``, a layout taken over from another decider: the pending ones only).
        Nothing moves out while a pending node is not yet running where it is placed, nor
        before its scale's CPU has been measured after it started there.
        """
        d, m = self.deployment, self.memory
        m.desired = {n: s for n, s in layout.items() if n in d.node_names}
        for n in d.node_names:
            if n not in m.desired and d.node(n).managed:
                m.desired[n] = default_scale(d, n)
        m.migrated = [(n, s) for n, s in m.desired.items()
                      if s != self.master and allowed(d, n, self.master).passed]
        m.pending = {n: (s, now) for n, s in m.desired.items()
                     if running is not None and running.get(n) != s}
        # Nodes placed off the master, or (re)started by this layout, get their grace period (on
        # the judging of their connections only). The first move out is held by the pending
        # moves and by the observations it needs (``migrate_out``), not by a fixed delay.
        m.last_move = {n: now for n, s in m.desired.items()
                       if n in m.pending or s != self.master and not settled}
        self._seeded = True
        if m.started is None:
            m.started = now

    # --- views ----------------------------------------------------------------------------
    @property
    def layout(self) -> Mapping[str, str]:
        """The desired layout (node -> scale) for every managed node."""
        return frozen_map(self.memory.desired)

    @property
    def grace_until(self) -> Mapping[str, float]:
        return self.memory.grace_until(self.settings.grace_s)

    @property
    def pending_timeout_s(self) -> float:
        """How long the agents get to apply a move before it is undone."""
        return pending_timeout_s(self.deployment, self.settings)

    # --- the loop ---------------------------------------------------------------------------
    def step(self, obs: Observations) -> List[Decision]:
        """One turn of Algorithm 1 at ``obs.now``; returns the moves to apply now."""
        now = obs.now
        if self.memory.started is None:
            self.memory.started = now
        names, scales = set(self.deployment.node_names), set(self.deployment.scale_names)
        running = {n: s for n, s in obs.running.items() if n in names and s in scales}
        self._upstream.update(obs, running)
        if not self._seeded:
            layout, _ = adopt(self.deployment, master_layout(self.deployment), running)
            self.reset(layout, now, running)
        step = Step(self.deployment, self.settings, obs, running, self.memory)
        step.hear()
        decisions = settle_pending(step)
        decisions += shared_answers(step)
        decisions += failover(step)

        self.below_for = self._delta.update(obs, self.settings)
        report = evaluate(self.deployment, self.settings, obs, self.grace_until,
                          below_for=self.below_for, since=self.memory.started)
        self.last_report = report
        snap = step.snapshot(report)

        decisions += relocate_lost(step, snap, decisions)
        back, actionable = migrate_back(step, snap, self._upstream, decisions)
        decisions += back
        if not actionable and not decisions:
            decisions += migrate_out(step, snap)
        for d in decisions:
            self._apply(d, now)
        self.notes = tuple(step.notes)
        self.unplaceable = frozen_map(step.unplaceable)
        return decisions

    def heard(self, kind: str, node: str, from_scale: str, now: float) -> None:
        """Another decider's decision (a standby hears the leader's): its hysteresis and
        failover memory, kept for the day this one takes over."""
        if node not in self.deployment.node_names:
            return
        m = self.memory
        if kind in (MIGRATE, REBALANCE):
            m.last_move_out = now
        elif kind in (MIGRATE_BACK, MOVE_AWAY, RELOCATE, FAILOVER):
            m.last_back[(node, from_scale)] = now
            if kind == FAILOVER:
                m.crashed[(node, from_scale)] = now

    def _apply(self, d: Decision, now: float) -> None:
        m = self.memory
        m.desired[d.node] = d.to_scale
        m.migrated = [(n, s) for n, s in m.migrated if n != d.node]
        if d.to_scale != self.master and allowed(self.deployment, d.node, self.master).passed:
            m.migrated.append((d.node, d.to_scale))
        if d.kind in (MIGRATE, REBALANCE):
            m.last_move_out = now
        elif d.kind != YIELD:
            m.last_back[(d.node, d.from_scale)] = now
        m.last_move[d.node] = now
        m.pending[d.node] = (d.to_scale, now)
        m.history.append((now, d))


def with_settings(deployment: Deployment, **changes) -> DeciderSettings:
    """The deployment's decider settings with some fields changed (validated by the caller)."""
    return replace(deployment.decider, **changes)


__all__ = ['MigrationPolicy', 'with_settings']
