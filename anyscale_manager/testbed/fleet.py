"""Robots of a fleet on this machine's loopback, for the fleet's tests and benches.

Each robot is a deployment of its own, in a ROS domain of its own: its decider, the agent of its
robot ('home', the master) and its agent of the shared server ('away', ``shared: true``). Every
server agent, of whichever robot, has the same ``agent.state_dir``: one host, one claims ledger
(agent/ledger.py). A robot's graph: sensor (home) -> worker (migratable, CPU ``worker_cpu``) ->
pinned (home), the worker's output watched with a Δ that a cold move meets; the server has
room for one worker.

Judged from outside: the worker processes under each server agent (psutil) and the active
claims in the host's database. Every process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
unless the fleet is given other places to run them (``Loopback`` is the default; testbed/
fleet_netns.py runs each robot and the server in network namespaces of their own).
"""

import os
import signal
import sqlite3
import subprocess
import sys
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Tuple

import psutil
import yaml

from ..agent.ledger import FILE_NAME
from . import ports
from ..runtime.delta import DeltaJudge, past_delta

BIN = os.path.dirname(sys.executable)
SERVER = 'away'
HOME = 'home'


@dataclass(frozen=True)
class FleetShape:
    """What every robot of the fleet runs, and the server's room."""

    capacity_cpu: float = 100.0        # the server's (and each robot's) capacity
    worker_cpu: float = 60.0
    rate_hz: float = 10.0
    freq_min_hz: float = 5.0
    # The worker is a plain node: a move, a preemption included, starts it cold, and its Δ
    # covers a cold start (validate's budget here: 12 beats at 4 Hz + 0.8 s = 3.8 s).
    tolerance_s: float = 5.0
    hysteresis_s: float = 60.0


def member_params(name: str, priority: int, run_dir: str, port_base: int,
                  shape: FleetShape, hosts: Optional[Mapping[str, str]] = None) -> dict:
    """Robot ``name``'s deployment file, as ROS parameters; ``hosts``: scale -> its address
    (``scales.<s>.host``), left to the default (this machine) when not given."""
    topic = f'/{name}'
    rate = ('--rate-hz', str(shape.rate_hz))

    def workload(node: str, *args: str) -> dict:
        return {'command': [os.path.join(BIN, 'workload'), '--name', node, *args, *rate]}
    nodes = {'sensor': {'launch': workload('sensor', '--pub', topic + '/s'), 'cpu': 1.0,
                        'residence': [HOME]},
             'worker': {'launch': workload('worker', '--sub', topic + '/s', '--pub',
                                           topic + '/w'), 'cpu': shape.worker_cpu},
             'pinned': {'launch': workload('pinned', '--sub', topic + '/w', '--pub',
                                           topic + '/p'), 'cpu': 1.0, 'residence': [HOME]}}
    flow = {'msg_type': 'std_msgs/msg/UInt8MultiArray', 'bandwidth_kbps': 1.0}
    connections = {'sensor_worker': dict(flow, topic=topic + '/s', publisher='sensor',
                                         subscriber='worker'),
                   'worker_pinned': dict(flow, topic=topic + '/w', publisher='worker',
                                         subscriber='pinned', freq_min_hz=shape.freq_min_hz,
                                         tolerance_s=shape.tolerance_s)}
    scales = {HOME: {'role': 'master', 'kind': 'robot', 'capacity_cpu': shape.capacity_cpu,
                     'cores': 2, 'clock_ghz': 1.0},
              SERVER: {'role': 'remote', 'kind': 'server', 'capacity_cpu': shape.capacity_cpu,
                       'cores': 4, 'clock_ghz': 2.0, 'shared': True}}
    for scale, host in (hosts or {}).items():
        scales[scale]['host'] = host
    return {
        'deployment': {'name': name, 'priority': priority},
        'scales': dict(scales, names=[HOME, SERVER]),
        'links': {'names': ['net'], 'net': {'ends': [HOME, SERVER], 'bandwidth_kbps': 100000.0,
                                            'medium': 'wired'}},
        'nodes': dict(nodes, names=list(nodes)),
        'connections': dict(connections, names=list(connections)),
        # Both scales are this one machine: no headroom kept; a missed echo is an agent not
        # scheduled on a loaded machine, so the link is judged down only after 3 s. Each robot
        # runs one decider: it listens 1.5 s for a leader before it leads, not 5 s.
        'decider': {'cpu_headroom': 1.0, 'period_s': 0.25, 'grace_s': 1.0,
                    'agent_timeout_s': 3.0, 'observation_max_age_s': 3.0,
                    'hysteresis_s': shape.hysteresis_s, 'discovery_s': 1.5},
        'monitoring': {'heartbeat_rate_hz': 4.0, 'heartbeat_misses_down': 12,
                       'scale_rate_hz': 4.0, 'bandwidth_probe_interval_s': 86400.0,
                       'bandwidth_probe_port': port_base},
        'agent': {'sigint_grace_s': 1.0, 'sigterm_grace_s': 1.0, 'readiness_timeout_s': 5.0,
                  'restart_backoff_s': 0.2, 'restart_backoff_max_s': 2.0,
                  'heartbeat_rate_hz': 4.0, 'state_dir': os.path.join(run_dir, 'host_state'),
                  'log_dir': os.path.join(run_dir, name)},
    }


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
                 port_base: int = 0, places=None):
        """``places``: where the processes run (``Loopback(environ)`` when not given)."""
        self.run_dir = run_dir
        self.places = places or Loopback(environ)
        self.shape = shape
        self.port_base = port_base or ports.port_base()
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
        params = member_params(name, priority, self.run_dir, self.port_base + 7 * index,
                               self.shape, self.places.hosts(name))
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
        """The live worker processes robot ``name``'s ``role`` agent supervises."""
        proc = self.procs.get(name, {}).get(role)
        if proc is None or proc.poll() is not None:
            return 0
        return workers_under(proc.pid)

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


def workers_under(pid: int) -> int:
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return 0
    return sum(1 for k in kids if is_worker(k))


def is_worker(proc: psutil.Process) -> bool:
    try:
        cmd = proc.cmdline()
        return proc.status() != psutil.STATUS_ZOMBIE and '--name' in cmd \
            and cmd[cmd.index('--name') + 1] == 'worker'
    except (psutil.Error, IndexError):
        return False


def other_domain(domain: int) -> int:
    """A second ROS domain for a second robot, away from ``domain``."""
    return domain + 100 if domain + 100 <= 230 else domain - 100
