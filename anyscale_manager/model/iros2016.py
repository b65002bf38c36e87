"""The IROS 2016 case-study instances (people-tracking cameras and youBots) as deployments."""

import copy
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Tuple

# instance -> (computers, robots, cameras)
INSTANCES: Dict[int, Tuple[int, int, int]] = {
    1: (2, 1, 1), 2: (2, 1, 2), 3: (2, 1, 3),
    4: (3, 2, 1), 5: (3, 2, 2), 6: (3, 2, 3),
    7: (4, 3, 1), 8: (4, 3, 2), 9: (4, 3, 3), 10: (4, 3, 4),
}
ROBOT_CAPACITY = 100.0
SERVER_CAPACITY = 400.0
WIRELESS_TOTAL_KBPS = 54000
WIRED_KBPS = 100000.0

# Profiling samples: (parameter, values, cpu, performance, cpu->performance form,
# parameter->cpu form, nominal cpu, nominal performance). Nominal = the middle setting that
# Problem 2 fixes.
TRACKER = ('output_frequency_hz', (10.0, 15.0, 20.0, 25.0), (80.0, 120.0, 160.0, 200.0),
           (40.0, 70.0, 90.0, 100.0), 'log', 'linear', 120.0, 70.0)
MODEL = ('goals', (4.0, 3500.0, 10000.0), (17.0, 39.0, 59.0), (20.0, 70.0, 100.0), 'log',
         'poly2', 39.0, 70.0)
AMCL = ('particles', (200.0, 500.0, 3000.0), (19.0, 41.0, 66.0), (20.0, 50.0, 100.0),
        'quadratic', 'poly2', 41.0, 50.0)
NAVIGATION = ('controller_frequency_hz', (2.0, 10.0, 20.0), (25.0, 39.0, 50.0),
              (10.0, 65.0, 100.0), 'log', 'poly2', 39.0, 65.0)


def _configurable(spec) -> Dict[str, Any]:
    parameter, values, cpu, perf, form, parameter_form, nominal_cpu, nominal_perf = spec
    return {
        'cpu': nominal_cpu,
        'performance': nominal_perf,
        'settings': {'parameter': parameter, 'values': list(values), 'cpu': list(cpu),
                     'performance': list(perf), 'form': form, 'parameter_form': parameter_form},
    }


def build_instance(number: int) -> Dict[str, Any]:
    """The deployment of one instance as a ROS parameters-file mapping."""
    computers, robots, cameras = INSTANCES[number]
    names = [f'c{i}' for i in range(1, computers + 1)]
    servers = names[robots:]
    scales: Dict[str, Any] = {'names': names}
    for i, name in enumerate(names):
        robot = i < robots
        scales[name] = {
            'role': 'master' if i == 0 else 'remote',
            'kind': 'robot' if robot else 'server',
            'capacity_cpu': ROBOT_CAPACITY if robot else SERVER_CAPACITY,
            'cores': 2 if robot else 4,
            'clock_ghz': 1.6 if robot else 3.3,
            'gain': 1.0,
            'host': name,
        }
    wireless: List[Tuple[str, str]] = [(names[i], names[j]) for i in range(robots)
                                       for j in range(i + 1, computers)]
    wired = [(servers[i], servers[j]) for i in range(len(servers))
             for j in range(i + 1, len(servers))]
    share = float(WIRELESS_TOTAL_KBPS // len(wireless)) if wireless else 0.0
    links: Dict[str, Any] = {'names': []}
    for (a, b), medium, bw in ([(p, 'wireless', share) for p in wireless]
                               + [(p, 'wired', WIRED_KBPS) for p in wired]):
        name = f'{a}_{b}'
        links['names'].append(name)
        links[name] = {'ends': [a, b], 'bandwidth_kbps': bw, 'medium': medium}

    nodes: Dict[str, Any] = {'names': []}

    def add(name: str, body: Dict[str, Any]) -> None:
        nodes['names'].append(name)
        nodes[name] = body

    add('experiment', {'cpu': 1.0, 'performance': 1.0, 'residence': list(servers)})
    for k in range(1, cameras + 1):
        add(f'tracker_{k}', {**_configurable(TRACKER), 'residence': list(servers)})
    for r in range(1, robots + 1):
        add(f'environment_{r}', {'cpu': 1.0, 'performance': 1.0})
        add(f'model_{r}', _configurable(MODEL))
        add(f'planner_{r}', {'cpu': 1.0, 'performance': 1.0,
                             'coresidence': [f'navigation_{r}']})
        add(f'amcl_{r}', _configurable(AMCL))
        add(f'navigation_{r}', {**_configurable(NAVIGATION), 'coresidence': [f'planner_{r}']})
        add(f'youbot_core_{r}', {'cpu': 16.0, 'performance': 1.0, 'residence': [names[r - 1]]})

    connections: Dict[str, Any] = {'names': []}

    def flow(pub: str, sub: str, topic: str, size: float) -> None:
        name = f'{pub}__{sub}'
        connections['names'].append(name)
        connections[name] = {'topic': topic, 'publisher': pub, 'subscriber': sub,
                             'bandwidth_kbps': size}

    for r in range(1, robots + 1):
        flow('experiment', f'environment_{r}', '/experiment', 1.0)
    for k in range(1, cameras + 1):
        flow(f'tracker_{k}', 'environment_1', f'/tracker_{k}/tracks', 3.0)
    for r in range(1, robots + 1):
        env = f'environment_{r}'
        for target in ('model', 'planner', 'youbot_core'):
            flow(env, f'{target}_{r}', f'/robot_{r}/environment', 1.0)
        for s in range(r + 1, robots + 1):
            flow(env, f'environment_{s}', f'/robot_{r}/environment', 1.0)
        flow(f'planner_{r}', f'navigation_{r}', f'/robot_{r}/costmap', 1.0)
        flow(f'navigation_{r}', env, f'/robot_{r}/navigation', 1.0)
        flow(f'youbot_core_{r}', f'navigation_{r}', f'/robot_{r}/scan', 1.0)
        flow(f'youbot_core_{r}', f'amcl_{r}', f'/robot_{r}/scan', 1.0)
        flow(f'amcl_{r}', env, f'/robot_{r}/amcl_pose', 1.0)

    return {'/**': {'ros__parameters': {
        'deployment': {
            'name': f'iros2016_instance_{number}',
            'description': f'IROS 2016 case study, instance {number}: {computers} computers, '
                           f'{robots} robot(s), {cameras} camera(s)',
        },
        'scales': scales,
        'links': links,
        'nodes': nodes,
        'connections': connections,
        # The paper's model fills a computer to its capacity: the case study's figures are
        # planned with every CPU usable, not with the decider's default headroom.
        'decider': {'cpu_headroom': 1.0},
    }}}


# The nodes each robot r brings to the case study, named <role>_<r> by build_instance.
ROBOT_NODE_ROLES = ('environment', 'model', 'planner', 'amcl', 'navigation', 'youbot_core')
# A robot's deployment takes this base (monitoring.bandwidth_probe_port) plus 10 per robot, so
# the agents of the robots' deployments on the shared server each have a port of their own.
PROBE_PORT_BASE = 47800
PROBE_PORT_STEP = 10


@dataclass(frozen=True)
class FleetSplit:
    """An instance as a fleet: one deployment file (as a mapping) per robot, and the
    connections no single file can hold (between two robots' nodes)."""

    members: Tuple[Tuple[str, Dict[str, Any]], ...]   # (robot scale, its deployment mapping)
    crossing: Tuple[str, ...]                         # connection names in no member
    owner: Mapping[str, str]                          # node -> the robot scale whose file has it


def split_fleet(data: Mapping[str, Any]) -> FleetSplit:
    """Split an instance's deployment mapping into one deployment per robot.

    Robot r (the r-th robot scale) gets its nodes (<role>_<r>, ``ROBOT_NODE_ROLES``), its own
    scale as master, every server as ``shared: true`` with the links among them, and the
    connections among its own nodes. The nodes that serve every robot from the server (the
    experiment and the camera trackers) go to robot 1. A connection between two robots' nodes
    (the experiment to robot 2's environment, one robot's environment to another's) is in no
    file: each robot is its own ROS domain; ``crossing`` names them. Raises ValueError on a
    mapping that is not an instance of this shape.
    """
    params = data['/**']['ros__parameters']
    scales = params['scales']
    robots = [s for s in scales['names'] if scales[s].get('kind') == 'robot']
    servers = [s for s in scales['names'] if s not in robots]
    if not robots:
        raise ValueError('no robot scale (scales.<s>.kind: robot) to split by')
    owner: Dict[str, str] = {}
    for name in params['nodes']['names']:
        role, _, index = name.rpartition('_')
        if role in ROBOT_NODE_ROLES and index.isdigit():
            r = int(index)
            if not 1 <= r <= len(robots):
                raise ValueError(f'nodes.{name}: robot {r}, but the instance has '
                                 f'{len(robots)} robot scale(s)')
            owner[name] = robots[r - 1]
        else:
            owner[name] = robots[0]
    for r, robot in enumerate(robots, start=1):
        if not any(owner[n] == robot and n.endswith(f'_{r}') for n in owner):
            raise ValueError(f"robot {r} ({robot}) has none of the case study's nodes "
                             f'({", ".join(f"{role}_{r}" for role in ROBOT_NODE_ROLES)})')
    base = params['deployment']['name']
    members = []
    placed = set()
    for r, robot in enumerate(robots, start=1):
        mine = [s for s in scales['names'] if s == robot or s in servers]
        own_scales: Dict[str, Any] = {'names': mine}
        for s in mine:
            body = copy.deepcopy(scales[s])
            if s == robot:
                body['role'] = 'master'
            else:
                body.update(role='remote', shared=True)
            own_scales[s] = body
        links: Dict[str, Any] = {'names': []}
        for name in params.get('links', {}).get('names', []):
            if all(e in mine for e in params['links'][name]['ends']):
                links['names'].append(name)
                links[name] = copy.deepcopy(params['links'][name])
        node_names = [n for n in params['nodes']['names'] if owner[n] == robot]
        nodes: Dict[str, Any] = {'names': node_names}
        nodes.update({n: copy.deepcopy(params['nodes'][n]) for n in node_names})
        connections: Dict[str, Any] = {'names': []}
        for name in params['connections']['names']:
            c = params['connections'][name]
            if owner[c['publisher']] == robot and owner[c['subscriber']] == robot:
                connections['names'].append(name)
                connections[name] = copy.deepcopy(c)
                placed.add(name)
        out: Dict[str, Any] = {
            'deployment': {
                'name': f'{base}_robot_{r}',
                'description': f'{params["deployment"].get("description", base)}; robot {r} '
                               f'({robot}) of the fleet, sharing {", ".join(servers)}',
            },
            'scales': own_scales,
        }
        if links['names']:
            out['links'] = links
        out['nodes'] = nodes
        if connections['names']:
            out['connections'] = connections
        for section, value in params.items():
            if section not in ('deployment', 'scales', 'links', 'nodes', 'connections'):
                out[section] = copy.deepcopy(value)
        monitoring = out.setdefault('monitoring', {})
        monitoring['bandwidth_probe_port'] = (monitoring.get('bandwidth_probe_port',
                                                             PROBE_PORT_BASE)
                                              + PROBE_PORT_STEP * (r - 1))
        members.append((robot, {'/**': {'ros__parameters': out}}))
    crossing = tuple(n for n in params['connections']['names'] if n not in placed)
    return FleetSplit(members=tuple(members), crossing=crossing, owner=owner)
