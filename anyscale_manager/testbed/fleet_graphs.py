"""What each robot of a test fleet runs: its deployment file, the copies that may go to the
shared server, and the connections its users' observer judges.

Two graphs (``FleetShape.graph``):

- ``worker``: sensor (home) -> worker (migratable, CPU ``worker_cpu``, a plain node moved cold)
  -> pinned (home); the worker's output watched with a Δ a cold move meets. The server has room
  for one worker.
- ``icar``: the ICAR 2015 test-bed's graph (config/icar2015_testbed.yaml: eleven nodes, AMCL and
  AR migratable lifecycle nodes with a standby copy on each scale, the robot's Δ 0 chain at
  real-time priority), the robot its ``home`` scale, the laptop turned into the shared server
  ``away`` (capacity ``capacity_cpu``: room for one robot's AMCL and AR, 50 + 33, not
  two). Every workload runs at ``reference_core`` (one robot core as a fraction of one core of
  this machine) and the robot's quota is its capacity at that speed, so that two robots and the
  server fit a 2-core machine.
"""

import functools
import os
import sys
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Tuple

import yaml

from .. import config_files

BIN = os.path.dirname(sys.executable)
SERVER = 'away'
HOME = 'home'
GRAPHS = ('worker', 'icar')
ICAR_FILE = 'icar2015_testbed.yaml'
ICAR_SCALES = {'robot': HOME, 'laptop': SERVER}


@dataclass(frozen=True)
class FleetShape:
    """What every robot of the fleet runs, and the server's room."""

    capacity_cpu: float = 100.0        # the server's (and, worker graph, each robot's) capacity
    worker_cpu: float = 60.0
    rate_hz: float = 10.0
    freq_min_hz: float = 5.0
    # The worker is a plain node: a move, a preemption included, starts it cold, and its Δ
    # covers a cold start (validate's budget here: 12 beats at 4 Hz + 0.8 s = 3.8 s).
    tolerance_s: float = 5.0
    hysteresis_s: float = 60.0
    graph: str = 'worker'
    reference_core: float = 0.2        # icar: one robot core in cores of this machine
    # icar: AMCL's work per output, in ms of one robot core. The ICAR file's 360 keeps AMCL
    # CPU-bound on a robot that sends AR away; a fleet's robot may have to keep AR, and its
    # manager and AR take a fixed share of its 0.4 cores (measured: AMCL got 0.19 cores there,
    # 2.3-2.5 Hz at 360 against a freq_min of 2, and a stretch below it past Δ at times). At
    # 240 it runs at 4.8 Hz there, near its 5 Hz cap.
    amcl_work_ms: float = 240.0

    def __post_init__(self):
        if self.graph not in GRAPHS:
            raise ValueError(f'unknown fleet graph {self.graph!r}; one of {", ".join(GRAPHS)}')

    @property
    def lifecycle(self) -> bool:
        """Whether the moving nodes are lifecycle copies, judged serving by their CPU over a
        window (fleet.Activity), not by their process."""
        return graph_class(self.graph).lifecycle


@dataclass(frozen=True)
class Judged:
    """A connection the robot's users' observer judges by the Δ rule."""

    name: str
    topic: str
    msg_type: str
    freq_min_hz: float
    tolerance_s: float


class WorkerGraph:
    """sensor -> worker -> pinned (the module's docstring)."""

    moving: Tuple[str, ...] = ('worker',)
    lifecycle = False
    what = 'worker'
    msg_type = 'std_msgs/msg/UInt8MultiArray'

    def __init__(self, shape: FleetShape):
        self.shape = shape

    def robot_cores(self) -> Optional[float]:
        """The robot's quota in cores of this machine (None: the bed's default)."""
        return None

    def server_cores(self) -> Optional[float]:
        """The server's quota in cores of this machine (None: the bed's default)."""
        return None

    def cpu(self, node: str) -> float:
        return self.shape.worker_cpu

    def judged(self, robot: str) -> List[Judged]:
        s = self.shape
        return [Judged('worker_pinned', f'/{robot}/w', self.msg_type, s.freq_min_hz,
                       s.tolerance_s)]

    def shown(self, robot: str) -> Judged:
        """The connection a demo's figure draws for ``robot``: the worker's output."""
        return self.judged(robot)[0]

    def needs(self) -> str:
        return f'a worker needs {self.shape.worker_cpu:g}'

    def params(self, name: str, priority: int, run_dir: str, port_base: int,
               hosts: Optional[Mapping[str, str]] = None) -> dict:
        """Robot ``name``'s deployment file, as ROS parameters; ``hosts``: scale -> its address
        (``scales.<s>.host``), left to the default (this machine) when not given."""
        shape = self.shape
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
        flow = {'msg_type': self.msg_type, 'bandwidth_kbps': 1.0}
        connections = {'sensor_worker': dict(flow, topic=topic + '/s', publisher='sensor',
                                             subscriber='worker'),
                       'worker_pinned': dict(flow, topic=topic + '/w', publisher='worker',
                                             subscriber='pinned',
                                             freq_min_hz=shape.freq_min_hz,
                                             tolerance_s=shape.tolerance_s)}
        scales = {HOME: {'role': 'master', 'kind': 'robot', 'capacity_cpu': shape.capacity_cpu,
                         'cores': 2, 'clock_ghz': 1.0},
                  SERVER: {'role': 'remote', 'kind': 'server',
                           'capacity_cpu': shape.capacity_cpu, 'cores': 4, 'clock_ghz': 2.0,
                           'shared': True}}
        _place(scales, hosts)
        return {
            'deployment': {'name': name, 'priority': priority},
            'scales': dict(scales, names=[HOME, SERVER]),
            'links': {'names': ['net'], 'net': {'ends': [HOME, SERVER],
                                                'bandwidth_kbps': 100000.0, 'medium': 'wired'}},
            'nodes': dict(nodes, names=list(nodes)),
            'connections': dict(connections, names=list(connections)),
            # Both scales are this one machine: no headroom kept; a missed echo is an agent not
            # scheduled on a loaded machine, so the link is judged down only after 3 s. Each
            # robot runs one decider: it listens 1.5 s for a leader before it leads, not 5 s.
            'decider': {'cpu_headroom': 1.0, 'period_s': 0.25, 'grace_s': 1.0,
                        'agent_timeout_s': 3.0, 'observation_max_age_s': 3.0,
                        'hysteresis_s': shape.hysteresis_s, 'discovery_s': 1.5},
            'monitoring': {'heartbeat_rate_hz': 4.0, 'heartbeat_misses_down': 12,
                           'scale_rate_hz': 4.0, 'bandwidth_probe_interval_s': 86400.0,
                           'bandwidth_probe_port': port_base},
            'agent': dict(_agent_dirs(name, run_dir), sigint_grace_s=1.0, sigterm_grace_s=1.0,
                          readiness_timeout_s=5.0, restart_backoff_s=0.2,
                          restart_backoff_max_s=2.0, heartbeat_rate_hz=4.0),
        }


class IcarGraph:
    """The ICAR 2015 test-bed's graph per robot, the laptop its share of the server (the
    module's docstring)."""

    moving: Tuple[str, ...] = ('amcl', 'ar')
    lifecycle = True
    what = 'AMCL and AR'

    def __init__(self, shape: FleetShape, path: Optional[str] = None):
        self.shape = shape
        self.path = path or config_files.find(ICAR_FILE)
        if self.path is None:
            raise FileNotFoundError(
                f'{ICAR_FILE} not found in {", ".join(config_files.candidates(ICAR_FILE))}')
        with open(self.path) as f:
            self.base = yaml.safe_load(f)['/**']['ros__parameters']

    def robot_cores(self) -> Optional[float]:
        """The robot's quota: its capacity at the shape's ``reference_core``."""
        robot = self.base['scales']['robot']
        return float(robot['capacity_cpu']) / 100.0 * self.shape.reference_core

    def server_cores(self) -> Optional[float]:
        """The server's quota: two cores of this machine, so that its readings (its capacity
        100 being two cores) keep a robot's AMCL and AR (about 25) well below the decider's
        headroom while another robot's agent and copies start there (a start-up took a one-core
        server to 98 and sent AR home)."""
        return 2.0

    def cpu(self, node: str) -> float:
        return float(self.base['nodes'][node]['cpu'])

    def judged(self, robot: str) -> List[Judged]:
        """Every connection with a minimum frequency, heard at the robot (where each one's
        subscriber runs but AR's: camera_ar is judged by AR's output, ar_navigation)."""
        conns = self.base['connections']
        return [Judged(c, conns[c]['topic'], conns[c]['msg_type'],
                       float(conns[c]['freq_min_hz']), float(conns[c]['tolerance_s']))
                for c in conns['names'] if conns[c].get('freq_min_hz')
                and conns[c]['subscriber'] not in self.moving]

    def shown(self, robot: str) -> Judged:
        """The connection a demo's figure draws for ``robot``: AMCL's pose to the EKF."""
        return next(j for j in self.judged(robot) if j.name == 'amcl_ekf')

    def needs(self) -> str:
        return ' and '.join(f'{n.upper() if len(n) < 5 else n} {self.cpu(n):g}'
                            for n in self.moving) + ' per robot'

    def params(self, name: str, priority: int, run_dir: str, port_base: int,
               hosts: Optional[Mapping[str, str]] = None) -> dict:
        base, shape = self.base, self.shape
        scales: Dict[str, dict] = {}
        for old, new in ICAR_SCALES.items():
            scales[new] = {k: v for k, v in base['scales'][old].items() if k != 'host'}
        scales[SERVER].update(shared=True, capacity_cpu=shape.capacity_cpu)
        _place(scales, hosts)
        links = {'names': list(base['links']['names'])}
        for link in links['names']:
            links[link] = dict(base['links'][link],
                               ends=[ICAR_SCALES[e] for e in base['links'][link]['ends']])
        nodes = {'names': list(base['nodes']['names'])}
        for node in nodes['names']:
            spec = dict(base['nodes'][node])
            if 'residence' in spec:
                spec['residence'] = [ICAR_SCALES[s] for s in spec['residence']]
            launch = spec.get('launch')
            if launch and launch.get('executable') == 'workload':
                arguments = list(launch['arguments'])
                if node == 'amcl':
                    arguments[arguments.index('--work-ms') + 1] = f'{shape.amcl_work_ms:g}'
                spec['launch'] = dict(launch, arguments=arguments + [
                    '--reference-core', f'{shape.reference_core:g}'])
            nodes[node] = spec
        return {
            'deployment': {'name': name, 'priority': priority,
                           'description': f'{name}: the ICAR 2015 graph, one robot of a fleet'},
            'scales': dict(scales, names=[HOME, SERVER]),
            'links': links,
            'nodes': nodes,
            'connections': base['connections'],
            'decider': dict(base['decider'], hysteresis_s=shape.hysteresis_s),
            'monitoring': dict(base['monitoring'], bandwidth_probe_port=port_base),
            'agent': dict(base['agent'], **_agent_dirs(name, run_dir)),
        }


def graph_class(name: str):
    return IcarGraph if name == 'icar' else WorkerGraph


@functools.lru_cache(maxsize=8)
def graph_of(shape: FleetShape):
    """The graph ``shape`` names (one per shape: the ICAR file is read once)."""
    return graph_class(shape.graph)(shape)


def _place(scales: Dict[str, dict], hosts: Optional[Mapping[str, str]]) -> None:
    for scale, host in (hosts or {}).items():
        scales[scale]['host'] = host


def _agent_dirs(name: str, run_dir: str) -> Dict[str, str]:
    """Every agent of the fleet keeps its state in one folder (one host, one claims ledger);
    each robot's nodes log apart."""
    return {'state_dir': os.path.join(run_dir, 'host_state'),
            'log_dir': os.path.join(run_dir, name)}
