"""Readers: one subscription per topic and QoS in a process, every reader called (real rclpy)."""

from std_msgs.msg import String

from spinning import RosContext

from anyscale_manager.nodes import qos
from anyscale_manager.nodes.executor import make_executor
from anyscale_manager.nodes.readers import Readers

TOPIC = '/anyscale_test/readers'


def test_readers_share_one_subscription_survive_a_failing_reader_and_drop_cleanly():
    with RosContext(make_executor) as ros:
        readers = Readers()
        got = {'early': [], 'late': [], 'other_qos': []}

        def failing(_msg):
            raise RuntimeError('a reader with a bug')

        early, late, broken, other = object(), object(), object(), object()
        # Asked for before the owner exists (the master's decider is built first).
        readers.subscribe(early, String, TOPIC, qos.LATCHED_READER,
                          lambda m: got['early'].append(m.data))
        readers.subscribe(broken, String, TOPIC, qos.LATCHED_READER, failing)
        owner = ros.node('readers_owner')
        readers.open(owner)
        readers.subscribe(late, String, TOPIC, qos.LATCHED_READER,
                          lambda m: got['late'].append(m.data))
        readers.subscribe(other, String, TOPIC, qos.MONITOR_READER,
                          lambda m: got['other_qos'].append(m.data))
        assert readers.count() == 2                 # one per QoS, not one per reader
        assert owner.count_subscribers(TOPIC) == 2
        pub = ros.node('readers_writer').create_publisher(String, TOPIC, qos.LATCHED)
        pub.publish(String(data='one'))
        ros.spin_until(lambda: got['early'] and got['late'] and got['other_qos'], 10.0,
                       'every reader called')
        assert got['early'] == got['late'] == got['other_qos'] == ['one']

        readers.drop(early)
        readers.drop(broken)
        assert readers.count() == 2                 # ``late`` still reads it
        pub.publish(String(data='two'))
        ros.spin_until(lambda: got['late'][-1:] == ['two'], 10.0, 'the remaining reader')
        assert got['early'] == ['one']
        readers.drop(late)
        readers.drop(other)
        assert readers.count() == 0
        ros.spin_until(lambda: owner.count_subscribers(TOPIC) == 0, 5.0, 'no subscription')
