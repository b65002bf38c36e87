"""The decider's book of what it has heard: agent reports and monitor readings, by receive time.

Pure (no ROS): the decider node feeds it decoded protocol messages with its own clock and asks
for an ``Observations`` snapshot each period. Freshness is judged by the receive time, never by
the sender's stamp. Messages that name things the deployment does not know are refused with a
``ValueError`` saying what and where; parts of a message that name unknown nodes or connections
are skipped.
"""

import math
from collections import deque
from dataclasses import dataclass
from typing import Collection, Deque, Dict, FrozenSet, Mapping, Optional, Tuple

from ..model.types import DeciderSettings, Deployment, frozen_map
from ..protocol import (LINK_MONITOR_START_S, AgentState, ConnectionStatus, HostShare,
                        LinkStatus, ProcState, ScaleStatus)
from .constraints import link_observation_key
from .delta import ConnectionVerdict
from .observations import ConnectionObs, CopyObs, LinkObs, Observations, ScaleObs

_RANK = {ProcState.RUNNING: 2, ProcState.STARTING: 1}
# A copy in one of these states is not running against its will: it exited, or was killed to
# be restarted, and waits for its restart.
DOWN_STATES = (ProcState.BACKOFF, ProcState.FAILED, ProcState.CRASHED)
MAX_IGNORED_KINDS = 100


@dataclass(frozen=True)
class AgentSeen:
    state: AgentState
    received: float


class ObservationBook:
    """Latest message per source, with the time it was received."""

    def __init__(self, deployment: Deployment, settings: DeciderSettings, started: float):
        self.deployment = deployment
        self.settings = settings
        self.started = started
        self.master_back_at = started
        # scale -> when its agent was heard again after a silence (a restart): its monitors
        # start afresh and have not measured yet.
        self.back_at: Dict[str, float] = {}
        self.agents: Dict[str, AgentSeen] = {}
        self.scales: Dict[str, ScaleObs] = {}
        self.links: Dict[str, LinkObs] = {}
        self.readings: Dict[Tuple[str, str], ConnectionObs] = {}   # (scale, connection)
        # scale -> the fresh per-node CPU readings, oldest first: (received, node -> CPU)
        self.cpu_history: Dict[str, Deque[Tuple[float, Mapping[str, float]]]] = {}
        self.ignored: Dict[str, int] = {}                           # what was skipped, counted
        # (scale, node) -> (when its copy there was heard to stop against its will, why), kept
        # until that copy serves again: a restart in place may have begun by the next report.
        self.crashes: Dict[Tuple[str, str], Tuple[float, str]] = {}

    # --- intake -------------------------------------------------------------------------------
    def _scale(self, name: str, where: str) -> None:
        if name not in self.deployment.scale_names:
            raise ValueError(f'{where}: unknown scale {name!r:.60}')

    def _skip(self, what: str) -> None:
        if what not in self.ignored and len(self.ignored) >= MAX_IGNORED_KINDS:
            what = 'more kinds (not itemised)'     # names come from senders: bounded
        self.ignored[what] = self.ignored.get(what, 0) + 1

    def agent_state(self, msg: AgentState, now: float) -> None:
        self._scale(msg.scale, 'agent_state.scale')
        for name in msg.nodes:
            if name not in self.deployment.node_names:
                self._skip(f'agent_state from {msg.scale}: unknown node {name[:60]}')
        before = self.agents.get(msg.scale)
        max_age = self.settings.observation_max_age_s
        quiet = before is None or now - before.received > max_age
        # A new agent process (its instance id changed: restarted faster than max_age, as a
        # re-exec does) starts its monitors afresh just as one back from a silence does.
        restarted = before is not None and None not in (before.state.instance, msg.instance) \
            and before.state.instance != msg.instance
        if msg.scale == self.deployment.master.name and (quiet or restarted):
            self.master_back_at = now    # the master's agent (and its link monitor) is back
        if restarted or (quiet and (before is not None or now - self.started > max_age)):
            self.back_at[msg.scale] = now
        self._note_crashes(msg, before.state if before is not None else None, now)
        self.agents[msg.scale] = AgentSeen(msg, now)

    def _note_crashes(self, msg: AgentState, before: Optional[AgentState], now: float) -> None:
        for name, report in msg.nodes.items():
            key = (msg.scale, name)
            old = before.nodes.get(name) if before is not None else None
            if report.state == ProcState.RUNNING and report.ready:
                self.crashes.pop(key, None)
            elif report.state in DOWN_STATES and (old is None or old.state not in DOWN_STATES):
                self.crashes[key] = (now, report.exit_reason)
            elif old is not None and report.restarts > old.restarts and key not in self.crashes:
                # Restarted between two reports: the crash itself was not heard.
                self.crashes[key] = (now, report.exit_reason or 'restarted')

    def copies(self, now: float) -> Dict[str, Dict[str, CopyObs]]:
        """node -> scale -> its copy there, from the agents not lost."""
        lost = self.lost_scales(now)
        out: Dict[str, Dict[str, CopyObs]] = {}
        for scale, seen in self.agents.items():
            if scale in lost:
                continue
            for name, report in seen.state.nodes.items():
                if name not in self.deployment.node_names:
                    continue
                crash = self.crashes.get((scale, name))
                out.setdefault(name, {})[scale] = CopyObs(
                    report.state, report.ready, None if crash is None else crash[0],
                    crash[1] if crash is not None else report.exit_reason,
                    report.exit_code, report.log_tail or '')
        return out

    def scale_status(self, msg: ScaleStatus, now: float) -> None:
        self._scale(msg.scale, 'scale_status.scale')
        if msg.cpu_total < 0:
            raise ValueError(f'scale_status.cpu_total: negative ({msg.cpu_total})')
        known = set(self.deployment.node_names)
        by_node = {n: v for n, v in msg.cpu_by_node.items() if n in known and v >= 0}
        self.scales[msg.scale] = ScaleObs(cpu_total=msg.cpu_total, stamp=now,
                                          cpu_by_node=frozen_map(self._mean_cpu(msg.scale,
                                                                                by_node, now)))

    def _mean_cpu(self, scale: str, latest: Mapping[str, float], now: float
                  ) -> Dict[str, float]:
        """Each node's CPU as the mean of its scale's fresh readings (observation_max_age_s).

        A monitor's reading covers one short interval (0.5 s at 2 Hz); a node that works in
        bursts (AMCL: 240 ms per scan) reads anywhere from a quarter to all of its usage in
        one, and the policy would rank the nodes on that noise. The scale's total stays the
        latest reading: it must show a node that just started there.
        """
        history = self.cpu_history.setdefault(scale, deque())
        history.append((now, latest))
        while history and now - history[0][0] > self.settings.observation_max_age_s:
            history.popleft()
        out = {}
        for node in latest:
            values = [by_node[node] for _, by_node in history if node in by_node]
            out[node] = sum(values) / len(values)
        return out

    def link_status(self, msg: LinkStatus, now: float) -> bool:
        """File a link monitor's report (under constraints.link_observation_key). True when it
        calls for a decision now rather than at the next period: the link went down, its
        figure shrank by more than 5 %, or its far end's warden has just fenced the dead
        agent's nodes; what was beyond it must be placed before the connections' Δ runs out."""
        d = self.deployment
        master = d.master.name
        self._scale(msg.master, 'link_status.master')
        self._scale(msg.remote, 'link_status.remote')
        if msg.master == master:
            if msg.remote == master:
                raise ValueError('link_status.remote: the master scale itself')
            key, peer_agent = msg.remote, msg.peer_agent
        else:
            link = d.link_between(msg.master, msg.remote)
            if link is None or master in link.ends or d.link_monitor(link) != msg.master:
                raise ValueError(f'link_status: scale {msg.master!r} does not watch a link '
                                 f'to {msg.remote!r} (only the master, and the first of two '
                                 'remote scales joined by a link, do)')
            # What the far end's warden says of its agent matters to fencing only over a
            # link from the master: the decider reaches that scale through it.
            key, peer_agent = link_observation_key(d, link), None
        available = msg.bandwidth_available_kbps
        if available is not None and available < 0:
            raise ValueError(f'link_status.bandwidth_available_kbps: negative ({available})')
        before = self.links.get(key)
        fresh = LinkObs(up=msg.up, stamp=now, available_kbps=available,
                        used_kbps=max(0.0, msg.bandwidth_used_kbps), rtt_ms=msg.rtt_ms,
                        peer_agent=peer_agent)
        self.links[key] = fresh
        if before is None:
            before = LinkObs(up=False, stamp=now)
        link = d.link_between(msg.master, msg.remote)
        last = before.available_kbps if before.available_kbps is not None else (
            link.bandwidth_kbps if link is not None else math.inf)
        lost = before.up and not fresh.up
        shrank = available is not None and available < 0.95 * last
        fenced = fresh.up and fresh.peer_agent == 'fenced' \
            and not (before.up and before.peer_agent == 'fenced')
        return lost or shrank or fenced

    def connection_status(self, msg: ConnectionStatus, now: float) -> None:
        self._scale(msg.scale, 'connection_status.scale')
        known = {c.name for c in self.deployment.connections}
        for name, r in msg.connections.items():
            if name not in known:
                self._skip(f'connection_status from {msg.scale}: unknown connection {name[:60]}')
                continue
            if r.rate_hz < 0 or r.below_for_s < 0:
                self._skip(f'connection_status from {msg.scale}: negative reading for {name}')
                continue
            self.readings[(msg.scale, name)] = ConnectionObs(
                rate_hz=r.rate_hz, stamp=now, below_for_s=r.below_for_s,
                bytes_per_s=max(0.0, r.bytes_per_s),
                below=ConnectionVerdict(r.below_for_s, r.level).below,
                senders=r.senders or 0, senders_for_s=r.senders_for_s or 0.0)

    # --- views --------------------------------------------------------------------------------
    def agent_fresh(self, scale: str, now: float) -> bool:
        seen = self.agents.get(scale)
        return seen is not None and now - seen.received <= self.settings.agent_timeout_s

    def lost_scales(self, now: float) -> FrozenSet[str]:
        """Scales whose agent has been silent for agent_timeout_s (or never spoke in that time),
        and those whose warden says it stopped their dead agent's nodes (at once: nothing of
        theirs runs any more)."""
        timeout = self.settings.agent_timeout_s
        lost = set(self._peer_agent(now, ('fenced',)))
        for s in self.deployment.scale_names:
            seen = self.agents.get(s)
            last = seen.received if seen is not None else self.started
            if now - last > timeout:
                lost.add(s)
        return frozenset(lost)

    def fencing(self, now: float) -> FrozenSet[str]:
        """Remote scales whose warden, heard over a live link, says their agent's nodes may
        still run: the agent process lives (restarting in place, or silent on ROS while its
        process runs) or is gone with its nodes not yet stopped (``Observations.fencing``)."""
        return self._peer_agent(now, ('alive', 'restarting', 'gone'))

    def _peer_agent(self, now: float, states: Tuple[str, ...]) -> FrozenSet[str]:
        max_age = self.settings.observation_max_age_s
        return frozenset(s for s, link in self.links.items()
                         if link.up and link.peer_agent in states and now - link.stamp <= max_age)

    def unjudged_links(self, now: float) -> FrozenSet[str]:
        """Keys of ``links`` (remote scales for the links from the master) whose report is
        missing or stale while the agent that watches the link is silent, or was heard again
        less than LINK_MONITOR_START_S plus observation_max_age_s ago (its new link monitor
        has not judged the link yet)."""
        max_age = self.settings.observation_max_age_s
        d = self.deployment
        master = d.master.name
        watched = [(s, master, self.master_back_at) for s in d.scale_names if s != master]
        for link in d.remote_links:
            host = d.link_monitor(link)
            watched.append((link_observation_key(d, link), host,
                            self.back_at.get(host, self.started)))
        out = set()
        for key, host, back_at in watched:
            seen = self.links.get(key)
            if seen is not None and now - seen.stamp <= max_age:
                continue
            agent = self.agents.get(host)
            starting = now - back_at <= LINK_MONITOR_START_S + max_age
            # A stale report is the link's silence only if the monitor's host was heard after
            # it went stale: an agent that dies can be heard last a moment after its monitor
            # (a SIGKILLed robot agent was; the link was then judged silent before the agent).
            stale_at = (seen.stamp if seen is not None else self.started) + max_age
            if agent is None or now - agent.received > max_age or starting \
                    or agent.received <= stale_at:
                out.add(key)
        return frozenset(out)

    def silent_agents(self, now: float) -> Dict[str, float]:
        """Scale -> seconds its agent has been silent, for agents not heard within
        observation_max_age_s (one never heard: counted from the start of watching)."""
        out = {}
        for s in self.deployment.scale_names:
            seen = self.agents.get(s)
            silent = now - (seen.received if seen is not None else self.started)
            if silent > self.settings.observation_max_age_s:
                out[s] = silent
        return out

    def unjudged_connections(self, now: float, running: Mapping[str, str],
                             desired: Optional[Mapping[str, str]] = None) -> FrozenSet[str]:
        """Monitored connections whose probe (on the subscriber's scale: where it runs, else
        where the layout places it) is hosted by a silent agent, or by one heard again less than
        LINK_MONITOR_START_S plus observation_max_age_s ago (its new probes measure from
        scratch)."""
        max_age = self.settings.observation_max_age_s
        silent = self.silent_agents(now)
        out = set()
        for c in self.deployment.connections:
            if not c.monitored:
                continue
            host = running.get(c.subscriber) or (desired or {}).get(c.subscriber)
            if host is None:
                continue
            back = self.back_at.get(host)
            if host in silent or (back is not None
                                  and now - back <= LINK_MONITOR_START_S + max_age):
                out.add(c.name)
        return frozenset(out)

    def all_agents_heard(self) -> bool:
        return all(s in self.agents for s in self.deployment.scale_names)

    @property
    def max_generation(self) -> int:
        return max((a.state.generation for a in self.agents.values()), default=0)

    def running(self, now: float, desired: Optional[Mapping[str, str]] = None,
                active_only: Collection[str] = ()) -> Dict[str, str]:
        """node -> scale where it actually runs, from the agents not lost.

        A node reported on two scales (a move in progress) counts where it is 'running' rather
        than 'starting', then where the layout wants it. For the nodes in ``active_only`` only a
        'running' copy counts: a node with standby copies has one starting on every scale it
        may run on, and a copy starting says nothing of where it will serve.
        """
        lost = self.lost_scales(now)
        known = set(self.deployment.node_names)
        best: Dict[str, Tuple[int, int, str]] = {}
        for scale, seen in self.agents.items():
            if scale in lost:
                continue
            for name, report in seen.state.running().items():
                if name not in known \
                        or (name in active_only and report.state != ProcState.RUNNING):
                    continue
                wanted = 1 if desired is not None and desired.get(name) == scale else 0
                rank = (_RANK.get(report.state, 0), wanted, scale)
                if name not in best or rank[:2] > best[name][:2]:
                    best[name] = rank
        return {n: r[2] for n, r in best.items()}

    def connections(self, running: Mapping[str, str]) -> Dict[str, ConnectionObs]:
        """One reading per connection: from the scale its subscriber runs on, else the newest."""
        out: Dict[str, ConnectionObs] = {}
        for c in self.deployment.connections:
            home = running.get(c.subscriber)
            if home is not None and (home, c.name) in self.readings:
                out[c.name] = self.readings[(home, c.name)]
                continue
            newest, stamp = None, -math.inf
            for (scale, name), reading in self.readings.items():
                if name == c.name and reading.stamp > stamp:
                    newest, stamp = reading, reading.stamp
            if newest is not None:
                out[c.name] = newest
        return out

    def shares(self, now: float) -> Dict[str, HostShare]:
        """Each shared scale's host as its agent last reported it, while that report is
        fresh (observation_max_age_s)."""
        max_age = self.settings.observation_max_age_s
        return {scale: seen.state.share for scale, seen in self.agents.items()
                if seen.state.share is not None and now - seen.received <= max_age
                and self.deployment.scale(scale).shared}

    def snapshot(self, now: float, desired: Optional[Mapping[str, str]] = None
                 ) -> Observations:
        running = self.running(now, desired)
        return Observations(now=now, running=frozen_map(running),
                            scales=frozen_map(self.scales), links=frozen_map(self.links),
                            connections=frozen_map(self.connections(running)),
                            lost_scales=self.lost_scales(now),
                            unjudged_links=self.unjudged_links(now),
                            silent_agents=frozen_map(self.silent_agents(now)),
                            unjudged_connections=self.unjudged_connections(now, running,
                                                                           desired),
                            copies=frozen_map({n: frozen_map(c)
                                               for n, c in self.copies(now).items()}),
                            fencing=self.fencing(now),
                            shares=frozen_map(self.shares(now)))
