"""ProbeManager: raw-subscription probes of the connections whose subscriber runs on this
scale, and who wrote (handovers).

The probe subscriptions live on a node of their own that no executor spins, and are drained
in batches (``take_message``, raw, with the message info) before each report, at each step of
the agent and, while a probed topic is fast, every ``DRAIN_PERIOD_S``; each arrival is placed
at its DDS reception time, not at the time it was taken. On a topic whose publisher is
migratable the same take also tells who wrote: the message info's publication sequence number
tells a newly started writer from the old one (``WriterStreams``). A callback per message
would cost far more than the message: on a 1 kHz image topic the events executor's dispatch
was 110 us per message against 8 us for a take (bench_probe_cost.py).

How often: a subscription holds ``qos.PROBE.depth`` messages (100: a 1 kHz topic's 0.1 s), and
a drain must come before it fills. Topics whose fastest rate yet fills at most a quarter of it
in a report period are drained only at the reports (twice a second by default, at most a
second apart); one fast topic, or one not heard yet whose writer is matched, drains them all
every 50 ms. A wake-up of
the executor costs about as much as a drain of a few messages (70 us on the test machine), and
twenty a second for topics at a few hertz were a tenth of the robot agent's CPU. Since the
arrivals keep their reception times, a later take changes no reading.

What is sent: the readings are taken every report period (``probe_publish_rate_hz``: the Δ
verdicts advance there, and the diagnostics go out there). A remote scale sends every one: its
readings of the connections that cross a link are what the link's monitor, at the other end,
judges a congestion by, and a reading that does not arrive there says the link holds it (a
full queue holds the far end's reports too; ``LinkMonitor.delivery_kbps``); a pause between
sends would read the same. The master scale's readings cross no link to their monitor (the
master watches each of its links itself): they are sent when they say something the last ones
sent did not (``moved``: a level, a stretch that ended, the senders, a figure moved by a
quarter), else once a refresh period (``monitors/common.refresh_s``, as the LinkStatus), which
spares its decider and its link monitor, on the weakest computer, most reports of a steady
graph.
"""

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, Iterable, Iterator, Optional, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

from .. import qos
from ... import protocol as p
from ...model.types import Connection, Deployment
from ...protocol_auth import Sealer
from ...runtime.bandwidth import DELIVERY_SPAN_S
from ...runtime.delta import DeltaJudge
from ...runtime.rates import (RateWindow, SenderOverlap, WriterStreams, live_window_s,
                              two_senders_past)
from .clocks import clock_offset_s
from ..steady_loop import destroy_steady, steady_timer
from .common import (PROBE_QOS, Cadence, Publishers, connection_status_refresh_s,
                     import_message_class, period_of, scale_of, status)

TYPE_RESOLVE_PERIOD_S = 1.0
# Every 50 ms while a topic is fast: the probe QoS holds 100 messages, a 1 kHz topic's 0.1 s,
# twice the period.
DRAIN_PERIOD_S = 0.05
DRAIN_LIMIT = 1000          # messages taken from one subscription per drain, at most
# A topic may be left to the reports' drains while its fastest rate yet brings at most this many
# messages between two of them: a quarter of what its subscription holds.
SLOW_DRAIN_MESSAGES = qos.PROBE.depth // 4
# A figure of a reading (rate, bytes per second, recent bytes per second) that moved by more
# than this fraction of the one last sent is a change (``moved``), as is one to or from nothing.
MOVED_FRACTION = 0.25


@dataclass
class _TopicProbe:
    """One raw subscription, shared by every probed connection on the topic."""

    topic: str
    window: RateWindow
    declared_type: str = ''
    subscription: object = None     # on the manager's reader node: drained, never spun
    type_name: str = ''
    writers: WriterStreams = field(default_factory=WriterStreams)
    overlap: SenderOverlap = field(default_factory=SenderOverlap)
    problem: str = ''          # why there is no subscription yet
    fatal: bool = False        # the type cannot be used here: no reading at all
    judges: Dict[str, DeltaJudge] = field(default_factory=dict)   # connection -> its Δ judge
    watched: bool = False      # its writers are told apart (a migratable publisher)
    peak_hz: Optional[float] = None   # its fastest rate between two drains (None: not heard)
    carried: int = 0           # taken by the agent's steps since the last timed drain


class ProbeManager:
    """Raw-subscription probes for the connections whose subscriber runs on this scale.

    With ``handovers``, the topics of connections whose publisher is migratable are watched:
    each message taken there also counts its writer (``poll_writers`` takes them between the
    reports). The agent asks ``writer_joined_since`` before it lets a moving node's old copy
    go. (The events executor the agent spins on does not hand message info to callbacks,
    hence the taking.)
    """

    def __init__(self, node, deployment: Deployment, scale: str, handovers: bool = False,
                 sealer: Optional[Sealer] = None):
        self._node = node
        self._handovers = handovers
        self._migratable = frozenset(deployment.migratable_nodes)
        self._deployment = deployment
        self._scale = scale_of(deployment, scale)
        settings = deployment.monitoring
        self._window_s = settings.probe_window_s
        RateWindow(self._window_s)       # validates the window before anything is created
        period = period_of(settings.probe_publish_rate_hz, 'probe_publish_rate_hz')
        self._topics: Dict[str, _TopicProbe] = {}
        self._probes: Dict[str, Connection] = {}
        self._out = Publishers(node, p.TOPIC_CONNECTION_STATUS, sealer)
        self._group = MutuallyExclusiveCallbackGroup()
        self._lock = threading.Lock()
        self.last: Optional[p.ConnectionStatus] = None
        # Hidden (leading underscore): a reader, not a node of the application.
        self._reader = Node(f'_{node.get_name()}_probes', namespace=node.get_namespace(),
                            context=node.context, start_parameter_services=False,
                            enable_rosout=False)
        # One timer drains, resolves types and publishes, each at its own period; it ticks
        # every DRAIN_PERIOD_S while a topic is fast, else at the reports' period.
        self._fast_s = min(DRAIN_PERIOD_S, period)
        self._slow_s = min(period, TYPE_RESOLVE_PERIOD_S)
        self._drained_at = time.monotonic()
        self._published = 0                 # readings taken for a report
        # The readings are taken every period; the master's are sent on a change (``moved``),
        # else every refresh_s, a remote scale's every period (see the module).
        self._refresh_s = connection_status_refresh_s(deployment, self._scale.name, period)
        self._sent: Optional[Dict[str, p.ConnectionReading]] = None
        self._sent_at = -math.inf
        self._cadence = Cadence(self._fast_s, time.monotonic())
        self._cadence.every(max(TYPE_RESOLVE_PERIOD_S, self._fast_s), self._resolve_pending)
        self._cadence.every(period, self._publish)
        self._timer = steady_timer(node, self._fast_s, self._on_tick, callback_group=self._group)

    @property
    def connections(self) -> Tuple[str, ...]:
        return tuple(sorted(self._probes))

    def set_connections(self, names: Iterable[str]) -> None:
        """Probe exactly these connections from now on; unknown names change nothing."""
        names = list(names)
        unknown = [n for n in names if n not in {c.name for c in self._deployment.connections}]
        if unknown:
            raise ValueError(f'set_connections: deployment {self._deployment.name!r} has no '
                             f'connection {", ".join(repr(n) for n in unknown)}')
        wanted = {n: self._deployment.connection(n) for n in names}
        with self._lock:
            topics = set(self._topics)
            for name in [n for n in self._probes if n not in wanted]:
                conn = self._probes.pop(name)
                self._release(conn.topic, name)
            for name, conn in wanted.items():
                if name in self._probes:
                    continue
                self._probes[name] = conn
                self._attach(conn)
            added = set(self._topics) - topics
        if added:
            self._retick(self._fast_s)      # a new topic's rate is not known yet

    def _resolve(self, topic: str) -> str:
        try:
            return self._node.resolve_topic_name(topic)
        except Exception:
            return topic

    def _attach(self, conn: Connection) -> None:
        topic = self._resolve(conn.topic)
        probe = self._topics.get(topic)
        if probe is None:
            probe = _TopicProbe(topic, RateWindow(self._window_s), declared_type=conn.msg_type)
            self._topics[topic] = probe
            self._subscribe(probe)
        elif conn.msg_type and probe.declared_type and conn.msg_type != probe.declared_type:
            self._node.get_logger().warning(
                f'connection {conn.name}: declares {conn.msg_type} on {topic}, another '
                f'connection on it declares {probe.declared_type}; probing with the latter')
        probe.judges[conn.name] = DeltaJudge(conn.freq_min_hz, conn.tolerance_s,
                                             started=time.monotonic(), window_s=self._window_s)
        self._set_watched(probe)

    def _set_watched(self, probe: _TopicProbe) -> None:
        probe.watched = self._handovers and probe.subscription is not None and any(
            self._deployment.connection(n).publisher in self._migratable for n in probe.judges)

    def _release(self, topic: str, name: str) -> None:
        topic = self._resolve(topic)
        probe = self._topics.get(topic)
        if probe is None:
            return
        probe.judges.pop(name, None)
        if not probe.judges:
            if probe.subscription is not None:
                self._reader.destroy_subscription(probe.subscription)
            del self._topics[topic]
        else:
            self._set_watched(probe)

    def _subscribe(self, probe: _TopicProbe) -> None:
        type_name = probe.declared_type
        if not type_name:
            types = dict(self._node.get_topic_names_and_types()).get(probe.topic)
            if not types:
                probe.problem = f'waiting for a publisher on {probe.topic} to learn its type'
                return
            type_name = types[0]
        try:
            cls = import_message_class(type_name)
        except ValueError as e:
            probe.problem, probe.fatal = str(e), True
            self._node.get_logger().error(f'probe on {probe.topic}: {e}')
            return
        probe.subscription = self._reader.create_subscription(
            cls, probe.topic, lambda _raw: None, PROBE_QOS, raw=True)
        probe.type_name, probe.problem, probe.fatal = type_name, '', False
        self._set_watched(probe)

    @property
    def tick_s(self) -> float:
        """The period the probes' timer ticks at now."""
        return self._cadence.tick_s

    def _on_tick(self) -> None:
        self.drain()
        published = self._published
        self._cadence.run(time.monotonic())
        # Slower right after a report (the next tick then falls on the next one), faster at
        # once.
        if self._slow_enough():
            if self._published != published:
                self._retick(self._slow_s)
        else:
            self._retick(self._fast_s)

    def _retick(self, tick_s: float) -> None:
        if tick_s != self._cadence.tick_s:
            self._cadence.retick(tick_s)
            self._timer.timer_period_ns = round(tick_s * 1e9)
            self._timer.reset()

    def _slow_enough(self) -> bool:
        """Whether no topic probed was ever faster than SLOW_DRAIN_MESSAGES in a slow tick (see
        the module). A topic not heard yet counts as fast once a writer is matched: its rate
        is not known, and its first messages are on their way."""
        with self._lock:
            for probe in self._topics.values():
                if probe.subscription is None:
                    continue
                if probe.peak_hz is None:
                    try:
                        if probe.subscription.get_publisher_count() > 0:
                            return False
                    except Exception:   # destroyed meanwhile
                        continue
                elif probe.peak_hz * self._slow_s > SLOW_DRAIN_MESSAGES:
                    return False
        return True

    def _resolve_pending(self) -> None:
        with self._lock:
            for probe in self._topics.values():
                if probe.subscription is None and not probe.fatal:
                    self._subscribe(probe)

    def drain(self) -> None:
        """Take every message the probe subscriptions hold: arrivals into their rate windows,
        the writers of watched topics into their streams."""
        with self._lock:
            self._drain_locked()

    def _drain_locked(self, timed: bool = True) -> None:
        """Take what every probe holds. The timer's and the reports' drains (``timed``) also
        measure each topic's peak rate; what the agent's steps take between them (at any
        moment, often a few tens of milliseconds after the last) is carried to the next: a
        rate counted over such a sliver read a 40 Hz topic as 54 Hz, and that peak held its
        drains fast for good."""
        # Reception times are on the system clock; the windows run on the monotonic one.
        offset_s = clock_offset_s()
        now = time.monotonic()
        # Two messages taken a moment apart (a report's drain right after the tick's) are no
        # burst: a rate is counted over at least a fast tick.
        elapsed = max(now - self._drained_at, self._fast_s)
        if timed:
            self._drained_at = now
        for probe in self._topics.values():
            subscription, window = probe.subscription, probe.window
            if subscription is None:
                continue
            count = 0
            try:
                writers = probe.writers if probe.watched else None
                for raw, info in _taken(subscription, DRAIN_LIMIT):
                    at = received_at(info, offset_s, now)
                    window.add(at, len(raw))
                    for judge in probe.judges.values():
                        judge.add(at)
                    if writers is not None:
                        writers.add(at, info.get('publication_sequence_number'))
                    count += 1
            except Exception:   # destroyed meanwhile: its topic is no longer probed
                continue
            if not timed:
                probe.carried += count
                continue
            count, probe.carried = count + probe.carried, 0
            if count:
                probe.peak_hz = max(probe.peak_hz or 0.0, count / elapsed)

    def poll_writers(self) -> None:
        """Take what the subscriptions hold when a topic is watched (see the class): who wrote
        each message, at its reception time; the arrivals count as at any drain."""
        with self._lock:
            if any(p.watched for p in self._topics.values()):
                self._drain_locked(timed=False)

    def writer_joined_since(self, name: str, since: float) -> Optional[bool]:
        """Whether connection ``name``'s topic was heard from a writer that started later than
        the others, first at or after ``since`` (a copy of its publisher started elsewhere);
        None when this scale does not watch it. Needs ``poll_writers`` called often."""
        with self._lock:
            conn = self._probes.get(name)
            probe = self._topics.get(self._resolve(conn.topic)) if conn else None
            if probe is None or not probe.watched:
                return None
            return probe.writers.joined_since(since)

    def readings(self, now: float) -> Dict[str, Tuple[p.ConnectionReading, str]]:
        """Connection -> (reading, note) for every probe that can measure; advances Δ."""
        out = {}
        counted: Dict[str, Tuple[int, float]] = {}     # topic -> (senders, for how long)
        with self._lock:
            self._drain_locked()
            for name, conn in sorted(self._probes.items()):
                probe = self._topics[self._resolve(conn.topic)]
                if probe.fatal:
                    continue
                verdict = probe.judges[name].verdict(now)
                # A topic silent past 1/freq_min reads 0 Hz at once (the window would decay).
                rate = 0.0 if verdict.silent else probe.window.rate_hz(now)
                senders = senders_for_s = None
                if probe.watched:
                    senders, senders_for_s = self._senders_locked(probe, now, counted)
                reading = p.ConnectionReading(rate_hz=rate,
                                              bytes_per_s=probe.window.bytes_per_s(now),
                                              below_for_s=verdict.below_for_s,
                                              level=verdict.level,
                                              ended_below_s=verdict.ended_below_s,
                                              recent_bytes_per_s=probe.window.recent_bytes_per_s(
                                                  now, DELIVERY_SPAN_S),
                                              senders=senders, senders_for_s=senders_for_s)
                out[name] = (reading, probe.problem)
        return out

    def _senders_locked(self, probe: _TopicProbe, now: float,
                        counted: Dict[str, Tuple[int, float]]) -> Tuple[int, float]:
        """The writers of ``probe``'s topic heard lately, and how long two or more have been:
        once per topic and reading, with the window of its slowest connection."""
        if probe.topic not in counted:
            slowest = min((c.freq_min_hz for c in self._probes.values()
                           if c.freq_min_hz and self._resolve(c.topic) == probe.topic),
                          default=None)
            window = live_window_s(slowest, probe.writers.forget_s)
            live = probe.writers.live(now, window)
            counted[probe.topic] = (live, probe.overlap.update(
                now, live, probe.writers.together_at(now, window)))
        return counted[probe.topic]

    def _publish(self) -> None:
        now = time.monotonic()
        self._published += 1
        readings = self.readings(now)
        message = p.ConnectionStatus(scale=self._scale.name, stamp=time.time(),
                                     connections={k: r for k, (r, _) in readings.items()})
        self.last = message
        if moved(self._sent, message.connections) or now - self._sent_at >= self._refresh_s:
            self._out.send(message)
            self._sent, self._sent_at = message.connections, now
        statuses = []
        with self._lock:
            probes = sorted(self._probes.items())
        for name, conn in probes:
            key = f'anyscale/connection/{name}'
            reading, note = readings.get(name, (None, ''))
            duplicate = reading is not None and reading.senders is not None and \
                two_senders_past(reading.senders_for_s,
                                 self._deployment.monitoring.duplicate_sender_s)
            level = p.STALE if reading is None else p.ERROR if duplicate else reading.level
            if not self._out.diagnostics_due(key, level):
                continue        # built only when it goes out: most readings say the same
            values = {'topic': conn.topic, 'publisher': conn.publisher,
                      'subscriber': conn.subscriber, 'freq_min_hz': conn.freq_min_hz,
                      'tolerance_s': conn.tolerance_s}
            if reading is None:
                probe = self._topics.get(self._resolve(conn.topic))
                statuses.append(status(key, level, probe.problem if probe else 'no probe',
                                       self._scale.host, values))
                continue
            values.update({'rate_hz': reading.rate_hz, 'bytes_per_s': reading.bytes_per_s,
                           'below_for_s': reading.below_for_s})
            text = _describe(conn, reading, note)
            if reading.senders is not None:
                values['senders'] = reading.senders
            if duplicate:
                text = (f'{reading.senders} senders for {reading.senders_for_s:.1f} s '
                        f'(copies of {conn.publisher} on more than one scale?); {text}')
            statuses.append(status(key, level, text, self._scale.host, values))
        self._out.send_diagnostics(statuses)

    def destroy(self) -> None:
        destroy_steady(self._node, self._timer)
        with self._lock:
            for probe in self._topics.values():
                if probe.subscription is not None:
                    self._reader.destroy_subscription(probe.subscription)
            self._topics.clear()
            self._probes.clear()
        self._reader.destroy_node()
        self._out.destroy()


def _taken(subscription, limit: int) -> Iterator[Tuple[bytes, dict]]:
    """Each message a raw subscription holds, at most ``limit``: (serialised message, its
    message info, {} where the middleware gives none), taken under the handle."""
    with subscription.handle:
        for _ in range(limit):
            taken = subscription.handle.take_message(subscription.msg_type, True)
            if taken is None:
                return
            info = taken[1] if len(taken) > 1 else None
            yield taken[0], info if isinstance(info, dict) else {}


def received_at(info, offset_s: float, now: float) -> float:
    """A message's DDS reception time on the monotonic clock (``offset_s``: clock_offset_s),
    never later than ``now``; ``now`` when the middleware gave none."""
    received_ns = info.get('received_timestamp', 0) if isinstance(info, dict) else 0
    return min(received_ns / 1e9 - offset_s, now) if received_ns else now


def moved(before: Optional[Dict[str, p.ConnectionReading]],
          after: Dict[str, p.ConnectionReading]) -> bool:
    """Whether readings ``after`` say something those last sent (``before``; None: none yet)
    did not: another set of connections, a level, a stretch below that ended, another count of
    senders, two senders at once (their readers judge how long by the reading: each one goes),
    or a figure moved by more than MOVED_FRACTION. A stretch below that goes on is no change:
    its readers time it from its start."""
    if before is None or before.keys() != after.keys():
        return True
    for name, a in after.items():
        b = before[name]
        if a.level != b.level or (a.ended_below_s or 0.0) > 0.0 or a.senders != b.senders \
                or a.senders_for_s or b.senders_for_s:
            return True
        if _moved(b.rate_hz, a.rate_hz) or _moved(b.bytes_per_s, a.bytes_per_s) \
                or _moved(b.recent_bytes_per_s, a.recent_bytes_per_s):
            return True
    return False


def _moved(before: Optional[float], after: Optional[float]) -> bool:
    if before is None or after is None:
        return before is not after
    if before == 0.0 or after == 0.0:
        return before != after
    return abs(after - before) > MOVED_FRACTION * before


def _describe(conn: Connection, reading: p.ConnectionReading, note: str) -> str:
    text = f'{reading.rate_hz:.3g} Hz'
    if conn.freq_min_hz is not None:
        if reading.level == p.OK:
            text += f' (freq_min {conn.freq_min_hz:g} Hz)'
        else:
            text += (f', below freq_min {conn.freq_min_hz:g} Hz for {reading.below_for_s:.1f} s'
                     f' (tolerance {conn.tolerance_s:g} s)')
    return f'{text}; {note}' if note else text
