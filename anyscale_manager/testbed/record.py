"""What the harness saw during a run, and the questions the tests and the demo ask of it.

Pure: the record is fed decoded observer lines and the harness's own actions, each stamped with
one monotonic clock, and answers "where did each node run at time t", "how long was a
connection below freq_min", "how many moves". No rclpy here.
"""

import json
import math
import time
from bisect import bisect_right
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Set, Tuple

from .. import protocol as p
from ..model.types import Connection, Deployment
from ..protocol_auth import check_signature
from ..runtime.delta import below_spans, past_delta, rate_below, stretch_start, time_below
from ..runtime.rates import RateWindow

MIGRATION_KINDS = ('migrate', 'migrate_back', 'move_away', 'rebalance', 'yield')
# How far behind its latest line the observer's arrivals may still be incomplete: it writes
# them every 0.2 s (observer.FLUSH_S), and a message received just before a flush may have its
# callback run after it. Judged any later, the observer's own lag would read as silence.
HEARD_LAG_S = 0.5
# A process the agent holds: serving, standing by, on its way up or on its way out.
LIVE_STATES = (p.ProcState.STARTING, p.ProcState.RUNNING, p.ProcState.STANDBY,
               p.ProcState.STOPPING)


@dataclass
class DeltaBreach:
    """A connection below freq_min for longer than its Δ, as observed on the test-bed (a
    stretch in time, not a constraint of the layout: model/violation.py)."""

    connection: str
    start: float           # when the rate first went below freq_min
    end: float             # when it came back (or the end of the judged span)
    tolerance_s: float
    source: str            # 'observer' (measured here) or the reporting scale's probe

    @property
    def excess_s(self) -> float:
        return (self.end - self.start) - self.tolerance_s


@dataclass
class Record:
    deployment: Deployment
    layouts: List[Tuple[float, p.Layout]] = field(default_factory=list)
    agent_states: Dict[str, List[Tuple[float, p.AgentState]]] = field(default_factory=dict)
    scale_status: Dict[str, List[Tuple[float, p.ScaleStatus]]] = field(default_factory=dict)
    link_status: List[Tuple[float, p.LinkStatus]] = field(default_factory=list)
    readings: Dict[str, List[Tuple[float, str, p.ConnectionReading]]] = \
        field(default_factory=dict)
    # connection -> (when its scale published the reading, on this record's clock; scale): a
    # reading repaired by DDS after a loss arrives late, but was sent when the probe still ran.
    readings_sent: Dict[str, List[Tuple[float, str]]] = field(default_factory=dict)
    # wall clock minus this record's (monotonic) clock: the machine's, shared by its namespaces
    wall_offset: float = field(default_factory=lambda: time.time() - time.monotonic())
    events: List[Tuple[float, p.Event]] = field(default_factory=list)
    objectives: List[Tuple[float, p.Objective]] = field(default_factory=list)
    arrivals: Dict[str, List[float]] = field(default_factory=dict)
    # Each arrival's publication sequence number (-1: not given), when the observer sends them.
    arrival_seqs: Dict[str, List[int]] = field(default_factory=dict)
    # When each arrival's writer sent it (its source timestamp; NaN: not given).
    arrival_sent: Dict[str, List[float]] = field(default_factory=dict)
    # topic -> (arrival, x, y, stamp, yaw) of each pose a ``--pose`` observer wrote
    # (testbed/poses.py; an older observer's rows have no yaw)
    poses: Dict[str, List[Tuple[float, ...]]] = field(default_factory=dict)
    # restore topic -> (arrival, x, y, stamp, yaw) of each pose someone set there (``--set-pose``)
    set_poses: Dict[str, List[Tuple[float, ...]]] = field(default_factory=dict)
    # link -> (time, up, rate kbit/s) of each change the harness made
    link_truth: Dict[str, List[Tuple[float, bool, float]]] = field(default_factory=dict)
    marks: List[Tuple[float, str]] = field(default_factory=list)
    problems: List[str] = field(default_factory=list)
    observer_ready: Optional[float] = None
    # The connection topics the observer subscribed to (None: every one); a connection whose
    # topic it does not hear is not judged from this record.
    topics: Optional[frozenset] = None
    # The observer's clock at its latest line: arrivals are judged up to HEARD_LAG_S before it.
    heard_until: float = -math.inf
    # The deployment's key, when it has one: layouts, agent states and objectives that fail
    # its check, or repeat a sender's sequence number (a replay), are kept apart in
    # ``refused`` (time, topic, why) instead of being taken for what the system did.
    key: Optional[bytes] = None
    refused: List[Tuple[float, str, str]] = field(default_factory=list)
    _last_seq: Dict[Tuple[str, str], int] = field(default_factory=dict, repr=False)

    # --- intake -------------------------------------------------------------------------------
    def ingest_line(self, line: str) -> None:
        """One line of the observer's output; anything malformed is kept as a problem."""
        try:
            obj = json.loads(line)
        except ValueError:
            if line.strip():
                self.problems.append(f'observer: not JSON: {line.strip()[:120]}')
            return
        if not isinstance(obj, dict) or not isinstance(obj.get('t'), (int, float)):
            self.problems.append(f'observer: unexpected line: {line.strip()[:120]}')
            return
        self.ingest(obj)

    def ingest(self, obj: Mapping) -> None:
        t = float(obj['t'])
        self.heard_until = max(self.heard_until, t)
        if obj.get('ready'):
            self.observer_ready = t
            return
        for key, kept, sizes in (('poses', self.poses, (4, 5)),
                                 ('set_poses', self.set_poses, (5,))):
            if key in obj:
                for topic, rows in obj[key].items():
                    kept.setdefault(topic, []).extend(
                        tuple(float(x) for x in r) for r in rows
                        if isinstance(r, list) and len(r) in sizes)
                return
        if 'arrivals' in obj:
            seqs, sent = obj.get('seqs') or {}, obj.get('sent') or {}
            for topic, times in obj['arrivals'].items():
                self.arrivals.setdefault(topic, []).extend(float(x) for x in times)
                numbers = seqs.get(topic)
                if not isinstance(numbers, list) or len(numbers) != len(times):
                    numbers = [-1] * len(times)
                self.arrival_seqs.setdefault(topic, []).extend(
                    x if isinstance(x, int) else -1 for x in numbers)
                stamps = sent.get(topic)
                if not isinstance(stamps, list) or len(stamps) != len(times):
                    stamps = [math.nan] * len(times)
                self.arrival_sent.setdefault(topic, []).extend(
                    float(x) if isinstance(x, (int, float)) else math.nan for x in stamps)
            return
        topic, data = obj.get('topic'), obj.get('data')
        try:
            self._project(t, topic, data)
        except p.ProtocolError as e:
            self.problems.append(str(e))

    def _authentic(self, t: float, topic: str, data: str, sender: Optional[str],
                   seq: Optional[int]) -> bool:
        """With a key: whether a signed message is genuine and new (else kept in refused)."""
        if self.key is None:
            return True
        why = check_signature(self.key, data)
        last = self._last_seq.get((topic, sender or ''))
        if not why and (seq is None or (last is not None and seq <= last)):
            why = f'sequence {seq} not above {last} (a replay)'
        if why:
            self.refused.append((t, topic, why))
            return False
        self._last_seq[(topic, sender or '')] = seq
        return True

    def _project(self, t: float, topic: str, data: str) -> None:
        if topic == p.TOPIC_LAYOUT:
            layout = p.Layout.from_json(data, topic)
            sender = layout.decider.id if layout.decider is not None else None
            if self._authentic(t, topic, data, sender, layout.seq):
                self.layouts.append((t, layout))
        elif topic == p.TOPIC_AGENT_STATE:
            state = p.AgentState.from_json(data, topic)
            if self._authentic(t, topic, data, state.instance, state.seq):
                self.agent_states.setdefault(state.scale, []).append((t, state))
        elif topic == p.TOPIC_SCALE_STATUS:
            status = p.ScaleStatus.from_json(data, topic)
            self.scale_status.setdefault(status.scale, []).append((t, status))
        elif topic == p.TOPIC_LINK_STATUS:
            self.link_status.append((t, p.LinkStatus.from_json(data, topic)))
        elif topic == p.TOPIC_CONNECTION_STATUS:
            status = p.ConnectionStatus.from_json(data, topic)
            for name, reading in status.connections.items():
                self.readings.setdefault(name, []).append((t, status.scale, reading))
                self.readings_sent.setdefault(name, []).append(
                    (min(t, status.stamp - self.wall_offset), status.scale))
        elif topic == p.TOPIC_EVENTS:
            self.events.append((t, p.Event.from_json(data, topic)))
        elif topic == p.TOPIC_OBJECTIVE:
            objective = p.Objective.from_json(data, topic)
            if self._authentic(t, topic, data, objective.decider, objective.seq):
                self.objectives.append((t, objective))

    def link_set(self, t: float, up: bool, rate_kbps: float, link: str = '') -> None:
        """The harness set ``link`` (default: the deployment's only link) up or down, at a
        rate."""
        self.link_truth.setdefault(link or self._only_link(), []).append((t, up, rate_kbps))

    def _only_link(self) -> str:
        links = self.deployment.links
        if len(links) != 1:
            raise ValueError(f'name the link: the deployment has '
                             f'{", ".join(x.name for x in links)}')
        return links[0].name

    def link_reports(self, link: Optional[str] = None) -> List[Tuple[float, p.LinkStatus]]:
        """The link monitors' reports: all of them, or those about ``link`` (by its ends)."""
        if link is None:
            return self.link_status
        found = [x for x in self.deployment.links if x.name == link]
        if not found:
            raise ValueError(f'unknown link {link!r}')
        ends = set(found[0].ends)
        return [(t, s) for t, s in self.link_status if {s.master, s.remote} == ends]

    def mark(self, t: float, text: str) -> None:
        self.marks.append((t, text))

    # --- where things run ---------------------------------------------------------------------
    def agent_state_at(self, scale: str, t: Optional[float] = None,
                       max_age_s: float = math.inf) -> Optional[p.AgentState]:
        """The scale's agent's last report received at or before t, if at most max_age_s old."""
        history = self.agent_states.get(scale, [])
        if t is None:
            t = history[-1][0] if history else 0.0
        i = bisect_right([x[0] for x in history], t)
        if not i or t - history[i - 1][0] > max_age_s:
            return None
        return history[i - 1][1]

    def serving_since(self, scale: str, nodes: Sequence[str], since: float) -> Optional[float]:
        """When the scale's agent first reported every one of ``nodes`` running and ready there
        at or after ``since`` (the other scales' last reports may still say the same until they
        are stale)."""
        for t, state in self.agent_states.get(scale, []):
            if t >= since and all(state.nodes.get(n) is not None and state.nodes[n].ready
                                  and state.nodes[n].state == p.ProcState.RUNNING for n in nodes):
                return t
        return None

    def running_on(self, scale: str, t: Optional[float] = None, ready_only: bool = False,
                   max_age_s: Optional[float] = None) -> Dict[str, p.NodeReport]:
        """Nodes the scale's agent reported (at or before t) as starting or running;
        ``ready_only``: only those that serve (state 'running' and ready; a lifecycle copy is
        that only while active). A standby copy (live, inactive) is never among them.

        A report older than max_age_s (default: the decider's agent timeout) says nothing:
        behind a cut link nobody here knows what runs over there.
        """
        if max_age_s is None:
            max_age_s = self.deployment.decider.agent_timeout_s
        state = self.agent_state_at(scale, t, max_age_s)
        if state is None:
            return {}
        return {n: r for n, r in state.running().items()
                if not ready_only or (r.state == p.ProcState.RUNNING and r.ready)}

    def copies(self, scale: str, t: Optional[float] = None,
               max_age_s: Optional[float] = None) -> Dict[str, p.NodeReport]:
        """Every live process the scale's agent reported (at or before t): serving, starting,
        standby (inactive) or stopping; same staleness rule as ``running_on``."""
        if max_age_s is None:
            max_age_s = self.deployment.decider.agent_timeout_s
        state = self.agent_state_at(scale, t, max_age_s)
        if state is None:
            return {}
        return {n: r for n, r in state.nodes.items() if r.state in LIVE_STATES and r.pid > 0}

    def standby_on(self, scale: str, t: Optional[float] = None,
                   max_age_s: Optional[float] = None) -> Dict[str, p.NodeReport]:
        """The scale's standby copies (live, inactive) as its agent last reported them."""
        return {n: r for n, r in self.copies(scale, t, max_age_s).items()
                if r.state == p.ProcState.STANDBY}

    def placement(self, t: Optional[float] = None, ready_only: bool = True,
                  max_age_s: Optional[float] = None) -> Dict[str, Tuple[str, ...]]:
        """node -> the scales whose agent reports it running (ready) at time t."""
        if t is None:
            t = self.last_time()
        out: Dict[str, List[str]] = {}
        for scale in self.deployment.scale_names:
            for node in self.running_on(scale, t, ready_only, max_age_s):
                out.setdefault(node, []).append(scale)
        return {n: tuple(s) for n, s in out.items()}

    def where(self, node: str, t: Optional[float] = None) -> Tuple[str, ...]:
        return self.placement(t).get(node, ())

    def layout_at(self, t: Optional[float] = None) -> Optional[p.Layout]:
        if t is None:
            return self.layouts[-1][1] if self.layouts else None
        i = bisect_right([x[0] for x in self.layouts], t)
        return self.layouts[i - 1][1] if i else None

    def last_time(self) -> float:
        times = [h[-1][0] for h in self.agent_states.values() if h]
        times += [x[-1] for x in self.arrivals.values() if x]
        if self.layouts:
            times.append(self.layouts[-1][0])
        return max(times) if times else 0.0

    # --- decisions ----------------------------------------------------------------------------
    def moves(self, since: float = -math.inf, until: float = math.inf,
              node: Optional[str] = None) -> List[Tuple[float, p.Event]]:
        return [(t, e) for t, e in self.events
                if e.kind in MIGRATION_KINDS and since <= t <= until
                and (node is None or e.node == node)]

    def start_counts(self, scale: str) -> Dict[str, Set[int]]:
        """node -> every pid the scale's agent ever reported for it, standby copies included
        (to find restarts)."""
        out: Dict[str, Set[int]] = {}
        for _, state in self.agent_states.get(scale, []):
            for node, r in state.nodes.items():
                if r.state in LIVE_STATES and r.pid > 0:
                    out.setdefault(node, set()).add(r.pid)
        return out

    # --- rates --------------------------------------------------------------------------------
    def topic_rate(self, topic: str, t: float, window_s: float = 2.0) -> float:
        """The observer's rate of a topic at time t, as the probes compute it."""
        times = self.arrivals.get(topic, [])
        hi = bisect_right(times, t)
        lo = bisect_right(times, t - window_s, 0, hi)
        w = RateWindow(window_s)
        for x in times[max(0, min(lo, hi - 2)):hi]:
            w.add(x)
        return w.rate_hz(t)

    def reading_at(self, connection: str, t: Optional[float] = None
                   ) -> Optional[Tuple[float, str, p.ConnectionReading]]:
        history = self.readings.get(connection, [])
        if t is None:
            return history[-1] if history else None
        i = bisect_right([x[0] for x in history], t)
        return history[i - 1] if i else None

    def below_spans(self, conn: Connection, start: float, end: float
                    ) -> List[Tuple[float, float]]:
        """Stretches in [start, end] where the observer's subscriber lived below the
        connection's freq_min, by the package's one Δ rule (runtime/delta.py) on its own
        arrival times (a stretch still open at ``end`` closes there). Only what the observer
        has surely written is judged: ``end`` is cut to ``judged_until()``, so a caller that
        judges up to "now" does not take the observer's lag for a silence (wait with the
        harness's ``wait_heard`` first to judge the whole span)."""
        if not conn.monitored or (self.topics is not None and conn.topic not in self.topics):
            return []
        end = min(end, self.judged_until())
        if end <= start:
            return []
        return below_spans(self.arrivals.get(conn.topic, []), conn.freq_min_hz, start, end)

    def judged_until(self) -> float:
        """Up to when the observer's arrivals are complete: HEARD_LAG_S before its latest
        line."""
        return self.heard_until - HEARD_LAG_S

    def observed_violations(self, conn: Connection, start: float, end: float
                            ) -> List[DeltaBreach]:
        """Stretches where the observer lived below the connection's freq_min for longer than
        its Δ (Δ = 0 tolerates no stretch at all)."""
        return [DeltaBreach(conn.name, a, b, conn.tolerance_s, 'observer')
                for a, b in self.below_spans(conn, start, end)
                if past_delta(b - a, conn.tolerance_s)]

    def into(self, conn: Connection, scale: str, t: float) -> bool:
        """Whether the connection flowed into ``scale`` at t: its subscriber may run only
        there, or an agent reported it serving there, or the layout placed it there."""
        sub = conn.subscriber
        if self.deployment.allowed_scales(sub) == (scale,):
            return True
        layout = self.layout_at(t)
        return scale in self.where(sub, t) or (
            layout is not None and layout.assignments.get(sub) == scale)

    def delta_violations(self, start: float, end: float, scale: str = 'robot'
                         ) -> List[DeltaBreach]:
        """Every monitored connection into ``scale`` (where the observer listens) that stayed
        below its freq_min for longer than its Δ in [start, end], measured by the observer, a
        reader no agent started; a connection counts while its subscriber served on ``scale``
        when Δ ran out."""
        out: List[DeltaBreach] = []
        for conn in self.deployment.connections:
            for v in self.observed_violations(conn, start, end):
                if self.into(conn, scale, min(v.end, v.start + v.tolerance_s)):
                    out.append(v)
        return sorted(out, key=lambda v: v.start)

    def silence(self, v: DeltaBreach, rel: Callable[[float], float] = lambda t: t
                ) -> Optional[str]:
        """Around a violation: the longest silence of its connection's topic heard between
        its start - 2 s and its end + 0.5 s: its length, when it began (``rel`` of the
        monotonic clock: the run's own seconds)
        and how many messages its writer numbered in between ('lost': sent, never heard here).
        Lost 0 means the writer sent nothing in between, not a lossy path; then the time its
        writer took between those two messages ('sent ... apart', from their source stamps)
        tells a writer that stalled (about the silence) from one whose messages were held on
        the way or read late here (much less). None: fewer than two arrivals or no numbers."""
        topic = self.deployment.connection(v.connection).topic
        arrivals = self.arrivals.get(topic, [])
        sent = self.arrival_sent.get(topic, [])
        if len(sent) != len(arrivals):
            sent = [math.nan] * len(arrivals)
        rows = [(t, s, u) for t, s, u in zip(arrivals, self.arrival_seqs.get(topic, []), sent)
                if v.start - 2.0 <= t <= v.end + 0.5]
        if len(rows) < 2:
            return None
        (t0, s0, u0), (t1, s1, u1) = max(zip(rows, rows[1:]),
                                         key=lambda ab: ab[1][0] - ab[0][0])
        if s0 < 0 or s1 < 0:
            return None
        text = f'silent {t1 - t0:.2f} s from {rel(t0):.3f} s, lost {s1 - s0 - 1}'
        if s1 - s0 == 1 and math.isfinite(u0) and math.isfinite(u1):
            text += f', sent {u1 - u0:.2f} s apart'
        return text

    def longest_below(self, start: float, end: float, scale: str = 'robot'
                      ) -> Dict[str, float]:
        """connection -> the longest time the observer read it below freq_min in [start, end],
        for the monitored connections into ``scale`` (what the Δ judgement saw, for logs)."""
        out: Dict[str, float] = {}
        for conn in self.deployment.connections:
            spans = [b - a for a, b in self.below_spans(conn, start, end)
                     if self.into(conn, scale, a)]
            if conn.monitored and (self.topics is None or conn.topic in self.topics):
                out[conn.name] = round(max(spans, default=0.0), 2)
        return out

    def reported_violations(self, start: float, end: float,
                            names: Optional[Sequence[str]] = None,
                            gap_s: float = 2.0, serving_only: bool = False) -> List[DeltaBreach]:
        """Spans where a probe reported a connection past its Δ (level ERROR).

        ``serving_only`` keeps only the reports of the probe on the scale where the layout
        placed the connection's subscriber when its Δ ran out: a copy left running on a scale
        that was cut off (and is stopped once the link returns) reports its starved inputs,
        but it served nobody.

        A span runs from the moment the connection went below freq_min (the reading's time minus
        its below_for_s) to the first reading of that probe that is no longer ERROR; a probe
        that stops reporting (its subscriber moved away, the link to it was cut) closes its
        span at its last ERROR reading.
        """
        out: List[DeltaBreach] = []
        for name, history in sorted(self.readings.items()):
            if names is not None and name not in names:
                continue
            conn = self.deployment.connection(name)
            tolerance = conn.tolerance_s or 0.0
            by_scale: Dict[str, List[Tuple[float, p.ConnectionReading]]] = {}
            for t, scale, r in history:
                if start <= t <= end:
                    by_scale.setdefault(scale, []).append((t, r))
            for scale, series in sorted(by_scale.items()):
                open_at: Optional[float] = None
                last_error = 0.0
                for t, r in series:
                    if open_at is not None and t - last_error > gap_s:
                        out.append(DeltaBreach(name, open_at, last_error, tolerance, scale))
                        open_at = None
                    if r.level == p.ERROR:
                        if open_at is None:
                            open_at = t - r.below_for_s
                        last_error = t
                    elif open_at is not None:
                        out.append(DeltaBreach(name, open_at, t, tolerance, scale))
                        open_at = None
                if open_at is not None:
                    out.append(DeltaBreach(name, open_at, last_error, tolerance, scale))
        if serving_only:
            out = [v for v in out if self._serving(v)]
        return sorted(out, key=lambda v: v.start)

    def settled(self, now: float, connections: Sequence[str], scale: str,
                quiet_s: float) -> bool:
        """No move for quiet_s, and the scale's probe reports each connection within its
        limits now (a fresh reading at level OK). After a move the subscribers' side may take a
        while to hear the new copy; a cut in that moment would be judged with the move's gap."""
        if self.moves(since=now - quiet_s):
            return False
        for name in connections:
            last = next((x for x in reversed(self.readings.get(name, [])) if x[1] == scale),
                        None)
            if last is None or now - last[0] > 1.0 or last[2].level != p.OK:
                return False
        return True

    def handovers(self, t0: float, t1: float, scale: str,
                  horizon_s: float = 6.0) -> List[Dict[str, object]]:
        """After each move out of ``scale`` in [t0, t1]: how that scale's own probes heard the
        moved node's outputs over the next ``horizon_s``: the least rate read, and the longest
        time below freq_min (0 when no reading was); and, from the agents' reports, when the
        new copy was ready (``ready_s``) and when ``scale`` stopped running its own
        (``left_s``), both from the move (None if not within the horizon)."""
        rows: List[Dict[str, object]] = []

        def first(where: str, t: float, node: str, cond) -> Optional[float]:
            for ts, state in self.agent_states.get(where, []):
                if t <= ts <= t + horizon_s and cond(state.nodes.get(node)):
                    return round(ts - t, 2)
            return None
        for t, e in self.moves(since=t0, until=t1):
            if e.kind != 'migrate' or e.from_scale != scale:
                continue
            ready_s = first(e.to_scale, t, e.node, lambda r: r is not None
                            and r.state == p.ProcState.RUNNING and r.ready)
            left_s = first(scale, t, e.node, lambda r: r is None or r.state != p.ProcState.RUNNING)
            for c in self.deployment.connections:
                if c.publisher != e.node or not c.monitored:
                    continue
                seen = [(ts, r) for ts, where, r in self.readings.get(c.name, [])
                        if where == scale and t <= ts <= t + horizon_s]
                if not seen:
                    continue
                # A run below lasts from its first reading to the next reading back above
                # (or to the last reading, if it is still below then).
                longest, start = 0.0, None
                for ts, r in seen:
                    was, start = start, stretch_start(start, ts, rate_below(c.freq_min_hz,
                                                                            r.rate_hz))
                    longest = max(longest, time_below(was if start is None else start, ts))
                rows.append({'t': round(t - t0, 2), 'node': e.node, 'connection': c.name,
                             'min_rate_hz': round(min(r.rate_hz for _, r in seen), 2),
                             'freq_min_hz': c.freq_min_hz, 'below_s': round(longest, 2),
                             'ready_s': ready_s, 'left_s': left_s})
        return rows

    def congestion_onsets(self, t0: float, t1: float, link: Optional[str] = None
                          ) -> List[float]:
        """Times in [t0, t1] at which the link monitor began to report the link (the only
        one, or the one named) congested."""
        out, was = [], False
        for t, s in self.link_reports(link):
            now = s.up and s.congested
            if now and not was and t0 <= t <= t1:
                out.append(t)
            was = now
        return out

    def timeline(self, t0: float, t1: float, nodes: Sequence[str] = ('amcl', 'ar'),
                 scale: str = 'robot', topic: str = '/amcl_pose',
                 link: Optional[str] = None) -> Dict[str, object]:
        """What happened between t0 and t1 (a cut), in seconds from t0: the link reported down,
        the link's state as its monitor reported it, the layouts, the scale's agent reports of
        the nodes (state, pid: a new pid is a cold start, the same pid a standby copy
        activated), a topic's arrivals at the scale, and the CPU the scale measured for the
        nodes. For failure messages and the benchmark's log."""
        def rel(t: float) -> float:
            return round(t - t0, 2)
        reports = []
        last: Dict[str, Tuple[str, int]] = {}
        for t, state in self.agent_states.get(scale, []):
            if t < t0 - 2.0 or t > t1:
                continue
            for n in nodes:
                rep = state.nodes.get(n)
                now = (rep.state, rep.pid) if rep is not None else ('absent', 0)
                if last.get(n) != now:
                    reports.append((rel(t), n) + now)
                    last[n] = now
        history = self.link_reports(link)
        down = [rel(t) for t, s in history if t >= t0 and not s.up][:1]
        changes, seen = [], None
        for t, s in history:
            if not t0 - 1.0 <= t <= t1:
                continue
            avail = None if s.bandwidth_available_kbps is None \
                else round(s.bandwidth_available_kbps)
            key = (s.up, s.congested, avail)
            if key != seen:
                delay = None if s.queueing_delay_ms is None else round(s.queueing_delay_ms)
                changes.append((rel(t), 'up' if s.up else 'down',
                                'congested' if s.congested else '', delay, avail,
                                round(s.bandwidth_used_kbps)))
                seen = key
        return {
            'link_down_reported': down,
            # (time, up/down, congested, queueing delay ms, available, used kbit/s) on change
            'link': changes,
            'layouts': [(rel(t), {n: lay.assignments.get(n) for n in nodes})
                        for t, lay in self.layouts if t0 <= t <= t1],
            'reports': reports,
            topic: [rel(t) for t in self.arrivals.get(topic, []) if t0 - 0.5 <= t <= t1],
            'cpu': [(rel(t), {n: round(v) for n, v in st.cpu_by_node.items() if n in nodes},
                     round(st.cpu_total))
                    for t, st in self.scale_status.get(scale, []) if t0 - 1.0 <= t <= t1],
            # The probe on the scale: (time, rate, below_for_s, level) of each connection into
            # the topic's subscribers there, as the decider heard them.
            'probe': {name: [(rel(t), round(r.rate_hz, 2), round(r.below_for_s, 2), r.level)
                             for t, src, r in history if src == scale and t0 <= t <= t1]
                      for name, history in sorted(self.readings.items())
                      if self.deployment.connection(name).topic == topic},
        }

    def _serving(self, v: DeltaBreach) -> bool:
        """Whether the scale that reported v hosted the serving subscriber when Δ ran out."""
        subscriber = self.deployment.connection(v.connection).subscriber
        layout = self.layout_at(min(v.end, v.start + v.tolerance_s))
        if layout is not None and subscriber in layout.assignments:
            return layout.assignments[subscriber] == v.source
        return v.source in self.deployment.allowed_scales(subscriber)


__all__ = ['DeltaBreach', 'LIVE_STATES', 'MIGRATION_KINDS', 'Record']
