"""An agent hears every peer's latched report, and a decider every rival's latched layout,
however many land at once.

The agent_state topic has one writer per agent (and the layout topic one per decider). A reader
whose history is shared by all of them must keep a sample of each: with room for one, the
reports that arrive together replace each other before the agent takes them, and the agent
learns of a peer only at its next heartbeat (a stop_before_start move then waited one report
period for the losing copy's deactivation). Here an agent starts after two peers have latched
their reports, and a deciding decider takes two rival deciders' layouts only once both are in
its reader: each must know both without either publishing again.
"""

import os
import sys
import time

import yaml
from rclpy.duration import Duration
from std_msgs.msg import String

from anyscale_manager.testbed.ports import port_base
from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.nodes import qos
from anyscale_manager.nodes.agent import AgentNode
from anyscale_manager.nodes.decider import DeciderNode
from anyscale_manager.nodes.executor import make_executor
from spinning import RosContext

DEADLINE_S = 15.0


def write_deployment(tmp_path, decider=None):
    talker = {'command': [sys.executable, '-c', 'import time; time.sleep(60)']}
    scale = {'capacity_cpu': 100.0}
    data = {'/**': {'ros__parameters': {
        'deployment': {'name': f'agent_peers_{os.getpid()}'},
        'scales': {'names': ['a', 'b', 'c'],
                   'a': dict(scale, role='master', kind='robot'),
                   'b': dict(scale, role='remote', kind='server'),
                   'c': dict(scale, role='remote', kind='server')},
        'nodes': {'names': ['worker'], 'worker': {'launch': talker, 'cpu': 1.0}},
        'decider': dict({'agent_timeout_s': 60.0}, **(decider or {})),
        'monitoring': {'bandwidth_probe_interval_s': 86400.0,
                       'bandwidth_probe_port': port_base()},
        'agent': {'state_dir': str(tmp_path / 'state'), 'log_dir': str(tmp_path / 'log')},
    }}}
    path = tmp_path / 'deployment.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path), data['/**']['ros__parameters']['deployment']['name']


def test_an_agent_starting_late_hears_every_peers_latched_report(tmp_path):
    path, name = write_deployment(tmp_path)
    with RosContext() as peers_ros, RosContext(make_executor) as agent_ros:
        peers = peers_ros.node('agent_peers_harness', spin=False)
        # Two peers' agents, each with its own writer, as each agent has.
        writers = []
        for scale in ('b', 'c'):
            pub = peers.create_publisher(String, p.TOPIC_AGENT_STATE, qos.LATCHED)
            state = p.AgentState(scale=scale, generation=0, stamp=time.time(), nodes={},
                                 instance=f'{scale}-instance', seq=1)
            pub.publish(String(data=auth.seal(None, state)))
            writers.append(pub)
        agent = agent_ros.own(AgentNode('a', context=agent_ros.context,
                                        cli_args=['--ros-args', '--params-file', path]))
        assert agent.deployment.name == name
        # Nothing spins the agent until both reports are in its reader: the case of reports
        # landing together.
        end = time.monotonic() + DEADLINE_S
        while time.monotonic() < end and not all(w.get_subscription_count() for w in writers):
            time.sleep(0.02)
        assert all(w.get_subscription_count() for w in writers), 'the agent never matched'
        # Both samples acknowledged by the agent's reader: both in its history, none taken yet.
        assert all(w.wait_for_all_acked(Duration(seconds=DEADLINE_S)) for w in writers), \
            'the agent never acknowledged both samples'
        agent_ros.add(agent)
        agent_ros.spin_until(lambda: set(agent.reconciler.peers) == {'b', 'c'},
                             end - time.monotonic(), 'the agent hearing both latched reports',
                             state=lambda: f'heard {sorted(agent.reconciler.peers)}')


def test_a_deciding_decider_hears_every_rivals_layout_landing_together(tmp_path):
    path, name = write_deployment(tmp_path, decider={'discovery_s': 0.2})
    with RosContext() as rivals_ros, RosContext(make_executor) as decider_ros:
        rivals = rivals_ros.node('decider_rivals_harness', spin=False)
        decider = decider_ros.add(DeciderNode(context=decider_ros.context,
                                              cli_args=['--ros-args', '--params-file', path]))
        end = time.monotonic() + DEADLINE_S
        decider_ros.spin_until(lambda: decider.lead.role == 'leader', end - time.monotonic(),
                               'the decider leading')
        # Two other deciders of this deployment, started after it (at its term they yield),
        # each with its own latched writer, publish while nothing spins the decider.
        writers = [rivals.create_publisher(String, p.TOPIC_LAYOUT, qos.LATCHED) for _ in (1, 2)]
        while time.monotonic() < end and not all(w.get_subscription_count() for w in writers):
            time.sleep(0.02)
        assert all(w.get_subscription_count() for w in writers), 'the decider never matched'
        for k, pub in enumerate(writers, 1):
            who = p.DeciderIdentity(id=f'rival-{k}', host='test', pid=k, started=time.time())
            layout = p.Layout(generation=k, deployment=name, assignments={'worker': 'a'},
                              reason='test', stamp=time.time(), decider=who, seq=1)
            pub.publish(String(data=auth.seal(None, layout)))
        # Both samples acknowledged by the decider's reader: both in its history, none taken.
        assert all(w.wait_for_all_acked(Duration(seconds=DEADLINE_S)) for w in writers), \
            'the decider never acknowledged both layouts'
        seen = set()

        def heard():
            seen.update(decider.lead.peers)
            return seen

        decider_ros.spin_until(lambda: heard() == {'rival-1', 'rival-2'}, end - time.monotonic(),
                               'the decider hearing both latched layouts',
                               state=lambda: f'heard {sorted(heard())} ({len(decider._layouts)} '
                               f'layouts kept, {decider._rejected} refused)')
