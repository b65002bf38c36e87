"""A planned IROS 2016 robot file (``plan --split-iros ... --write-dir``) made runnable.

The instance files are planning data: nodes with a CPU and a performance, no command. Here each
node becomes a workload stand-in (nodes/workload.py) that burns the node's planned CPU:

- Its rate is its setting where the setting is a frequency (``*_hz``: the trackers' output
  frequency, navigation's controller frequency), else ``DEFAULT_RATE_HZ``.
- ``--work-ms`` is CPU per output in ms of one reference core, so a node of ``cpu`` percent of a
  reference core at ``rate`` Hz does ``cpu * 10 / rate`` ms per output (``work_ms_for``).
- One reference core (the file's ``capacity_cpu`` 100) is ``cpu_factor`` of one core of this
  machine (the workload's ``--reference-core``): the case study's server alone is 400, more
  than a shared two-core machine holds at the workload's default of 0.3.
- Its connections are its topics: it publishes each topic it is the publisher of (a node with
  none, the model, publishes ``/<node>/output`` so that its output can be heard) and subscribes
  to each topic it is the subscriber of.
- A workload does its work for an input of its first ``--sub``, and no node of the graph is a
  sensor at the node's own rate (the trackers' cameras are not in the file; the robot's base
  reads the environment). So each scale has a pacer per rate of its nodes: a sensor at that
  rate pinned there (``pace_<rate>hz_<scale>``, no work, CPU 0 in the file: it costs what any
  ROS process costs idle, as every node does) whose topic comes first in those nodes' inputs.
  On the node's own scale, the pace does not depend on a link. A node's output rate is then
  its planned rate as long as it gets its CPU, which is what the live run checks.

The server keeps ``shared: true``, each scale gets its host address, and the decider's first
layout stays the planner's (each pacer on its scale). Pure: no ROS, no files.
"""

import copy
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Tuple

DEFAULT_RATE_HZ = 10.0
DEFAULT_CPU_FACTOR = 0.15
PACER_CPU = 0.0
# Where a topic name needs a node's own output (a node the file gives no outgoing connection).
OUTPUT_SUFFIX = 'output'


@dataclass(frozen=True)
class LiveNode:
    """One node of the runnable deployment and what the plan predicts of it."""

    name: str
    scale: str
    setting: str             # 'goals=10000', or '-' for a node without settings
    rate_hz: float
    work_ms: float           # per output, ms of one reference core
    cpu: float               # planned, percent of one reference core
    performance: float       # planned
    output_topic: str        # the topic whose rate is the node's delivered rate
    pacer: bool = False      # a pacer, not a node of the case study


@dataclass(frozen=True)
class LiveDeployment:
    """A robot's runnable deployment (``params``: ROS parameters, unwrapped) and its nodes."""

    name: str
    params: Dict[str, Any]
    nodes: Tuple[LiveNode, ...]
    cpu_factor: float

    def node(self, name: str) -> LiveNode:
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(name)


def work_ms_for(cpu: float, rate_hz: float) -> float:
    """ms of one reference core per output for ``cpu`` percent of a reference core at
    ``rate_hz`` outputs a second."""
    return cpu * 10.0 / rate_hz


def cpu_of(work_ms: float, rate_hz: float) -> float:
    """The inverse of ``work_ms_for``: percent of one reference core."""
    return work_ms * rate_hz / 10.0


def machine_percent(cpu: float, cpu_factor: float) -> float:
    """Percent of one core of this machine that ``cpu`` (of a reference core) is given."""
    return cpu * cpu_factor


def reference_percent(machine_pct: float, cpu_factor: float) -> float:
    """Percent of one core of this machine back in percent of a reference core."""
    return machine_pct / cpu_factor


def rate_label(rate_hz: float) -> str:
    """'10' for 10 Hz, '11_125' for 11.125 Hz: a part of a ROS name."""
    return f'{rate_hz:g}'.replace('.', '_')


def pacer_name(rate_hz: float, scale: str) -> str:
    """The pacer of the nodes of ``scale`` that run at ``rate_hz``; its topic is ``/<name>``."""
    return f'pace_{rate_label(rate_hz)}hz_{scale}'


def _rate_of(body: Mapping[str, Any]) -> Tuple[float, str]:
    settings = body.get('settings')
    parameters = (body.get('launch') or {}).get('parameters') or {}
    if not settings:
        return DEFAULT_RATE_HZ, '-'
    parameter = settings.get('parameter', 'cpu')
    if parameter not in parameters:
        return DEFAULT_RATE_HZ, '-'
    value = parameters[parameter]
    setting = f'{parameter}={value:g}' if isinstance(value, (int, float)) else \
        f'{parameter}={value}'
    if parameter.endswith('_hz'):
        rate = float(value)
        if not rate > 0:
            raise ValueError(f'{parameter}: a rate must be > 0, got {value}')
        return rate, setting
    return DEFAULT_RATE_HZ, setting


def live_deployment(planned: Mapping[str, Any], cpu_factor: float = DEFAULT_CPU_FACTOR,
                    hosts: Optional[Mapping[str, str]] = None,
                    workload: str = 'workload') -> LiveDeployment:
    """The runnable deployment of a planned robot file (``planned``: the file as read, with or
    without its ``/**: ros__parameters`` wrapper). ``hosts``: scale -> address; ``workload``:
    the workload executable. Raises ValueError on a file without a planned layout."""
    if not cpu_factor > 0:
        raise ValueError(f'cpu_factor must be > 0, got {cpu_factor}')
    params = copy.deepcopy(dict(planned.get('/**', {}).get('ros__parameters', planned)))
    layout = dict((params.get('decider') or {}).get('layout') or {})
    nodes = params['nodes']
    names = list(nodes['names'])
    missing = [n for n in names if n not in layout]
    if missing:
        raise ValueError(f'decider.layout: no scale for {", ".join(missing)}: give the planned '
                         'file (plan --split-iros ... --write-dir), not the split one')
    scales = params['scales']
    connections = params.get('connections') or {'names': []}
    outputs: Dict[str, List[str]] = {n: [] for n in names}
    inputs: Dict[str, List[str]] = {n: [] for n in names}
    for c in connections['names']:
        body = connections[c]
        if body['publisher'] in outputs and body['topic'] not in outputs[body['publisher']]:
            outputs[body['publisher']].append(body['topic'])
        if body['subscriber'] in inputs and body['topic'] not in inputs[body['subscriber']]:
            inputs[body['subscriber']].append(body['topic'])

    def command(name: str, subs: List[str], pubs: List[str], rate: float,
                work_ms: float) -> List[str]:
        argv = [workload, '--name', name]
        for t in subs:
            argv += ['--sub', t]
        for t in pubs:
            argv += ['--pub', t]
        return argv + ['--rate-hz', f'{rate:g}', '--work-ms', f'{work_ms:.6g}',
                       '--reference-core', f'{cpu_factor:g}']

    live: List[LiveNode] = []
    pacers: List[Tuple[str, float]] = []
    for name in names:
        body = nodes[name]
        rate, setting = _rate_of(body)
        scale = layout[name]
        if (scale, rate) not in pacers:
            pacers.append((scale, rate))
        cpu = float(body['cpu'])
        work_ms = work_ms_for(cpu, rate)
        pubs = outputs[name] or [f'/{name}/{OUTPUT_SUFFIX}']
        launch = dict(body.get('launch') or {})
        launch['command'] = command(name, ['/' + pacer_name(rate, scale)] + inputs[name], pubs,
                                    rate, work_ms)
        body['launch'] = launch
        live.append(LiveNode(name, scale, setting, rate, work_ms, cpu,
                             float(body.get('performance', 0.0)), pubs[0]))
    for scale, rate in sorted(pacers):
        name = pacer_name(rate, scale)
        if name in nodes:
            raise ValueError(f'nodes.{name}: the name of a pacer is taken')
        topic = '/' + name
        nodes[name] = {'cpu': PACER_CPU, 'performance': 0.0, 'residence': [scale],
                       'launch': {'command': [workload, '--name', name, '--pub', topic,
                                              '--rate-hz', f'{rate:g}']}}
        nodes['names'].append(name)
        layout[name] = scale
        live.append(LiveNode(name, scale, '-', rate, 0.0, PACER_CPU, 0.0, topic, pacer=True))
    for scale, host in (hosts or {}).items():
        if scale in scales:
            scales[scale]['host'] = host
    decider = params.setdefault('decider', {})
    decider['layout'] = layout
    decider['initial_layout'] = 'explicit'
    deployment = params['deployment']
    deployment['description'] = (
        f"{deployment.get('description', '')}; live: each node a workload stand-in, one "
        f'reference core = {cpu_factor:g} of a core of this machine').lstrip('; ')
    return LiveDeployment(deployment['name'], params, tuple(live), cpu_factor)


__all__ = ['DEFAULT_CPU_FACTOR', 'DEFAULT_RATE_HZ', 'LiveDeployment', 'LiveNode', 'cpu_of',
           'live_deployment', 'machine_percent', 'pacer_name', 'reference_percent',
           'work_ms_for']
