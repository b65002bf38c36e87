"""Generated deployments for scale tests: many nodes, many computers, IROS-like profiles."""

import random
from dataclasses import replace
from typing import List, Tuple

from ..model.types import (MASTER, REMOTE, ROBOT, SERVER, WIRED, WIRELESS, Connection,
                           Deployment, Launch, Link, Node, Scale, Settings)

# (parameter, values, cpu, performance, form, parameter_form): the case study's four profiles.
PROFILES = (
    ('output_frequency_hz', (10.0, 15.0, 20.0, 25.0), (80.0, 120.0, 160.0, 200.0),
     (40.0, 70.0, 90.0, 100.0), 'log', 'linear'),
    ('goals', (4.0, 3500.0, 10000.0), (17.0, 39.0, 59.0), (20.0, 70.0, 100.0), 'log', 'poly2'),
    ('particles', (200.0, 500.0, 3000.0), (19.0, 41.0, 66.0), (20.0, 50.0, 100.0),
     'quadratic', 'poly2'),
    ('controller_frequency_hz', (2.0, 10.0, 20.0), (25.0, 39.0, 50.0), (10.0, 65.0, 100.0),
     'log', 'poly2'),
)


def generate_deployment(nodes: int = 1000, computers: int = 50, seed: int = 0,
                        configurable_share: float = 0.25, robot_share: float = 0.6
                        ) -> Deployment:
    """A random but always feasible deployment of ``nodes`` nodes on ``computers`` computers.

    Robots (capacity 100) and servers (400) are linked all to all (wireless to robots, wired
    between servers). A quarter of the nodes are configurable with the case study's profiles
    (the 200-CPU tracker profile only on servers), a tenth are pinned to one robot, some pairs
    must share a scale, and every node but the first subscribes to an earlier one. Fixed CPU
    is sized so that the smallest settings use about half of the total capacity.
    """
    if nodes < 2 or computers < 2:
        raise ValueError('need at least 2 nodes and 2 computers')
    rng = random.Random(seed)
    robots = max(1, int(round(computers * robot_share)))
    scales: List[Scale] = []
    for i in range(computers):
        robot = i < robots
        scales.append(Scale(name=f'c{i + 1}', role=MASTER if i == 0 else REMOTE,
                            kind=ROBOT if robot else SERVER,
                            capacity_cpu=100.0 if robot else 400.0, cores=2 if robot else 4,
                            clock_ghz=1.6 if robot else 3.3, gain=1.0, host=f'c{i + 1}'))
    names = [s.name for s in scales]
    servers = names[robots:]
    links = []
    share = 20000.0
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            wired = a in servers and b in servers
            links.append(Link(name=f'{a}_{b}', ends=(a, b),
                              bandwidth_kbps=100000.0 if wired else share,
                              medium=WIRED if wired else WIRELESS))
    total_capacity = sum(s.capacity_cpu for s in scales)
    fixed_mean = max(1.0, (0.5 * total_capacity - nodes * configurable_share * 30.0)
                     / max(1.0, nodes * (1 - configurable_share)))
    out: List[Node] = []
    for i in range(nodes):
        name = f'n{i}'
        residence: Tuple[str, ...] = ()
        settings = None
        if rng.random() < configurable_share:
            k = rng.randrange(len(PROFILES)) if servers else rng.randrange(1, len(PROFILES))
            parameter, values, cpu, perf, form, parameter_form = PROFILES[k]
            settings = Settings(parameter=parameter, values=values, cpu=cpu, performance=perf,
                                form=form, parameter_form=parameter_form)
            if k == 0:
                residence = tuple(servers)
            node = Node(name=name, launch=Launch(), cpu=cpu[len(cpu) // 2],
                        performance=perf[len(perf) // 2], residence=residence,
                        settings=settings)
        else:
            cpu_share = round(rng.uniform(0.2, 1.8) * fixed_mean, 1)
            if rng.random() < 0.1:
                residence = (names[rng.randrange(robots)],)
            node = Node(name=name, launch=Launch(), cpu=cpu_share, performance=1.0,
                        residence=residence)
        out.append(node)
    # Coresidence pairs among unpinned fixed nodes (always satisfiable).
    free = [i for i, n in enumerate(out) if not n.residence and n.settings is None]
    rng.shuffle(free)
    pairs = free[:max(0, nodes // 40) * 2]
    for first, second in zip(pairs[::2], pairs[1::2]):
        out[first] = _with(out[first], coresidence=(out[second].name,))
        out[second] = _with(out[second], coresidence=(out[first].name,))
    connections: List[Connection] = []
    for i in range(1, nodes):
        for _ in range(1 + (rng.random() < 0.5)):
            j = rng.randrange(max(0, i - 50), i)
            connections.append(Connection(name=f'e{len(connections)}', topic=f'/t{j}',
                                          publisher=out[j].name, subscriber=out[i].name,
                                          bandwidth_kbps=float(rng.randint(1, 50))))
    return Deployment(name=f'generated_{nodes}x{computers}_{seed}', source='<generated>',
                      scales=tuple(scales), links=tuple(links), nodes=tuple(out),
                      connections=tuple(connections))


def _with(node: Node, **changes) -> Node:
    return replace(node, **changes)
