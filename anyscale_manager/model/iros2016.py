"""The IROS 2016 case-study instances (people-tracking cameras and youBots) as deployments."""

from typing import Any, Dict, List, Tuple

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
