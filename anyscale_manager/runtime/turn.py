"""The decider's turn, pure: observations and a clock in; the layout, decisions, events,
diagnostics, objective and plan check out.

``DeciderTurn`` holds everything a decider knows between turns (the observation book, the
policy, the liveness and single-machine watches, the cost integral, the layout and its
generation, the violations and notes already announced). The rclpy decider
(nodes/decider.py) feeds the book from its topics, calls ``turn(now)`` once a period (and at
once on a cut, a crash or a shrinking link) and publishes what comes back; the unit tests
drive the same object with a hand-written clock, and the simulator hands it the observations
of its simulated world with the world's clock (``turn(now, observed)``). Nothing here reads a
clock or touches ROS.
"""

from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Protocol, Sequence, Set, Tuple

from .. import protocol as p
from ..model.types import DeciderSettings, Deployment
from .constraints import ConstraintReport
from .cost import CostIntegrator
from .hosts import SingleMachineWatch
from .intake import ObservationBook
from .layout import adopt, initial_plan
from .liveness import LivenessWatch
from .observations import Decision, Observations
from .plan_check import PlanCheckReport, check_plan, expectations
from .policy import MigrationPolicy
from .rates import two_senders_past

# (kind, node, from scale, to scale, reason, generation): one message of /anyscale/events.
EventTuple = Tuple[str, str, str, str, str, int]
# (generation, assignments, reason): one layout to publish.
LayoutTuple = Tuple[int, Dict[str, str], str]
# Said of a takeover whose leader's layout was not heard.
NOT_HEARD = 'its layout was not heard: what runs is adopted'
# The diagnostic value of the time since this generation's layout was made (seconds; '' before
# the first): re-publications re-stamp a layout, so a view that heard it late reads its age here.
LAYOUT_AGE = 'layout age s'


class TurnPolicy(Protocol):
    """What the turn asks of its migration policy: ``MigrationPolicy`` (Algorithm 1) in the live
    decider; the simulator may hand it another policy to judge under the same turn."""

    @property
    def last_report(self) -> Optional[ConstraintReport]: ...

    @property
    def notes(self) -> Tuple[str, ...]: ...

    @property
    def unplaceable(self) -> Mapping[str, str]: ...

    @property
    def migrated(self) -> Sequence[Tuple[str, str]]: ...

    @property
    def layout(self) -> Mapping[str, str]: ...

    def step(self, obs: Observations) -> List[Decision]: ...

    def reset(self, layout: Mapping[str, str], now: float,
              running: Optional[Mapping[str, str]] = None, *, settled: bool = False) -> None: ...

    def heard(self, kind: str, node: str, from_scale: str, now: float) -> None: ...

    def update_settings(self, settings: DeciderSettings) -> None: ...


@dataclass
class TurnOutput:
    """What one turn asks its caller to publish and log."""

    # New layouts to publish, in order (a first layout and a first decision in one turn).
    layouts: List[LayoutTuple] = field(default_factory=list)
    # The moves of this turn, in order (each is also an event): what the agents are to apply.
    decisions: List[Decision] = field(default_factory=list)
    events: List[EventTuple] = field(default_factory=list)
    logs: List[Tuple[str, str]] = field(default_factory=list)      # (info|warn|error, text)
    # Perf_map now, its integral and the time it covers (None before the first layout).
    objective: Optional[Tuple[float, float, float]] = None
    plan: Optional[PlanCheckReport] = None
    level: int = p.OK                                               # the decider's health
    message: str = ''
    values: Dict[str, object] = field(default_factory=dict)


class DeciderTurn:
    """The decider between and during its turns (see the module)."""

    def __init__(self, deployment: Deployment, settings: DeciderSettings, started: float,
                 policy: Optional[TurnPolicy] = None):
        self.deployment = deployment
        self.settings = settings
        self.started = started
        self.planned, self.placements = initial_plan(deployment, settings)
        self.book = ObservationBook(deployment, settings, started)
        self.policy: TurnPolicy = policy if policy is not None else \
            MigrationPolicy(deployment, settings)
        # Silent agents, lost scales and nodes with nowhere to go: said when they change.
        self.liveness = LivenessWatch(deployment, settings)
        # Scales whose agents report one machine (single-machine mode): said when it changes.
        self.machines = SingleMachineWatch(deployment.scale_names)
        self.cost = CostIntegrator(deployment)
        self.expected = expectations(deployment, self.placements)
        self.generation = 0
        self.layout: Optional[Dict[str, str]] = None
        self.layout_made: Optional[float] = None      # when this generation was made
        self.reason = ''
        self.last_report: Optional[ConstraintReport] = None
        self.decisions = 0
        self._active: Set[Tuple[str, str]] = set()    # (kind, subject) violations announced
        self._said: Set[str] = set()                  # warnings and notes announced
        self._duplicated: Set[str] = set()            # connections announced with two senders
        # Why this decider took over a leader whose layout it never heard, until every agent
        # has said what runs (the layout it then adopts).
        self._pending_takeover_reason: Optional[str] = None

    def update_settings(self, settings: DeciderSettings) -> None:
        self.settings = settings
        self.policy.update_settings(settings)
        self.book.settings = settings
        self.liveness.settings = settings

    # --- one turn -----------------------------------------------------------------------------
    def turn(self, now: float, observed: Optional[Observations] = None) -> TurnOutput:
        """One turn at ``now``. ``observed``: a snapshot made elsewhere (the simulator's world),
        taken instead of the book's; it is all there is to know, so the first layout is not
        held back for the agents."""
        out = TurnOutput()
        if self.layout is None:
            if observed is None and not self._agents_known(now):
                out.message = 'waiting for the agents to report what runs'
                return out
            if self._pending_takeover_reason is not None:
                out = self.take_over(now, None, 0, self._pending_takeover_reason)
            else:
                self._start(now, out, observed)
        layout = self._layout()
        obs = observed if observed is not None else self.book.snapshot(now, layout)
        decisions = self.policy.step(obs)
        report = self.policy.last_report
        self.last_report = report
        if decisions:
            self.layout = layout = dict(self.policy.layout)
            self.generation += 1
            self._new_layout('; '.join(f'{d.kind} {d.node}: {d.reason}' for d in decisions), out,
                             now)
            out.decisions.extend(decisions)
            for d in decisions:
                self.decisions += 1
                self._event(out, d.kind, d.node, d.from_scale, d.to_scale, d.reason)
                out.logs.append(('info', f'{d.kind} {d.node} {d.from_scale} -> {d.to_scale}: '
                                         f'{d.reason}'))
        self._announce(report, out)
        self._single_machine(out)
        self._two_senders(now, out)
        for n in self.liveness.update(obs, self.policy.unplaceable, report, layout):
            self._event(out, n.kind, n.node, n.scale, '', n.text)
            out.logs.append((n.level if n.level in ('error', 'warn') else 'info', n.text))

        cpu_by_node: Dict[str, float] = {}
        for so in obs.scales.values():
            cpu_by_node.update(so.cpu_by_node)
        perf, integral = self.cost.update(now, obs.running, cpu_by_node)
        out.objective = (perf, integral, self.cost.elapsed_s)
        out.plan = check_plan(self.deployment, self.expected, obs, self.settings)
        for w in out.plan.warnings:
            self._say_once(w, out)

        level, message = p.OK, 'constraints hold'
        if self.machines.groups:
            message += f' (single-machine mode: {self.machines.summary()})'
        if report is not None and report.violations:
            level, message = p.WARN, f'{len(report.violations)} violation(s): ' + \
                report.violations[0].reason
        live_level, live_message = self.liveness.summary()
        if live_level != p.OK:
            # A silent agent or a node with nowhere to go says more than a violation it causes.
            level, message = live_level, live_message
        out.level, out.message = level, message
        out.values = self.values(now, perf, integral, obs)
        return out

    def values(self, now: float, perf: float = 0.0, integral: float = 0.0,
               obs: Optional[Observations] = None) -> Dict[str, object]:
        """The decider's diagnostic values that the turn knows (``obs``: this turn's)."""
        lost = obs.lost_scales if obs is not None else self.book.lost_scales(now)
        return {
            'generation': self.generation,
            'nodes running': len(obs.running) if obs is not None else 0,
            'lost scales': ', '.join(sorted(lost)),
            'silent agents': ', '.join(sorted(self.liveness.silent_since)),
            'cannot be placed': ', '.join(sorted(self.liveness.unplaceable)),
            'migrated': ', '.join(f'{n}@{s}' for n, s in self.policy.migrated),
            'decisions': self.decisions,
            'perf_map': round(perf, 3), 'perf integral': round(integral, 3),
            'migration': self.settings.migration,
            'single machine': self.machines.summary() or 'no',
            LAYOUT_AGE: '' if self.layout_made is None else round(now - self.layout_made, 1),
        }

    # --- the first layout ---------------------------------------------------------------------
    def _layout(self) -> Dict[str, str]:
        if self.layout is None:
            raise RuntimeError('the decider has no layout yet')
        return self.layout

    def _running(self, now: float) -> Dict[str, str]:
        """Where nodes serve, as the agents report it: a standby node's copies all start at
        boot, so only its active copy counts (a starting one adopted the laptop's fresh
        standby copies)."""
        with_standby = [n for n in self.deployment.node_names
                        if self.deployment.standby_scales(n)]
        return self.book.running(now, active_only=with_standby)

    def _start(self, now: float, out: TurnOutput, observed: Optional[Observations]) -> None:
        # Adopt where nodes serve.
        running = dict(observed.running) if observed is not None else self._running(now)
        layout, notes = adopt(self.deployment, self.planned, running)
        # Above what the agents applied, so that their comparisons across scales stay sane;
        # agents take a new decider's first layout whatever its number, so near the bound
        # it starts again from 1.
        self.generation = max(self.book.max_generation, 0) + 1
        if self.generation > p.MAX_GENERATION - p.MAX_GENERATION_STEP:
            self.generation = 1
        self.layout = layout
        self.policy.reset(layout, now, running)
        lost = sorted(observed.lost_scales if observed is not None
                      else self.book.lost_scales(now))
        reason = f'first layout ({self.settings.initial_layout})'
        if notes:
            reason += ': ' + '; '.join(notes)
        self._new_layout(reason, out, now)
        for note in notes:
            self._event(out, 'adopt', '', '', '', note)
        if lost:
            self._event(out, 'warning', '', '', '', 'no report from the agent of '
                        + ', '.join(lost) + ' at start')
        out.logs.append(('info', f'generation {self.generation}: {reason}'))

    def _agents_known(self, now: float) -> bool:
        """Whether what runs is known well enough to adopt it: every agent has reported, or
        agent_timeout_s has passed since this decider started (the silent ones count as lost)."""
        return self.book.all_agents_heard() or now - self.started >= self.settings.agent_timeout_s

    # --- a standby's turn ----------------------------------------------------------------------
    def heard_decision(self, kind: str, node: str, from_scale: str, now: float) -> None:
        """The leader's decision (its event), remembered for hysteresis after a takeover."""
        self.policy.heard(kind, node, from_scale, now)

    def lead(self, now: float, reason: str, took_over: bool,
             heard: Optional[Tuple[int, Mapping[str, str]]] = None) -> Optional[TurnOutput]:
        """This decider has just come to lead (``reason``: why); the layout it leads on from.

        ``heard``: the last layout (generation, assignments) of the leader it takes over from,
        when it heard one: that layout. Else its own last layout (a leader that stepped down
        leads again). Else, ``took_over`` a leader whose layout it did not hear (it died just
        after this decider found it): what runs, as the agents report it, once every agent has
        reported (a standby just started may not have heard them all yet: adopting then would
        move what runs on the scales not heard; until then the layout stands and its first turn
        takes over). A decider that leads without having followed anyone returns None: its
        first turn makes the first layout. A takeover is also said as an event of its own."""
        self._pending_takeover_reason = None
        if heard is not None:
            out = self.take_over(now, dict(heard[1]), heard[0], reason)
        elif self.layout is not None:
            out = self.take_over(now, dict(self.layout), self.generation, reason)
        elif took_over and self._agents_known(now):
            out = self.take_over(now, None, 0, reason)
        elif took_over:
            self._pending_takeover_reason = reason
            out = TurnOutput()
            missing = sorted(set(self.deployment.scale_names) - set(self.book.agents))
            out.logs.append(('info', f'{reason}; {NOT_HEARD} once every agent has reported '
                                     f'(not yet: {", ".join(missing)}; at most '
                                     f'{self.settings.agent_timeout_s:g} s after this decider '
                                     'started)'))
        else:
            return None
        if took_over:
            self._event(out, 'takeover', '', '', '', reason)
        return out

    def take_over(self, now: float, assignments: Optional[Dict[str, str]], generation: int,
                  reason: str) -> TurnOutput:
        """Lead on from the layout of the decider taken over from: nothing moves that it did
        not move; only the nodes not yet running where it placed them get a grace period.
        ``assignments`` None: its layout was not heard: what runs, as the agents report it,
        is adopted."""
        out = TurnOutput()
        self._pending_takeover_reason = None
        running = self._running(now)
        if assignments is None:
            assignments, notes = adopt(self.deployment, self.planned, running)
            reason += f'; {NOT_HEARD}' + (' (' + '; '.join(notes) + ')' if notes else '')
        layout = dict(self.layout or self.planned)
        for node, scale in assignments.items():
            if node in layout and scale in self.deployment.allowed_scales(node):
                layout[node] = scale
        self.generation = max(generation, self.generation, self.book.max_generation, 0) + 1
        if self.generation > p.MAX_GENERATION - p.MAX_GENERATION_STEP:
            self.generation = 1
        self.layout = layout
        self.policy.reset(layout, now, running, settled=True)
        self._new_layout(reason, out, now)
        out.logs.append(('info', f'generation {self.generation}: {reason}'))
        return out

    # --- what is said -------------------------------------------------------------------------
    def _event(self, out: TurnOutput, kind: str, node: str, from_scale: str, to_scale: str,
               reason: str) -> None:
        out.events.append((kind, node, from_scale, to_scale, reason, self.generation))

    def _new_layout(self, reason: str, out: TurnOutput, now: float) -> None:
        self.reason = reason[:2000]
        self.layout_made = now
        out.layouts.append((self.generation, dict(self._layout()), self.reason))
        self._event(out, 'layout', '', '', '', self.reason)

    def _announce(self, report: Optional[ConstraintReport], out: TurnOutput) -> None:
        """Events for violations as they appear and clear, and for new notes (not each turn)."""
        active = set()
        if report is not None:
            for v in report.violations:
                key = (v.kind, v.subject)
                active.add(key)
                if key not in self._active:
                    self._event(out, 'violation', ','.join(v.nodes), '', '',
                                f'{v.kind}: {v.reason}')
        for kind, subject in sorted(self._active - active):
            self._event(out, 'cleared', '', '', '', f'{kind} on {subject} holds again')
        self._active = active
        for note in self.policy.notes:
            self._say_once(note, out, kind='note')

    def _two_senders(self, now: float, out: TurnOutput) -> None:
        """An error event when a probe has heard two or more writers of a connection's topic
        at once for longer than a move's overlap (monitoring.duplicate_sender_s), and an event
        when that ends."""
        bound = self.deployment.monitoring.duplicate_sender_s
        max_age = self.settings.observation_max_age_s
        seen: Dict[str, Tuple[str, int, float]] = {}
        for (scale, name), r in self.book.readings.items():
            if now - r.stamp <= max_age and two_senders_past(r.senders_for_s, bound):
                seen.setdefault(name, (scale, r.senders, r.senders_for_s))
        for name, (scale, senders, for_s) in sorted(seen.items()):
            if name in self._duplicated:
                continue
            conn = self.deployment.connection(name)
            text = (f'{conn.topic} ({name}): {senders} senders heard at once on {scale} for '
                    f'{for_s:.1f} s (> duplicate_sender_s {bound:g} s): copies of '
                    f'{conn.publisher} serve on more than one scale')
            self._event(out, 'duplicate', conn.publisher, scale, '', text)
            out.logs.append(('error', text))
        for name in sorted(self._duplicated - set(seen)):
            self._event(out, 'cleared', '', '', '', f'{name}: one sender again')
        self._duplicated = set(seen)

    def _single_machine(self, out: TurnOutput) -> None:
        """One line, one event, when scales start or stop sharing one machine."""
        hosts = {scale: (seen.state.host_id or '', seen.state.host or '')
                 for scale, seen in self.book.agents.items()}
        text = self.machines.update(hosts)
        if text:
            out.logs.append(('info', text))
            self._event(out, 'single_machine', '', '', '', text)

    def _say_once(self, text: str, out: TurnOutput, kind: str = 'warning') -> None:
        if text in self._said:
            return
        if len(self._said) > 1000:
            self._said.clear()
        self._said.add(text)
        self._event(out, kind, '', '', '', text)
