"""Which catalogue nodes this scale should run now: the latched layout plus the move orders.

Pure and clock-free: the caller passes its monotonic ``now``. The layout says where each node
belongs; the move order says when a moving node may start on its new scale and when it must stop
on its old one:

- start_before_stop: the gaining scale starts the node at once; the losing scale keeps its copy
  until the gaining scale's agent reports it running and ready (under the generation that moved
  it, or a newer one) and, where the losing scale subscribes to the node's output, it has heard
  a newly started writer of it since the move (at most ``HEAR_PATIENCE_S`` after the ready
  report); or until ``readiness_timeout_s`` has passed since the move. Except a lifecycle node
  moved to the master scale where it has a standby copy: the losing (remote) scale lets go at
  once, since the master's copy serves within milliseconds of the layout and the word that it
  does would have to cross the link the move may be escaping.
- stop_before_start: the losing scale stops its copy at once; the gaining scale starts the node
  only when every other live agent has applied the layout's generation and reports no live copy.
  An agent silent for longer than ``agent_timeout_s`` no longer counts.

So two copies of a node overlap at most ``readiness_timeout_s`` plus the stop graces
(start_before_stop) and never (stop_before_start) while the agents hear each other.

A lifecycle node with standby keeps a live, inactive copy on every scale in its standby list
(``standby_here``): "runs here" then means "is active here", and a move is an activation on
the gaining scale and a deactivation on the losing one, under the same move orders.

A remote scale cut off from the master (neither the master's agent nor the decider heard for
``agent_timeout_s``) stops its migratable nodes: the decider, on the master, has brought them
home when it saw the link go down, and a copy left running here would publish stale results
beside them once the link is back. They stay stopped (a standby copy: inactive) until a newer
layout arrives. While only
the decider is silent the agents keep running what runs (fail-static), and while only the
master's agent is silent the decider may place that scale's nodes here.
"""

from dataclasses import dataclass, field
from typing import Callable, Dict, FrozenSet, Iterable, List, Mapping, Optional, Set, Tuple

from ..model import types as t
from ..protocol import MAX_GENERATION_STEP, AgentState, Layout, ProcState

# A copy whose process runs there: it must stop before this scale starts its own.
LIVE = (ProcState.STARTING, ProcState.RUNNING, ProcState.STOPPING)
NO_GENERATION = -1
# moved_from for a node placed by the first layout this agent hears when that layout is not the
# deployment's first (a later generation): where the node served before is not known here.
UNKNOWN_SCALE = '?'
# How long a losing scale keeps its copy past the new copy's ready report while it has not heard
# the new copy (its inputs may not reach it yet; or the copies' sequence numbers overlap).
HEAR_PATIENCE_S = 5.0
# A remote scale that has not heard from the master for this long, while a peer it still hears
# serves one of its nodes under a newer layout, stands its copy down (Reconciler.superseded_by):
# longer than the master's word normally takes (its agent reports at 2 Hz, the decider's
# objective every turn), far shorter than agent_timeout_s.
SUPERSEDED_QUIET_S = 1.0


@dataclass(frozen=True)
class Peer:
    """The last report of another scale's agent, stamped with the receiver's clock."""

    scale: str
    generation: int
    heard: float
    nodes: Mapping[str, Tuple[ProcState, bool]]     # node -> (state, ready)
    decider: str = ''                         # the decider whose layouts it follows
    term: int = 0                             # that decider's leadership term
    # Nodes it may not start or serve for want of room on its shared host (agent/claims.py),
    # with why: a copy moving there is kept here meanwhile.
    refused: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class LayoutVerdict:
    applied: bool
    warnings: Tuple[str, ...]


class Reconciler:
    def __init__(self, deployment: t.Deployment, scale: str, catalogue: Iterable[str],
                 readiness_timeout_s: float, agent_timeout_s: float):
        self.deployment = deployment
        self.scale = scale
        self.catalogue = tuple(catalogue)
        self.readiness_timeout_s = readiness_timeout_s
        self.agent_timeout_s = agent_timeout_s
        # Nodes that keep an inactive copy here wherever the layout places them.
        self.standby_here: FrozenSet[str] = frozenset(
            n for n in self.catalogue if scale in deployment.standby_scales(n))
        self.generation = NO_GENERATION
        self.assignments: Dict[str, str] = {}
        # node -> the scale the layout placed it on before its last move ('' for none).
        self.moved_from: Dict[str, str] = {}
        self._moved_at: Dict[str, float] = {}
        self._moved_gen: Dict[str, int] = {}
        self._ready_at: Dict[str, float] = {}   # moving away: when the new copy was first ready
        self.peers: Dict[str, Peer] = {}
        self._released: Set[str] = set()      # handed over to their new scale: never wanted back
        self.waiting: Dict[str, str] = {}     # node -> why its start or stop is held back
        self.master = deployment.master.name
        self._migratable = frozenset(deployment.migratable_nodes)
        self.contact: Optional[float] = None  # last word from the master's agent or the decider
        self.decider = ''                     # the decider of the applied layout, its term
        self.term = 0
        self._cut_generation: Optional[int] = None   # the layout held when contact was lost

    @property
    def has_layout(self) -> bool:
        return self.generation != NO_GENERATION

    # --- inputs ---------------------------------------------------------------------------
    def apply_layout(self, layout: Layout, now: float,
                     new_decider: bool = False) -> LayoutVerdict:
        """Take a decoded layout; ignore it whole if it is for another deployment or stale.

        ``new_decider``: the first layout of a decider followed from now on (authority.py):
        generations count per decider, so its number is not compared with the last one's.
        """
        d = self.deployment
        if layout.deployment != d.name:
            return LayoutVerdict(False, (f'layout generation {layout.generation} is for '
                                         f'deployment {layout.deployment!r:.60}, not '
                                         f'{d.name!r}; ignored',))
        if not new_decider and layout.generation <= self.generation:
            return LayoutVerdict(False, (f'layout generation {layout.generation} is not newer '
                                         f'than the applied {self.generation}; ignored',))
        if not new_decider and self.has_layout \
                and layout.generation - self.generation > MAX_GENERATION_STEP:
            return LayoutVerdict(False, (f'layout generation {layout.generation} jumps more '
                                         f'than {MAX_GENERATION_STEP} past the applied '
                                         f'{self.generation} (a decider adds one per '
                                         'decision); ignored',))
        warnings: List[str] = []
        nodes = set(d.node_names)
        scales = set(d.scale_names)
        accepted: Dict[str, str] = {}
        for node, scale in sorted(layout.assignments.items()):
            where = f'layout generation {layout.generation}: {node!r:.60}'
            if node not in nodes:
                warnings.append(f'{where}: unknown node; entry ignored')
            elif scale not in scales:
                warnings.append(f'{where}: unknown scale {scale!r:.60}; entry ignored')
            elif not d.node(node).managed:
                warnings.append(f'{where}: not a managed node; entry ignored')
            elif scale not in d.allowed_scales(node):
                warnings.append(f'{where}: may not run on {scale!r}; entry ignored')
            else:
                accepted[node] = scale
        missing = [n for n in self.catalogue if n not in accepted]
        if missing:
            warnings.append(f'layout generation {layout.generation} does not place '
                            f'{", ".join(missing)}; keeping them as they are')
        # This agent's first layout, of a deployment already running (it started late, or its
        # link came up after the first layouts): a node may have served elsewhere before.
        joined_late = self.generation == NO_GENERATION and layout.generation > 1
        for node, scale in accepted.items():
            if self.assignments.get(node) != scale:
                self.moved_from[node] = self.assignments.get(
                    node, UNKNOWN_SCALE if joined_late else '')
                self._moved_at[node] = now
                self._moved_gen[node] = layout.generation
                self._ready_at.pop(node, None)
                self._released.discard(node)
            self.assignments[node] = scale
        self.generation = layout.generation
        self.decider = layout.decider.id if layout.decider is not None else ''
        self.term = layout.term or 0
        self._cut_generation = None
        return LayoutVerdict(True, tuple(warnings))

    def heard_master(self, now: float) -> None:
        """Word from the master scale: its agent's report, the decider's output, or (for a
        just-started agent) the start itself, so that silence is counted from there."""
        self.contact = now if self.contact is None else max(self.contact, now)

    def cut_off(self, now: float) -> bool:
        """Whether this remote scale has heard nothing from the master for agent_timeout_s."""
        return (self.scale != self.master and self.contact is not None
                and now - self.contact > self.agent_timeout_s)

    def next_due(self, now: float) -> Optional[float]:
        """When the master's silence next changes what this remote scale may run, unless word
        comes first: SUPERSEDED_QUIET_S after the last word (a copy stands down if a peer
        serves it under a newer layout), then past agent_timeout_s (its migratable nodes
        stop). None on the master, once both are past, or before any word."""
        if self.scale == self.master or self.contact is None:
            return None
        # A millisecond past each: both rules compare with the silence strictly.
        due = (self.contact + SUPERSEDED_QUIET_S + 1e-3,
               self.contact + self.agent_timeout_s + 1e-3)
        return min((t for t in due if t > now), default=None)

    def peer_news(self, before: Optional[Peer], now: float) -> bool:
        """Whether the report just recorded for a peer (``before``: its previous one) can
        change what runs here: a peer heard for the first time or again after a silence of
        SUPERSEDED_QUIET_S or more, or one whose layout, nodes or decider changed. Its
        unchanged heartbeat only keeps it counted."""
        if before is None:
            return True
        after = self.peers.get(before.scale)
        return after is None or now - before.heard >= SUPERSEDED_QUIET_S or (
            (after.generation, after.nodes, after.decider, after.term, after.refused)
            != (before.generation, before.nodes, before.decider, before.term, before.refused))

    def peer_state(self, state: AgentState, now: float) -> Optional[str]:
        """Record another agent's report; a warning when it cannot be one of our peers."""
        if state.scale == self.scale:
            return None   # our own report, or a second agent on this scale (the lock stops it)
        if state.scale not in self.deployment.scale_names:
            return f'agent state from unknown scale {state.scale!r:.60}; ignored'
        if state.scale == self.master:
            self.heard_master(now)
        self.peers[state.scale] = Peer(
            scale=state.scale, generation=state.generation, heard=now,
            nodes={n: (r.state, r.ready) for n, r in state.nodes.items()},
            decider=state.decider or '', term=state.term or 0,
            refused=({} if state.share is None else
                     dict(state.share.refused, **state.share.waiting)))
        return None

    def superseded_by(self, node: str, now: float) -> Optional[Peer]:
        """A peer that serves ``node`` under a newer layout of the decider this scale follows,
        while this scale has not heard from the master for ``SUPERSEDED_QUIET_S``: the decider
        has moved the node there (this scale is cut off from the master, not from that peer),
        so the copy here stands down at once instead of after agent_timeout_s, and the peer's
        subscribers do not hear two copies. Heard from the master within that time, the layout
        itself is on its way and the usual handover applies."""
        if self.contact is None or now - self.contact < SUPERSEDED_QUIET_S:
            return None
        for peer in self._fresh(now):
            if peer.decider == self.decider and peer.term == self.term \
                    and peer.generation > self.generation \
                    and peer.nodes.get(node) == (ProcState.RUNNING, True) \
                    and now - peer.heard <= SUPERSEDED_QUIET_S:
                return peer
        return None

    def _fresh(self, now: float) -> List[Peer]:
        return [p for p in self.peers.values() if now - p.heard <= self.agent_timeout_s]

    def reported_not_serving(self, node: str, scale: str, now: float, within_s: float) -> bool:
        """Whether ``scale``'s agent reported, within ``within_s``, its copy of ``node``
        neither serving nor starting (crashed, backing off, stopped, stopping, or a standby);
        False when not heard lately. A starting copy (a lifecycle copy being activated) serves
        soon: its agent counts it as serving and keeps it so while a move away waits."""
        peer = self.peers.get(scale)
        if peer is None or now - peer.heard > within_s:
            return False
        state = peer.nodes.get(node, (ProcState.STOPPED, False))[0]
        return state not in (ProcState.RUNNING, ProcState.STARTING)

    def reported_serving(self, node: str, scale: str, now: float, within_s: float) -> bool:
        """Whether ``scale``'s agent reported, within ``within_s``, its copy of ``node``
        serving (running and ready); False when not heard lately."""
        peer = self.peers.get(scale)
        if peer is None or now - peer.heard > within_s:
            return False
        return peer.nodes.get(node) == (ProcState.RUNNING, True)

    def copies_elsewhere(self, node: str, now: float) -> int:
        """How many live instances of ``node`` other live agents account for in the ROS graph
        (a plain node's readiness counts the instances of its name)."""
        return sum(p.nodes.get(node, ('', False))[0] in LIVE for p in self._fresh(now))

    # --- the decision of what runs here ---------------------------------------------------
    def desired(self, now: float, active: Iterable[str],
                heard_here: Optional[Callable[[str, float], Optional[bool]]] = None
                ) -> Set[str]:
        """Catalogue nodes that should serve here now: a live process, and for a lifecycle
        node an active one (``active``: those that do now).

        ``heard_here(node, since)``: whether this scale hears the node's new copy elsewhere
        (a newly started writer of its outputs heard here since the move at ``since``); None
        when nothing here can tell. A copy moving away is kept until then (at most
        ``HEAR_PATIENCE_S`` past the ready report), so that this scale's subscribers do not wait
        for the new copy with the old one gone.
        """
        active = set(active)
        want: Set[str] = set()
        self.waiting = {}
        if self._cut_generation is None and self.cut_off(now):
            self._cut_generation = self.generation
        for node in self.catalogue:
            target = self.assignments.get(node)
            here = node in active
            if target is None:
                if here:
                    want.add(node)   # no layout places it: leave it as it is (fail-static)
                continue
            order = self.deployment.node(node).move_order
            # Whether it serves here now or not: once stood down, a copy is neither served
            # again nor started while the peer serves it (else it would be reactivated at the
            # next step and stood down again, round and round).
            peer = self.superseded_by(node, now) if target == self.scale \
                and node in self._migratable else None
            if peer is not None:
                self.waiting[node] = (f'stood down: {peer.scale} serves it under layout '
                                      f'generation {peer.generation}, newer than the '
                                      f'{self.generation} held here (nothing heard from '
                                      f'{self.master} for {now - self.contact:.1f} s)')
                continue
            if target == self.scale and self._cut_generation is not None \
                    and node in self._migratable:
                self.waiting[node] = (f'stopped: cut off from {self.master}, whose decider '
                                      f'has taken it back (until a layout newer than '
                                      f'generation {self._cut_generation})')
                continue
            if target == self.scale:
                if here or order != t.STOP_BEFORE_START:
                    want.add(node)
                    continue
                holder = self._held_elsewhere(node, now)
                if holder:
                    self.waiting[node] = holder
                else:
                    want.add(node)
            elif here and order == t.START_BEFORE_STOP and node not in self._released \
                    and target == self.master and target in self.deployment.standby_scales(node):
                # Moved home to the master's standby copy: let go at once. That copy serves
                # within milliseconds of the layout (the master hears it first), and the word
                # that it does would come back over the very link the move may be escaping: a
                # copy kept here until then keeps pulling its input across a congested link
                # (a laptop kept AR, and its 6 Mbit/s of images, 1 s past a move back for
                # bandwidth, starving AMCL's laser input behind them).
                self._released.add(node)
            elif here and order == t.START_BEFORE_STOP and node not in self._released:
                waited = now - self._moved_at.get(node, now)
                refused = self._refused_on(target, node, now)
                if refused:
                    # The host there has no room for it: it serves on here, whatever the
                    # time, until the decider places it anew.
                    want.add(node)
                    self.waiting[node] = f'kept: {target} does not take it ({refused})'
                    continue
                ready = self._ready_on(target, node, now)
                heard = None
                if ready:
                    ready_for = now - self._ready_at.setdefault(node, now)
                    if heard_here is not None and ready_for < HEAR_PATIENCE_S:
                        heard = heard_here(node, self._moved_at.get(node, now))
                if (ready and heard is not False) or waited >= self.readiness_timeout_s:
                    # Once let go it stays let go, whatever the new copy reports afterwards.
                    self._released.add(node)
                else:
                    want.add(node)
                    until = (f'heard here from {target} (ready there)' if ready else
                             f'running and ready on {target}')
                    self.waiting[node] = (f'kept until it is {until} (waited {waited:.1f} of '
                                          f'{self.readiness_timeout_s:g} s)')
        return want

    def _held_elsewhere(self, node: str, now: float) -> str:
        for p in sorted(self._fresh(now), key=lambda p: p.scale):
            state = p.nodes.get(node, (ProcState.STOPPED, False))[0]
            if state in LIVE:
                return f'waiting for {p.scale} to stop it (there: {state})'
            if p.generation < self.generation:
                return (f'waiting for {p.scale} to apply generation {self.generation} '
                        f'(it has {p.generation})')
        return ''

    def _refused_on(self, scale: str, node: str, now: float) -> str:
        """Why ``scale``'s agent, heard lately under the generation that moved ``node``,
        does not take it for want of room ('' when it does not say so)."""
        peer = self.peers.get(scale)
        if peer is None or now - peer.heard > self.agent_timeout_s \
                or peer.generation < self._moved_gen.get(node, self.generation):
            return ''
        return peer.refused.get(node, '')

    def _ready_on(self, scale: str, node: str, now: float) -> bool:
        peer = self.peers.get(scale)
        if peer is None or now - peer.heard > self.agent_timeout_s:
            return False
        if peer.generation < self._moved_gen.get(node, self.generation):
            return False
        state, ready = peer.nodes.get(node, (ProcState.STOPPED, False))
        return state == ProcState.RUNNING and ready
