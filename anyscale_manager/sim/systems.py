"""The systems of the paper's Fig. 7: N processing nodes, M migratable, K scales.

* 6N x 2M is the ICAR test-bed itself, read from its deployment file
  (config/icar2015_testbed.yaml).
* 12N x 6M and 18N x 9M are generated from it: the same robot, sensors and critical core
  (odometry, EKF, navigation, decision), more critical nodes fed with Delta = 0, and M
  migratable nodes alternating between the test-bed's two kinds: localisers like AMCL (laser in,
  pose out to the EKF, they govern the robot's speed) and recognisers like AR (camera in at
  6 Mbit/s, markers out to navigation, they do not). Each generated value is the test-bed's
  value times a seeded factor in [0.7, 1.3]; the processing nodes' CPU is then scaled so the
  robot carries the test-bed's load at baseline (153 of 200), which keeps the all-on-master
  baseline correct, as the paper requires.
* K adds remote scales, each more powerful than the last: laptop (4 x 2.8 GHz, the
  test-bed's), workstation (8 x 3.0 GHz), server (16 x 3.2 GHz); gain alpha = cores x GHz
  relative to the robot, capacity in robot-core percent; each reached over its own 802.11g link.
"""

import copy
import math
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import yaml

from .. import config_files
from ..model.loader import load_mapping
from .model import SimSystem, profiles_from_deployment

FIG7_TYPES = ((6, 2), (12, 6), (18, 9))
FIG7_SCALES = (2, 3, 4)
# name, cores, clock (GHz); the first is the test-bed's laptop.
REMOTE_LADDER = (('laptop', 4, 2.8), ('workstation', 8, 3.0), ('server', 16, 3.2))
LINK_KBPS = 54000.0
TESTBED_FILE = 'icar2015_testbed.yaml'
TESTBED_SPEED_WEIGHTS = {'amcl': 1.0}   # 0.4 m/s only with AMCL remote (Section V)
BASELINE_LOAD_CPU = 153.0                # the test-bed's robot load with every node on it
JITTER = (0.7, 1.3)


def find_testbed() -> str:
    """The test-bed deployment file: installed share directory first, then the source tree."""
    path = config_files.find(TESTBED_FILE)
    if path is None:
        raise FileNotFoundError(f'cannot find {TESTBED_FILE} (looked in: '
                                f'{", ".join(config_files.candidates(TESTBED_FILE))})')
    return path


def _read_yaml(path: str) -> Dict[str, Any]:
    with open(path, encoding='utf-8') as f:
        data = yaml.safe_load(f)
    try:
        return data['/**']['ros__parameters']
    except (TypeError, KeyError) as e:
        raise ValueError(f'{path}: expected a ROS 2 parameters file with /**: '
                         'ros__parameters') from e


def _add_scales(params: Dict[str, Any], k: int) -> None:
    """Give a deployment with one master and the laptop K - 1 remote scales of the ladder."""
    if not 2 <= k <= len(REMOTE_LADDER) + 1:
        raise ValueError(f'K must be in 2..{len(REMOTE_LADDER) + 1}, got {k}')
    scales = params['scales']
    master = next(scales[n] for n in scales['names'] if scales[n]['role'] == 'master')
    master_power = master['cores'] * master['clock_ghz']
    remotes = []
    for name, cores, clock in REMOTE_LADDER[:k - 1]:
        remotes.append((name, {
            'role': 'remote', 'kind': 'server',
            'capacity_cpu': round(cores * clock / master['clock_ghz'] * 100.0, 3),
            'cores': cores, 'clock_ghz': clock,
            'gain': round(cores * clock / master_power, 4), 'host': name,
        }))
    set_remote_scales(params, remotes)


def set_remote_scales(params: Dict[str, Any], remotes: List[Tuple[str, Dict[str, Any]]]) -> None:
    """Make ``remotes`` (name, scale section) the deployment's only remote scales, each reached
    from the master over its own 802.11g link; links to the scales dropped go with them."""
    scales = params['scales']
    master_name = next(n for n in scales['names'] if scales[n]['role'] == 'master')
    names = [master_name]
    for name, section in remotes:
        names.append(name)
        scales[name] = dict(section)
    for extra in [n for n in scales['names'] if n not in names]:
        scales.pop(extra, None)
    scales['names'] = names
    links = params.setdefault('links', {'names': []})
    kept = []
    for name in list(links.get('names', [])):
        ends = links[name]['ends']
        if all(e in names for e in ends):
            kept.append(name)
        else:
            links.pop(name)
    joined = {tuple(sorted(links[n]['ends'])) for n in kept}
    for name in names[1:]:
        if tuple(sorted((master_name, name))) not in joined:
            link = f'wifi_{name}'
            links[link] = {'ends': [master_name, name], 'bandwidth_kbps': LINK_KBPS,
                           'medium': 'wireless'}
            kept.append(link)
    links['names'] = kept


def _workload(name: str) -> Dict[str, Any]:
    return {'package': 'anyscale_manager', 'executable': 'workload',
            'arguments': ['--name', name]}


def _connection(topic: str, pub: str, sub: str, fmin: float, fopt: float, tol: float,
                kbps: float) -> Dict[str, Any]:
    return {'topic': topic, 'publisher': pub, 'subscriber': sub, 'freq_min_hz': float(fmin),
            'freq_opt_hz': float(fopt), 'tolerance_s': float(tol), 'bandwidth_kbps': float(kbps)}


def generated_parameters(n: int, m: int, rng: np.random.Generator,
                         base: Dict[str, Any]) -> Tuple[Dict[str, Any], Dict[str, float]]:
    """A test-bed-like application with N processing nodes, M of them migratable."""
    if m < 2 or n < m + 4:
        raise ValueError(f'need M >= 2 and N >= M + 4 (the critical core), got N={n}, M={m}')
    params = copy.deepcopy(base)
    params['deployment'] = {'name': f'sim_{n}n_{m}m',
                            'description': f'generated from the ICAR test-bed: N={n}, M={m}'}
    nodes = params['nodes']
    conns = params['connections']

    def jitter() -> float:
        return float(rng.uniform(*JITTER))

    keep_nodes = ['laser', 'odometer', 'camera', 'user', 'map_server', 'odometry', 'ekf',
                  'navigation', 'decision']
    keep_conns = ['laser_navigation', 'odometer_odometry', 'odometry_ekf', 'ekf_navigation']
    new_nodes = {k: nodes[k] for k in keep_nodes}
    new_conns = {k: conns[k] for k in keep_conns}
    for i in range(1, n - m - 4 + 1):
        name = f'guard_{i}'
        new_nodes[name] = {'launch': _workload(name), 'cpu': 10.0 * jitter()}
        new_conns[f'ekf_{name}'] = _connection('/pose', 'ekf', name, 2.0, 5.0, 0.0, 6.0)
    speed: Dict[str, float] = {}
    # The generated migratable nodes keep standby copies as the test-bed's do.
    standby = bool(nodes['amcl'].get('standby', False))
    lifecycle = bool(nodes['amcl'].get('lifecycle', False))
    localisers = math.ceil(m / 2)
    for i in range(1, m + 1):
        if i <= localisers:
            name = f'localiser_{i}'
            base_hz = 2.0 * jitter()
            opt_hz = base_hz * 2.5 * jitter()
            new_nodes[name] = {'launch': _workload(name), 'cpu': 50.0 * jitter(),
                               'standby': standby, 'lifecycle': lifecycle}
            new_conns[f'laser_{name}'] = _connection('/scan', 'laser', name, 5.0, 10.0, 2.0,
                                                     200.0 * jitter())
            new_conns[f'{name}_ekf'] = _connection(f'/{name}/pose', name, 'ekf', base_hz,
                                                   opt_hz, 2.0, 6.0)
            speed[name] = 1.0 / localisers
        else:
            name = f'recogniser_{i - localisers}'
            new_nodes[name] = {'launch': _workload(name), 'cpu': 33.0 * jitter(),
                               'standby': standby, 'lifecycle': lifecycle}
            new_conns[f'camera_{name}'] = _connection('/image', 'camera', name, 1.0, 30.0, 1.0,
                                                      6000.0 * jitter())
            new_conns[f'{name}_navigation'] = _connection(f'/{name}/markers', name,
                                                          'navigation', 1.0, 30.0, 1.0, 62.0)
    # Scale the processing nodes so the robot carries the test-bed's load at baseline.
    fixed = [k for k in new_nodes if k in ('laser', 'odometer', 'camera', 'user', 'map_server',
                                           'decision')]
    fixed_cpu = sum(new_nodes[k]['cpu'] for k in fixed)
    scalable = [k for k in new_nodes if k not in fixed]
    factor = (BASELINE_LOAD_CPU - fixed_cpu) / sum(new_nodes[k]['cpu'] for k in scalable)
    for k in scalable:
        new_nodes[k] = dict(new_nodes[k], cpu=round(new_nodes[k]['cpu'] * factor, 3))
    new_nodes['names'] = [k for k in new_nodes]
    new_conns['names'] = [k for k in new_conns]
    params['nodes'] = new_nodes
    params['connections'] = new_conns
    return params, speed


def system_parameters(n: int, m: int, seed: int = 0, testbed_path: Optional[str] = None
                      ) -> Tuple[Dict[str, Any], Dict[str, float], str]:
    """The parameters of an N x M application (its scales still the test-bed's), its speed
    weights and the test-bed file it comes from; 6N x 2M is the test-bed file itself."""
    path = testbed_path or find_testbed()
    base = _read_yaml(path)
    if (n, m) == (6, 2):
        return copy.deepcopy(base), dict(TESTBED_SPEED_WEIGHTS), path
    rng = np.random.default_rng([seed, n, m, 20150901])
    params, speed = generated_parameters(n, m, rng, base)
    return params, speed, path


def system_from_parameters(params: Dict[str, Any], speed: Dict[str, float], label: str,
                           n: int, m: int, source: str) -> SimSystem:
    """A system from its parameters, checked to have N processing and M migratable nodes."""
    deployment = load_mapping({'/**': {'ros__parameters': params}}, source=f'{source} ({label})')
    processing = [x for x in deployment.node_names if x not in deployment.data_providers
                  and x not in ('user', 'map_server')]
    if len(processing) != n or len(deployment.migratable_nodes) != m:
        raise ValueError(f'{label}: built {len(processing)} processing nodes and '
                         f'{len(deployment.migratable_nodes)} migratable, expected {n} and {m}')
    return SimSystem(label=label, n=n, m=m, k=len(deployment.scales), deployment=deployment,
                     profiles=profiles_from_deployment(deployment, speed))


def build_system(n: int, m: int, k: int, seed: int = 0,
                 testbed_path: Optional[str] = None) -> SimSystem:
    """One system of Fig. 7; 6N x 2M is the test-bed file itself."""
    params, speed, path = system_parameters(n, m, seed, testbed_path)
    _add_scales(params, k)
    return system_from_parameters(params, speed, f'{n}N x {m}M x {k}K', n, m, path)


def fig7_systems(seed: int = 0, testbed_path: Optional[str] = None) -> List[SimSystem]:
    return [build_system(n, m, k, seed, testbed_path)
            for n, m in FIG7_TYPES for k in FIG7_SCALES]
