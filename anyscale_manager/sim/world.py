"""The simulated world: a robot on its path, its scales and links, and the nodes' placement.

Each period the world is refreshed at the robot's position, turned into the same
``Observations`` the live monitors produce, handed to a policy, and the policy's decisions are
applied with a start-up delay. The semantics follow the real monitors:

* a link whose coverage is lost reads ``up=False`` with 0 kbit/s available; while up, its
  available bandwidth is the schedule's goodput at the robot's position; a link between two
  remote scales is always up at its nominal bandwidth;
* a connection whose ends are on scales that cannot reach each other reads 0 Hz, and a node
  that receives none of its inputs publishes nothing; ``below_for_s`` is how long a connection has
  been below its freq_min, as the probes track it;
* a node's output rate depends on the CPU it gets on its scale (``model.node_rate``);
* a remote scale cut off from the master stops reporting: its ``ScaleObs`` keeps the stamp of
  its last report, and after the deployment's ``agent_timeout_s`` it is listed as lost;
* a moved node's new instance serves after ``migration_delay_s`` (``standby_resume_s`` when the
  gaining scale keeps a standby copy of it: that copy is activated); with ``start_before_stop``
  the old instance serves until then (if it can still be reached), with ``stop_before_start``
  nothing does; ``running`` reports the serving instance, as the agents would.

A stretch of a monitored connection below its freq_min that outlasts its Δ is a Δ violation
(``runtime.delta.past_delta``), recorded once per stretch in ``delta_violations``. A world made
with ``loop=True`` drives lap after lap (the same coverage every lap, as a robot circling one
floor) and never finishes; ``lap_times`` holds when each lap ended.
"""

from typing import Dict, Iterable, List, Mapping, Optional, Tuple

from ..model.types import STOP_BEFORE_START, Deployment, frozen_map
from ..runtime.constraints import link_observation_key, required_kbps
from ..runtime.delta import past_delta, rate_below, stretch_start, time_below
from ..runtime.observations import ConnectionObs, Decision, LinkObs, Observations, ScaleObs
from .model import PathModel, SimSystem, node_rate, robot_speed
from .path import LinkSchedule

EPS = 1e-9


class SimulationError(RuntimeError):
    """A policy asked for something the deployment forbids."""


class World:
    """Mutable state of one simulated lap; time and position advance only in ``advance``."""

    def __init__(self, system: SimSystem, schedules: Mapping[str, LinkSchedule],
                 path: PathModel, layout: Optional[Mapping[str, str]] = None,
                 loop: bool = False):
        d: Deployment = system.deployment
        self.system = system
        self.deployment = d
        self.path = path
        self.master = d.master.name
        self.remotes = tuple(s.name for s in d.remote_scales)
        missing = [s for s in self.remotes if s not in schedules]
        if missing:
            raise ValueError(f'no link schedule for remote scale(s) {", ".join(missing)}')
        self.schedules = dict(schedules)
        self.profiles = system.profiles
        self.t = 0.0
        self.s = 0.0
        self.loop = loop
        self.lap_times: List[float] = []
        self.finish_time_s: Optional[float] = None
        self.placement: Dict[str, str] = {n: self.master for n in d.node_names}
        if layout:
            for node, scale in layout.items():
                if scale not in d.allowed_scales(node):
                    raise ValueError(f'initial layout puts {node!r} on {scale!r}, which it may '
                                     'not run on')
                self.placement[node] = scale
        self.serving: Dict[str, bool] = {n: True for n in d.node_names}
        self.pending: Dict[str, Tuple[str, float]] = {}
        self.migrations = 0
        self.decisions: List[Tuple[float, Decision]] = []
        self._gain = {s.name: d.worth(s.name) / d.worth(d.master.name) for s in d.scales}
        self._capacity = {s.name: s.capacity_cpu for s in d.scales}
        self._cpu = {n.name: n.cpu for n in d.nodes}
        self._inputs: Dict[str, List[str]] = {n: [] for n in d.node_names}
        for c in d.connections:
            self._inputs[c.subscriber].append(c.publisher)
        self._monitored = tuple(c for c in d.connections if c.monitored)
        self._link_kbps = {}
        for c in d.connections:
            self._link_kbps[c.name] = c.bandwidth_kbps
        self._below_since: Dict[str, Optional[float]] = {c.name: None for c in self._monitored}
        self._tolerance = {c.name: c.tolerance_s for c in self._monitored}
        self.delta_violations: List[Tuple[float, str]] = []    # (when past Δ, connection)
        self._violated: Dict[str, float] = {}                  # connection -> stretch counted
        self._starved_since: Dict[str, Optional[float]] = {n: None for n in system.speed_nodes}
        self._last_seen: Dict[str, Optional[float]] = {s: None for s in self.remotes}
        self._refresh()

    # --- state at the current position ----------------------------------------------------
    def _refresh(self) -> None:
        s = self.s
        self.link_up = {r: self.schedules[r].up(s) for r in self.remotes}
        self.link_kbps = {r: self.schedules[r].available_kbps(s) if self.link_up[r] else 0.0
                          for r in self.remotes}
        for r in self.remotes:
            if self.link_up[r]:
                self._last_seen[r] = self.t
        demand: Dict[str, float] = {}
        for n, scale in self.placement.items():
            demand[scale] = demand.get(scale, 0.0) + self._cpu[n]
        self.cpu_share = {sc: min(1.0, self._capacity[sc] / x) if x > 0 else 1.0
                          for sc, x in demand.items()}
        out = {}
        for n, scale in self.placement.items():
            if not self.serving[n]:
                out[n] = 0.0
                continue
            inputs = self._inputs[n]
            if inputs and not any(self.connected(self.placement[p], scale) for p in inputs):
                out[n] = 0.0
                continue
            out[n] = node_rate(self.profiles[n], self._gain[scale], self.cpu_share[scale])
        self.output_hz = out
        self.connection_hz = {}
        for c in self._monitored:
            ok = self.connected(self.placement[c.publisher], self.placement[c.subscriber])
            rate = out[c.publisher] if ok else 0.0
            self.connection_hz[c.name] = rate
            since = stretch_start(self._below_since[c.name], self.t,
                                  rate_below(c.freq_min_hz, rate, EPS))
            self._below_since[c.name] = since
            if since is not None and self._violated.get(c.name) != since and \
                    past_delta(time_below(since, self.t), self._tolerance[c.name]):
                self._violated[c.name] = since
                self.delta_violations.append((self.t, c.name))
        self.delivered_hz = {}
        for n in self._starved_since:
            rate = out[n] if self.connected(self.placement[n], self.master) else 0.0
            self.delivered_hz[n] = rate
            self._starved_since[n] = stretch_start(
                self._starved_since[n], self.t, rate_below(self.profiles[n].rate_base_hz, rate,
                                                           EPS))

    def reachable(self, scale: str) -> bool:
        return scale == self.master or self.link_up.get(scale, False)

    def connected(self, a: str, b: str) -> bool:
        """Remote scales talk through the master (each has one link, to the master)."""
        return a == b or (self.reachable(a) and self.reachable(b))

    def speed_mps(self) -> float:
        starved = {n: time_below(since, self.t) for n, since in self._starved_since.items()
                   if since is not None}
        return robot_speed(self.path, self.profiles, self.delivered_hz, starved)

    def lost_scales(self) -> frozenset:
        timeout = self.deployment.decider.agent_timeout_s
        lost = set()
        for r in self.remotes:
            seen = self._last_seen[r]
            if not self.link_up[r] and (seen is None or self.t - seen > timeout):
                lost.add(r)
        return frozenset(lost)

    # --- what the monitors report ---------------------------------------------------------
    def observe(self) -> Observations:
        t = self.t
        by_scale: Dict[str, Dict[str, float]] = {s: {} for s in self.deployment.scale_names}
        for n, scale in self.placement.items():
            by_scale[scale][n] = self._cpu[n] * self.cpu_share.get(scale, 1.0)
        scales = {}
        for name, nodes in by_scale.items():
            stamp = t if self.reachable(name) else self._last_seen.get(name)
            if stamp is None:
                continue   # never heard from: no report at all
            scales[name] = ScaleObs(cpu_total=sum(nodes.values()), stamp=stamp,
                                    cpu_by_node=frozen_map(nodes))
        used = {r: 0.0 for r in self.remotes}
        for c in self.deployment.connections:
            a, b = self.placement[c.publisher], self.placement[c.subscriber]
            if a != b:
                for end in (a, b):
                    if end in used:
                        used[end] += c.bandwidth_kbps
        links = {r: LinkObs(up=self.link_up[r], stamp=t, available_kbps=self.link_kbps[r],
                            used_kbps=used[r] if self.link_up[r] else 0.0)
                 for r in self.remotes}
        # A link between two remote scales (off the robot's path) is always up at its nominal
        # bandwidth, reported by the agent that watches it as any link is.
        required = required_kbps(self.deployment, self.placement)
        for link in self.deployment.remote_links:
            links[link_observation_key(self.deployment, link)] = LinkObs(
                up=True, stamp=t, available_kbps=link.bandwidth_kbps,
                used_kbps=required[link.name])
        connections = {}
        for c in self._monitored:
            since = self._below_since[c.name]
            connections[c.name] = ConnectionObs(
                rate_hz=self.connection_hz[c.name], stamp=t,
                below_for_s=time_below(since, t), below=since is not None)
        return Observations(now=t, running=frozen_map(self.placement), scales=frozen_map(scales),
                            links=frozen_map(links), connections=frozen_map(connections),
                            lost_scales=self.lost_scales())

    # --- what the agents do ---------------------------------------------------------------
    def apply(self, decisions: Iterable[Decision]) -> None:
        d = self.deployment
        for dec in decisions:
            if dec.node not in self.placement:
                raise SimulationError(f'decision for unknown node {dec.node!r}: {dec}')
            if dec.to_scale not in d.allowed_scales(dec.node):
                raise SimulationError(f'decision moves {dec.node!r} to {dec.to_scale!r}, which '
                                      f'it may not run on: {dec}')
            target = dec.to_scale
            pending = self.pending.get(dec.node)
            if pending and pending[0] == target:
                continue   # already starting there
            if not pending and self.placement[dec.node] == target:
                continue   # already there
            self.decisions.append((self.t, dec))
            if target == self.placement[dec.node]:
                self.pending.pop(dec.node, None)   # cancelled before it started
                self.serving[dec.node] = True
                continue
            self.migrations += 1
            # A scale that keeps a standby copy activates it rather than starting one.
            warm = target in d.standby_scales(dec.node)
            delay = self.path.standby_resume_s if warm else self.path.migration_delay_s
            self.pending[dec.node] = (target, self.t + delay)
            if d.node(dec.node).move_order == STOP_BEFORE_START:
                self.serving[dec.node] = False

    def advance(self, dt: float) -> None:
        """Drive for ``dt`` seconds at the current speed, then start what is due."""
        if self.finish_time_s is not None:
            return
        v = self.speed_mps()
        remaining = self.path.length_m - self.s
        if v > 0 and v * dt >= remaining and self.loop:
            self.lap_times.append(self.t + remaining / v)
            self.s = min(self.s + v * dt - self.path.length_m, self.path.length_m)
        elif v > 0 and v * dt >= remaining:
            self.finish_time_s = self.t + remaining / v
            self.s = self.path.length_m
        else:
            self.s += v * dt
        self.t += dt
        for node, (target, ready_at) in list(self.pending.items()):
            if ready_at <= self.t + EPS:
                self.placement[node] = target
                self.serving[node] = True
                del self.pending[node]
        self._refresh()

    @property
    def driven_m(self) -> float:
        """The distance driven so far, over every lap."""
        return len(self.lap_times) * self.path.length_m + self.s

    @property
    def finished(self) -> bool:
        return self.finish_time_s is not None
