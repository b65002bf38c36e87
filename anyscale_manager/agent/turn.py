"""The agent's turn, pure: what the agent knows between turns, its inputs and a clock in; the
processes and lifecycle goals it wants, its report, log lines and next tick period out.

``AgentTurn`` holds the agent of one scale (the supervisor, the reconciler of layouts and move
orders, one lifecycle ``Driver`` per lifecycle node, the decider it follows, the machines of the
other agents). The rclpy agent (nodes/agent.py) decodes and checks each signed message and hands
it over (``on_layout``, ``on_agent_state``, ``on_objective``), calls ``step(now, inputs)`` from
its timer with what it observed of the ROS graph, and publishes and logs what comes back. The
unit tests drive the same object with a hand-written clock. Nothing here reads a clock or
touches ROS: time and the wall clock come in as arguments.
"""

from dataclasses import dataclass, field, replace
from typing import (Callable, Collection, Dict, Iterable, List, Mapping, Optional, Protocol,
                    Sequence, Set, Tuple)

from .. import protocol
from ..model.types import Deployment
from ..protocol import LIVE_STATES, LifecycleState, ProcState
from ..runtime.hosts import HostBook
from . import lifecycle as lc
from .authority import Follower
from .catalogue import copy_restore_topic, Entry
from .claims import HostClaims
from .reconcile import Reconciler, UNKNOWN_SCALE
from .state import StateBook
from .supervisor import Supervisor

TICK_S = 0.1
# While a node is stopping the loop runs this often: a stop_before_start move waits until the
# old copy is seen gone here (and reported) before the other scale starts the new one.
STOPPING_TICK_S = 0.02
# With nothing under way (every process up and seen, or stopped as wanted; every lifecycle copy
# at its goal; no move, stop or hand-over waiting) a step has work only when an input arrives
# (a layout, a peer's news, an exit, a signal, an answer of a lifecycle copy: each steps at
# once) or at a deadline the turn knows (the master's silence on a remote scale, a node's DDS
# ports): the next step is due then, and at the latest after this. Ten steps a second with
# nothing to do were a tenth of the robot agent's CPU.
IDLE_TICK_S = 1.0
# A copy to be handed a state when this agent has heard none yet waits this long at most for
# the first one from the copy the layout moves the node from, unless that copy's agent said,
# at most PEER_FRESH_BEATS heartbeats ago, that it neither serves nor starts; while that agent
# says its copy serves, up to half of agent.readiness_timeout_s (the copy there serves on
# meanwhile, and its writer may take seconds to be found across a link that just opened).
FIRST_STATE_WAIT_S = 3.0
PEER_FRESH_BEATS = 3.0
# A layout that names unknown nodes or scales is logged entry by entry up to this many.
MAX_LAYOUT_WARNINGS = 5
# The layouts of a decider not followed come as often as it publishes: said once this often.
NOT_FOLLOWED_EVERY_S = 10.0
NOT_A_PEER = 'agent_state: not a peer'

# (info|warn|error, text): one log line.
LogLine = Tuple[str, str]


def _no_poll(name: str) -> None:
    """No lifecycle services here (a test without them): nothing to call."""


class RestoreChannel(Protocol):
    """The agent's writers of its copies' restore topics (nodes/state_relay.py): one per node,
    on the restore topic of its live process (catalogue.copy_restore_topic)."""

    def ready(self, name: str, topic: str) -> bool:
        """Whether node ``name``'s process here subscribes to ``topic`` (its writer follows
        ``topic`` from now on)."""

    def send(self, name: str, topic: str, data: bytes) -> None:
        """Publish a serialised state message on ``topic``."""

    def delivered(self, name: str, topic: str) -> bool:
        """Whether the process's reader acknowledged what was sent on ``topic``."""


@dataclass
class AgentInputs:
    """What the ROS side observed for one step."""

    wall: float                              # the wall clock now: the report's stamp
    # How many nodes of each name the ROS graph shows (plain and namespaced names); read only
    # when ``AgentTurn.watches_graph``.
    visible: Mapping[str, int] = field(default_factory=dict)
    # Make the service call that lifecycle copy ``name``'s driver asks for now, if any
    # (nodes/lifecycle_client.py); its answer reaches the driver later.
    poll: Callable[[str], None] = _no_poll
    # Whether connection ``name``'s topic was heard from a writer that joined at or after
    # ``since`` (the probes); None without probes.
    writer_joined: Optional[Callable[[str, float], Optional[bool]]] = None
    probed: Collection[str] = ()             # the connections the probes watch now
    # State messages heard since the last step: (node, serialised message, sequence number).
    heard: Sequence[Tuple[str, bytes, int]] = ()
    # Messages others published on a node's own restore topic (a pose set in RViz), which
    # its copies, remapped, do not hear: (node, serialised message).
    requests: Sequence[Tuple[str, bytes]] = ()
    restore: Optional[RestoreChannel] = None     # None: no state is handed to any copy


@dataclass
class AgentOutput:
    """What one step or one input asks its caller to do."""

    logs: List[LogLine] = field(default_factory=list)
    # Lines on repeated bad input, each of a kind: (kind, warn|error, text), for a throttled log.
    notes: List[Tuple[str, str, str]] = field(default_factory=list)
    step: bool = False                       # run a step now (an input that changes what runs)
    wanted: Set[str] = field(default_factory=set)      # the processes wanted (supervisor's)
    goals: Dict[str, Optional[LifecycleState]] = field(default_factory=dict)
    report: Optional[protocol.AgentState] = None       # to publish now
    tick_s: Optional[float] = None           # the period of the next steps (None: as it is)
    probe_connections: Optional[Tuple[str, ...]] = None   # the probes' new connections


def name_counts(names_and_namespaces: Iterable[Tuple[str, str]]) -> Dict[str, int]:
    """How many nodes of each name the ROS graph shows, by full name and, in the root
    namespace, by plain name too (``AgentInputs.visible``)."""
    counts: Dict[str, int] = {}
    for name, ns in names_and_namespaces:
        full = ns.rstrip('/') + '/' + name
        for key in {name, full} if ns in ('', '/') else {full}:
            counts[key] = counts.get(key, 0) + 1
    return counts


def node_reports(reports: Mapping[str, protocol.NodeReport], drivers: Mapping[str, lc.Driver],
                 wall_offset: float) -> Dict[str, protocol.NodeReport]:
    """Each node's part of the agent's report: the supervisor's (``since`` on the monotonic
    clock) with ``since`` on the wall clock, a lifecycle copy's read through its driver
    (agent/lifecycle.py report)."""
    nodes = {}
    for name, r in reports.items():
        since = r.since + wall_offset if r.since else 0.0
        state, ready, reason, label = r.state, r.ready, r.exit_reason, None
        driver = drivers.get(name)
        if driver is not None:
            state, ready, reason, label = lc.report(r.state, r.ready, r.exit_reason, driver)
        nodes[name] = replace(r, state=state, since=since, ready=ready, exit_reason=reason,
                              lifecycle=label)
    return nodes


class AgentTurn:
    """The agent between and during its turns (see the module)."""

    def __init__(self, deployment: Deployment, scale: str, catalogue: Mapping[str, Entry],
                 supervisor: Supervisor, *, instance: str, wall_offset: float,
                 host_id: str = '', host_name: str = ''):
        d = deployment
        s = d.agent
        self.deployment = d
        self.scale = scale
        self.catalogue = dict(catalogue)
        self.supervisor = supervisor
        self.instance = instance                  # this agent process, in its reports
        self.wall_offset = wall_offset            # wall clock minus the caller's monotonic one
        self.host_id, self.host_name = host_id, host_name
        self.reconciler = Reconciler(d, scale, self.catalogue,
                                     readiness_timeout_s=s.readiness_timeout_s,
                                     agent_timeout_s=d.decider.agent_timeout_s)
        self.follower = Follower(d.decider.lease_s)
        self.hosts = HostBook()                   # the machine each other scale's agent reports
        self.drivers: Dict[str, lc.Driver] = {
            name: lc.Driver(name, change_timeout_s=s.lifecycle_timeout_s,
                            backoff_s=max(s.restart_backoff_s, 0.1),
                            backoff_max_s=max(s.restart_backoff_max_s, 0.1))
            for name, entry in self.catalogue.items() if entry.lifecycle and entry.startable}
        # Each stateful node's latest state, handed to a copy before it serves here.
        self.states = StateBook({n: d.node(n).state for n, e in self.catalogue.items()
                                 if e.state_topic and e.startable and d.node(n).state},
                                s.state_max_bytes, s.state_stale_s)
        self._logs: List[LogLine] = []            # the current step's log lines
        self.shutdown_requests = 0
        self.restarting = False
        self.tick_s = TICK_S
        self._lifecycle_pid: Dict[str, int] = {}
        self._finalize_since: Dict[str, float] = {}
        self._published_view: Dict[str, tuple] = {}
        self._publish_due = False                 # a report is news even if nothing changed
        self._last_waiting: Dict[str, str] = {}
        # A state set by others that the copy it is for could not be sent yet (its restore
        # input not matched yet): sent as soon as it is, unless a hand-over supersedes it.
        self._to_forward: Dict[str, bytes] = {}
        self._probe_names: Optional[Tuple[str, ...]] = None
        self._not_followed_at: Optional[float] = None
        # A shared scale's claims on its host (agent/claims.py); None on a scale of its own.
        self.claims: Optional[HostClaims] = None

    # --- queries ----------------------------------------------------------------------------
    @property
    def watches_graph(self) -> bool:
        """Whether a step needs the ROS graph's node names (``AgentInputs.visible``): a plain
        node is up once its name shows there (a lifecycle copy once it answers get_state), and
        only a copy not seen yet is looked for."""
        return any(n not in self.drivers for n in self.supervisor.unseen())

    @property
    def finished(self) -> bool:
        return bool(self.shutdown_requests) and self.supervisor.all_stopped()

    def serving(self) -> Set[str]:
        """Nodes that serve here now: a live plain process, or a lifecycle copy that is active
        or being activated (not one whose state is not known yet)."""
        out = set()
        sup = self.supervisor
        for name in sup.active():
            d = self.drivers.get(name)
            if d is None:
                out.add(name)
            elif sup.state(name) != ProcState.STOPPING:
                if d.state == lc.ACTIVE or (d.known and d.goal == lc.ACTIVE and not d.failed):
                    out.add(name)
        return out

    def serving_pids(self) -> Dict[str, int]:
        """The pids of the copies that serve: an inactive standby copy's CPU is not its node's."""
        serving = self.serving()
        return {n: pid for n, pid in self.supervisor.pids().items() if n in serving}

    def supervised_pids(self) -> List[int]:
        """Every live process this agent supervises: serving, standby or stopping copies."""
        return list(self.supervisor.pids().values())

    def shared_with(self, now: float) -> tuple:
        """The other scales whose agents, heard within agent_timeout_s, run on this machine."""
        return self.hosts.sharing(self.scale, self.host_id, now,
                                  self.deployment.decider.agent_timeout_s)

    def is_own(self, state: protocol.AgentState) -> bool:
        """Whether a report on the agent_state topic is this agent's own."""
        return state.scale == self.scale and state.instance == self.instance

    def report(self, stamp: float) -> protocol.AgentState:
        """This agent's report, stamped ``stamp`` on the wall clock (the caller numbers it)."""
        f = self.follower
        return protocol.AgentState(
            scale=self.scale, generation=self.reconciler.generation, stamp=stamp,
            nodes=node_reports(self.supervisor.reports(), self.drivers, self.wall_offset),
            decider=f.followed_id, term=f.term, instance=self.instance,
            host_id=self.host_id or None, host=self.host_name or None,
            share=None if self.claims is None else self.claims.report())

    def activation_held(self, name: str, now: float, inputs: AgentInputs) -> str:
        """Why the copy of lifecycle node ``name``, placed here, may not be activated yet ('':
        it may). Held, it is kept inactive, its process running, and the reason is logged
        like a move's wait. A copy of a node with ``state:`` is handed the node's latest state
        first (``_hand_state``)."""
        return self._hand_state(name, now, inputs)

    def _hand_state(self, name: str, now: float, inputs: AgentInputs) -> str:
        """Hand the copy of ``name`` here its node's latest state, once per spell of serving:
        '' once handed (or there is none to hand), else what it waits for. A lifecycle copy
        is handed it while inactive (configured: its restore input exists), and activated only
        once its reader has acknowledged it."""
        states = self.states
        pid = self.supervisor.pids().get(name, 0)
        if not states.needs(name, pid):
            return ''
        driver = self.drivers.get(name)
        if driver is not None and driver.state != lc.INACTIVE:
            return 'its state is handed to the copy once it is configured'
        pending = states.begin(name, pid, now)
        channel = inputs.restore
        topic = self._restore_topic(name)
        if not pending.sent:
            handover, lines = states.handover(name, pid, now)
            if handover.data is None:
                # Nothing heard yet (this agent just started, or its link just came up): the
                # copy the layout moves the node from serves on until this one is ready (one
                # being activated there too), and its state is on its way (its writer found
                # within a discovery round), unless its agent said lately that it neither
                # serves nor starts (a crash, a standby: nothing to wait for).
                # This agent's first layout came mid-run (it started late, or its link came
                # up after the first layouts): where the node served before is not known here,
                # and a copy may serve elsewhere with its state on the way: wait as for one.
                before = self.reconciler.moved_from.get(name, '')
                fresh_s = PEER_FRESH_BEATS / self.deployment.agent.heartbeat_rate_hz
                limit = FIRST_STATE_WAIT_S
                if self.reconciler.reported_serving(name, before, now, fresh_s):
                    limit = max(limit, self.deployment.agent.readiness_timeout_s / 2.0)
                if before and before != self.scale \
                        and not self.reconciler.reported_not_serving(name, before, now, fresh_s) \
                        and now - pending.since < limit:
                    where = 'serving before this agent heard a layout' \
                        if before == UNKNOWN_SCALE else f'on {before}'
                    pending.awaiting_first = True
                    return f'its state is handed to the copy first: waiting for the first ' \
                           f'state of its copy {where}'
                self._logs.extend(lines)            # none to be had: it starts from its own
                states.handed(name, pid)
                return ''
            if pending.awaiting_first:              # it came: the restore input's wait begins
                pending.awaiting_first, pending.since = False, now
            if channel is None or not topic:        # no ROS side to hand it with (a test)
                states.handed(name, pid)
                return ''
            if not channel.ready(name, topic):
                return f'its state is handed to the copy first: waiting for its restore ' \
                       f'input ({topic})'
            channel.send(name, topic, handover.data)     # the latest, as it is now
            pending.sent = True
            self._logs.extend(lines)
        if channel is None or not topic or channel.delivered(name, topic):
            states.handed(name, pid)
            return ''
        return 'its state is handed to the copy first: waiting for its acknowledgement'

    # --- inputs -----------------------------------------------------------------------------
    def begin(self, now: float) -> AgentOutput:
        """The agent starts: adopt what a previous agent process left running, and count the
        master's silence from here (a remote scale stops its nodes after agent_timeout_s)."""
        out = AgentOutput()
        for note in self.supervisor.adopt(now):
            # Unreadable, or not this agent's: a warning.
            out.logs.append(('warn' if note.startswith('state file') else 'info',
                             f'adoption: {note}'))
        if self.scale != self.deployment.master.name:
            self.reconciler.heard_master(now)
        if self.claims is not None:
            out.logs.extend(self.claims.begin(now))
        return out

    def on_layout(self, layout: protocol.Layout, now: float) -> AgentOutput:
        """A layout of this deployment that passed the signature check."""
        out = AgentOutput()
        follow = self.follower.consider(layout.decider, now, layout.term)
        if not follow.accept:
            if self._not_followed_at is None \
                    or now - self._not_followed_at >= NOT_FOLLOWED_EVERY_S:
                self._not_followed_at = now
                out.logs.append(('warn', follow.reason))
            return out
        if follow.reason:
            out.logs.append(('info', follow.reason))
        # The decider runs on the master scale: its layout, even one latched and delivered
        # when the link comes back, is word from there now. Counted before the layout is
        # applied, so that the first step after it does not take the silence before it for a
        # cut and stop what the layout just placed here.
        self.reconciler.heard_master(now)
        if not follow.switched and layout.generation == self.reconciler.generation:
            return out      # the followed decider's re-publication: its lease, nothing new
        verdict = self.reconciler.apply_layout(layout, now, new_decider=follow.switched)
        out.logs.extend(('warn', w) for w in verdict.warnings[:MAX_LAYOUT_WARNINGS])
        if len(verdict.warnings) > MAX_LAYOUT_WARNINGS:
            out.logs.append(('warn', f'layout generation {layout.generation}: '
                                     f'{len(verdict.warnings) - MAX_LAYOUT_WARNINGS} more '
                                     'entries ignored (not listed)'))
        if verdict.applied:
            mine = sorted(n for n, s in self.reconciler.assignments.items() if s == self.scale)
            out.logs.append(('info', f'layout generation {layout.generation} applied '
                                     f'({layout.reason or "no reason given"}); here: '
                                     f'{", ".join(mine) or "nothing"}'))
            out.step = True
            # The new generation is news for the others even when nothing here changed.
            self._publish_due = True
        return out

    def on_agent_state(self, state: protocol.AgentState, now: float) -> AgentOutput:
        """Another agent's report (not this one's own) that passed the signature check: a step
        at once when it is news (Reconciler.peer_news)."""
        out = AgentOutput()
        before = self.reconciler.peers.get(state.scale)
        warning = self.reconciler.peer_state(state, now)
        if warning:
            out.notes.append((NOT_A_PEER, 'warn', warning))
        elif state.scale != self.scale:
            self.hosts.heard(state.scale, state.host_id, state.host, now)
            out.step = self.reconciler.peer_news(before, now)
        return out

    def on_objective(self, objective: protocol.Objective, now: float) -> AgentOutput:
        """The decider's output at one of its steps, checked: word from the master scale."""
        self.reconciler.heard_master(now)
        return AgentOutput()

    def request_shutdown(self, now: float) -> AgentOutput:
        """Stop every node: lifecycle copies are finalized first, then signalled. A second
        request skips the graces."""
        self.shutdown_requests += 1
        out = AgentOutput()
        if self.shutdown_requests == 1:
            out.logs.append(('info', 'shutting down: stopping every node of this scale'))
            out.step = True
        else:
            out.logs.append(('warn', 'second shutdown request: killing every node now'))
            self.supervisor.kill_all(now)
        return out

    def request_restart(self) -> AgentOutput:
        """Restart in place, leaving every node running for the next agent process to adopt."""
        out = AgentOutput()
        if self.shutdown_requests:
            out.logs.append(('warn', 'restart requested while shutting down: ignored'))
            return out
        out.logs.append(('info', 'restarting in place: the nodes of this scale keep running '
                                 'and are adopted by the new agent process (same pid)'))
        self.restarting = True
        # The warden waits restart_grace_s for the new process, not adopt_grace_s.
        self.supervisor.restarting = True
        self.supervisor.save()
        return out

    # --- one step ---------------------------------------------------------------------------
    def _may_serve(self, name: str) -> bool:
        """The lifecycle copy of ``name`` here may be active: it says so, it was asked to
        activate (or was active) and has not been seen inactive since (a transition under way,
        one that timed out), or it was adopted and has not said yet (a copy this agent started
        begins inactive)."""
        driver = self.drivers.get(name)
        if driver is None:
            return False
        return driver.may_be_active or (driver.state == lc.UNKNOWN
                                        and self.supervisor.adopted(name))

    def hear_states(self, heard: Sequence[Tuple[str, bytes, int]], now: float) -> List[LogLine]:
        """State messages heard (``AgentInputs.heard``) into the book of the latest state of
        each node, between steps as well as at them; returns what to log."""
        out: List[LogLine] = []
        for node, data, seq in heard:
            out.extend(self.states.heard(node, data, now, seq))
        return out

    def step(self, now: float, inputs: AgentInputs) -> AgentOutput:
        """One step at ``now``: decide what runs here, drive the processes and lifecycles."""
        out = AgentOutput()
        self._logs = out.logs
        sup = self.supervisor
        out.logs.extend(self.hear_states(inputs.heard, now))
        self._forward_requests(inputs, out, now)
        if self.shutdown_requests:
            want: Set[str] = set()
            goals: Dict[str, Optional[LifecycleState]] = {n: lc.FINALIZED for n in self.drivers}
        else:
            placed = self.reconciler.desired(
                now, self.serving(), heard_here=lambda node, since: self._heard_here(
                    node, since, inputs))
            live = [n for n in self.drivers if sup.state(n) in LIVE_STATES]
            goals, want = lc.goals(self.drivers, placed, self.reconciler.standby_here,
                                   self.reconciler.has_layout, live)
            waiting = dict(self.reconciler.waiting)
            for name, goal in goals.items():
                if goal == lc.ACTIVE and self.drivers[name].state != lc.ACTIVE:
                    why = self.activation_held(name, now, inputs)
                    if why:
                        goals[name] = lc.INACTIVE
                        waiting[name] = why
                elif goal != lc.ACTIVE:
                    self.states.stood_down(name)     # its next spell is handed the state anew
            self._note_waiting(waiting, out)
        want |= {n for n, g in goals.items() if g == lc.FINALIZED and self._finalizing(n, now)}
        if self.claims is not None:
            out.logs.extend(self.claims.gate(now, want, goals, lambda n: n in sup.pids(),
                                             self._may_serve))
            self._publish_due |= self.claims.report_changed
        sup.set_wanted(want, now)
        self._sync_drivers()
        for name, goal in goals.items():
            driver = self.drivers[name]
            # A copy whose state is not known yet (just started, or adopted) is only asked
            # for it: activating or deactivating it blind could leave two copies serving.
            driver.set_goal(goal if driver.known or goal == lc.FINALIZED else None)
            out.goals[name] = driver.goal
        out.wanted = set(want)
        changed = sup.step(now, lambda entry: self._visible(entry, now, inputs.visible))
        if self.claims is not None and self.shutdown_requests:
            # Shutting down: a copy gone in this step gives its room back now, before the
            # agent exits (its claim would otherwise hold the room for a lease).
            out.logs.extend(self.claims.gate(now, set(), {}, lambda n: n in sup.pids()))
            self._publish_due |= self.claims.report_changed
        self._sync_drivers()
        self._hand_plain_states(now, inputs)
        self._follow_restore_topics(inputs)
        self._drive_lifecycles(now, inputs.poll)
        out.logs.extend(self.states.expired(now, self.deployment.agent.lifecycle_timeout_s))
        out.logs.extend(sup.events)
        sup.events.clear()
        # Answers to lifecycle requests arrive between steps: compare with what was last
        # published, not with the start of this step.
        view = {n: (d.state, d.goal, d.failed) for n, d in self.drivers.items()}
        if changed or view != self._published_view or self._publish_due:
            self._published_view = view
            self._publish_due = False
            out.report = self.report(inputs.wall)
        names = self._probe_connections()
        if names != self._probe_names:
            self._probe_names = out.probe_connections = names
        stopping = any(sup.state(n) == ProcState.STOPPING for n in sup.names)
        # A hand-over under way is looked at again soon: the copy's activation waits on it.
        if stopping or self.states.pending():
            tick = STOPPING_TICK_S
        elif self._under_way():
            tick = TICK_S
        else:
            due = [t for t in (self.reconciler.next_due(now), sup.next_due(now)) if t is not None]
            tick = IDLE_TICK_S if not due else min(IDLE_TICK_S,
                                                   max(STOPPING_TICK_S, min(due) - now))
        self.tick_s = out.tick_s = tick
        return out

    def _under_way(self) -> bool:
        """Whether a step may have work before an input arrives (IDLE_TICK_S): a process on its
        way (starting, backing off, not seen yet, stopping), a lifecycle copy not at its goal,
        a move held back, a shutdown, or a state set by others not forwarded yet. (The states
        kept here are taken between steps: ``hear_states``.)"""
        sup = self.supervisor
        return bool(self.shutdown_requests or self.reconciler.waiting or self._finalize_since
                    or self._to_forward or not sup.settled
                    or any(not d.settled for n, d in self.drivers.items()
                           if sup.state(n) in LIVE_STATES))

    def _restore_topic(self, name: str) -> str:
        """The restore topic of ``name``'s live process here ('' when none runs)."""
        instance = self.supervisor.instances().get(name)
        return copy_restore_topic(self.catalogue[name], instance) if instance else ''

    def _follow_restore_topics(self, inputs: AgentInputs) -> None:
        """Each live stateful process's writer follows its restore topic from its start: by
        the time it is to serve (a failover), the writer and its reader are matched."""
        if inputs.restore is None:
            return
        for name in self.states.specs:
            topic = self._restore_topic(name)
            if topic:
                inputs.restore.ready(name, topic)

    def _forward_requests(self, inputs: AgentInputs, out: AgentOutput, now: float) -> None:
        """What others publish on a node's restore topic (a pose set in RViz) is the node's
        state from now on: kept as its latest here (a copy taking over is handed it), and sent
        to the copy serving here, or to one being handed its state here once that was sent (a
        copy still waiting for its hand-over gets it as the latest state); to a copy whose
        restore input is not matched yet, as soon as it is."""
        if inputs.restore is None:
            return
        for node, data in inputs.requests:
            out.logs.extend(self.states.set_by_others(node, data, now))
            self._to_forward[node] = data
        if not self._to_forward:
            return
        serving = self.serving()
        for node, data in list(self._to_forward.items()):
            topic = self._restore_topic(node)
            pending = self.states.pending_for(node)
            taking = pending is not None and pending.sent
            if not (node in serving and pending is None or taking) or not topic:
                # No copy here to send it to: it is the latest state of the book, handed to
                # the next copy that serves here.
                del self._to_forward[node]
            elif inputs.restore.ready(node, topic):
                inputs.restore.send(node, topic, data)
                del self._to_forward[node]
                out.logs.append(('info', f'{node}: a message on '
                                         f'{self.states.specs[node].restore} handed to its '
                                         'copy here'))

    def _hand_plain_states(self, now: float, inputs: AgentInputs) -> None:
        """A plain copy (no lifecycle to hold it back) of a stateful node serving here is
        handed the state as soon as its restore input appears; a stopped one stands down."""
        for name in self.states.specs:
            if name in self.drivers:
                continue
            if self.supervisor.state(name) in LIVE_STATES:
                self._hand_state(name, now, inputs)
            else:
                self.states.stood_down(name)

    def _note_waiting(self, waiting: Mapping[str, str], out: AgentOutput) -> None:
        """Say why a node's start or stop is held back, once per reason (its figures aside)."""
        for node, why in waiting.items():
            if self._last_waiting.get(node) != why.split(' (')[0]:
                out.logs.append(('info', f'{node}: {why}'))
        self._last_waiting = {n: w.split(' (')[0] for n, w in waiting.items()}

    def _visible(self, entry: Entry, now: float, counts: Mapping[str, int]) -> bool:
        if entry.lifecycle:
            # Up once it answers get_state on its own services.
            return entry.name in self.drivers and self.drivers[entry.name].known
        # A copy still running on another scale has the same name: count ours.
        elsewhere = self.reconciler.copies_elsewhere(entry.name, now)
        return counts.get(entry.ros_name, 0) > elsewhere

    def _finalizing(self, name: str, now: float) -> bool:
        """Whether a lifecycle copy that must stop keeps its process a while longer: until it
        is finalized, its driver gave up, or lifecycle_timeout_s has passed since it was asked
        (a node that does not answer is signalled all the same)."""
        if self.supervisor.state(name) not in LIVE_STATES:
            self._finalize_since.pop(name, None)
            return False
        driver = self.drivers[name]
        since = self._finalize_since.setdefault(name, now)
        if driver.state == lc.FINALIZED or driver.failed \
                or now - since > self.deployment.agent.lifecycle_timeout_s:
            return False
        return True

    def _sync_drivers(self) -> None:
        """A new process (started, restarted or gone) starts its driver afresh."""
        pids = self.supervisor.pids()
        for name, driver in self.drivers.items():
            pid = pids.get(name, 0)
            if self._lifecycle_pid.get(name, 0) != pid:
                self._lifecycle_pid[name] = pid
                driver.reset()
                self._finalize_since.pop(name, None)

    def _drive_lifecycles(self, now: float, poll: Callable[[str], None]) -> None:
        sup = self.supervisor
        for name, driver in self.drivers.items():
            if sup.state(name) not in LIVE_STATES:
                continue
            if driver.failed and driver.goal in (lc.ACTIVE, lc.INACTIVE):
                sup.restart(name, now, f'its lifecycle did not reach {driver.goal}: '
                                       f'{driver.problem}')
                continue
            poll(name)
            sup.events.extend(driver.events)
            driver.events.clear()

    def _heard_here(self, node: str, since: float, inputs: AgentInputs) -> Optional[bool]:
        """Whether this scale has heard, since ``since``, a newly started writer (the node's
        copy elsewhere) on every output of ``node`` that it watches; None when it watches
        none."""
        if inputs.writer_joined is None:
            return None
        joined = [inputs.writer_joined(c.name, since) for c in self.deployment.connections
                  if c.publisher == node and c.name in inputs.probed]
        heard = [j for j in joined if j is not None]
        return all(heard) if heard else None

    def _probe_connections(self) -> Tuple[str, ...]:
        """The connections whose subscriber serves here: the ones this scale's probes watch."""
        d = self.deployment
        here = self.serving()
        for n in d.nodes:
            if not n.managed and d.allowed_scales(n.name) == (self.scale,):
                here.add(n.name)
        return tuple(c.name for c in d.connections if c.subscriber in here)
