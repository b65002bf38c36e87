"""LinkMonitor: heartbeats, RTT, loss, up/down and bandwidth of each link its scale watches
(Deployment.link_monitor: the master's links, and a link between two remote scales from its end
first in scales.names).

The heartbeats are UDP datagrams to each remote scale's warden (agent/warden.py), a process
that outlives the agent: its answer proves the link, and says how the scale's agent is (alive,
restarting, gone, fenced). A dead or restarting agent is therefore never taken for a cut link,
and a cut link (no answer) is never taken for a dead agent.
"""

import math
import secrets
import socket
import threading
import time
from dataclasses import dataclass
from typing import Dict, Optional, Set, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_msgs.msg import String

from ... import protocol as p
from .. import qos
from ...agent import warden
from ...model.types import Deployment
from ...protocol_auth import Gate, Sealer, StatusGate
from ...runtime.bandwidth import (DELIVERY_SPAN_S, BandwidthEstimate, crossing_connections,
                                  delivered_kbps, used_kbps)
from ...runtime.rates import HeartbeatTracker
from ..steady_loop import destroy_steady, steady_timer
from .common import (LATCHED_QOS, Cadence, Publishers, connection_status_refresh_s, period_of,
                     refresh_s, scale_of, status)
from .echoes import EchoSocket
from .throughput import ProbeServer, probe_throughput
from ..throttled_log import ThrottledLog

CHECKS_PER_BEAT = 4            # up/down judged this many times per heartbeat period
RESOLVE_RETRY_S = 5.0
# What a tracker judges over, in seconds rather than beats, so that a faster beat sees a cut
# sooner without making the queueing-delay verdict twitchier: a scale starved of CPU for a
# moment delays a beat or two, a full link delays all of them. Half a second: a throttle is
# answered within Δ; a false verdict alone moves nothing (the crossing connections must also
# deliver below their need, see BandwidthEstimate).
CONGESTION_SPAN_S = 0.5
LOSS_SPAN_S = 10.0
BASE_SPAN_S = 60.0


def heartbeat_tracker(period_s: float, misses_down: int,
                      congestion_s: float = 0.0) -> HeartbeatTracker:
    """A tracker whose windows span CONGESTION_SPAN_S (queueing delay reached by 3 of the last 4
    beats at 2-8 Hz, 4 of 5 at 10 Hz), LOSS_SPAN_S and BASE_SPAN_S, at any beat rate. A beat
    sent ``congestion_s`` late restarts the queueing judgement: this process stalled that long,
    and read the echoes in flight as late as a full queue would have returned them."""
    recent = max(4, math.ceil(CONGESTION_SPAN_S / period_s - 1e-9))
    loss = max(40, math.ceil(LOSS_SPAN_S / period_s - 1e-9))
    return HeartbeatTracker(period_s, misses_down, loss_window=loss,
                            base_window=max(240, loss, math.ceil(BASE_SPAN_S / period_s - 1e-9)),
                            recent=recent, agree=recent - max(1, recent // 5),
                            stall_s=congestion_s if congestion_s > 0 else math.inf)


@dataclass
class _Remote:
    scale: object
    link_name: str
    beats: HeartbeatTracker
    bandwidth: Optional[BandwidthEstimate]
    was_up: bool = False
    probing: bool = False
    probe_done: float = -math.inf      # when this monitor's last probe ended
    probe_acked: float = -math.inf     # when the link last acknowledged the running probe's data
    congested: bool = False
    delay_s: Optional[float] = None
    quiet_since: float = -math.inf     # beats sent earlier say nothing of congestion
    started: float = 0.0               # when this monitor began beating to it
    result: Optional[Tuple[float, Optional[float], str, float]] = None  # done, bps, error, used
    address: Optional[Tuple[str, int]] = None   # the warden's, resolved
    resolved_at: float = -math.inf
    peer_agent: Optional[str] = None            # what its warden last said of its agent
    peer_for_s: float = 0.0                     # ... and for how long, when it said so
    peer_at: float = 0.0
    sent: Optional[Tuple] = None                # what the last LinkStatus said that matters
    sent_at: float = -math.inf


class LinkMonitor:
    """The watching end of a link (the master for its links, the first of two remote scales
    for theirs: Deployment.link_monitor): heartbeats, RTT, loss, up/down, congestion and
    bandwidth. A remote scale also serves the throughput probe (its warden answers the
    heartbeats)."""

    def __init__(self, node, deployment: Deployment, scale: str,
                 sealer: Optional[Sealer] = None):
        self._node = node
        self._deployment = deployment
        self._scale = scale_of(deployment, scale)
        settings = deployment.monitoring
        self._period = period_of(settings.heartbeat_rate_hz, 'heartbeat_rate_hz')
        # An unchanged LinkStatus every refresh_s (a link not reported for the decider's
        # observation_max_age_s counts as down); a change of what the decider acts on (up,
        # congested, the far agent, the bandwidth figure) at once.
        self._refresh_s = refresh_s(deployment, self._period)
        self._group = MutuallyExclusiveCallbackGroup()
        self._log = node.get_logger()
        self._bad = ThrottledLog(self._log)
        # Names from senders are keys below only when the deployment knows them (memory).
        self._known_scales = set(deployment.scale_names)
        self._known_nodes = set(deployment.node_names)
        self._known_connections = {c.name for c in deployment.connections}
        self._timers = []
        self._subs = []
        self._server: Optional[ProbeServer] = None
        self._remotes: Dict[str, _Remote] = {}
        # Signed when the deployment has a key: what it publishes, and what it reads.
        self._sealer = sealer or Sealer(None, '')
        window = deployment.security.replay_window_s
        self._connections_gate = StatusGate(self._sealer.key, window)
        self._states_gate = Gate(self._sealer.key, window)
        self._lock = threading.Lock()
        self._beats_lock = threading.RLock()    # the trackers (reentrant: a beat judges too)
        self.last: Dict[str, p.LinkStatus] = {}
        if not self._scale.is_master:
            self._start_remote(settings)
        # The master watches its link to every remote scale; a remote scale, its links to the
        # remote scales after it (Deployment.link_monitor): every link that can carry a flow.
        self._watching = self._scale.is_master or bool(deployment.watched_from(scale))
        if self._watching:
            self._start_watching(settings, deployment.watched_from(scale))

    # the watching end -----------------------------------------------------------------------
    def _start_watching(self, settings, far: Tuple[str, ...]) -> None:
        for remote in (self._deployment.scale(name) for name in far):
            link = self._deployment.link_between(self._scale.name, remote.name)
            estimate = None
            if link is not None:
                estimate = BandwidthEstimate(settings.bandwidth_probe_interval_s,
                                             link.bandwidth_kbps)
            self._remotes[remote.name] = _Remote(
                remote, link.name if link else f'{self._scale.name}-{remote.name}',
                heartbeat_tracker(self._period, settings.heartbeat_misses_down,
                                  settings.congestion_delay_ms / 1000.0), estimate,
                started=time.monotonic())
        # (scale, conn) -> (B/s over the probe window, B/s over DELIVERY_SPAN_S, when heard)
        self._readings: Dict[Tuple[str, str], Tuple[float, float, float]] = {}
        self._running: Dict[str, Dict[str, str]] = {}          # scale -> node -> scale
        self._out = Publishers(self._node, p.TOPIC_LINK_STATUS, self._sealer)
        # Echoes carry the kernel's arrival time (EchoSocket) and are read by the executor
        # just before every judgement: a starved process reads them late but knows when they
        # came, so its own stall is never taken for the link's silence. Up and down are judged
        # CHECKS_PER_BEAT times a period, so a cut is published within a quarter period of the
        # rule being met.
        self._monitor_id = secrets.token_hex(8)   # echoes answer this process's beats only
        self._sock = EchoSocket(warden.MAX_DATAGRAM)
        # Through the process's shared subscriptions when its node has them (nodes/readers.py:
        # the agent and the master's decider read both topics too), with the decider's QoS.
        readers = getattr(self._node, 'readers', None)
        for topic, callback, profile in (
                (p.TOPIC_CONNECTION_STATUS, self._on_connections, qos.MONITOR_READER),
                (p.TOPIC_AGENT_STATE, self._on_agent_state, LATCHED_QOS)):
            if readers is None:
                self._subs.append(self._node.create_subscription(
                    String, topic, callback, profile, callback_group=self._group))
            else:
                readers.subscribe(self, String, topic, profile, callback)
        self._readers = readers
        # One timer: each tick judges up and down, and beats when a beat is due. Due times, not
        # a count of ticks: rcl skips the ticks a busy executor missed, and counting them would
        # send every beat after a stall late, and fewer beats than the period says. While every
        # link is up and none is probed, the timer wakes only for the beats and for the first
        # moment a link could be judged down (``_pace``).
        check_s = self._check_s = self._period / CHECKS_PER_BEAT
        self._cadence = Cadence(check_s, time.monotonic())
        self._cadence.every(check_s, self._check)
        self._cadence.every(self._period, self._beat)
        self._timer = steady_timer(self._node, check_s, self._on_tick,
                                   callback_group=self._group)
        self._timers.append(self._timer)
        self.quiet = False          # whether the timer wakes for the beats and deadlines only
        # A scale's last reading stands for as long as its probes may go without sending one
        # (a period for a remote scale, a refresh period for the master: ProbeManager) and a
        # period of lateness; older, it delivers nothing (the far end's reports wait in a full
        # queue too).
        probe_period = period_of(settings.probe_publish_rate_hz, 'probe_publish_rate_hz')
        self._readings_max_age = max(3.0, 3.0 * refresh_s(self._deployment, probe_period))
        self._delivery_stale_s = {
            s.name: min(self._readings_max_age, DELIVERY_SPAN_S + probe_period + max(
                probe_period, connection_status_refresh_s(self._deployment, s.name,
                                                          probe_period)))
            for s in self._deployment.scales}
        self._probe_duration = settings.bandwidth_probe_duration_s
        self._congestion_s = settings.congestion_delay_ms / 1000.0

    def _decode(self, cls, msg: String, topic: str):
        self._bad.flush()
        try:
            return cls.from_json(msg.data, topic)
        except p.ProtocolError as e:
            self._bad.warn(topic, f'link monitor: ignoring a bad message: {e}')
            return None

    def _read_echoes(self) -> None:
        """File every echo waiting in the socket at its arrival time (under _beats_lock)."""
        for at, data in self._sock.drain():
            echo = warden.parse_echo(data, self._deployment.name, self._sealer.key,
                                     self._monitor_id)
            if echo is None:
                self._bad.warn('heartbeat echo', 'link monitor: ignoring a datagram that is '
                                                 'not an echo of this deployment')
                continue
            scale, seq, agent, for_s = echo
            remote = self._remotes.get(scale)
            if remote is None:
                continue
            if remote.beats.echo(at, seq) is not None and at >= remote.peer_at:
                remote.peer_agent, remote.peer_for_s, remote.peer_at = agent, for_s, at

    def _on_connections(self, msg: String) -> None:
        now = time.monotonic()
        report = self._decode(p.ConnectionStatus, msg, p.TOPIC_CONNECTION_STATUS)
        if report is None or report.scale not in self._known_scales:
            return
        why = self._connections_gate.check(msg.data, report, time.time())
        if why:
            self._bad.warn(p.TOPIC_CONNECTION_STATUS, f'link monitor: dropped a connection '
                                                      f'status from {report.scale}: {why}')
            return
        for name, reading in report.connections.items():
            if name in self._known_connections:
                recent = reading.recent_bytes_per_s
                self._readings[(report.scale, name)] = (
                    reading.bytes_per_s, reading.bytes_per_s if recent is None else recent, now)

    def _on_agent_state(self, msg: String) -> None:
        state = self._decode(p.AgentState, msg, p.TOPIC_AGENT_STATE)
        if state is None or state.scale not in self._known_scales:
            return
        why = self._states_gate.check_from(msg.data, f'{state.scale}/{state.instance}',
                                           state.seq, state.stamp, time.time())
        if why:
            self._bad.warn(p.TOPIC_AGENT_STATE, f'link monitor: dropped an agent state of '
                                                f'{state.scale}: {why}')
        else:
            self._running[state.scale] = {n: state.scale for n in state.running()
                                          if n in self._known_nodes}

    def used_kbps(self, remote: str, now: float) -> float:
        """kbit/s of the connections measured crossing the link to ``remote`` now."""
        fresh = self._crossing(remote, now)
        return used_kbps({n: bps for n, (bps, _, _, _) in fresh.items()}, fresh)

    def delivery_kbps(self, remote: str, now: float) -> Tuple[float, float]:
        """(delivered, needed) kbit/s of the connections crossing the link to ``remote`` that
        are measured: over the last DELIVERY_SPAN_S, against their declared bandwidth; a
        reading older than that span and two report periods (a refresh period and one for
        the master's own) delivers nothing (``delivered_kbps``)."""
        fresh = self._crossing(remote, now)
        needed = sum(self._deployment.connection(n).bandwidth_kbps for n in fresh)
        return delivered_kbps({n: (recent, age, stale_s)
                               for n, (_, recent, age, stale_s) in fresh.items()}), needed

    def _crossing(self, remote: str, now: float
                  ) -> Dict[str, Tuple[float, float, float, float]]:
        """Connection -> (B/s, recent B/s, the reading's age in s, the age past which it
        delivers nothing) for those crossing the link to ``remote`` with a fresh reading."""
        # Every live copy counts: while a node is handed over, the copy still running on the
        # far end receives across the link (merging the reports into one place per node hid
        # that flow, depending on which scale had reported first).
        placed: Dict[str, Set[str]] = {}
        for scale, nodes in self._running.items():
            for node in nodes:
                placed.setdefault(node, set()).add(scale)
        crossing = crossing_connections(
            ((c.name, c.publisher, c.subscriber) for c in self._deployment.connections),
            placed, self._scale.name, remote)
        # Each connection as measured by the copy of its subscriber that receives across the
        # link: a copy on the other end measures traffic that does not cross it.
        fresh = {}
        for name, where in crossing.items():
            bps, recent, at = self._readings.get((where, name), (0.0, 0.0, -math.inf))
            if now - at <= self._readings_max_age:
                fresh[name] = (bps, recent, now - at, self._delivery_stale_s[where])
        return fresh

    def _on_tick(self) -> None:
        self._cadence.run(time.monotonic())
        self._pace(time.monotonic())

    def _pace(self, now: float) -> None:
        """When the timer wakes next. While a link is down, starting or probed, every check
        period (CHECKS_PER_BEAT a beat): an echo ends a cut at the next check, and a probe's
        acknowledgements move the verdict. While every link is up and none is probed, the down
        rule (HeartbeatTracker.up) can first be met at the last echo plus misses_down periods,
        or at a beat, which checks before and after it is sent: the timer wakes at the next
        beat or that moment, whichever comes first, and a cut is judged no later than at the
        next check, as before (a check between two beats would find the link up)."""
        with self._beats_lock:
            remotes = list(self._remotes.values())
            quiet = bool(remotes) and all(
                r.was_up and not r.probing and now - r.probe_done > self._period
                and r.beats.last_echo is not None for r in remotes)
            down_at = min((r.beats.last_echo + r.beats.timeout_s for r in remotes
                           if r.beats.last_echo is not None), default=math.inf)
        if quiet:
            # A millisecond past: the rule compares the silence strictly.
            wake = min(self._cadence.due(self._beat), down_at + 1e-3)
            period = max(wake - now, 1e-3)
        elif not self.quiet:
            return                  # ticking every check period already
        else:
            period = self._check_s
        self.quiet = quiet
        self._timer.timer_period_ns = round(period * 1e9)
        self._timer.reset()

    def _beat(self) -> None:
        with self._beats_lock:
            self._beat_locked()

    def _beat_locked(self) -> None:
        self._check()
        now = time.monotonic()
        used_by: Dict[str, float] = {}
        for name, remote in self._remotes.items():
            self._collect_probe(remote, now)
            used = used_by[name] = self.used_kbps(name, now)
            self._judge_congestion(remote, now, used)   # on the beats already sent
            if remote.congested and remote.bandwidth is not None and not remote.probing:
                self._judge_delivery(remote, now)
            seq = remote.beats.next_beat(now)
            self._send_beat(remote, seq, now)
            if remote.bandwidth is not None and not remote.probing \
                    and remote.bandwidth.due(now, self._up(remote, now), used, remote.congested):
                remote.bandwidth.started(now)
                remote.probing = True
                remote.probe_acked = -math.inf
                remote.quiet_since = math.inf      # the probe fills the queue on purpose
                threading.Thread(target=self._run_probe, args=(remote, used), daemon=True,
                                 name=f'anyscale-bw-{name}').start()
        # A late beat can be the one that completes misses_down unanswered (see
        # HeartbeatTracker): judged with the echoes that came meanwhile read, before the status
        # goes out. What goes out is that verdict: judged before the reading, the beat just sent
        # counted as unanswered against echoes still unread, and a "down" nobody logged reached
        # the decider (a node moved home on a link that never went down).
        self._check()
        for name, remote in self._remotes.items():
            if self._status_key(remote) != remote.sent or now - remote.sent_at >= self._refresh_s:
                self._publish(remote, now, used_by[name])

    def _send_beat(self, remote: _Remote, seq: int, now: float) -> None:
        name = remote.scale.name
        if remote.address is None and now - remote.resolved_at >= RESOLVE_RETRY_S:
            remote.resolved_at = now
            try:
                remote.address = (socket.gethostbyname(remote.scale.host),
                                  warden.warden_port(self._deployment, name))
            except OSError as e:
                self._log.warning(f'link to {name}: cannot resolve {remote.scale.host!r} '
                                  f'({e}); retrying every {RESOLVE_RETRY_S:g} s',
                                  throttle_duration_sec=60.0)
        if remote.address is None:
            return
        try:
            self._sock.sendto(warden.beat(self._deployment.name, name, seq, self._sealer.key,
                                          self._monitor_id), remote.address)
        except OSError:
            pass        # no route (a cut link): the missing echo says so

    def _judge_congestion(self, remote: _Remote, now: float, used: float) -> None:
        """A link whose queue holds the heartbeats looks full (a throttle shows within about
        half a second, where a rate past its Δ would take seconds). It is not probed while so
        (a probe would fill it further); what its crossing connections deliver is judged
        instead (``_judge_delivery``)."""
        up = remote.beats.up(now)
        delay = remote.beats.queueing_delay_s(now, since=remote.quiet_since) if up else None
        if not up or self._congestion_s <= 0:
            congested = False
        elif delay is None:             # not judged (a probe, a return): the verdict stands
            congested = remote.congested
        else:
            congested = delay > self._congestion_s
        if congested != remote.congested:
            if congested:
                self._log.warning(
                    f'link to {remote.scale.name} looks congested: queueing delay '
                    f'{delay * 1000.0:.0f} ms > {self._congestion_s * 1000.0:g} ms with '
                    f'{used:.0f} kbit/s crossing')
            else:
                self._log.info(f'link to {remote.scale.name} is no longer congested')
        remote.congested = congested
        remote.delay_s = delay

    def _judge_delivery(self, remote: _Remote, now: float) -> None:
        """On a congested link, connections delivering below their need say it carries less
        than they need: the figure is published at once and the decider sends back what no
        longer fits (see BandwidthEstimate)."""
        delivered, needed = self.delivery_kbps(remote.scale.name, now)
        figure = remote.bandwidth.congested(now, delivered, needed)
        if figure is not None:
            self._log.warning(
                f'link to {remote.scale.name}: congested, and the connections crossing it '
                f'deliver {delivered:.0f} of the {needed:.0f} kbit/s they need: it carries at '
                f'most {figure:.0f} kbit/s now (probed once it is no longer congested)')

    def _run_probe(self, remote: _Remote, used: float) -> None:
        try:
            bps, error = probe_throughput(remote.scale.host,
                                          warden.warden_port(self._deployment, remote.scale.name),
                                          self._probe_duration,
                                          deployment=self._deployment.name,
                                          scale=remote.scale.name,
                                          acked=lambda t: setattr(remote, 'probe_acked', t)), ''
        except (OSError, ValueError) as e:
            bps, error = None, str(e) or type(e).__name__
        with self._lock:
            remote.result = (time.monotonic(), bps, error, used)

    def _collect_probe(self, remote: _Remote, now: float) -> None:
        with self._lock:
            result, remote.result = remote.result, None
        if result is None:
            return
        remote.probing = False
        done, bps, error, used = result
        remote.probe_done = done
        # The probe's own queue drains within the link's latency; one beat period covers it.
        remote.quiet_since = done + self._period
        if bps is None:
            remote.bandwidth.failed(done, error)
            self._log.warning(f'bandwidth probe to {remote.scale.name}: {error}',
                              throttle_duration_sec=60.0)
        else:
            remote.bandwidth.record(done, bps * 8.0 / 1000.0, used)

    def _up(self, remote: _Remote, now: float) -> bool:
        """The link's verdict. This monitor's own probe fills the link on purpose, and the
        heartbeats wait behind its data in the link's queue or are dropped from it. While it
        runs, the link counts as heard when it last acknowledged the probe's data (TCP's ACKs
        come back on the reverse path, beside the echoes): a cut stops both, and is read as
        soon as at any other time. Once the probe has ended (its result is in, collected at
        the next beat, or was) and for a beat period after, while its data drains from the
        queue, one period more is allowed."""
        if not (remote.probing or now - remote.probe_done <= self._period):
            return remote.beats.up(now)
        last_echo = remote.beats.last_echo
        ended = not remote.probing or remote.result is not None
        allowance = self._period if ended else 0.0
        if last_echo is not None and remote.probe_acked > last_echo:
            allowance += remote.probe_acked - last_echo
        return remote.beats.up(now, allowance)

    def _check(self) -> None:
        with self._beats_lock:
            self._check_locked()

    def _check_locked(self) -> None:
        self._bad.flush()
        self._read_echoes()
        now = time.monotonic()
        for remote in self._remotes.values():
            up = self._up(remote, now)
            if up != remote.was_up:
                remote.was_up = up
                if up:
                    # Beats sent while it was down were lost to the cut, not to a queue; and
                    # what the link carried before the outage may not hold where it came back.
                    remote.quiet_since = max(remote.quiet_since, now)
                    if remote.bandwidth is not None:
                        remote.bandwidth.remeasure()
                if up:
                    # How late the echo that ended the silence came back tells a peer or a
                    # queue that answered late from beats that were lost.
                    rtt = remote.beats.last_rtt_s
                    self._log.info(f'link to {remote.scale.name} is up' + (
                        '' if rtt is None else f' (its first echo: round trip {rtt:.3f} s)'))
                else:
                    self._log.info(f'link to {remote.scale.name} is DOWN: '
                                   f'{remote.beats.silence(now)}')
                self._publish(remote, now, self.used_kbps(remote.scale.name, now))

    @staticmethod
    def _status_key(remote: _Remote) -> Tuple:
        """What of a LinkStatus the decider acts on at once; the rest (round trip, loss, the
        traffic crossing) goes out at the refresh rate."""
        up = remote.was_up
        estimate = remote.bandwidth
        return (up, remote.congested and up, remote.peer_agent if up else None,
                None if estimate is None else estimate.available_kbps)

    def _publish(self, remote: _Remote, now: float, used: float) -> None:
        beats, estimate = remote.beats, remote.bandwidth
        if beats.last_echo is None and now - remote.started < p.LINK_MONITOR_START_S:
            return      # not heard yet, and the remote may not have discovered us yet
        up = remote.was_up          # the verdict _check judged, logged and acted on
        rtt = beats.rtt_s()
        available = estimate.available_kbps if estimate is not None else None
        age = estimate.age_s(now) if estimate is not None else None
        message = p.LinkStatus(master=self._scale.name, remote=remote.scale.name,
                               stamp=time.time(), up=up,
                               rtt_ms=None if rtt is None else rtt * 1000.0,
                               loss=beats.loss(now), bandwidth_available_kbps=available,
                               bandwidth_available_age_s=age, bandwidth_used_kbps=used,
                               queueing_delay_ms=None if remote.delay_s is None
                               else remote.delay_s * 1000.0,
                               congested=remote.congested and up,
                               peer_agent=remote.peer_agent if up else None,
                               peer_agent_for_s=(remote.peer_for_s + now - remote.peer_at)
                               if up and remote.peer_agent is not None else None)
        self.last[remote.scale.name] = message
        self._out.send(message)
        remote.sent, remote.sent_at = self._status_key(remote), now
        reference = available if available is not None else (
            estimate.nominal_kbps if estimate is not None else None)
        if not up:
            level, text = p.ERROR, f'down: no echo for over {beats.timeout_s:g} s'
        elif message.congested:
            delay = message.queueing_delay_ms
            level, text = p.WARN, ('congested: queueing delay '
                                   + ('being probed' if delay is None else f'{delay:.0f} ms')
                                   + f', used {used:.0f} kbit/s')
        elif message.loss > 0.2 or (reference and used > 0.9 * reference):
            level, text = p.WARN, f'up, loss {message.loss:.0%}, used {used:.0f} kbit/s'
        else:
            level, text = p.OK, f'up, rtt {message.rtt_ms or 0.0:.1f} ms'
        values = {'remote': remote.scale.name, 'up': up, 'rtt_ms': message.rtt_ms,
                  'loss': message.loss, 'bandwidth_available_kbps': available,
                  'bandwidth_available_age_s': age, 'bandwidth_used_kbps': used,
                  'queueing_delay_ms': message.queueing_delay_ms,
                  'congested': message.congested}
        if estimate is not None and estimate.source is not None:
            values['bandwidth_available_from'] = estimate.source
        if estimate is not None and estimate.last_error:
            values['bandwidth_probe_error'] = estimate.last_error
        name = f'anyscale/link/{remote.link_name}'
        if self._out.diagnostics_due(name, level):
            self._out.send_diagnostics([status(name, level, text, self._scale.host, values)])

    # remote side ----------------------------------------------------------------------------
    def _start_remote(self, settings) -> None:
        # The scale's own port (TCP here, UDP for its warden's heartbeats): any number of
        # scales may share a machine.
        port = warden.warden_port(self._deployment, self._scale.name)
        try:
            self._server = ProbeServer(self._scale.host, port, self._log,
                                       deployment=self._deployment.name,
                                       scale=self._scale.name)
        except OSError as e:
            self._log.error(
                f'scale {self._scale.name}: throughput probe server on TCP '
                f'{self._scale.host}:{port} not started ({e.strerror or e}): another process '
                f'holds the port; free it, give the scale a port of its own '
                f'(scales.{self._scale.name}.port) or move every derived one with '
                'monitoring.bandwidth_probe_port (scale i uses that + 1 + i). Until then the '
                'master uses the nominal bandwidth of this link')

    def destroy(self) -> None:
        for timer in self._timers:
            destroy_steady(self._node, timer)
        for sub in self._subs:
            self._node.destroy_subscription(sub)
        if self._watching and self._readers is not None:
            self._readers.drop(self)
        if self._watching:
            self._sock.close()
            self._out.destroy()
        if self._server is not None:
            self._server.close()
