"""Two scales of this one machine for tests that run the real decider and agents as processes.

home is the master (a robot), away a remote server, joined by one wired link; the nodes are the
package's workload node, real ROS nodes the agents see in the graph. Here: the deployment file,
starting the programs and a listener of what they publish (waited on with spinning.py).
"""

import os
import sys
import time
from contextlib import contextmanager

import psutil
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import String

from anyscale_manager.testbed.ports import port_base
from anyscale_manager import protocol as p
from anyscale_manager.nodes import qos
from processes import LoggedProcess
from spinning import RosContext

BIN = os.path.dirname(sys.executable)
CONNECTION = {'msg_type': 'std_msgs/msg/UInt8MultiArray', 'bandwidth_kbps': 1.0}


def workload(name, *args):
    return {'command': [os.path.join(BIN, 'workload'), '--name', name, *args]}


# A test starts one decider: it listens this long for a leader before it leads, not the 5 s
# default (a second decider is given the default on its command line).
ONE_DECIDER_DISCOVERY_S = 1.5


def worker_and_pinned(topic, rate_hz=2.0):
    """worker (migratable) and pinned (home), talking to nobody: the nodes, no connections."""
    rate = ('--rate-hz', str(rate_hz))
    return {'worker': {'launch': workload('worker', '--pub', topic + '/worker', *rate),
                       'cpu': 1.0},
            'pinned': {'launch': workload('pinned', '--pub', topic + '/pinned', *rate),
                       'cpu': 1.0, 'residence': ['home']}}, {}


def chain(topic, rate_hz, connection=None, **worker_pinned):
    """sensor (home) -> worker (migratable) -> pinned (home), with both connections; a node
    that subscribes to nothing would be a data provider, pinned to the master.
    ``worker_pinned``: more fields of that connection (its frequency and Δ)."""
    connection = dict(CONNECTION, **(connection or {}))
    rate = ('--rate-hz', str(rate_hz))
    nodes = {'sensor': {'launch': workload('sensor', '--pub', topic + '/s', *rate),
                        'cpu': 1.0, 'residence': ['home']},
             'worker': {'launch': workload('worker', '--sub', topic + '/s', '--pub',
                                           topic + '/w', *rate), 'cpu': 1.0},
             'pinned': {'launch': workload('pinned', '--sub', topic + '/w', '--pub',
                                           topic + '/p', *rate),
                        'cpu': 1.0, 'residence': ['home']}}
    connections = {'sensor_worker': dict(connection, topic=topic + '/s', publisher='sensor',
                                         subscriber='worker'),
                   'worker_pinned': dict(connection, topic=topic + '/w', publisher='worker',
                                         subscriber='pinned', **worker_pinned)}
    return nodes, connections


def write_deployment(tmp_path, name, graph, capacity_cpu=100000.0, link_kbps=100000.0,
                     decider=None, monitoring=None, agent=None, port_offset=0,
                     file_name='deployment.yaml'):
    """The deployment file of ``graph`` (nodes, connections) on home and away; ``decider``,
    ``monitoring`` and ``agent`` override single entries of the defaults below. The link is
    loopback and never fails here: a missed echo is an agent not scheduled on a loaded machine,
    so the link is judged down only after 3 s of silence, and throughput is probed once."""
    nodes, connections = graph
    params = {
        'deployment': {'name': name},
        'scales': {'names': ['home', 'away'],
                   'home': {'role': 'master', 'kind': 'robot', 'capacity_cpu': capacity_cpu,
                            'cores': 2, 'clock_ghz': 1.0},
                   'away': {'role': 'remote', 'kind': 'server', 'capacity_cpu': capacity_cpu,
                            'cores': 4, 'clock_ghz': 2.0, 'gain': 3.0}},
        'links': {'names': ['net'],
                  'net': {'ends': ['home', 'away'], 'bandwidth_kbps': link_kbps,
                          'medium': 'wired'}},
        'nodes': dict(nodes, names=list(nodes)),
        # Both scales are this one machine: with the default capacity no headroom is kept.
        'decider': dict({'cpu_headroom': 1.0, 'period_s': 0.25, 'grace_s': 1.0,
                         'agent_timeout_s': 3.0, 'observation_max_age_s': 3.0,
                         'hysteresis_s': 60.0, 'discovery_s': ONE_DECIDER_DISCOVERY_S},
                        **(decider or {})),
        'monitoring': dict({'heartbeat_rate_hz': 4.0, 'heartbeat_misses_down': 12,
                            'scale_rate_hz': 4.0, 'bandwidth_probe_interval_s': 86400.0,
                            'bandwidth_probe_port': port_base(port_offset)},
                           **(monitoring or {})),
        'agent': dict({'sigint_grace_s': 1.0, 'sigterm_grace_s': 1.0,
                       'readiness_timeout_s': 5.0, 'restart_backoff_s': 0.2,
                       'restart_backoff_max_s': 2.0, 'heartbeat_rate_hz': 4.0,
                       'state_dir': str(tmp_path / 'state'), 'log_dir': str(tmp_path / 'log')},
                      **(agent or {})),
    }
    if connections:
        params['connections'] = dict(connections, names=list(connections))
    path = tmp_path / file_name
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
    return str(path)


def start(procs, tmp_path, env, path, name, *args):
    """Start the decider (a name beginning 'decider') or an agent, logged to <name>.out, and
    add it to ``procs`` as (name, process)."""
    exe = 'decider' if name.startswith('decider') else 'agent'
    proc = LoggedProcess(tmp_path / f'{name}.out',
                         [os.path.join(BIN, exe), '--ros-args', '--params-file', path, *args],
                         env)
    procs.append((name, proc))
    return proc


def start_agents(procs, tmp_path, env, path):
    return {scale: start(procs, tmp_path, env, path, f'agent_{scale}', '-p', f'scale:={scale}')
            for scale in ('home', 'away')}


@contextmanager
def listening(name):
    """(executor, seen): a node of its own context that keeps what the decider and the agents
    publish. seen: 'layouts' and 'events' in order, 'states' the last per scale, 'scales' and
    'links' as (receipt time, status), 'objectives' a count, 'diagnostics' the decider's last
    key -> value (and 'message')."""
    ros = RosContext()
    node = ros.node(name)
    seen = {'layouts': [], 'states': {}, 'events': [], 'scales': [], 'links': [],
            'objectives': 0, 'diagnostics': {}}

    def keep(key, cls):
        def take(m):
            seen[key].append((time.monotonic(), cls.from_json(m.data)))
        return take

    def agent_state(m):
        s = p.AgentState.from_json(m.data)
        seen['states'][s.scale] = s

    def objective(m):
        seen['objectives'] += 1

    def diagnostics(m):
        for status in m.status:
            if status.name.startswith('anyscale_decider:'):
                seen['diagnostics'] = {kv.key: kv.value for kv in status.values}
                seen['diagnostics']['message'] = status.message
    node.create_subscription(String, p.TOPIC_LAYOUT,
                             lambda m: seen['layouts'].append(p.Layout.from_json(m.data)),
                             qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_AGENT_STATE, agent_state, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_EVENTS,
                             lambda m: seen['events'].append(p.Event.from_json(m.data)),
                             qos.EVENTS)
    node.create_subscription(String, p.TOPIC_SCALE_STATUS, keep('scales', p.ScaleStatus),
                             qos.MONITOR_READER)
    node.create_subscription(String, p.TOPIC_LINK_STATUS, keep('links', p.LinkStatus),
                             qos.MONITOR_READER)
    node.create_subscription(String, p.TOPIC_OBJECTIVE, objective, 10)
    node.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, diagnostics, 50)
    with ros:
        yield ros.executor, seen


def released(seen, scale, node):
    """Whether ``scale`` reports ``node`` stopped under the latest layout (an older report can
    show it 'starting' while a copy kept for a move still runs)."""
    s = seen['states'].get(scale)
    if s is None or not seen['layouts']:
        return False
    r = s.nodes.get(node)
    return s.generation >= seen['layouts'][-1].generation and (r is None or r.state == 'stopped')


def wardens_of(tmp_path):
    """The warden processes the agents of a test started (children of no test process): those
    whose command line names a path under ``tmp_path``."""
    out = []
    for proc in psutil.process_iter(['cmdline']):
        cmd = proc.info['cmdline'] or []
        if 'anyscale_manager.agent.warden' in cmd and any(
                str(a).startswith(str(tmp_path)) for a in cmd):
            out.append(proc)
    return out


def stop_wardens(tmp_path):
    for proc in wardens_of(tmp_path):
        proc.kill()


def runs(seen, scale, node):
    """Whether the last report of ``scale``'s agent has ``node`` running."""
    s = seen['states'].get(scale)
    r = s.nodes.get(node) if s else None
    return r is not None and r.state == 'running'
