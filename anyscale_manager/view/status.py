"""The status view of a running deployment as text: pure, no ROS, the clock passed in.

``StatusBook`` keeps the latest message of each kind with the local time it arrived; ``render``
turns it into the table ``anyscale-manager status`` shows. A figure older than what its judge
allows is marked ``STALE <age> s`` instead of being shown as current: a scale's CPU and a
connection's rate past ``decider.observation_max_age_s``, an agent past ``agent_timeout_s``, the
layout past ``lease_s`` (the decider re-publishes it every ``lease_s / 3``), a link's measured
bandwidth on a link that is down or past two probe intervals (its probes fail or cannot run).
A measured bandwidth above the link's nominal (an active probe over loopback measures memory
copies) is shown capped at the nominal and says so. The layout's age is the time since its
generation (or its assignments) changed, as this view witnessed it; the decider re-stamps each
re-publication, so the message's own stamp says when it was last sent, not when it was made.
Scales whose agents report one machine are said (single-machine mode, ``runtime.hosts``), and a
scale's CPU measured as its agent's own processes is marked ``own processes``.

A layout heard before the view started is as old as the leading decider's diagnostics say
(``runtime.turn.LAYOUT_AGE``, taken with ``take_decider_values``). CPU is in reference-core
percent, the unit of ``capacity_cpu``; a scale spreads its capacity over the CPUs it measures
(``ScaleStatus.cores``), so one busy CPU reads ``capacity_cpu / cores`` there, and where that is
not 100 the same load is also shown in percent of one of its machine's CPUs (``core%``, as top
shows a process), with a legend. A copy that exited unasked is said under the nodes with its
exit code and the last line of its log (``runtime.liveness.exit_text``). With nothing heard, the
view says which ROS domain and discovery range it listened on and what to check.
"""

import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

from .. import protocol as p
from .. import protocol_auth as auth
from ..model.types import Deployment
from ..runtime.delta import ConnectionVerdict, rate_below
from ..runtime.hosts import describe, shared_groups
from ..runtime.liveness import exit_text
from ..runtime.observations import CopyObs
from ..runtime.rates import two_senders_past
from ..runtime.turn import LAYOUT_AGE
from .shared import share_lines

# A measured bandwidth older than this many probe intervals: probes fail or cannot run.
BANDWIDTH_STALE_INTERVALS = 2.0


def stale_mark(age_s: Optional[float]) -> str:
    return 'STALE' if age_s is None else f'STALE {age_s:.1f} s'


def rtt_text(up: bool, rtt_ms: Optional[float]) -> str:
    """No RTT on a link that is down: the last echo's RTT says nothing of the link now."""
    return f'{rtt_ms:.1f} ms' if up and rtt_ms is not None else '-'


def bandwidth_stale_after_s(deployment: Deployment) -> float:
    m = deployment.monitoring
    return BANDWIDTH_STALE_INTERVALS * m.bandwidth_probe_interval_s + m.bandwidth_probe_duration_s


def bandwidth_text(measured_kbps: Optional[float], nominal_kbps: float, up: bool,
                   age_s: Optional[float], stale_after_s: float, mbit: bool = False) -> str:
    """``available / nominal``: capped at the nominal (and saying so), stale when it is old or
    the link is down (nothing can be measured on it), ``not measured`` before a first probe.

    ``age_s`` is how old the measurement is now; ``mbit``: in Mbit/s, with the unit (else
    kbit/s, without: a table's heading names it).
    """
    def num(kbps: float) -> str:
        return f'{kbps / 1000:.1f}' if mbit else f'{kbps:.0f}'

    unit = ' Mbit/s' if mbit else ''
    if measured_kbps is None:
        return f'not measured / {num(nominal_kbps)}{unit} (nominal assumed)'
    text = f'{num(min(measured_kbps, nominal_kbps))} / {num(nominal_kbps)}{unit}'
    if measured_kbps > nominal_kbps:
        text += ' >nominal (loopback?)'
    if not up or (age_s is not None and age_s > stale_after_s):
        text += ' ' + stale_mark(age_s)
    return text


@dataclass
class StatusBook:
    """The latest message of each kind, with the local time it arrived (pure, no ROS).

    ``layout_made`` is when this book saw the layout's generation or assignments change; None
    while the layout it holds is the first it heard (made before the view started).
    """

    deployment: Deployment
    layout: Optional[Tuple[p.Layout, float]] = None
    layout_made: Optional[float] = None
    layout_first_heard: Optional[float] = None
    objective: Optional[Tuple[p.Objective, float]] = None
    agents: Dict[str, Tuple[p.AgentState, float]] = field(default_factory=dict)
    scales: Dict[str, Tuple[p.ScaleStatus, float]] = field(default_factory=dict)
    links: Dict[str, Tuple[p.LinkStatus, float]] = field(default_factory=dict)
    readings: Dict[Tuple[str, str], Tuple[p.ConnectionReading, float]] = \
        field(default_factory=dict)
    events: List[p.Event] = field(default_factory=list)
    # decider id -> its last beat (leader or standby), of this deployment
    deciders: Dict[str, Tuple[p.DeciderBeat, float]] = field(default_factory=dict)
    ignored: int = 0
    foreign: int = 0
    # With the deployment's key: every message must be signed, unaltered and new (per sender
    # and topic); the others are counted in ``refused`` and dropped.
    key: Optional[bytes] = None
    refused: int = 0
    # The environment the view listens with (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE):
    # said when nothing is heard. None: not known, not said.
    environ: Optional[Mapping[str, str]] = None
    # The leading decider's diagnostic values (runtime/turn.py values), when they were heard.
    decider_values: Optional[Tuple[Dict[str, str], float]] = None
    _gates: Dict[str, auth.Gate] = field(default_factory=dict)
    _wall: float = 0.0

    def take(self, topic: str, text: str, now: float, wall: Optional[float] = None) -> None:
        """Decode one message of ``topic``; malformed ones are counted and dropped, and so are
        those about scales or connections the deployment does not have (another deployment on
        the domain; and names from senders never grow the book). ``wall``: the wall clock a
        signed message's stamp is judged against (with a key; default: this machine's)."""
        self._wall = time.time() if wall is None else wall
        scales = self.deployment.scale_names
        try:
            if topic == p.TOPIC_LAYOUT:
                m = p.Layout.from_json(text, topic)
                if self._verified(topic, text, m):
                    self._take_layout(m, now)
            elif topic == p.TOPIC_OBJECTIVE:
                m = p.Objective.from_json(text, topic)
                if self._verified(topic, text, m):
                    self.objective = (m, now)
            elif topic == p.TOPIC_AGENT_STATE:
                m = p.AgentState.from_json(text, topic)
                if self._verified(topic, text, m):
                    self._keep(self.agents, m.scale, m, now, m.scale in scales)
            elif topic == p.TOPIC_SCALE_STATUS:
                m = p.ScaleStatus.from_json(text, topic)
                if self._verified(topic, text, m):
                    self._keep(self.scales, m.scale, m, now, m.scale in scales)
            elif topic == p.TOPIC_LINK_STATUS:
                m = p.LinkStatus.from_json(text, topic)
                if self._verified(topic, text, m):
                    # Keyed by link: the monitor of each is one of its ends.
                    known = m.master in scales and m.remote in scales
                    link = self.deployment.link_between(m.master, m.remote) if known else None
                    # The master also watches remote scales it has no declared link to: kept
                    # by no row, and not foreign either.
                    if link is not None and self.deployment.link_monitor(link) == m.master:
                        self._keep(self.links, link.name, m, now, True)
                    elif not known:
                        self._keep(self.links, None, m, now, False)
            elif topic == p.TOPIC_CONNECTION_STATUS:
                m = p.ConnectionStatus.from_json(text, topic)
                known = {c.name for c in self.deployment.connections}
                if self._verified(topic, text, m):
                    for name, r in m.connections.items():
                        self._keep(self.readings, (m.scale, name), r, now,
                                   m.scale in scales and name in known)
            elif topic == p.TOPIC_EVENTS:
                m = p.Event.from_json(text, topic)
                if self._verified(topic, text, m):
                    self.events = (self.events + [m])[-8:]
            elif topic == p.TOPIC_DECIDER:
                m = p.DeciderBeat.from_json(text, topic)
                if self._verified(topic, text, m):
                    ours = m.deployment == self.deployment.name
                    if ours and m.decider.id not in self.deciders and len(self.deciders) >= 8:
                        del self.deciders[min(self.deciders,
                                              key=lambda k: self.deciders[k][1])]
                    self._keep(self.deciders, m.decider.id, m, now, ours)
        except p.ProtocolError:
            self.ignored += 1

    def take_decider_values(self, values: Mapping[str, str], now: float) -> None:
        """The leading decider's diagnostic values (its /diagnostics status), heard at ``now``:
        the age of its layout. Unsigned: what they say is shown, never acted on."""
        self.decider_values = ({str(k): str(v)[:100] for k, v in list(values.items())[:64]},
                               now)

    def _verified(self, topic: str, text: str, message: Any) -> bool:
        """Without a key, everything; with one, what its topic's gate lets through."""
        if self.key is None:
            return True
        wall = self._wall
        if topic == p.TOPIC_LAYOUT:
            gate = self._gates.setdefault(topic, auth.LayoutGate(self.key))
            why = gate.check(text, message, wall)
        else:
            gate = self._gates.setdefault(topic, auth.StatusGate(self.key))
            if topic == p.TOPIC_AGENT_STATE:
                why = gate.check_from(text, f'{message.scale}/{message.instance}', message.seq,
                                      message.stamp, wall)
            elif topic == p.TOPIC_OBJECTIVE:
                why = gate.check_from(text, message.decider, message.seq, message.stamp, wall)
            else:
                why = gate.check(text, message, wall)
        if why:
            self.refused += 1
        return not why

    def _keep(self, book: dict, key, message, now: float, known: bool) -> None:
        if known:
            book[key] = (message, now)
        else:
            self.foreign += 1

    def _take_layout(self, layout: p.Layout, now: float) -> None:
        if self.layout is None:
            self.layout_first_heard = now
        else:
            old = self.layout[0]
            if (old.generation, old.assignments) != (layout.generation, layout.assignments):
                self.layout_made = now
        self.layout = (layout, now)

    @property
    def heard_anything(self) -> bool:
        return bool(self.layout or self.agents or self.scales or self.links or self.readings)

    def complete(self) -> bool:
        return self.layout is not None and all(s in self.agents
                                               for s in self.deployment.scale_names)


def _table(rows: List[List[str]]) -> List[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def discovery_range(environ: Mapping[str, str]) -> str:
    """The discovery range a ROS process with ``environ`` uses (Jazzy: SUBNET by default;
    the deprecated ROS_LOCALHOST_ONLY=1 means LOCALHOST when no range is given)."""
    given = environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').strip().upper()
    if given:
        return given
    return 'LOCALHOST' if environ.get('ROS_LOCALHOST_ONLY', '').strip() == '1' else 'SUBNET'


def listening_text(environ: Mapping[str, str]) -> str:
    """'ROS_DOMAIN_ID=7, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (this machine only)': where a
    ROS process with this environment looks for the others."""
    domain = environ.get('ROS_DOMAIN_ID', '').strip()
    text = f'ROS_DOMAIN_ID={domain}' if domain else 'ROS_DOMAIN_ID=0 (unset: the default)'
    reach = discovery_range(environ)
    how = {'LOCALHOST': 'this machine only', 'OFF': 'no discovery at all',
           'SUBNET': 'this machine and its subnet'}.get(reach, '')
    if not environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').strip():
        how = ('from ROS_LOCALHOST_ONLY=1; ' if reach == 'LOCALHOST' else 'unset: the default; ') \
            + how
    text += f', ROS_AUTOMATIC_DISCOVERY_RANGE={reach}' + (f' ({how})' if how else '')
    peers = environ.get('ROS_STATIC_PEERS', '').strip()
    return text + (f', ROS_STATIC_PEERS={peers}' if peers else '')


def nothing_heard_text(book: StatusBook) -> str:
    """Why a view may hear no layout, and what to check."""
    if book.environ is None:
        listened, reach = '', ''
    else:
        listened, reach = f' on {listening_text(book.environ)}', discovery_range(book.environ)
    if book.heard_anything:
        return (f'no layout heard{listened}, though agents or monitors of this deployment '
                'were: is the decider running (ros2 node list shows /anyscale_decider)?')
    text = (f'no layout heard, nor anything else{listened}: check that the decider and the '
            'agents run with the same ROS_DOMAIN_ID')
    if reach == 'LOCALHOST':
        text += ("; LOCALHOST hears this machine's processes only: run the view on the "
                 'master scale, or with the discovery range the scales use')
    elif reach == 'OFF':
        text += '; OFF discovers nothing, not even on this machine'
    else:
        text += ('; that a decider on this machine runs with the same discovery range, and '
                 'that the scales are on this subnet (else ROS_STATIC_PEERS)')
    return text + '; and the same Fast DDS profile (FASTRTPS_DEFAULT_PROFILES_FILE)'


def _layout_line(book: StatusBook, now: float) -> str:
    if not book.layout:
        return nothing_heard_text(book)
    layout, heard = book.layout
    told = _decider_layout_age(book, layout.generation, now)
    if book.layout_made is not None:
        made = f'made {now - book.layout_made:.1f} s ago'
    elif told is not None:
        made = f'made {told:.1f} s ago'
    else:
        made = f'made before this view started (over {now - book.layout_first_heard:.1f} s ago)'
    text = f'layout generation {layout.generation}, {made}'
    if layout.decider is not None:
        text += f', by decider {layout.decider.describe()}'
    if now - heard > book.deployment.decider.lease_s:
        text += f'; decider silent, {stale_mark(now - heard)}'
    return text


def _decider_layout_age(book: StatusBook, generation: int, now: float) -> Optional[float]:
    """The age of layout ``generation`` now, as the leading decider's diagnostics said it."""
    if book.decider_values is None:
        return None
    values, at = book.decider_values
    try:
        if int(values.get('generation', '')) != generation:
            return None
        age = float(values.get(LAYOUT_AGE, ''))
    except ValueError:
        return None
    return age + (now - at) if age >= 0 else None


def _deciders_line(book: StatusBook, now: float) -> str:
    """Who leads and who stands by, from the deciders' beats ('' before any is heard)."""
    if not book.deciders:
        return ''
    # A decider silent for a lease is gone (its beats come every beat_s).
    lease = book.deployment.decider.lease_s
    live = sorted(((b, at) for b, at in book.deciders.values() if now - at <= lease),
                  key=lambda x: (x[0].role != 'leader', -x[0].term, x[0].decider.id))
    if not live:
        return f'deciders: none heard for {lease:g} s'
    return 'deciders: ' + '; '.join(
        f'{b.decider.id} {b.role}' + (f' (term {b.term})' if b.role == 'leader' else '')
        for b, _ in live)


def _objective_line(book: StatusBook, now: float) -> str:
    if not book.objective:
        return 'objective not heard'
    o, at = book.objective
    d = book.deployment.decider
    text = f'objective perf_map {o.perf_map:.1f}, integral {o.integral:.0f} over ' \
           f'{o.elapsed_s:.0f} s'
    if now - at > max(d.observation_max_age_s, 3.0 * d.period_s):
        text += ' ' + stale_mark(now - at)
    return text


def _single_machine_line(book: StatusBook) -> str:
    """'single-machine mode: robot, laptop on host vm (...)', or '' when no scales share one."""
    hosts = {s: a.host_id or '' for s, (a, _) in book.agents.items()}
    names = {s: a.host or '' for s, (a, _) in book.agents.items()}
    groups = shared_groups(hosts, book.deployment.scale_names)
    if not groups:
        return ''
    return ('single-machine mode: ' + '; '.join(describe(g, names) for g in groups)
            + " (each scale's CPU: its own processes unless a cgroup quota confines it; "
            'a loopback bandwidth is capped at the nominal)')


def per_core(book: StatusBook, scale: str) -> Tuple[float, float, bool]:
    """(what one busy CPU reads on ``scale`` in reference-core percent, its CPUs, whether they
    are the ones its monitor reports): capacity_cpu spread over the CPUs it measures (the
    declared ``cores`` when its agent does not say)."""
    s = book.deployment.scale(scale)
    found = book.scales.get(scale)
    measured = found[0].cores if found is not None else None
    cores = float(s.cores if measured is None else measured)
    return s.capacity_cpu / max(cores, 1e-3), cores, measured is not None


def same_unit(ref_per_core: float) -> bool:
    """Whether a reference-core percent reads as a percent of one of the scale's CPUs."""
    return abs(ref_per_core - 100.0) < 0.5


def cpu_text(ref: float, ref_per_core: float) -> str:
    """'64' where the units agree, '64 = 18 core%' where they do not."""
    text = f'{ref:.0f}'
    if not same_unit(ref_per_core) and ref_per_core > 0:
        text += f' = {100.0 * ref / ref_per_core:.0f} core%'
    return text


def cpu_legend(book: StatusBook) -> str:
    """One line saying why a scale's CPU and its core% differ ('' where none does)."""
    parts = []
    for s in book.deployment.scales:
        if s.name not in book.scales:
            continue
        ratio, cores, reported = per_core(book, s.name)
        if not same_unit(ratio):
            how = '' if reported else ', as declared'
            parts.append(f'{ratio:.0f} on {s.name} ({s.capacity_cpu:g} over {cores:g} '
                         f'CPU{"" if cores == 1 else "s"}{how})')
    if not parts:
        return ''
    return ("CPU in reference-core percent (capacity_cpu's unit): a scale spreads its "
            'capacity_cpu over the CPUs it measures, so one busy CPU reads ' + ', '.join(parts)
            + "; core% is the same load in percent of one of its machine's CPUs, as top "
            'shows a process')


def _scale_rows(book: StatusBook, now: float) -> List[str]:
    d = book.deployment
    rows = [['SCALE', 'ROLE', 'CPU USED / CAPACITY', 'AGENT']]
    for s in d.scales:
        cpu = '-'
        if s.name in book.scales:
            st, at = book.scales[s.name]
            cpu = f'{st.cpu_total:.0f} / {s.capacity_cpu:.0f} ' \
                  f'({st.cpu_total / s.capacity_cpu:.0%})'
            ratio = per_core(book, s.name)[0]
            if not same_unit(ratio):
                cpu += f' = {100.0 * st.cpu_total / ratio:.0f} core%'
            if st.cpu_source == 'processes':
                cpu += ' own processes'
            if now - at > d.decider.observation_max_age_s:
                cpu += ' ' + stale_mark(now - at)
        agent = 'not heard'
        if s.name in book.agents:
            a, at = book.agents[s.name]
            if now - at > d.decider.agent_timeout_s:
                agent = f'SILENT, {stale_mark(now - at)}, generation {a.generation}'
            else:
                agent = f'ok, generation {a.generation}, {now - at:.1f} s ago'
            if a.decider:
                agent += f', follows {a.decider}'
        rows.append([s.name, s.role, cpu, agent])
    return _table(rows)


def _link_rows(book: StatusBook, now: float) -> List[str]:
    d = book.deployment
    max_age = d.decider.observation_max_age_s
    rows = [['LINK', 'ENDS', 'STATE', 'RTT', 'AVAILABLE / NOMINAL kbit/s', 'USED kbit/s']]
    for link in d.links:
        state, rtt, avail, used = 'not heard', '-', f'- / {link.bandwidth_kbps:.0f}', '-'
        if link.name in book.links:
            ls, at = book.links[link.name]
            silent = now - at > max_age
            if silent:
                state = f'SILENT, {stale_mark(now - at)} (counts as down)'
            else:
                state = ('up, CONGESTED' if ls.congested else 'up') if ls.up else 'DOWN'
                rtt = rtt_text(ls.up, ls.rtt_ms)
                used = f'{ls.bandwidth_used_kbps:.0f}'
            age = None if ls.bandwidth_available_age_s is None \
                else ls.bandwidth_available_age_s + (now - at)
            avail = bandwidth_text(ls.bandwidth_available_kbps, link.bandwidth_kbps,
                                   ls.up and not silent, age, bandwidth_stale_after_s(d))
        rows.append([link.name, '-'.join(link.ends), state, rtt, avail, used])
    return _table(rows)


def _placement(book: StatusBook) -> Tuple[Dict[str, Tuple[str, str, float]], Dict[str, list]]:
    """node -> (scale, state, when its agent was heard) where it runs; node -> standby scales."""
    running: Dict[str, Tuple[str, str, float]] = {}
    standby: Dict[str, list] = {}
    for scale, (a, at) in book.agents.items():
        for n, r in a.nodes.items():
            if r.state == p.ProcState.STANDBY:
                standby.setdefault(n, []).append(scale if r.lifecycle == p.LifecycleState.INACTIVE
                                                 else f'{scale} ({r.lifecycle})')
            elif n not in running or r.state == p.ProcState.RUNNING \
                    or running[n][1] == p.ProcState.STOPPED:
                running[n] = (scale, r.state, at)
    return running, standby


def _connection_rows(book: StatusBook, now: float, running) -> List[str]:
    d = book.deployment
    rows = [['CONNECTION', 'RATE Hz', 'MIN Hz', 'BELOW s / Δ s', 'STATUS']]
    for c in d.connections:
        if not c.monitored:
            continue
        home = running.get(c.subscriber, (None,))[0]
        found = book.readings.get((home, c.name)) if home else None
        if found is None:
            found = max((v for (s, n), v in book.readings.items() if n == c.name),
                        key=lambda v: v[1], default=None)
        if found is None:
            rows.append([c.name, '-', f'{c.freq_min_hz:g}', f'- / {c.tolerance_s:g}',
                         'no reading'])
            continue
        r, at = found
        if now - at > d.decider.observation_max_age_s:
            rows.append([c.name, '-', f'{c.freq_min_hz:g}', f'- / {c.tolerance_s:g}',
                         f'{stale_mark(now - at)} (counts as 0 Hz), last {r.rate_hz:.1f} Hz'])
            continue
        verdict = ConnectionVerdict.judge(r.below_for_s, c.tolerance_s,
                                          rate_below(c.freq_min_hz, r.rate_hz))
        status = ('VIOLATED (past Δ)' if verdict.past_delta else
                  'below, within Δ' if verdict.below else 'ok')
        doubled = [(v.senders, v.senders_for_s or 0.0, s)
                   for (s, n), (v, got) in book.readings.items()
                   if n == c.name and now - got <= d.decider.observation_max_age_s
                   and two_senders_past(v.senders_for_s, d.monitoring.duplicate_sender_s)]
        if doubled:
            senders, for_s, scale = max(doubled, key=lambda x: x[1])
            status = f'{senders} SENDERS for {for_s:.0f} s (heard on {scale}); {status}'
        rows.append([c.name, f'{r.rate_hz:.1f}', f'{c.freq_min_hz:g}',
                     f'{r.below_for_s:.1f} / {c.tolerance_s:g}', status])
    return _table(rows)


def _node_cpu(book: StatusBook, node: str, scale: str, now: float) -> str:
    """The node's CPU on the scale it runs on, by its monitor's latest fresh reading."""
    found = book.scales.get(scale)
    if found is None or now - found[1] > book.deployment.decider.observation_max_age_s:
        return '-'
    value = found[0].cpu_by_node.get(node)
    return '-' if value is None else cpu_text(value, per_core(book, scale)[0])


def _node_rows(book: StatusBook, now: float, running, standby) -> List[str]:
    d = book.deployment
    wanted = book.layout[0].assignments if book.layout else {}
    rows = [['NODE', 'LAYOUT', 'RUNNING ON', 'STATE', 'CPU', 'STANDBY ON']]
    for n in d.nodes:
        if not n.managed:
            continue
        where, state, at = running.get(n.name, ('-', 'not reported', now))
        if now - at > d.decider.agent_timeout_s:
            state += f', {stale_mark(now - at)}'
        target = wanted.get(n.name, where)
        mark = '' if target == where else '  (moving)'
        if mark and target in book.agents \
                and now - book.agents[target][1] > d.decider.agent_timeout_s:
            # Nothing can start it there (the decider says so in an 'unplaceable' event).
            mark = f'  (not placed: agent of {target} silent)'
        rows.append([n.name, wanted.get(n.name, '-'), where + mark, state,
                     _node_cpu(book, n.name, where, now),
                     ', '.join(sorted(standby.get(n.name, ()))) or '-'])
    return _table(rows)


def exit_lines(book: StatusBook) -> List[str]:
    """One line per copy that exited unasked or cannot be started, as its agent reports it:
    its exit code and the last line of its log."""
    out = []
    for scale in book.deployment.scale_names:
        if scale not in book.agents:
            continue
        for name, r in sorted(book.agents[scale][0].nodes.items()):
            if r.exit_code is None and not r.log_tail and r.state != p.ProcState.FAILED:
                continue
            copy = CopyObs(r.state, r.ready, None, r.exit_reason, r.exit_code,
                           r.log_tail or '')
            restarts = f' (restarts: {r.restarts})' if r.restarts else ''
            out.append(f'  {r.state}{restarts}: {exit_text(name, scale, copy)}')
    return out


def render(book: StatusBook, now: float) -> str:
    """The status view as text, its figures judged at ``now`` (the clock of ``take``)."""
    lines = [f'deployment {book.deployment.name}', _layout_line(book, now)]
    deciders = _deciders_line(book, now)
    lines += [deciders] if deciders else []
    lines.append(_objective_line(book, now))
    shared = _single_machine_line(book)
    lines += [shared, ''] if shared else ['']
    running, standby = _placement(book)
    lines += _scale_rows(book, now)
    legend = cpu_legend(book)
    lines += [legend, ''] if legend else ['']
    lines += _link_rows(book, now) + ['']
    lines += _connection_rows(book, now, running) + ['']
    lines += _node_rows(book, now, running, standby)
    lines += exit_lines(book)
    shares = share_lines(book.agents, book.deployment.scale_names, book.deployment.name)
    lines += [''] + shares if shares else []
    if book.events:
        lines += ['', 'RECENT EVENTS']
        lines += [f'  {e.kind} {e.node} {e.from_scale}->{e.to_scale}: {e.reason}'[:160]
                  if e.node else f'  {e.kind}: {e.reason}'[:160] for e in book.events]
    if book.ignored or book.foreign or book.refused:
        lines.append('')
    if book.refused:
        lines.append(f'{book.refused} message(s) refused: unsigned, forged or replayed (this '
                     'deployment has a key)')
    if book.ignored:
        lines.append(f'{book.ignored} malformed message(s) ignored')
    if book.foreign:
        lines.append(f'{book.foreign} report(s) of scales or connections not in this '
                     'deployment ignored')
    return '\n'.join(lines)


__all__ = ['BANDWIDTH_STALE_INTERVALS', 'StatusBook', 'bandwidth_stale_after_s',
           'bandwidth_text', 'cpu_legend', 'cpu_text', 'discovery_range', 'exit_lines',
           'listening_text',
           'nothing_heard_text', 'per_core', 'render', 'rtt_text', 'stale_mark']
