"""What others publish on a stateful node's own restore topic (a pose set in RViz, a one-shot
latched initial pose) reaches the agent's state relay (nodes/state_relay.py) over real DDS: once
each, whether its writer is volatile or latched and whether it published before the relay's
readers were matched, and never a latched writer's old history replayed on a late match."""

import time

from std_msgs.msg import Int64
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from anyscale_manager.agent.catalogue import Entry
from anyscale_manager.nodes import state_relay
from anyscale_manager.nodes.state_relay import StateRelay
from spinning import RosContext

ENTRY = Entry('counter', ('sleep', '5'), state_topic='/sr_counter',
              restore_topic='/sr_counter/a/restore', restore_input='/sr_restore')
VOLATILE = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Relay:
    def __init__(self, ros):
        self.node = ros.node('sr_agent')
        self.lines = []
        self.relay = StateRelay(self.node, {'counter': ENTRY}, {'counter': 'std_msgs/msg/Int64'},
                                lambda level, text: self.lines.append((level, text)))
        self.taken = []

    def drain(self):
        _, requests = self.relay.drain(time.monotonic())
        self.taken += [deserialize_message(data, Int64).data for _, data in requests]
        return self.taken

    def close(self):
        self.relay.destroy()


def test_a_latched_one_shot_sent_before_the_match_and_a_volatile_one_are_each_taken_once():
    with RosContext() as ros:
        user = ros.node('sr_user')
        latched = user.create_publisher(Int64, ENTRY.restore_input, LATCHED)
        latched.publish(Int64(data=1))               # before the relay's readers exist
        relay = Relay(ros)
        try:
            ros.spin_until(lambda: relay.drain() == [1], 10.0, 'the latched one taken',
                           state=lambda: relay.taken)
            rviz = user.create_publisher(Int64, ENTRY.restore_input, VOLATILE)
            ros.spin_until(lambda: rviz.get_subscription_count() == 1, 10.0,
                           'the volatile writer matched by the volatile reader')
            rviz.publish(Int64(data=2))
            latched.publish(Int64(data=3))           # through both readers: taken once
            ros.spin_until(lambda: relay.drain()[1:] == [2, 3] or len(relay.taken) > 3, 10.0,
                           'the volatile and the latched message', state=lambda: relay.taken)
            ros.spin_for(0.5)
            assert relay.drain() == [1, 2, 3]
            assert relay.lines[-1][0] == 'info' and 'keeping its state' in relay.lines[-1][1]
        finally:
            relay.close()


def test_a_latched_writers_history_replayed_on_a_late_match_is_not_taken(monkeypatch):
    monkeypatch.setattr(state_relay, 'REQUEST_REPLAY_S', 0.3)
    with RosContext() as ros:
        user = ros.node('sr_user')
        latched = user.create_publisher(Int64, ENTRY.restore_input, LATCHED)
        latched.publish(Int64(data=7))
        sent = time.monotonic()
        ros.spin_until(lambda: time.monotonic() - sent > 0.6, 5.0, 'the message aged')
        relay = Relay(ros)
        try:
            ros.spin_until(lambda: relay.drain() or any('matched late' in t
                                                        for _, t in relay.lines),
                           10.0, 'the replayed message seen', state=lambda: relay.lines)
            ros.spin_for(0.3)
            assert relay.drain() == []
            said = [t for _, t in relay.lines if 'matched late' in t]
            assert len(said) == 1 and 'on /sr_restore sent' in said[0], relay.lines
        finally:
            relay.close()
