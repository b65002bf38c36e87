"""A fleet in simulation: N robots, each its own deployment, decider turn and world, sharing K
servers through the claims ledger their agents keep on each server (agent/ledger.py).

Each robot is the base system (``systems.system_parameters``: 6N x 2M is the test-bed) with the
K servers (server_0, server_1, ...) as its remote scales, ``shared: true``, each of the same
capacity and the test-bed laptop's power; its own deployment name (robot_<i>) and priority
(robot i: i mod ``priority_levels``); its own link schedules, drawn from (seed, run, i). Every
server has one ledger in a temporary folder, and each robot's agent there is the live agent's
``agent.claims.HostClaims`` over the real ``Ledger``: it claims, is refused, waits for a
preemption, releases and renews as a live agent does, on the simulated clock.

Every decider period:

1. each robot's observations are its world's, with ``shares``: each server's ``HostShare`` as
   the robot's agent there last reported it; a server the robot cannot reach keeps the report
   its decider heard last;
2. each robot's decider turn decides; a move to a shared server waits for that server's
   agent, any other move is applied to the robot's world at once;
3. the agents gate their robots' layouts (``HostClaims.gate``), robot after robot in an order
   drawn afresh each time (the agents of several robots reach a ledger in no fixed order): a
   move granted is applied to the world (its copy starts there); one refused or waiting is not
   (the node serves where it was) and is reported at the next period;
4. every world advances one period, and the agents gate again, as their ticks between two
   turns do: a copy that has stopped on a server releases its claim there, and a waiting claim
   is asked again.

The robots drive lap after lap (``World(loop=True)``) for ``duration_s``, so every robot is on
the road for the whole run.
"""

import copy
import os
import tempfile
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, List, Mapping, Optional, Set, Tuple

import numpy as np

from ..agent.claims import HostClaims
from ..agent.ledger import Answer, Claim, Ledger
from ..model.capacity import claim_lease_s
from ..model.types import frozen_map
from ..protocol import HostShare
from ..runtime.observations import Decision
from ..runtime.turn import DeciderTurn
from .fleet_figures import FleetRun, RobotResult, ServerResult
from .model import PathModel, SimSystem
from .path import LinkSchedule, draw_schedules
from .runner import HEURISTIC, make_policy, peak_kbps
from .systems import REMOTE_LADDER, set_remote_scales, system_from_parameters, \
    system_parameters
from .world import SimulationError, World

SERVER_PREFIX = 'server_'
# Each server has the power of the test-bed's laptop (4 x 2.8 GHz): on it AMCL reaches its
# optimal rate, as in the paper.
_, SERVER_CORES, SERVER_CLOCK_GHZ = REMOTE_LADDER[0]
SERVER_CAPACITY_CPU = 700.0
MAX_ROBOTS = 50
MAX_SERVERS = 3
# The stream of the agents' order at each period, apart from the robots' link draws.
ORDER_STREAM = 104729
OVER_EPS = 1e-6
# (t, server, the 'robot/node' copies live there, the CPU claimed there) of every period.
Sample = Tuple[float, str, Tuple[str, ...], float]


@dataclass(frozen=True)
class FleetSpec:
    """A fleet: ``robots`` copies of the N x M base system sharing ``servers`` servers."""

    robots: int = 10
    servers: int = 1
    n: int = 6
    m: int = 2
    capacity_cpu: float = SERVER_CAPACITY_CPU      # each server's
    duration_s: float = 600.0
    priority_levels: int = 1                       # robot i has priority i mod this
    seed: int = 0

    def __post_init__(self):
        checks = (
            (1 <= self.robots <= MAX_ROBOTS, f'robots must be in 1..{MAX_ROBOTS}'),
            (1 <= self.servers <= MAX_SERVERS, f'servers must be in 1..{MAX_SERVERS}'),
            (self.capacity_cpu > 0, 'capacity_cpu must be > 0'),
            (self.duration_s > 0, 'duration_s must be > 0'),
            (self.priority_levels >= 1, 'priority_levels must be >= 1'),
            (self.seed >= 0, 'seed must be >= 0'),
        )
        for ok, message in checks:
            if not ok:
                raise ValueError(f'FleetSpec: {message}, got {self}')

    @property
    def server_names(self) -> Tuple[str, ...]:
        return tuple(f'{SERVER_PREFIX}{i}' for i in range(self.servers))

    def priority(self, robot: int) -> int:
        return robot % self.priority_levels


def robot_system(spec: FleetSpec, robot: int, base: Tuple[Dict[str, Any], Dict[str, float], str]
                 ) -> SimSystem:
    """Robot ``robot`` of the fleet: the base system (``system_parameters``' answer) with the
    shared servers as its remote scales, its own name and priority."""
    params, speed, source = copy.deepcopy(base)
    scales = params['scales']
    master = next(scales[n] for n in scales['names'] if scales[n]['role'] == 'master')
    gain = round(SERVER_CORES * SERVER_CLOCK_GHZ / (master['cores'] * master['clock_ghz']), 4)
    set_remote_scales(params, [(name, {
        'role': 'remote', 'kind': 'server', 'capacity_cpu': spec.capacity_cpu,
        'cores': SERVER_CORES, 'clock_ghz': SERVER_CLOCK_GHZ, 'gain': gain, 'host': name,
        'shared': True}) for name in spec.server_names])
    params['deployment'] = {'name': f'robot_{robot}', 'priority': spec.priority(robot),
                            'description': f'robot {robot} of a fleet of {spec.robots}'}
    label = f'robot_{robot}: {spec.n}N x {spec.m}M, {spec.servers} shared server(s)'
    return system_from_parameters(params, speed, label, spec.n, spec.m, source)


def robot_schedules(system: SimSystem, path: PathModel, seed: int, run: int,
                    robot: int) -> Dict[str, LinkSchedule]:
    """The robot's coverage of each server's link: its own draw, from (seed, run, robot)."""
    rng = np.random.default_rng([seed, run, robot])
    remotes = [s.name for s in system.deployment.remote_scales]
    return draw_schedules(rng, path, remotes, peak_kbps(system, path))


class ClaimTally:
    """Every claim decision a ledger made in the run: its answer and what it cost."""

    def __init__(self) -> None:
        self.granted = self.refused = self.waiting = 0
        self.seconds: List[float] = []

    def add(self, answer: Answer, seconds: float) -> None:
        self.seconds.append(seconds)
        if answer.granted:
            self.granted += 1
        elif answer.waiting:
            self.waiting += 1
        else:
            self.refused += 1


class TimedLedger(Ledger):
    """The ledger, its claim decisions tallied and timed (the rules are the ledger's own)."""

    def __init__(self, state_dir: str, deployment: str, lease_s: float, tally: ClaimTally):
        super().__init__(state_dir, deployment, lease_s)
        self.tally = tally

    def claim(self, claim: Claim, now: float) -> Answer:
        start = time.perf_counter()
        answer = super().claim(claim, now)
        self.tally.add(answer, time.perf_counter() - start)
        return answer


class FleetRobot:
    """One robot: its world, its decider's turn, and its agent on each shared server."""

    def __init__(self, system: SimSystem, schedules: Mapping[str, LinkSchedule],
                 path: PathModel, ledgers: Mapping[str, str], tally: ClaimTally,
                 overrides: Optional[Mapping[str, object]] = None):
        d = system.deployment
        self.name = d.name
        self.system = system
        self.world = World(system, schedules, path, loop=True)
        policy = make_policy(HEURISTIC, system, overrides=overrides)
        self.settings = policy.settings
        self.turn = DeciderTurn(d, policy.settings, self.world.t, policy)
        lease = claim_lease_s(d)
        self.agents = {s: HostClaims(TimedLedger(folder, d.name, lease, tally), d, s)
                       for s, folder in ledgers.items()}
        self.heard: Dict[str, HostShare] = {}       # server -> the report its decider heard
        self.waiting_moves: Dict[str, Decision] = {}   # node -> its move to a shared server
        self.server_time_s = 0.0

    def begin(self, now: float) -> None:
        for agent in self.agents.values():
            agent.begin(now)

    def close(self) -> None:
        for agent in self.agents.values():
            agent.ledger.close()

    def live(self, node: str, server: str) -> bool:
        """Whether the node's copy runs on ``server``: serving, starting, or still serving
        while its next copy starts elsewhere."""
        pending = self.world.pending.get(node)
        return self.world.placement[node] == server or (pending is not None and
                                                        pending[0] == server)

    def decide(self, now: float) -> None:
        """The decider's turn on the world's observations and the servers' reports."""
        for server, agent in self.agents.items():
            report = agent.report()
            if report is not None and self.world.reachable(server):
                self.heard[server] = report
        obs = replace(self.world.observe(), shares=frozen_map(self.heard))
        for dec in self.turn.turn(now, obs).decisions:
            if dec.to_scale in self.agents:
                self.waiting_moves[dec.node] = dec
            else:
                self.waiting_moves.pop(dec.node, None)
                self.world.apply([dec])

    def gate(self, now: float) -> None:
        """Each server's agent claims what the layout puts there; what it grants starts."""
        layout = self.turn.layout or {}
        for server, agent in self.agents.items():
            want = {n for n, s in layout.items() if s == server}

            def live(node: str, server: str = server) -> bool:
                return self.live(node, server)

            agent.gate(now, want, {}, live)
            for node in sorted(want):
                if live(node):
                    continue
                move = self.waiting_moves.pop(node, None)
                if move is None:
                    raise SimulationError(f'{self.name}: {node} is granted on {server} with no '
                                          'move there')
                self.world.apply([move])

    def on_servers(self) -> bool:
        """Whether a node of this robot serves on a shared server."""
        return any(s in self.agents and self.world.serving[n]
                   for n, s in self.world.placement.items())


class _Watch:
    """The servers' figures, sampled once a period: claimed and running CPU, over-commit, and
    the asks to leave as the asked robots' agents read them."""

    def __init__(self, spec: FleetSpec, observers: Mapping[str, Ledger],
                 trace: Optional[List[Sample]]):
        self.spec = spec
        self.observers = observers
        self.trace = trace
        self.claimed_s = {s: 0.0 for s in observers}       # integral of claimed CPU
        self.peak_claimed = {s: 0.0 for s in observers}
        self.peak_running = {s: 0.0 for s in observers}
        self.over_s = {s: 0.0 for s in observers}
        self.asked: Set[Tuple[str, str, str]] = set()
        self.asks: List[Tuple[float, str, str, str]] = []

    def sample(self, now: float, dt: float, robots: List[FleetRobot]) -> None:
        cap = self.spec.capacity_cpu
        for server, observer in self.observers.items():
            # Every claim on the host: the observer holds none, so all are others'.
            claimed = observer.share(now).others_cpu()
            live = [(r, n) for r in robots for n in r.system.deployment.node_names
                    if r.live(n, server)]
            running = sum(r.system.deployment.node(n).cpu for r, n in live)
            self.claimed_s[server] += claimed * dt
            self.peak_claimed[server] = max(self.peak_claimed[server], claimed)
            self.peak_running[server] = max(self.peak_running[server], running)
            if max(claimed, running) > cap + OVER_EPS:
                self.over_s[server] += dt
            if self.trace is not None:
                self.trace.append((now, server, tuple(sorted(f'{r.name}/{n}' for r, n in live)),
                                   claimed))
        asked = set()
        for r in robots:
            for server, agent in r.agents.items():
                if agent.share is not None:
                    asked |= {(server, f'{r.name}/{node}', by)
                              for node, by in agent.share.asked.items()}
        self.asks += [(now, *ask) for ask in sorted(asked - self.asked)]
        self.asked = asked
        for r in robots:
            if r.on_servers():
                r.server_time_s += dt


def run_fleet(spec: FleetSpec, run: int = 0, path: PathModel = PathModel(),
              testbed_path: Optional[str] = None,
              overrides: Optional[Mapping[str, object]] = None,
              trace: Optional[List[Sample]] = None) -> FleetRun:
    """One run of the fleet for ``spec.duration_s``; ``trace`` collects every period's samples
    of every server."""
    start = time.perf_counter()
    base = system_parameters(spec.n, spec.m, spec.seed, testbed_path)
    systems = [robot_system(spec, i, base) for i in range(spec.robots)]
    tally = ClaimTally()
    robots: List[FleetRobot] = []
    observers: Dict[str, Ledger] = {}
    with tempfile.TemporaryDirectory(prefix='anyscale-fleet-') as folder:
        ledgers = {s: os.path.join(folder, s) for s in spec.server_names}
        try:
            for i, system in enumerate(systems):
                robots.append(FleetRobot(system, robot_schedules(system, path, spec.seed, run, i),
                                         path, ledgers, tally, overrides))
            lease = claim_lease_s(systems[0].deployment)
            observers = {s: Ledger(f, '', lease) for s, f in ledgers.items()}
            watch = _Watch(spec, observers, trace)
            _drive(spec, run, robots, watch)
        finally:
            for r in robots:
                r.close()
            for observer in observers.values():
                observer.close()
    return _result(spec, run, robots, watch, tally, time.perf_counter() - start)


def _drive(spec: FleetSpec, run: int, robots: List[FleetRobot], watch: _Watch) -> None:
    dt = robots[0].settings.period_s
    if any(r.settings.period_s != dt for r in robots):
        raise ValueError('the robots of a fleet must share one decider period')
    order = np.random.default_rng([spec.seed, run, ORDER_STREAM])
    for r in robots:
        r.begin(0.0)
    for _ in range(int(round(spec.duration_s / dt))):
        now = robots[0].world.t
        # The agents tick several times a decider period: what they did since the last turn
        # (copies stopped release their claims, waiting claims are asked again), the turns,
        # then what they do with the new layouts.
        for i in order.permutation(len(robots)):
            robots[i].gate(now)
        for r in robots:
            r.decide(now)
        for i in order.permutation(len(robots)):
            robots[i].gate(now)
        watch.sample(now, dt, robots)
        for r in robots:
            r.world.advance(dt)


def _result(spec: FleetSpec, run: int, robots: List[FleetRobot], watch: _Watch,
            tally: ClaimTally, wall_s: float) -> FleetRun:
    duration = robots[0].world.t
    out = []
    for r in robots:
        w = r.world
        r.turn.cost.update(duration, dict(w.placement))
        speed = w.driven_m / duration
        saved = (1.0 - w.path.speed_min_mps / speed) * 100.0 if speed > 0 else -np.inf
        out.append(RobotResult(
            name=r.name, priority=r.system.deployment.priority, driven_m=w.driven_m,
            improvement_pct=float(saved), server_time_s=r.server_time_s,
            delta_violations=len(w.delta_violations), migrations=w.migrations,
            perf_map_mean=r.turn.cost.mean))
    servers = tuple(ServerResult(
        name=s, capacity_cpu=spec.capacity_cpu,
        utilisation=watch.claimed_s[s] / duration / spec.capacity_cpu,
        peak_claimed_cpu=watch.peak_claimed[s], peak_running_cpu=watch.peak_running[s],
        overcommit_s=watch.over_s[s]) for s in spec.server_names)
    return FleetRun(spec=spec, run=run, duration_s=duration, robots=tuple(out), servers=servers,
                    granted=tally.granted, refused=tally.refused, waiting=tally.waiting,
                    asks=tuple(watch.asks), claim_s=tuple(tally.seconds), wall_s=wall_s)


def run_fleet_runs(spec: FleetSpec, runs: int, path: PathModel = PathModel(),
                   testbed_path: Optional[str] = None,
                   overrides: Optional[Mapping[str, object]] = None,
                   progress: Optional[Callable[[FleetRun], None]] = None) -> List[FleetRun]:
    """``runs`` runs of one fleet, run r drawing its links from (seed, r)."""
    if runs < 1:
        raise ValueError(f'runs must be >= 1, got {runs}')
    out = []
    for r in range(runs):
        out.append(run_fleet(spec, r, path, testbed_path, overrides))
        if progress is not None:
            progress(out[-1])
    return out
