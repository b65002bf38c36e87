"""Robots of a fleet on this machine, for the fleet's tests, benches and demo.

Each robot is a deployment of its own, in a ROS domain of its own: its decider, the agent of its
robot ('home', the master) and its agent of the shared server ('away', ``shared: true``). Every
server agent, of whichever robot, has the same ``agent.state_dir``: one host, one claims ledger
(agent/ledger.py). What a robot runs is its graph (testbed/fleet_graphs.py): a worker the
server has room for one of, or the ICAR test-bed's graph, whose AMCL and AR of one robot fill
the server.

Judged from outside: the copies of the migratable nodes that serve under each agent (psutil: a
plain node's live process; a lifecycle node's process busy on its CPU, as only an active copy
is) and the active claims in the host's database. Every process runs with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, unless the fleet is given other places to run them
(``Loopback`` is the default; testbed/fleet_netns.py runs each robot and the server in network
namespaces of their own).
"""

import os
import signal
import sqlite3
import subprocess
import time
from collections import deque
from typing import Deque, Dict, List, Mapping, Optional, Tuple

import psutil
import yaml

from ..agent.ledger import FILE_NAME
from . import ports
from ..runtime.delta import DeltaJudge, past_delta
from .fleet_graphs import BIN, FleetShape, graph_of, HOME, SERVER

# A lifecycle copy serves when its main thread (the executor's: the node's callbacks and
# work) is busy, measured over two windows: AR active takes 4.6-6 % of a core there (30 images
# a second), AMCL 35 %; an inactive copy 0.0 % but for its configuration (3 % over 0.2 s, once),
# while its middleware threads take up to 4.6 % over 0.2 s as a robot's nodes boot and discover
# one another. Busy over the short window, so that a copy deactivated a moment ago does not
# still count beside the one activated in its place; and over the long one, so that a burst
# is not taken for serving.
ACTIVE_CPU = 0.02
ACTIVE_WINDOW_S = 0.2
ACTIVE_LONG_S = 1.0
# A process this young is starting (the interpreter, rclpy, its configuration: a standby copy
# is busy then too), not serving. On the ICAR graph a copy serves long after its start: its
# standby copy is started with its agent and activated when the layout moves it there.
STARTING_S = 4.0


class Loopback:
    """Where a fleet's processes run: all on this machine, DDS on its loopback, each robot in
    its own ROS domain. Another place (fleet_netns.FleetNetwork) answers the same calls."""

    def __init__(self, environ: Mapping[str, str]):
        self.environ = dict(environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                            PYTHONUNBUFFERED='1')

    def hosts(self, name: str) -> Optional[Dict[str, str]]:
        """Robot ``name``'s scales' addresses for its file (None: this machine's default)."""
        return None

    def popen(self, name: str, role: str, argv: List[str], domain: int,
              log) -> subprocess.Popen:
        """Robot ``name``'s ``role`` process (its agent on a scale, its decider)."""
        return subprocess.Popen(argv, env=dict(self.environ, ROS_DOMAIN_ID=str(domain)),
                                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


class Fleet:
    """The robots started so far; each robot's processes by role ('decider', 'home', 'away')."""

    def __init__(self, run_dir: str, environ: Mapping[str, str], shape: FleetShape = FleetShape(),
                 port_base: int = 0, places=None, graph=None):
        """``places``: where the processes run (``Loopback(environ)`` when not given);
        ``graph``: the shape's graph, when the caller has it already (fleet_graphs.graph_of)."""
        self.run_dir = run_dir
        self.places = places or Loopback(environ)
        self.shape = shape
        self.graph = graph or graph_of(shape)
        self.port_base = port_base or ports.port_base()
        self._activity = Activity()
        # (robot, role) -> the copies of its migratable nodes seen under that agent, by pid
        self._copies: Dict[Tuple[str, str], Dict[int, psutil.Process]] = {}
        self.paths: Dict[str, str] = {}
        self._index: Dict[str, int] = {}     # a robot's place in the fleet: its ports
        self.domains: Dict[str, str] = {}
        self.procs: Dict[str, Dict[str, subprocess.Popen]] = {}
        self._logs: List = []

    def start(self, name: str, domain: int, priority: int = 0) -> None:
        """Robot ``name``: its file written (again, with ``priority``, for a robot stopped
        and started anew), its server agent, robot agent and decider started."""
        if name in self.procs:
            raise ValueError(f'{name} is running; stop it before starting it again')
        index = self._index.setdefault(name, len(self._index))
        params = self.graph.params(name, priority, self.run_dir, self.port_base + 7 * index,
                                   self.places.hosts(name))
        path = os.path.join(self.run_dir, f'{name}.yaml')
        with open(path, 'w') as f:
            yaml.safe_dump({'/**': {'ros__parameters': params}}, f)
        self.paths[name] = path
        self.domains[name] = str(domain)
        path = self.paths[name]
        self.procs[name] = {
            SERVER: self._spawn(name, SERVER, ['agent', '--ros-args', '--params-file', path,
                                               '-p', f'scale:={SERVER}'], domain),
            HOME: self._spawn(name, HOME, ['agent', '--ros-args', '--params-file', path,
                                           '-p', f'scale:={HOME}'], domain),
            'decider': self._spawn(name, 'decider', ['decider', '--ros-args', '--params-file',
                                                     path], domain)}

    def _spawn(self, name: str, role: str, argv: List[str], domain: int) -> subprocess.Popen:
        log = open(os.path.join(self.run_dir, f'{name}_{role}.out'), 'ab')
        self._logs.append(log)
        return self.places.popen(name, role, [os.path.join(BIN, argv[0]), *argv[1:]], domain,
                                 log)

    def text(self, name: str, role: str) -> str:
        with open(os.path.join(self.run_dir, f'{name}_{role}.out'), errors='replace') as f:
            return f.read()

    def workers(self, name: str, role: str) -> int:
        """The copies of robot ``name``'s migratable nodes that serve under its ``role``
        agent."""
        return len(self.serving(name, role))

    def serving(self, name: str, role: str) -> Tuple[str, ...]:
        """The migratable nodes of robot ``name`` whose copy under its ``role`` agent serves
        (the module's docstring), sorted."""
        known = self._copies.setdefault((name, role), {})
        proc = self.procs.get(name, {}).get(role)
        if proc is not None and proc.poll() is None:
            try:
                for kid in psutil.Process(proc.pid).children(recursive=True):
                    if node_of(kid) in self.graph.moving:
                        known.setdefault(kid.pid, kid)
            except psutil.NoSuchProcess:
                pass
        # A copy is followed past its agent's death (an orphan serves until fenced).
        out = []
        for pid, kid in list(known.items()):
            node = node_of(kid) if kid.is_running() else None
            if node is None:
                del known[pid]
            elif not self.graph.lifecycle or self._activity.busy(kid):
                out.append(node)
        return tuple(sorted(out))

    def serving_cpu(self, name: str, role: str) -> float:
        """The CPU the file declares for the copies ``serving(name, role)`` names."""
        return sum(self.graph.cpu(n) for n in self.serving(name, role))

    def on_server(self) -> Dict[str, int]:
        return {name: self.workers(name, SERVER) for name in self.procs}

    def claimed_cpu(self) -> float:
        """The host's active claims, summed (0 before the ledger exists)."""
        return float(sum(self.claims_by_robot().values()))

    def claims_by_robot(self) -> Dict[str, float]:
        """The CPU of each robot's active claims on the host (empty before the ledger exists)."""
        path = os.path.join(self.run_dir, 'host_state', FILE_NAME)
        if not os.path.exists(path):
            return {}
        con = sqlite3.connect(path)
        try:
            return {name: float(cpu) for name, cpu in con.execute(
                'SELECT deployment, SUM(cpu) FROM claims WHERE active = 1 GROUP BY deployment')}
        except sqlite3.OperationalError:
            return {}
        finally:
            con.close()

    def dead(self, but: Tuple[Tuple[str, str], ...] = ()) -> Optional[str]:
        """The first process that exited unasked, with the end of its output, else None."""
        for name, roles in self.procs.items():
            for role, proc in roles.items():
                if (name, role) not in but and proc.poll() is not None:
                    return f'{name} {role} exited ({proc.returncode}):\n' \
                           f'{self.text(name, role)[-3000:]}'
        return None

    def outputs(self) -> str:
        return '\n'.join(f'--- {n} {r}\n{self.text(n, r)[-2500:]}'
                         for n, roles in self.procs.items() for r in roles)

    def stop(self, name: str, timeout_s: float = 20.0) -> None:
        """Robot ``name``'s processes, decider first, each SIGINT then SIGKILL past a timeout."""
        for role in ('decider', HOME, SERVER):
            proc = self.procs.get(name, {}).get(role)
            if proc is None or proc.poll() is not None:
                continue
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        self.procs.pop(name, None)

    def close(self) -> None:
        """Every robot stopped, and the wardens of the run (they outlive an agent killed)."""
        for name in list(self.procs):
            self.stop(name)
        for proc in psutil.process_iter(['cmdline']):
            cmd = proc.info['cmdline'] or []
            if 'anyscale_manager.agent.warden' in cmd and any(
                    str(a).startswith(self.run_dir) for a in cmd):
                proc.kill()
        for log in self._logs:
            log.close()


def stretches_past_delta(arrivals: List[float], start: float, end: float,
                         shape: FleetShape) -> Tuple[int, float]:
    """(how many stretches below freq_min went past Δ, the longest stretch below) of the worker's
    output heard at ``arrivals`` within [start, end], judged by the Δ rule (runtime/delta.py)."""
    judge = DeltaJudge(shape.freq_min_hz, shape.tolerance_s, started=start)
    for t in arrivals:
        if start <= t <= end:
            judge.add(t)
    stretches = [b - a for a, b in judge.take_ended()]
    open_since = judge.below_since(end)
    if open_since is not None:
        stretches.append(end - open_since)
    return (sum(past_delta(x, shape.tolerance_s) for x in stretches),
            max(stretches, default=0.0))


def node_of(proc: psutil.Process) -> Optional[str]:
    """The node a live workload process runs (its ``--name``), else None."""
    try:
        cmd = proc.cmdline()
        if proc.status() == psutil.STATUS_ZOMBIE or '--name' not in cmd:
            return None
        return cmd[cmd.index('--name') + 1]
    except (psutil.Error, IndexError):
        return None


def is_worker(proc: psutil.Process) -> bool:
    return node_of(proc) == 'worker'


def cpu_seconds(proc: psutil.Process) -> Optional[float]:
    """The CPU time of ``proc``'s main thread, to the nanosecond where the kernel keeps
    scheduler statistics (/proc/PID/task/PID/schedstat; psutil's clock-tick counts move by
    10 ms, a twentieth of a 0.2 s window, and span every thread), else psutil's; None once it
    is gone."""
    try:
        with open(f'/proc/{proc.pid}/task/{proc.pid}/schedstat') as f:
            return int(f.read().split()[0]) / 1e9
    except (OSError, ValueError, IndexError):
        pass
    try:
        times = proc.cpu_times()
    except psutil.Error:
        return None
    return times.user + times.system


class Activity:
    """Whether a process has been busy lately: its main thread's CPU since the last sample of
    it taken at least ``ACTIVE_WINDOW_S`` before and since the oldest kept (up to
    ``ACTIVE_LONG_S``), each at least ``ACTIVE_CPU`` (unknown, so not busy, until a sample is
    that old); a process younger than ``STARTING_S`` (starting: its main thread busy with
    the interpreter and rclpy) is not."""

    def __init__(self):
        self._seen: Dict[Tuple[int, float], Deque[Tuple[float, float]]] = {}

    def busy(self, proc: psutil.Process) -> bool:
        try:
            key = (proc.pid, proc.create_time())
        except psutil.Error:
            return False
        if time.time() - key[1] < STARTING_S:
            return False
        cpu = cpu_seconds(proc)
        if cpu is None:
            return False
        now = time.monotonic()
        seen = self._seen.setdefault(key, deque())
        seen.append((now, cpu))
        while len(seen) > 2 and now - seen[1][0] >= ACTIVE_LONG_S:
            seen.popleft()
        recent = [(t, c) for t, c in seen if now - t >= ACTIVE_WINDOW_S]
        if not recent:
            return False
        return all((cpu - c) / (now - t) >= ACTIVE_CPU for t, c in (seen[0], recent[-1]))


def other_domain(domain: int) -> int:
    """A second ROS domain for a second robot, away from ``domain``."""
    return domain + 100 if domain + 100 <= 230 else domain - 100
