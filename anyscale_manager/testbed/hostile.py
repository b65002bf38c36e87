"""A hostile publisher on the deployment's domain: forged, replayed and malformed messages.

    python -m anyscale_manager.testbed.hostile --deployment-file FILE [--duration 6]
                                               [--rate-hz 20] [--seed N]

A plain rclpy process with no key, as a script on the domain would be. For ``--duration``
seconds it sends, at ``--rate-hz``, one message at a time drawn from ``Forger``: layouts that
would move every node (no identity and generation 10**15; a made-up decider that claims to have
started first, signed with a key of its own; the real decider's identity with a far sequence
number); real layouts and agent states heard on the domain, sent again (replays); agent states
claiming that a scale runs nothing; objectives in the decider's name; and malformed payloads on
every project topic (not JSON, NaN, unknown fields, wrong types, deep nesting, a layout of
another deployment, out-of-bound numbers, one payload over the size limit). Well-formed
forged monitor reports (a link reported down, a scale reported full) are tested on their own,
with real processes, in test/test_decider_authority.py. It prints what it sent, by label, as
one JSON line, and exits 0. The test-bed's soak runs it (docs/testbed.md).
"""

import argparse
import json
import random
import sys
import time
from typing import Dict, List, Optional, Tuple

from .. import protocol as p
from ..model.loader import load_deployment
from ..model.types import Deployment
from ..protocol_auth import sign
from ..interrupt import restore_ctrl_c

GARBAGE = (
    'not json', '{', '[]', 'null', '42', '""', '{"generation": NaN}',
    '{"generation": Infinity, "deployment": "x"}',
)
PROJECT_TOPICS = (p.TOPIC_LAYOUT, p.TOPIC_AGENT_STATE, p.TOPIC_SCALE_STATUS,
                  p.TOPIC_LINK_STATUS, p.TOPIC_CONNECTION_STATUS, p.TOPIC_OBJECTIVE)
LABELS = {'layout_anonymous': 2.0, 'layout_own_key': 2.0, 'layout_stolen_identity': 2.0,
          'layout_replay': 2.0, 'layout_other_deployment': 1.0, 'state_forged': 2.0,
          'state_replay': 1.5, 'objective_forged': 1.0, 'malformed': 5.0}


class Forger:
    """Draws hostile messages (topic, JSON text, label). Pure: clock and randomness passed in."""

    def __init__(self, deployment: Deployment, rng: random.Random):
        self.deployment = deployment
        self.rng = rng
        self.own_key = bytes(rng.randrange(256) for _ in range(32))
        self.heard: Dict[str, List[str]] = {p.TOPIC_LAYOUT: [], p.TOPIC_AGENT_STATE: []}
        self.seq = 0
        self.oversized_sent = False

    def hear(self, topic: str, text: str) -> None:
        """A real message (to replay later); the last 20 per topic are kept."""
        kept = self.heard.get(topic)
        if kept is not None and text not in kept:
            kept.append(text)
            del kept[:-20]

    def _real_layout(self) -> Optional[p.Layout]:
        for text in reversed(self.heard[p.TOPIC_LAYOUT]):
            try:
                layout = p.Layout.from_json(text)
            except p.ProtocolError:
                continue
            if layout.decider is not None:
                return layout
        return None

    def _assignments(self) -> Dict[str, str]:
        """Every managed node off the master: applied, it would stop the master's nodes."""
        remote = [s.name for s in self.deployment.remote_scales]
        return {n.name: self.rng.choice(remote) for n in self.deployment.nodes if n.managed}

    def _layout(self, **fields) -> Dict[str, object]:
        self.seq += 1
        data = {'generation': 10 ** 15, 'deployment': self.deployment.name,
                'assignments': self._assignments(), 'reason': 'hostile', 'stamp': time.time()}
        data.update(fields)
        return data

    def draw(self, now_wall: float) -> Tuple[str, str, str]:
        labels = list(LABELS)
        label = self.rng.choices(labels, [LABELS[k] for k in labels])[0]
        real = self._real_layout()
        if label in ('layout_replay', 'layout_stolen_identity', 'objective_forged') \
                and real is None:
            label = 'layout_anonymous'
        if label == 'state_replay' and not self.heard[p.TOPIC_AGENT_STATE]:
            label = 'state_forged'
        if label == 'layout_anonymous':
            return p.TOPIC_LAYOUT, json.dumps(self._layout(stamp=now_wall)), label
        if label == 'layout_own_key':
            data = self._layout(stamp=now_wall, seq=self.seq, decider={
                'id': f'{self.rng.getrandbits(64):016x}', 'host': 'hostile', 'pid': 1,
                'started': 0.0})
            data['auth'] = sign(self.own_key, data)
            return p.TOPIC_LAYOUT, json.dumps(data), label
        if label == 'layout_stolen_identity':
            data = self._layout(stamp=now_wall, seq=(real.seq or 0) + 10 ** 6,
                                generation=real.generation + 1,
                                decider=real.decider.to_dict())
            data['auth'] = real.auth or sign(self.own_key, data)    # not this content's
            return p.TOPIC_LAYOUT, json.dumps(data), label
        if label == 'layout_replay':
            return p.TOPIC_LAYOUT, self.rng.choice(self.heard[p.TOPIC_LAYOUT]), label
        if label == 'layout_other_deployment':
            return (p.TOPIC_LAYOUT,
                    json.dumps(self._layout(stamp=now_wall, deployment='another_robot')), label)
        if label == 'state_forged':
            scale = self.rng.choice(list(self.deployment.scale_names))
            data = {'scale': scale, 'generation': 10 ** 15, 'stamp': now_wall,
                    'instance': f'{self.rng.getrandbits(32):08x}', 'seq': self.seq,
                    'nodes': {n.name: {'state': 'stopped', 'pid': 0, 'since': now_wall,
                                       'restarts': 0, 'ready': False, 'exit_reason': ''}
                              for n in self.deployment.nodes if n.managed}}
            if self.rng.random() < 0.5:
                data['auth'] = sign(self.own_key, data)
            self.seq += 1
            return p.TOPIC_AGENT_STATE, json.dumps(data), label
        if label == 'state_replay':
            return p.TOPIC_AGENT_STATE, self.rng.choice(self.heard[p.TOPIC_AGENT_STATE]), label
        if label == 'objective_forged':
            self.seq += 1
            data = {'stamp': now_wall, 'perf_map': 1.0, 'integral': 1.0, 'elapsed_s': 1.0,
                    'decider': real.decider.id, 'seq': (real.seq or 0) + 10 ** 6}
            return p.TOPIC_OBJECTIVE, json.dumps(data), label
        return self._malformed(now_wall)

    def _malformed(self, now_wall: float) -> Tuple[str, str, str]:
        topic = self.rng.choice(PROJECT_TOPICS)
        kind = self.rng.randrange(8)
        if kind == 0 and not self.oversized_sent:
            self.oversized_sent = True
            return p.TOPIC_LAYOUT, json.dumps(
                self._layout(reason='x' * (p.MAX_PAYLOAD_BYTES + 10))), 'malformed'
        if kind == 1:
            return topic, '[' * 5000 + ']' * 5000, 'malformed'
        if kind == 2:
            return topic, json.dumps(self._layout(command=['rm', '-rf', '/'])), 'malformed'
        if kind == 3:
            return topic, json.dumps(self._layout(generation=-5)), 'malformed'
        if kind == 4:
            return topic, json.dumps(self._layout(generation=2 ** 60)), 'malformed'
        if kind == 5:
            return topic, json.dumps({'scale': 7, 'stamp': 'now', 'nodes': [],
                                      'cpu_total': None, 'up': 'yes'}), 'malformed'
        if kind == 6:
            return topic, json.dumps({'scale': 'robot', 'stamp': now_wall, 'cpu_total': 1e300,
                                      'capacity_cpu': -1.0, 'cpu_by_node': {'': 1.0},
                                      'mem_percent': 0.0, 'load_1m': 0.0}), 'malformed'
        return topic, self.rng.choice(GARBAGE), 'malformed'


def main(args: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.utilities import remove_ros_args
    from std_msgs.msg import String

    from ..nodes import qos
    from ..nodes.shutdown import shut_rclpy_down

    argv = sys.argv if args is None else args
    parser = argparse.ArgumentParser(prog='hostile')
    parser.add_argument('--deployment-file', required=True)
    parser.add_argument('--duration', type=float, default=6.0)
    parser.add_argument('--rate-hz', type=float, default=20.0)
    parser.add_argument('--seed', type=int, default=0)
    a = parser.parse_args(remove_ros_args(argv)[1:])
    if not (a.duration >= 0 and a.rate_hz > 0):
        print('hostile: --duration must be >= 0 and --rate-hz > 0', file=sys.stderr)
        return 2
    forger = Forger(load_deployment(a.deployment_file), random.Random(a.seed))
    rclpy.init(args=argv)
    node = None
    sent: Dict[str, int] = {}
    try:
        node = Node('anyscale_hostile')
        profiles = {p.TOPIC_LAYOUT: qos.LATCHED, p.TOPIC_AGENT_STATE: qos.LATCHED}
        pubs = {t: node.create_publisher(String, t, profiles.get(t, qos.STATUS))
                for t in PROJECT_TOPICS}
        for topic in (p.TOPIC_LAYOUT, p.TOPIC_AGENT_STATE):
            node.create_subscription(String, topic,
                                     lambda m, t=topic: forger.hear(t, m.data),
                                     qos.LATCHED_READER)
        end = time.monotonic() + a.duration
        period = 1.0 / a.rate_hz
        next_at = time.monotonic()
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=max(0.0, next_at - time.monotonic()))
            if time.monotonic() >= next_at:
                topic, text, label = forger.draw(time.time())
                pubs[topic].publish(String(data=text))
                sent[label] = sent.get(label, 0) + 1
                next_at += period
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        shut_rclpy_down()
    print(json.dumps({'sent': sent}, sort_keys=True), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
