"""The fleet (testbed/fleet.py) in network namespaces: each robot a namespace of its own, the
server one namespace for every robot's server agent, and a shaped link per robot.

Scales: each robot's namespace (``robot_a``, ``robot_b``: its decider, its home agent and the
nodes that agent starts, under the robot's CPU quota) and ``server`` (every robot's server
agent, one ``agent.state_dir`` and so one claims ledger, under the server's quota). Links:
``link_a`` joins robot_a and the server, ``link_b`` robot_b and the server, each a veth pair
shaped by tbf and cut or restored on its own (testbed/netns.py through links.NamespaceLinks).
Each robot's file names its namespaces' addresses (``scales.home.host``, ``scales.away.host``),
and each process gets the test-bed's environment (harness.child_env): its robot's ROS domain,
the namespace's neighbours as static peers, UDP only.

Judged from outside (``FleetBed.sample``): the worker processes under each agent (psutil sees
every namespace), the server's claims by robot, each link's state, and what each robot's users
hear of its worker's output: an observer (testbed/observer.py) in the robot's namespace, where
the worker's consumer is pinned; its lines fill the run's ``FleetRecord``.
"""

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from ..protocol import TOPIC_LAYOUT
from .errors import HarnessError
from .fleet import Fleet, FleetShape, HOME, SERVER
from .fleet_graphs import graph_of
from .fleet_record import FleetRecord, FleetSample
from .harness import child_env
from .links import NamespaceLinks
from .netns import DEFAULT_RATE_KBPS

SERVER_SCALE = 'server'
ROBOT_PREFIX = 'robot_'
# CPU quotas in cores of this machine: a robot runs its decider, its home agent and three
# workload nodes; the server two agents and a worker. Enough that a cold start of the worker
# (a Python process importing rclpy) fits within the worker's Δ on a machine shared with
# other work. The ICAR graph's robot gets its capacity at the graph's reference core
# (fleet_graphs.py); the server holds one robot's AMCL and AR in either.
ROBOT_CORES = 0.6
SERVER_CORES = 1.0
BOOT_TIMEOUT_S = 90.0
# A booting robot's CPU weight against the others (its quota lifted meanwhile).
BOOT_WEIGHT = 0.125


def link_name(robot: str) -> str:
    """The link of ``robot`` to the server: link_a for robot_a."""
    return 'link_' + (robot[len(ROBOT_PREFIX):] if robot.startswith(ROBOT_PREFIX) else robot)


class FleetNetwork:
    """Where the fleet's processes run in namespaces; answers as fleet.Loopback does."""

    def __init__(self, robots: Sequence[str], run_dir: str,
                 rate_kbps: float = DEFAULT_RATE_KBPS, robot_cores: float = ROBOT_CORES,
                 server_cores: float = SERVER_CORES):
        if SERVER_SCALE in robots or len(set(robots)) != len(robots) or not robots:
            raise ValueError(f'robots must be distinct names other than {SERVER_SCALE!r}, '
                             f'got {list(robots)}')
        self.robots = tuple(robots)
        self.run_dir = run_dir
        self.links = {r: link_name(r) for r in self.robots}
        cores = {r: robot_cores for r in self.robots}
        cores[SERVER_SCALE] = server_cores
        self.control = NamespaceLinks(
            self.robots + (SERVER_SCALE,),
            [(self.links[r], r, SERVER_SCALE, rate_kbps) for r in self.robots], cores)
        self._up = {r: True for r in self.robots}

    def setup(self) -> 'FleetNetwork':
        self.control.setup()
        return self

    def teardown(self) -> List[str]:
        """Remove the namespaces and cgroups; what had to be cleaned (processes left)."""
        if self.control.network is None:
            return []
        return self.control.teardown()

    @property
    def addresses(self) -> Dict[str, str]:
        """Each namespace's address (the network must be set up)."""
        network = self.control.network
        if network is None:
            raise HarnessError("the fleet's network is not set up")
        return dict(network.addresses)

    def scale_of(self, name: str, role: str) -> str:
        """The namespace robot ``name``'s ``role`` process runs in."""
        return SERVER_SCALE if role == SERVER else name

    def hosts(self, name: str) -> Dict[str, str]:
        return {HOME: self.addresses[name], SERVER: self.addresses[SERVER_SCALE]}

    def env(self, name: str, scale: str, domain: int) -> Dict[str, str]:
        """The environment of a process of robot ``name`` in ``scale``'s namespace: its static
        peers are its robot's namespaces only (the other robots' are other ROS domains)."""
        peer = self.addresses[SERVER_SCALE] if scale != SERVER_SCALE else self.addresses[name]
        return child_env(domain, os.path.join(self.run_dir, 'ros_log'), peer)

    def popen(self, name: str, role: str, argv: List[str], domain: int,
              log) -> subprocess.Popen:
        scale = self.scale_of(name, role)
        return self.control.popen(scale, argv, self.env(name, scale, domain), True,
                                  stdout=log, stderr=subprocess.STDOUT)

    def observer(self, robot: str, domain: int, topics: Sequence[str], stdout,
                 stderr) -> subprocess.Popen:
        """An observer of ``topics`` (``TOPIC:TYPE``) in ``robot``'s namespace, outside its
        quota, at a real-time priority where it may have one: the instrument that judges must
        not wait for a core behind the processes it judges."""
        argv = [sys.executable, '-m', 'anyscale_manager.testbed.observer']
        for topic in topics:
            argv += ['--topic', topic]
        argv += ['--project', TOPIC_LAYOUT]
        if os.geteuid() == 0 and shutil.which('chrt'):
            argv = ['chrt', '--rr', '10'] + argv
        return self.control.popen(robot, argv, self.env(robot, robot, domain), False,
                                  stdout=stdout, stderr=stderr)

    def set_robot_cores(self, robot: str, cores: Optional[float], weight: float = 1.0) -> None:
        """``robot``'s CPU quota, in cores of this machine (None: the whole machine), and its
        weight against the other groups (``CpuGroup.set_weight``)."""
        group = self.control.cpu_group(robot)
        if group is not None:
            group.set_cores(cores)
            group.set_weight(weight)

    def cut(self, robot: str) -> None:
        self.control.cut(self.links[robot])
        self._up[robot] = False

    def restore(self, robot: str) -> None:
        self.control.restore(self.links[robot])
        self._up[robot] = True

    def up(self, robot: str) -> bool:
        return self._up[robot]


class FleetBed:
    """A fleet in namespaces, started and torn down as one thing, with its record.

    ``setup()`` (or ``with``) builds the network; ``start(robot, domain, priority)`` starts
    the observer in the robot's namespace, then the robot's processes; ``until(holds,
    timeout_s, what)`` samples the fleet while waiting; ``cut`` and ``restore`` act on a
    robot's link and mark it; ``close()`` stops everything and says what had to be cleaned.
    Samples, marks and what each robot's users heard are in ``record`` (a FleetRecord).
    """

    def __init__(self, run_dir: str, robots: Sequence[str] = ('robot_a', 'robot_b'),
                 shape: FleetShape = FleetShape(), network: Optional[FleetNetwork] = None):
        self.run_dir = run_dir
        self.robots = tuple(robots)
        self.graph = graph_of(shape)
        self.robot_cores = self.graph.robot_cores() or ROBOT_CORES
        self.network = network or FleetNetwork(
            self.robots, run_dir, robot_cores=self.robot_cores,
            server_cores=self.graph.server_cores() or SERVER_CORES)
        self.fleet = Fleet(run_dir, {}, shape, places=self.network, graph=self.graph)
        self.shape = shape
        self.record = FleetRecord(time.monotonic())
        self._observers: Dict[str, subprocess.Popen] = {}
        self._readers: List[threading.Thread] = []
        self._logs: List = []
        self._closed = False

    def setup(self) -> 'FleetBed':
        """The namespaces, links and quotas built (nothing of a robot runs yet)."""
        self.network.setup()
        return self

    def __enter__(self) -> 'FleetBed':
        return self.setup()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- life cycle ---------------------------------------------------------------------------
    def start(self, robot: str, domain: int, priority: int = 0,
              observer_timeout_s: float = 30.0) -> None:
        """Robot ``robot``: its observer (ready before anything of the robot runs, so that its
        users' first message is heard; kept when the robot is started again), then its
        server agent, home agent and decider."""
        if robot not in self.robots:
            raise ValueError(f'unknown robot {robot!r}; this bed has {", ".join(self.robots)}')
        if robot not in self._observers:
            self._start_observer(robot, domain, observer_timeout_s)
        big = self.graph.lifecycle
        if big:
            # Eleven Python nodes starting at once under an Atom-sized quota take many seconds
            # (the ICAR test-bed's harness does the same): the whole machine until each
            # connection is heard, then the quota. Nothing of this robot is judged before. A
            # real robot boots on its own computer: here its boot gets what the others leave
            # (an eighth of their weight), or a robot's copies on the server slowed while
            # another robot booted (amcl_ekf 2.04 s below its 2 Hz, Δ 2 s, once in CI).
            self.network.set_robot_cores(robot, None, weight=BOOT_WEIGHT)
        self.fleet.start(robot, domain, priority)
        self.mark(f'{robot} started (priority {priority}, ROS domain {domain})')
        if big:
            started = time.monotonic()
            self.until(lambda s: all(self.record.heard(robot, j.topic)
                                     and self.record.heard(robot, j.topic)[-1] > started
                                     for j in self.graph.judged(robot)),
                       BOOT_TIMEOUT_S, f'every connection of {robot} heard')
            self.network.set_robot_cores(robot, self.robot_cores)
            self.mark(f'{robot}: CPU quota {self.robot_cores:g} cores')

    def stop(self, robot: str) -> float:
        """Stop ``robot``'s processes as a user would (SIGINT; its observer listens on);
        return when they had ended."""
        self.fleet.stop(robot)
        t = time.monotonic()
        self.record.mark(t, f'{robot} stopped')
        return t

    def _start_observer(self, robot: str, domain: int, timeout_s: float) -> None:
        err = open(os.path.join(self.run_dir, f'{robot}_observer.err'), 'ab')
        self._logs.append(err)
        topics = [f'{j.topic}:{j.msg_type}' for j in self.graph.judged(robot)]
        proc = self.network.observer(robot, domain, topics, subprocess.PIPE, err)
        self._observers[robot] = proc
        stream = proc.stdout
        if stream is None:
            raise HarnessError(f"{robot}'s observer has no output pipe")

        lines = open(os.path.join(self.run_dir, f'{robot}_observer.jsonl'), 'ab')
        self._logs.append(lines)

        def read() -> None:
            # Every line kept in the run folder too: what the robot's users heard, each
            # message's sequence number and send time, for a reading the record does not make.
            for raw in iter(stream.readline, b''):
                lines.write(raw)
                self.record.ingest_line(robot, raw.decode('utf-8', 'replace'))
        reader = threading.Thread(target=read, name=f'{robot}-observer', daemon=True)
        reader.start()
        self._readers.append(reader)
        self.until(lambda _s: self.record.ready(robot), timeout_s,
                   f"{robot}'s observer ready")

    def close(self) -> List[str]:
        """Every robot stopped (SIGINT), the observers, then the namespaces removed; return
        what had to be cleaned up beyond that."""
        if self._closed:
            return []
        self._closed = True
        notes: List[str] = []
        for robot in self.robots:
            if not self.network.up(robot):
                # Each robot stops as it would in service, its agents hearing one another.
                self.network.restore(robot)
        self.fleet.close()
        for robot, proc in self._observers.items():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                notes.append(f"{robot}'s observer did not stop on SIGINT; killed")
                proc.kill()
                proc.wait(5.0)
        for reader in self._readers:
            reader.join(5.0)
        notes += self.network.teardown()
        for log in self._logs:
            log.close()
        with open(os.path.join(self.run_dir, 'marks.txt'), 'w') as f:
            f.writelines(f'{t:.3f} {text}\n' for t, text in self.record.marks)
        return notes

    # --- acting and observing -----------------------------------------------------------------
    def mark(self, text: str) -> None:
        self.record.mark(time.monotonic(), text)

    def cut(self, robot: str) -> float:
        """Cut ``robot``'s link to the server; return when."""
        self.network.cut(robot)
        t = time.monotonic()
        self.record.mark(t, f'{self.network.links[robot]} cut')
        return t

    def restore(self, robot: str) -> float:
        self.network.restore(robot)
        t = time.monotonic()
        self.record.mark(t, f'{self.network.links[robot]} restored')
        return t

    def sample(self) -> FleetSample:
        """The fleet now, kept in the record."""
        t = time.monotonic()
        serving = {r: {role: self.fleet.serving(r, role) for role in (HOME, SERVER)}
                   for r in self.fleet.procs}
        sample = FleetSample(
            t, {r: {role: len(nodes) for role, nodes in at.items()}
                for r, at in serving.items()},
            {r: self.network.up(r) for r in self.robots}, self.fleet.claims_by_robot(),
            {r: at[SERVER] for r, at in serving.items()},
            {r: sum(self.graph.cpu(n) for n in at[SERVER]) for r, at in serving.items()})
        self.record.add(sample)
        return sample

    def dead(self, but: Tuple[Tuple[str, str], ...] = ()) -> Optional[str]:
        """The first process of the fleet or observer that exited unasked, else None."""
        for robot, proc in self._observers.items():
            if proc.poll() is not None:
                return f"{robot}'s observer exited ({proc.returncode})"
        return self.fleet.dead(but)

    def until(self, holds: Callable[[FleetSample], bool], timeout_s: float, what: str,
              every_s: float = 0.2, but: Tuple[Tuple[str, str], ...] = ()) -> FleetSample:
        """Sample every ``every_s`` until ``holds(sample)``; return that sample. Fails (with
        the timeline and every process's output: HarnessError) past ``timeout_s`` or when a
        process exits, but those of ``but`` ((robot, role): ended on purpose)."""
        end = time.monotonic() + timeout_s
        while True:
            sample = self.sample()
            if holds(sample):
                return sample
            dead = self.dead(but)
            if dead is not None:
                raise HarnessError(f'{what}: {dead}\n{self.describe()}')
            if time.monotonic() > end:
                raise HarnessError(f'{what}: not within {timeout_s:g} s\n{self.describe()}')
            time.sleep(every_s)

    def describe(self) -> str:
        return '\n'.join(self.record.timeline(self.robots)[-60:]) + '\n' + self.fleet.outputs()


__all__ = ['FleetBed', 'FleetNetwork', 'ROBOT_CORES', 'SERVER_CORES', 'SERVER_SCALE',
           'link_name']
