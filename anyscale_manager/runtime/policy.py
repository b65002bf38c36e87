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

import math
from dataclasses import replace
from typing import Dict, List, Mapping, Optional, Sequence, Set, Tuple

from ..model.types import DeciderSettings, Deployment, frozen_map
from .constraints import (CPU, FREQUENCY, LINK_DOWN, ConstraintReport, DeltaTracker, evaluate,
                          is_fresh, link_capacity, node_cpu, required_kbps, scale_cpu,
                          usable_cpu)
from .layout import adopt, default_scale, master_layout
from .upstream import UpstreamWatch
from .observations import (FAILOVER, MIGRATE, MIGRATE_BACK, MOVE_AWAY, REBALANCE, RELOCATE,
                           Decision, Observations)


class MigrationPolicy:
    """Algorithm 1 with its state: the migrated list, migrate-back and move times, pending moves.

    Time comes only from ``obs.now``. The same object runs in the live decider, the simulator
    and the unit tests.
    """

    def __init__(self, deployment: Deployment, settings: Optional[DeciderSettings] = None):
        self.deployment = deployment
        self.settings = settings or deployment.decider
        self.master = deployment.master.name
        self.desired: Dict[str, str] = {}
        self.migrated: List[Tuple[str, str]] = []      # (node, scale), in migration order
        # (node, scale it came back from) -> time of its last migrate-back (or relocation)
        self.last_back: Dict[Tuple[str, str], float] = {}
        self.last_move: Dict[str, float] = {}          # node -> time of its last move (grace)
        self.pending: Dict[str, Tuple[str, float]] = {}  # node -> (scale, when asked)
        # scale -> (when the last move there settled, the node that moved)
        self.arrived: Dict[str, Tuple[float, str]] = {}
        self.last_move_out = -math.inf
        self.started: Optional[float] = None
        self.last_report: Optional[ConstraintReport] = None
        self.below_for: Mapping[str, float] = frozen_map()
        self.notes: Tuple[str, ...] = ()               # why nothing (more) moved this step
        # node -> why no scale with a live agent may host it (this step)
        self.unplaceable: Mapping[str, str] = frozen_map()
        self.history: List[Tuple[float, Decision]] = []
        # (node, scale) -> when its copy there crashed and was failed over: one failover per
        # crash, and no failover back to that scale within the hysteresis T.
        self.crashed: Dict[Tuple[str, str], float] = {}
        self._delta = DeltaTracker(deployment)
        self._upstream = UpstreamWatch(deployment, self.settings)
        self._seeded = False

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
        self.desired = {n: s for n, s in layout.items() if n in self.deployment.node_names}
        for n in self.deployment.node_names:
            if n not in self.desired and self.deployment.node(n).managed:
                self.desired[n] = default_scale(self.deployment, n)
        self.migrated = [(n, s) for n, s in self.desired.items()
                         if s != self.master and self.master in self.deployment.allowed_scales(n)]
        self.pending = {n: (s, now) for n, s in self.desired.items()
                        if running is not None and running.get(n) != s}
        # Nodes placed off the master, or (re)started by this layout, get their grace period (on
        # the judging of their connections only). The first move out is held by the pending
        # moves and by the observations it needs (``_migrate_out``), not by a fixed delay.
        self.last_move = {n: now for n, s in self.desired.items()
                          if n in self.pending or s != self.master and not settled}
        self._seeded = True
        if self.started is None:
            self.started = now

    # --- views ----------------------------------------------------------------------------
    def _since_start(self, now: float) -> float:
        """Time since the first step (0 before it)."""
        return 0.0 if self.started is None else now - self.started

    @property
    def layout(self) -> Mapping[str, str]:
        """The desired layout (node -> scale) for every managed node."""
        return frozen_map(self.desired)

    @property
    def grace_until(self) -> Mapping[str, float]:
        return frozen_map({n: t + self.settings.grace_s for n, t in self.last_move.items()})

    @property
    def pending_timeout_s(self) -> float:
        """How long the agents get to apply a move before it is undone."""
        return self.deployment.agent.readiness_timeout_s + self.settings.agent_timeout_s

    # --- the loop ---------------------------------------------------------------------------
    def step(self, obs: Observations) -> List[Decision]:
        """One turn of Algorithm 1 at ``obs.now``; returns the moves to apply now."""
        now = obs.now
        if self.started is None:
            self.started = now
        running = self._running(obs)
        self._upstream.update(obs, running)
        if not self._seeded:
            layout, _ = adopt(self.deployment, master_layout(self.deployment), running)
            self.reset(layout, now, running)
        notes: List[str] = []
        decisions: List[Decision] = []
        self._unplaceable: Dict[str, str] = {}
        decisions += self._settle_pending(obs, running, now, notes)
        decisions += self._failover(obs, running, notes)

        self.below_for = self._delta.update(obs, self.settings)
        report = evaluate(self.deployment, self.settings, obs, self.grace_until,
                          below_for=self.below_for, since=self.started)
        self.last_report = report

        decisions += self._relocate_lost(obs, running, report, notes, decisions)
        back, actionable = self._migrate_back(obs, running, report, decisions, notes)
        decisions += back
        if not actionable and not decisions:
            decisions += self._migrate_out(obs, running, report, notes)
        for d in decisions:
            self._apply(d, now)
        self.notes = tuple(notes)
        self.unplaceable = frozen_map(self._unplaceable)
        return decisions

    # --- pieces -----------------------------------------------------------------------------
    def _running(self, obs: Observations) -> Dict[str, str]:
        names, scales = set(self.deployment.node_names), set(self.deployment.scale_names)
        return {n: s for n, s in obs.running.items() if n in names and s in scales}

    def _in_migrated(self, node: str) -> bool:
        return any(n == node for n, _ in self.migrated)

    def _agent_silent(self, obs: Observations, scale: str) -> str:
        """Why the agent of ``scale`` cannot take a node now ('' when it can)."""
        if scale in obs.lost_scales:
            return f'the agent of {scale} is lost (silent > {self.settings.agent_timeout_s:g} s)'
        if scale in obs.silent_agents:
            return f'the agent of {scale} is silent'
        return ''

    def _unreachable(self, obs: Observations, scale: str) -> str:
        """Why a node cannot be placed on ``scale`` now ('' when it can): its agent is silent,
        or no link from the master reaches it."""
        why = self._agent_silent(obs, scale)
        if why or scale == self.master:
            return why
        link = self.deployment.link_between(self.master, scale)
        if link is None:
            return f'no link from {self.master} to {scale}'
        up, _, _, down = link_capacity(self.deployment, self.settings, obs, link, self.started)
        return '' if up else down

    def _hold_for_master(self, obs: Observations, node: str, notes: List[str]) -> bool:
        """Whether a move of ``node`` back to the master waits because the master's agent is
        silent (it could not start the node there): the layout is kept, and said why."""
        why = self._agent_silent(obs, self.master)
        if why:
            notes.append(f'{node} is not brought back to {self.master}: {why}, nothing can '
                         f'start it there; the layout is kept')
        return bool(why)

    def _settle_pending(self, obs: Observations, running: Mapping[str, str], now: float,
                        notes: List[str]) -> List[Decision]:
        out = []
        for node, (scale, asked) in list(self.pending.items()):
            if running.get(node) == scale:
                del self.pending[node]
                # From now on a CPU reading of that scale can include the node's load.
                self.arrived[scale] = (now, node)
            elif now - asked > self.pending_timeout_s:
                if scale != self.master and self._in_migrated(node) \
                        and self._hold_for_master(obs, node, notes):
                    continue
                del self.pending[node]
                where = running.get(node, 'nowhere')
                if scale != self.master and self._in_migrated(node):
                    out.append(Decision(
                        MIGRATE_BACK, node, scale, self.master,
                        f'{node} still not running on {scale} {now - asked:.1f} s after the '
                        f'move (runs {where}); undoing it'))
                else:
                    notes.append(f'{node} not yet running on {scale} {now - asked:.1f} s after '
                                 f'it was asked (runs {where})')
        return out

    def _failover(self, obs: Observations, running: Mapping[str, str],
                  notes: List[str]) -> List[Decision]:
        """A serving copy that crashed hands over to a standby copy on another scale.

        The node's copy on the scale the layout places it stopped against its will (its agent
        reported it exited or restarted, ``CopyObs.crashed_at``) and the node serves nowhere
        else: the first inactive standby copy, on the most powerful scale that can host it now
        (live agent, link up, CPU, bandwidth, residence; the master only needs a live agent),
        is activated there by a new layout;
        the crashed scale's agent restarts its own copy as a standby. With no such copy the
        node is restarted in place by its agent (nothing to decide). The hysteresis T bars
        voluntary moves, not the rescue of a dead copy: a ready standby takes over whatever T
        says, one whose copy has not crashed within T first. A node whose copies crashed on
        every scale it may serve on within T crashes wherever it runs: that is said, with its
        crashes, beside the failover.
        """
        now = obs.now
        out: List[Decision] = []
        report = None
        for node, scale in sorted(self.desired.items()):
            copies = obs.copies.get(node) or frozen_map()
            here = copies.get(scale)
            if here is None or here.crashed_at is None:
                continue
            if self.crashed.get((node, scale), -math.inf) >= here.crashed_at:
                continue                                   # this crash was answered
            if running.get(node) not in (None, scale) or node in self.pending:
                continue
            self.crashed[(node, scale)] = here.crashed_at
            standby = [s for s, c in copies.items() if s != scale and c.state == 'standby']
            if not standby:
                if self.deployment.standby_scales(node):
                    notes.append(f'{node} crashed on {scale} ({here.exit_reason}); no standby '
                                 f'copy ready elsewhere: restarted in place')
                continue
            if report is None:
                report = evaluate(self.deployment, self.settings, obs, self.grace_until,
                                  since=self.started)
            cpu = node_cpu(self.deployment, self.settings, obs, node)
            target, refused = None, []
            recent = {s: now - self.crashed[(node, s)] for s in copies
                      if (node, s) in self.crashed
                      and now - self.crashed[(node, s)] < self.settings.hysteresis_s}
            # Copies that have not crashed within T first, then by power (a stable sort).
            for s in sorted(self._scales_by_power(standby), key=lambda x: x in recent):
                ok, why = self._can_host_copy(obs, running, report, node, cpu, s)
                if not ok:
                    refused.append(f'{s}: {why}')
                    continue
                target = s
                break
            if target is None:
                notes.append(f'{node} crashed on {scale} ({here.exit_reason}); restarted in '
                             f'place: no standby copy may take over ({"; ".join(refused)})')
                continue
            out.append(Decision(FAILOVER, node, scale, target,
                                f'{node} crashed on {scale} ({here.exit_reason}); its standby '
                                f'copy on {target} takes over'))
            if target in recent:
                crashes = ', '.join(f'{s} {age:.1f} s ago' for s, age in sorted(recent.items()))
                notes.append(f'{node} crashes wherever it runs (within T = '
                             f'{self.settings.hysteresis_s:g} s: {crashes}): failed over to '
                             f'{target} all the same; each agent restarts its copy with the '
                             'crash-loop backoff (agent.restart_backoff_s)')
        return out

    def _can_host_copy(self, obs: Observations, running: Mapping[str, str],
                       report: ConstraintReport, node: str, cpu: float,
                       scale: str) -> Tuple[bool, str]:
        """Whether a standby copy on ``scale`` may serve now. What cannot be told yet (a link
        or CPU not observed since the start) does not hold a failover back: the copy is there,
        and the alternative is a cold restart.

        The master takes a node back whatever its CPU reads, as a move back does when a
        constraint breaks (Algorithm 1): it is every node's home, and refusing leaves the node
        to a cold restart in place, silent meanwhile, then sent home anyway once its
        connections have been below freq_min past Δ. (A CPU-bound node's CPU measured on a
        stronger scale is what it got there, not what it needs; the master, run near its quota
        by the decider and its agent, read as full and sent such crashes to in-place restarts:
        ``/amcl_pose`` below 2 Hz for 4.9 s in a crash loop of AMCL on the laptop.) Once it is
        home, the migration rule sends it out again after T like any other."""
        if scale == self.master:
            why = self._agent_silent(obs, scale)
            return not why, why
        without = {n: s for n, s in running.items() if n != node}
        ok, why = self._can_host(obs, without, report, (node,), cpu, scale)
        return ok is not False, why

    def _relocate_lost(self, obs: Observations, running: Mapping[str, str],
                       report: ConstraintReport, notes: List[str],
                       already: Sequence[Decision]) -> List[Decision]:
        """Nodes placed on a lost remote scale go where a live agent can run them (the master
        first); the master's own nodes stay (its agent is silent: the layout is kept)."""
        lost = set(obs.lost_scales) & set(self.deployment.scale_names)
        if not lost:
            return []
        out: List[Decision] = []
        moved = {d.node for d in already}
        extra_cpu: Dict[str, float] = {}
        placed = dict(running)
        for d in already:
            placed[d.node] = d.to_scale
        for scale in sorted((lost & set(obs.fencing)) - {self.master}):
            notes.append(f'the nodes of {scale} stay placed there: its agent is silent but its '
                         'warden says they may still run (the agent restarts, or is gone and '
                         'they are not stopped yet): never two copies serving')
        for node, scale in list(self.desired.items()):
            if scale not in lost or scale == self.master or node in moved \
                    or scale in obs.fencing:
                continue
            target, why_not = self._relocation_target(obs, placed, report, node, scale,
                                                      extra_cpu)
            if target is None:
                self._unplaceable[node] = why_not
                continue
            placed[node] = target
            extra_cpu[target] = extra_cpu.get(target, 0.0) + self.deployment.node(node).cpu
            out.append(Decision(RELOCATE, node, scale, target,
                                f'{self._lost_reason(obs, report, scale)}; {node} placed '
                                f'on {target}'))
        return out

    def _lost_reason(self, obs: Observations, report: ConstraintReport, scale: str) -> str:
        """Why ``scale`` is lost, telling a silent agent behind a live link from a cut link."""
        silent = obs.silent_agents.get(scale)
        text = (f'scale {scale} lost: its agent has been silent'
                + ('' if silent is None else f' for {silent:.1f} s')
                + f' (> agent_timeout_s {self.settings.agent_timeout_s:g} s)')
        link = self.deployment.link_between(self.master, scale)
        if link is None:
            return text
        load = report.links.get(link.name)
        if load is None:
            return text
        if not load.up:
            return (f'{text}, and {load.reason or f"link {link.name} down"}: a cut link and a '
                    f'dead agent look alike from {self.master}')
        if load.observed:
            return (f'{text} while link {link.name} is up: the agent, not the link, is gone, '
                    f'and its nodes may be gone with it')
        return text

    def _relocation_target(self, obs: Observations, placed: Mapping[str, str],
                           report: ConstraintReport, node: str, lost: str,
                           extra_cpu: Mapping[str, float]) -> Tuple[Optional[str], str]:
        """(scale, '') where a node of a lost scale goes, or (None, why no scale may host it):
        the next-best scale (``_next_best``), else the master, else the most powerful
        reachable scale with CPU to spare (a node the master may not run)."""
        allowed = self.deployment.allowed_scales(node)
        usable, refused = [], []
        for scale in allowed:
            why = self._unreachable(obs, scale)
            if not why:
                usable.append(scale)
            else:
                refused.append(why)                 # each reason names its scale
        if not usable:
            return None, (f'allowed scales {", ".join(allowed)} have no live agent or are '
                          f'unreachable ({"; ".join(refused)})')
        target, _ = self._next_best(obs, placed, report, node, lost, extra_cpu)
        if target != self.master:
            return target, ''
        if self.master in usable:
            return self.master, ''
        cpu = self.deployment.node(node).cpu
        for scale in self._scales_by_power(usable):
            used, _ = scale_cpu(self.deployment, self.settings, obs, scale)
            room = usable_cpu(self.deployment.scale(scale).capacity_cpu, self.settings)
            if used + extra_cpu.get(scale, 0.0) + cpu <= room:
                return scale, ''
        return self._scales_by_power(usable)[0], ''

    def _scales_by_power(self, names: Sequence[str]) -> List[str]:
        order = {s.name: i for i, s in enumerate(self.deployment.scales)}
        scales = [self.deployment.scale(n) for n in names]
        scales.sort(key=lambda s: (-s.power, -s.gain, order[s.name]))
        return [s.name for s in scales]

    def _migrate_back(self, obs: Observations, running: Mapping[str, str],
                      report: ConstraintReport, already: Sequence[Decision],
                      notes: List[str]) -> Tuple[List[Decision], bool]:
        """Algorithm 1's violation branch. Returns the moves and whether any was called for.

        While the master's agent is silent a move back is called for but not made (nothing
        could start the node there): the layout is kept, and the notes say why."""
        taken = {d.node for d in already}
        out: List[Decision] = []
        actionable = False
        migrated = [n for n, _ in self.migrated]
        # Where every node will be once the moves asked for (earlier, and in this step) are
        # made: what the next-best scale is judged against.
        placed = dict(running)
        for n, (where, _) in self.pending.items():
            if n in placed:
                placed[n] = where
        for d in already:
            placed[d.node] = d.to_scale
        sent: Dict[str, float] = {}                     # scale -> CPU sent there this step

        def beyond(node: str, far: Sequence[str]) -> bool:
            # Placed beyond a link: where it is sent, else where it runs. A node already sent
            # to this side of the link is not, though its old copy beyond it is reported
            # running until the new one serves (a turn a moment later would send it again).
            return (self.desired.get(node) or running.get(node)) in far

        def back(node: str, reason: str) -> None:
            if node in taken or node not in migrated:
                return
            taken.add(node)
            # Every managed node has a desired scale; what runs is the fallback.
            leaving = self.desired.get(node) or running.get(node, '')
            target, why = self._next_best(obs, placed, report, node, leaving, sent)
            placed[node] = target         # one held for the master counts as back too
            if target == self.master:
                if self._hold_for_master(obs, node, notes):
                    return
                out.append(Decision(MIGRATE_BACK, node, leaving, self.master, reason + (
                    f'; no other scale may take it ({why})' if why else '')))
            else:
                out.append(Decision(MOVE_AWAY, node, leaving, target,
                                    f'{reason}; {node} to {target}, the next-best scale: {why}'))
            sent[target] = sent.get(target, 0.0) + node_cpu(self.deployment, self.settings,
                                                            obs, node)

        # A link down (or silent) brings back at once everything placed beyond it, running
        # or still starting there: waiting for the connections' Δ would be too late.
        for link_name, load in report.links.items():
            if load.up or self.master not in load.ends:
                continue        # a link between two remote scales: the do-while below
            far = [e for e in load.ends if e != self.master]
            placed_beyond = [n for n in migrated if beyond(n, far)]
            if placed_beyond:
                actionable = True
                reason = load.reason or f'link {link_name} down'
                quiet = [e for e in far if e in obs.silent_agents]
                if quiet:
                    reason += (f' and the agent of {", ".join(quiet)} is silent too: a cut link '
                               f'and a dead agent look alike from {self.master}')
                for n in placed_beyond:
                    back(n, reason)
        for v in report.of_kind(LINK_DOWN, FREQUENCY):
            if v.kind == LINK_DOWN and self.master not in report.links[v.subject].ends:
                continue        # only the connections crossing it move: the do-while below
            upstream = self._upstream.explains(obs, running, v.subject) \
                if v.kind == FREQUENCY else ''
            if upstream:
                notes.append(f'{v.subject} below freq_min, explained upstream: {upstream}; '
                             'nothing moved for it')
                continue
            culprits = [n for n in v.nodes if n in migrated]
            if v.kind == LINK_DOWN:
                far = [e for e in report.links[v.subject].ends if e != self.master]
                culprits = [n for n in culprits if beyond(n, far)]
            actionable = actionable or bool(culprits)
            for n in culprits:
                back(n, v.reason)
        for v in report.of_kind(CPU):
            culprits = [n for n in reversed(migrated) if n in v.nodes]
            if not culprits:
                continue
            actionable = True
            # One node at a time, and not before the CPU freed by the last one leaving this
            # scale can show in its measurement (the grace period).
            left = [n for n, (where, _) in self.pending.items() if running.get(n) == v.subject
                    and where != v.subject]
            recent = [n for n, t in self.last_move.items() if n not in migrated
                      and obs.now - t < self.settings.grace_s]
            # Nor within the grace period of a node's arrival there: a process starting (a
            # Python node: about a core for a second) is not the load it will be.
            settling = [n for n in culprits
                        if obs.now - self.last_move.get(n, -math.inf) < self.settings.grace_s]
            if not left and not recent and not settling \
                    and not any(n in taken for n in culprits):
                back(culprits[0], v.reason + f'; {culprits[0]} was the last moved there')
        # do ... while required_BW > network_BW: pick, among the migrated nodes crossing an
        # overloaded link, the one whose return frees the most bandwidth on it (ties: the most
        # recently migrated), until every link fits. Moves already asked for count as done.
        # A link between two remote scales that is down carries nothing: what crosses it
        # moves, one node at a time, to where nothing does (the rest stays where it is).
        # An overloaded link that no move can relieve (what crosses it is pinned there, or
        # already moving) does not hold back the others.
        for _ in range(len(migrated) + 1):
            pick = None
            for link_name, required, usable in self._overloaded_links(report, placed):
                best, best_gain = None, 0.0
                for n in reversed(migrated):
                    if n in taken or placed.get(n, self.master) == self.master:
                        continue
                    where, _ = self._next_best(obs, placed, report, n, placed[n], sent)
                    trial = dict(placed, **{n: where})
                    gain = required - required_kbps(self.deployment, trial)[link_name]
                    if gain > best_gain:
                        best, best_gain = n, gain
                if best is not None:
                    pick = (link_name, required, usable, best, best_gain)
                    break
            if pick is None:
                break
            link_name, required, usable, best, best_gain = pick
            actionable = True
            load = report.links[link_name]
            if not load.up:
                back(best, f'{load.reason}: {required:.0f} kbit/s cross it; {best} frees '
                           f'{best_gain:.0f} kbit/s')
            else:
                back(best, f'link {link_name}: required {required:.0f} kbit/s > usable '
                           f'{usable:.0f} kbit/s{load.cap_note}; {best} frees '
                           f'{best_gain:.0f} kbit/s')
        return out, actionable

    def _next_best(self, obs: Observations, placed: Mapping[str, str],
                   report: ConstraintReport, node: str, leaving: Optional[str],
                   sent: Mapping[str, float]) -> Tuple[str, str]:
        """(scale, why) for a node that must leave ``leaving``: the most powerful remote scale
        more powerful than the master that can host it now (live agent, its links up and
        observed, CPU and bandwidth, counting what this step already sent there; not a scale
        it left within T), else the master (Algorithm 1's migrate-back). With hysteresis scope
        'node' (the paper's rule as written) always the master."""
        d = self.deployment
        if self.settings.hysteresis_scope == 'node':
            return self.master, ''
        power = d.master.power
        others = [s for s in d.allowed_scales(node)
                  if s not in (leaving, self.master) and d.scale(s).power > power]
        if not others:
            return self.master, ''
        cpu = node_cpu(d, self.settings, obs, node)
        without = {n: s for n, s in placed.items() if n != node}
        refused = []
        for scale in self._scales_by_power(others):
            held = self._held((node,), scale, obs.now)
            if held:
                refused.append(held)
                continue
            cut = self._handover_cut(report, leaving, scale)
            if cut:
                refused.append(f'{scale}: {cut}')
                continue
            ok, why = self._can_host(obs, without, report, (node,), cpu, scale,
                                     sent.get(scale, 0.0))
            if ok:
                return scale, why
            refused.append(f'{scale}: {why}')
        return self.master, '; '.join(refused)

    def _handover_cut(self, report: ConstraintReport, leaving: Optional[str],
                      scale: str) -> str:
        """Why a node may not move from ``leaving`` straight to ``scale`` now ('' when it
        may): the link between them is down. The copy that stops and the one that starts hear
        each other's reports over it; across a cut, the handover would wait out its timeouts."""
        link = self.deployment.link_between(leaving, scale) if leaving is not None else None
        if link is None or report.links[link.name].up:
            return ''
        return f'{report.links[link.name].reason} (the handover from {leaving} needs it)'

    def _overloaded_links(self, report: ConstraintReport,
                          running: Mapping[str, str]) -> List[Tuple[str, float, float]]:
        required = required_kbps(self.deployment, running)
        out = []
        for name, load in report.links.items():
            watched = load.up or self.master not in load.ends     # down: usable 0
            if watched and required[name] > load.usable_kbps:
                out.append((name, required[name], load.usable_kbps))
        return out

    def _migrate_out(self, obs: Observations, running: Mapping[str, str],
                     report: ConstraintReport, notes: List[str]) -> List[Decision]:
        """Algorithm 1's else branch: at most one node (or coresidence group) moves out."""
        now = obs.now
        if not self.settings.migration:
            return []
        why = self._agent_silent(obs, self.master)
        if why:
            notes.append(f'no move out: {why}, nothing could stop the copy left on '
                         f'{self.master}')
            return []
        if self.pending:
            notes.append('waiting for ' + ', '.join(
                f'{n} to run on {s}' for n, (s, _) in sorted(self.pending.items())))
            return []
        max_age = self.settings.observation_max_age_s
        if self.master not in obs.scales and self._since_start(now) <= max_age:
            # The nodes are ranked by their measured CPU: give the master's scale monitor the
            # same start-up allowance as every other observation (after it, nominal CPU).
            notes.append(f'waiting for a first CPU report from {self.master} (nodes are ranked '
                         f'by measured CPU)')
            return []
        units = self._candidate_units(obs, running)
        remotes = self._scales_by_power([s.name for s in self.deployment.remote_scales])
        for unit, cpu in units:
            if self.settings.hysteresis_scope == 'node':
                held = self._held(unit, None, now)
                if held:
                    notes.append(held)
                    continue
            for scale in remotes:
                held = self._held(unit, scale, now)
                if held:
                    notes.append(held)
                    continue
                ok, why = self._can_host(obs, running, report, unit, cpu, scale)
                if ok is None:
                    # Not a no: not known yet. Picking another scale or node now would be a
                    # choice made on a partial view, so the move out waits for the observation.
                    notes.append(f'{unit[0]} -> {scale}: waiting: {why}')
                    return []
                if not ok:
                    notes.append(f'{unit[0]} -> {scale}: {why}')
                    continue
                power = self.deployment.scale(scale).power
                reason = (f'{_unit_text(unit)}: CPU {cpu:.0f}, the most CPU-intensive '
                          f'migratable node that fits, to {scale} (power {power:g}): {why}')
                return [Decision(MIGRATE, n, self.master, scale, reason) for n in unit]
        return self._rebalance(obs, running, report, notes)

    def _rebalance(self, obs: Observations, running: Mapping[str, str],
                   report: ConstraintReport, notes: List[str]) -> List[Decision]:
        """Beyond the paper: a node (or coresidence group) on a remote scale moves to a more
        powerful remote scale that can host it, when the cost function gains at least
        ``rebalance_min_gain`` (CPU x (alpha there - alpha here)), not before T has passed
        since it last moved, nor to a scale it left within T. One move per turn: the largest
        gain; each move only raises the cost function, so nothing ping-pongs without a
        violation in between (and a violation's move back holds the scale for T)."""
        s, d, now = self.settings, self.deployment, obs.now
        if not s.rebalance:
            return []
        remotes = self._scales_by_power([x.name for x in d.remote_scales])
        best = None
        for unit, here in self._remote_units(running):
            since = max(self.last_move.get(n, -math.inf) for n in unit)
            if now - since < s.hysteresis_s:
                continue
            cpu = sum(node_cpu(d, s, obs, n) for n in unit)
            without = {n: x for n, x in running.items() if n not in unit}
            for scale in remotes:
                gain = cpu * (d.scale(scale).gain - d.scale(here).gain)
                if scale == here or gain < s.rebalance_min_gain or gain <= 0:
                    continue
                if self._held(unit, scale, now) or self._handover_cut(report, here, scale):
                    continue
                ok, why = self._can_host(obs, without, report, unit, cpu, scale)
                if not ok:
                    continue
                if best is None or gain > best[0]:
                    best = (gain, unit, here, scale, cpu, why)
                break                  # the most powerful scale that fits, for this unit
        if best is None:
            return []
        gain, unit, here, scale, cpu, why = best
        reason = (f'{_unit_text(unit)}: CPU {cpu:.0f} on {here} (alpha '
                  f'{d.scale(here).gain:g}) to {scale} (alpha {d.scale(scale).gain:g}): the cost '
                  f'function gains {gain:.0f} >= rebalance_min_gain {s.rebalance_min_gain:g}; '
                  f'{why}')
        return [Decision(REBALANCE, n, here, scale, reason) for n in unit]

    def _remote_units(self, running: Mapping[str, str]) -> List[Tuple[Tuple[str, ...], str]]:
        """Migratable nodes settled on a remote scale, with their coresidents, and the scale."""
        return [(unit, here) for unit, here in self._settled_units(running)
                if here != self.master]

    def _settled_units(self, running: Mapping[str, str]) -> List[Tuple[Tuple[str, ...], str]]:
        """Each coresidence group of migratable nodes that all run where the layout places
        them, on one scale, with that scale (in deployment order)."""
        migratable = set(self.deployment.migratable_nodes)
        seen: Set[str] = set()
        units: List[Tuple[Tuple[str, ...], str]] = []
        for node in self.deployment.migratable_nodes:
            if node in seen:
                continue
            group = self.deployment.coresidence_group(node)
            seen.update(group)
            here = running.get(node)
            if here is not None and all(m in migratable and running.get(m) == here
                                        and self.desired.get(m) == here for m in group):
                units.append((tuple(group), here))
        return units

    def _held(self, unit: Tuple[str, ...], scale: Optional[str], now: float) -> str:
        """Why the hysteresis T holds ``unit`` back from ``scale`` (any scale if None), or ''.

        Scope 'node' (the paper's literal rule): a node migrated back is not moved out again
        within T. Scope 'scale' (the default): it is not moved back to the scale it came back
        from within T, but may go to another remote scale, whose link did not fail it.
        """
        t = self.settings.hysteresis_s
        latest = None
        for (n, came_from), when in self.last_back.items():
            if n in unit and (scale is None or came_from == scale) and now - when < t:
                if latest is None or when > latest[0]:
                    latest = (when, n, came_from)
        if latest is None:
            return ''
        when, n, came_from = latest
        target = '' if scale is None else f' -> {scale}'
        return (f'{unit[0]}{target}: {n} migrated back from {came_from} {now - when:.1f} s ago, '
                f'within T = {t:g} s')

    def _candidate_units(self, obs: Observations, running: Mapping[str, str]
                         ) -> List[Tuple[Tuple[str, ...], float]]:
        """Migratable nodes on the master with their coresidents, by CPU, largest first."""
        units = [(unit, sum(node_cpu(self.deployment, self.settings, obs, m) for m in unit))
                 for unit, here in self._settled_units(running) if here == self.master]
        order = {n: i for i, n in enumerate(self.deployment.node_names)}
        units.sort(key=lambda u: (-u[1], order[u[0][0]]))
        return units

    def _can_host(self, obs: Observations, running: Mapping[str, str],
                  report: ConstraintReport, unit: Tuple[str, ...], cpu: float,
                  scale: str, sent_cpu: float = 0.0) -> Tuple[Optional[bool], str]:
        """(True | False | None, why): None when it cannot be told yet (the link or the CPU of
        the scale not observed since the start, or its CPU not measured since the last node
        moved there started running). ``sent_cpu``: what this turn already sent there."""
        d, s = self.deployment, self.settings
        silent = self._agent_silent(obs, scale)
        if silent:
            return False, silent
        if any(scale not in d.allowed_scales(n) for n in unit):
            return False, 'not allowed there'
        link = d.link_between(self.master, scale)
        if link is None:
            return False, f'no link from {self.master}'
        up, observed, available, why = link_capacity(d, s, obs, link, self.started)
        if not up:
            return False, why
        if not observed:
            return None, f'link {link.name} not observed yet'
        seen, why = self._cpu_seen(obs, scale)
        if not seen:
            return seen, why
        used, _ = scale_cpu(d, s, obs, scale)
        used += sent_cpu
        usable = usable_cpu(d.scale(scale).capacity_cpu, s)
        if used + cpu > usable:
            return False, f'CPU {used:.0f} + {cpu:.0f} > usable {usable:.0f}'
        trial = dict(running, **{n: scale for n in unit})
        before, after = required_kbps(d, running), required_kbps(d, trial)
        detail = []
        for name, need in after.items():
            if need <= before[name]:
                continue
            load = report.links[name]
            if not load.up:
                return False, f'link {name} down'
            if need > load.usable_kbps:
                return False, (f'link {name} would need {need:.0f} kbit/s > usable '
                               f'{load.usable_kbps:.0f}{load.cap_note}')
            detail.append(f'link {name} {need:.0f}/{load.usable_kbps:.0f} kbit/s'
                          f'{load.cap_note}')
        return True, f'CPU {used:.0f} + {cpu:.0f} <= {usable:.0f}' + \
            ''.join('; ' + x for x in detail)

    def _cpu_seen(self, obs: Observations, scale: str) -> Tuple[Optional[bool], str]:
        """Whether the scale's CPU measurement can be trusted to host one more node.

        True: a fresh report, received after the last node moved there started running (so it
        includes that node's load). None (wait): no report yet within ``observation_max_age_s``
        of the start, or none since the last node started there. False: its reports stopped.
        """
        so = obs.scales.get(scale)
        max_age = self.settings.observation_max_age_s
        if so is None or not is_fresh(so.stamp, obs.now, self.settings):
            if so is None and self._since_start(obs.now) <= max_age:
                return None, f'no CPU report from {scale} yet'
            last = 'never' if so is None else f'{obs.now - so.stamp:.1f} s ago'
            return False, (f'no fresh CPU report from {scale} (last {last}, max age '
                           f'{max_age:g} s)')
        arrived = self.arrived.get(scale)
        if arrived is not None and so.stamp <= arrived[0]:
            return None, (f'CPU of {scale} not measured since {arrived[1]} started there '
                          f'({obs.now - arrived[0]:.1f} s ago)')
        return True, ''

    def heard(self, kind: str, node: str, from_scale: str, now: float) -> None:
        """Another decider's decision (a standby hears the leader's): its hysteresis and
        failover memory, kept for the day this one takes over."""
        if node not in self.deployment.node_names:
            return
        if kind in (MIGRATE, REBALANCE):
            self.last_move_out = now
        elif kind in (MIGRATE_BACK, MOVE_AWAY, RELOCATE, FAILOVER):
            self.last_back[(node, from_scale)] = now
            if kind == FAILOVER:
                self.crashed[(node, from_scale)] = now

    def _apply(self, d: Decision, now: float) -> None:
        self.desired[d.node] = d.to_scale
        self.migrated = [(n, s) for n, s in self.migrated if n != d.node]
        if d.to_scale != self.master and self.master in self.deployment.allowed_scales(d.node):
            self.migrated.append((d.node, d.to_scale))
        if d.kind in (MIGRATE, REBALANCE):
            self.last_move_out = now
        else:
            self.last_back[(d.node, d.from_scale)] = now
        self.last_move[d.node] = now
        self.pending[d.node] = (d.to_scale, now)
        self.history.append((now, d))


def _unit_text(unit: Tuple[str, ...]) -> str:
    """'amcl', or 'amcl (with map_server)' for a coresidence group."""
    return unit[0] if len(unit) == 1 else f'{unit[0]} (with {", ".join(unit[1:])})'


def with_settings(deployment: Deployment, **changes) -> DeciderSettings:
    """The deployment's decider settings with some fields changed (validated by the caller)."""
    return replace(deployment.decider, **changes)


__all__ = ['MigrationPolicy', 'with_settings']
