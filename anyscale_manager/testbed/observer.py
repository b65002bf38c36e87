"""The harness's eyes: an rclpy node that prints what it sees as JSON lines on stdout.

    python -m anyscale_manager.testbed.observer [--topic /amcl_pose[:TYPE] ...]
                                                [--project TOPIC ...]

Started by the harness inside the robot's namespace (next to the decider), outside any CPU
quota; a second one, with ``--project /anyscale/agent_state`` only, listens on the laptop, so that
the laptop agent's reports are heard while the link is cut. It subscribes to every project
topic (or only those given with ``--project``) and, raw, to the given data topics, and writes one
JSON object per line: ``{"t": <monotonic>, "topic": ..., "data": <the String's JSON text>}`` for
project messages and ``{"t": ..., "arrivals": {topic: [monotonic, ...]}, "seqs": {topic: [n,
...]}, "sent": {topic: [monotonic, ...]}}`` every 0.2 s for the data topics (``seqs``: each
message's publication sequence number, -1 where the middleware gives none; every DDS writer
counts its own from 1, so two copies of a node publishing at once show as two interleaved
series; ``sent``: when its writer sent it, from the source timestamp, null where the
middleware gives none: a writer that stalled shows there, a path that held its messages back
does not), ``{"t": ..., "poses": {topic:
[[monotonic, x, y, stamp, yaw], ...]}}`` for the ``--pose`` topics (a node's state, a pose)
and ``{"t": ..., "set_poses": {topic: [[monotonic, x, y, stamp, yaw], ...]}}`` for the
``--set-pose`` topics (a pose someone sets on a node's restore topic: a user's initial pose).
CLOCK_MONOTONIC is the same in every network namespace, so the harness can put these times next
to its own (link cuts, kills). It parses nothing but those poses: judging is the harness's job.
"""

import argparse
import json
import sys
import time
from typing import Dict, List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from std_msgs.msg import String

from .. import protocol as p
from ..nodes import qos
from ..nodes.monitors.clocks import clock_offset_s
from ..nodes.monitors.probes import received_at
from ..nodes.workload_messages import DEFAULT_TYPE, message_class
from ..nodes.workload_pose import yaw_of
from ..interrupt import restore_ctrl_c
from ..nodes.shutdown import shut_rclpy_down

LATCHED = qos.LATCHED_READER
RELIABLE = qos.EVENTS
BEST_EFFORT = qos.PROBE
PROJECT_TOPICS = {
    p.TOPIC_LAYOUT: LATCHED, p.TOPIC_AGENT_STATE: LATCHED, p.TOPIC_EVENTS: RELIABLE,
    p.TOPIC_SCALE_STATUS: RELIABLE, p.TOPIC_LINK_STATUS: RELIABLE,
    p.TOPIC_CONNECTION_STATUS: RELIABLE, p.TOPIC_OBJECTIVE: RELIABLE,
}
FLUSH_S = 0.2


class Observer(Node):
    def __init__(self, data_topics: List[str], out=sys.stdout,
                 project_topics: Optional[List[str]] = None, pose_topics: List[str] = (),
                 set_pose_topics: List[str] = ()):
        """``data_topics``: ``TOPIC[:TYPE]`` each (the type a raw subscription needs to match
        its writers; std_msgs/msg/UInt8MultiArray when left out). ``pose_topics``: topics of
        geometry_msgs/msg/PoseWithCovarianceStamped whose poses are written too (a node's
        state: the end-to-end tests judge that it does not jump). ``set_pose_topics``: the
        restore topics on which someone may set such a pose (a user's initial pose, which the
        agents hand to the serving copy: a jump asked for)."""
        super().__init__('anyscale_testbed_observer')
        self._out = out
        types = dict((t.split(':', 1) + [DEFAULT_TYPE])[:2] for t in data_topics)
        data_topics = list(types)
        self._arrivals: Dict[str, List[float]] = {t: [] for t in data_topics}
        self._offset_s = clock_offset_s()     # system clock minus monotonic, renewed each flush
        self._seqs: Dict[str, List[int]] = {t: [] for t in data_topics}
        self._sent: Dict[str, List[Optional[float]]] = {t: [] for t in data_topics}
        for topic, profile in PROJECT_TOPICS.items():
            if project_topics is None or topic in project_topics:
                self.create_subscription(String, topic, self._project(topic), profile)
        for topic in data_topics:
            self.create_subscription(message_class(types[topic]), topic, self._data(topic),
                                     BEST_EFFORT, raw=True)
        self._poses: Dict[str, List[list]] = {t: [] for t in pose_topics}
        self._set_poses: Dict[str, List[list]] = {t: [] for t in set_pose_topics}
        if pose_topics or set_pose_topics:
            from geometry_msgs.msg import PoseWithCovarianceStamped
            for topic in pose_topics:
                self.create_subscription(PoseWithCovarianceStamped, topic,
                                         self._pose(topic, self._poses), BEST_EFFORT)
            for topic in set_pose_topics:
                # Reliable and transient-local: a pose set once (latched) when this reader
                # was not matched yet is still heard; each keeps its own stamp.
                self.create_subscription(PoseWithCovarianceStamped, topic,
                                         self._pose(topic, self._set_poses), LATCHED)
        self.create_timer(FLUSH_S, self._flush)
        self._write({'t': time.monotonic(), 'ready': True})

    def _write(self, obj) -> None:
        self._out.write(json.dumps(obj, separators=(',', ':')) + '\n')
        self._out.flush()

    def _project(self, topic: str):
        def callback(msg: String) -> None:
            self._write({'t': time.monotonic(), 'topic': topic, 'data': msg.data})
        return callback

    def _data(self, topic: str):
        def callback(_raw: bytes, info) -> None:
            # Each message at its DDS reception time, as the probes place it: this process
            # runs its callbacks late and in bursts when the machine is busy, and a burst
            # stamped at callback time would show gaps no subscriber lived through.
            self._arrivals[topic].append(received_at(info, self._offset_s, time.monotonic()))
            seq = info.get('publication_sequence_number') if isinstance(info, dict) else None
            self._seqs[topic].append(seq if isinstance(seq, int) else -1)
            sent_ns = info.get('source_timestamp', 0) if isinstance(info, dict) else 0
            self._sent[topic].append(sent_ns / 1e9 - self._offset_s if sent_ns else None)
        return callback

    def _pose(self, topic: str, kept: Dict[str, List[list]]):
        def callback(msg) -> None:
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9
            p, o = msg.pose.pose.position, msg.pose.pose.orientation
            yaw = yaw_of(o.z, o.w) if abs(o.z) + abs(o.w) > 0.0 else 0.0
            kept[topic].append([time.monotonic(), p.x, p.y, stamp, yaw])
        return callback

    def _flush(self) -> None:
        self._offset_s = clock_offset_s()
        for key, kept in (('poses', self._poses), ('set_poses', self._set_poses)):
            batch = {t: v for t, v in kept.items() if v}
            if batch:
                self._write({'t': time.monotonic(), key: batch})
                for topic in batch:
                    kept[topic] = []
        batch = {t: a for t, a in self._arrivals.items() if a}
        if batch:
            # In reception order (DDS threads may hand over two messages out of order).
            order = {t: sorted(range(len(a)), key=a.__getitem__) for t, a in batch.items()}
            self._write({'t': time.monotonic(),
                         'arrivals': {t: [batch[t][i] for i in order[t]] for t in batch},
                         'seqs': {t: [self._seqs[t][i] for i in order[t]] for t in batch},
                         'sent': {t: [None if self._sent[t][i] is None
                                      else round(self._sent[t][i], 6) for i in order[t]]
                                  for t in batch}})
            for topic in batch:
                self._arrivals[topic] = []
                self._seqs[topic] = []
                self._sent[topic] = []


def main(args: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    argv = sys.argv if args is None else args
    parser = argparse.ArgumentParser(prog='observer')
    parser.add_argument('--topic', action='append', default=[], metavar='TOPIC[:TYPE]')
    parser.add_argument('--project', action='append', choices=sorted(PROJECT_TOPICS),
                        help='listen to only these project topics (default: all of them)')
    parser.add_argument('--pose', action='append', default=[], metavar='TOPIC',
                        help='also write the poses of this PoseWithCovarianceStamped topic')
    parser.add_argument('--set-pose', action='append', default=[], metavar='TOPIC',
                        help='also write the poses set on this restore topic, with their yaw')
    a = parser.parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    node = None
    try:
        node = Observer(a.topic, project_topics=a.project, pose_topics=a.pose,
                        set_pose_topics=a.set_pose)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException, BrokenPipeError):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        shut_rclpy_down()
    return 0


if __name__ == '__main__':
    sys.exit(main())
