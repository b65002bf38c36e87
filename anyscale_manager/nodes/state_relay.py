"""The agent's hands on its nodes' state topics: it hears each one and hands a copy its state.

For each node of the catalogue that declares ``state:``, one reader of the state topic (depth
1, best effort: it matches any writer, and only the latest message is kept) on a node no
executor spins, taken by the agent's turn (``drain``): receiving costs DDS its copy of each
message, and Python one take per turn at most. Messages stay serialised: nothing here knows the
state's fields. And one writer of the copy's own restore topic (``Entry.restore_topic``, which
only this scale's copy subscribes to), reliable and transient-local so that it matches a restore
input of any reliability and durability (Nav2 AMCL's /initialpose is reliable, volatile). Each
started process has a restore topic of its own (``copy_restore_topic``): the writer follows the
live process's, so a reader of a process killed a moment ago (DDS counts it until its lease
ends, 20 s) never holds up the acknowledgement of the next one.

Messages that others publish on the node's own restore topic (RViz's "2D Pose Estimate" on
/initialpose) no longer reach a copy, whose input is remapped: two more readers of that topic
(reliable, as RViz publishes; one volatile, one transient-local for a latched writer's message
sent before the match) hand them to the copy that serves here.

A hand-over is published once the copy's restore input is matched, and counts as delivered when
the copy's reader has acknowledged it: the agent activates the copy only then, so the state is
there before the copy's first output. The type of a state topic the file does not declare is
learnt from the graph, at most once a second until it is known.
"""

from collections import deque
from typing import Any, Callable, Deque, List, Mapping, Optional, Tuple

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .workload_messages import EndpointError, message_class
from ..agent.catalogue import Entry

READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
WRITER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
# What others publish on a restore topic is read twice: by a volatile reader (it matches every
# writer, RViz's too) and by a transient-local one (it also gets what a latched writer sent
# before the two were matched: a one-shot initial pose published as its publisher starts).
REQUEST_QOS, LATCHED_REQUEST_QOS = (
    QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE,
               durability=durability)
    for durability in (DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL))
# A message of a latched writer delivered this long after it was sent is history replayed on a
# late match (a link back up, an agent started later), not a state set now: left out, said.
REQUEST_REPLAY_S = 3.0
REMEMBERED_REQUESTS = 32
LEARN_PERIOD_S = 1.0
# A hand-over's acknowledgement is waited for this long in the step that sends it (on one
# machine or a LAN it comes within milliseconds), then looked at again at each step.
ACK_WAIT = Duration(nanoseconds=20_000_000)
# (node, serialised message, writer's sequence number or -1)
Heard = Tuple[str, bytes, int]


class _Relay:
    """One stateful node's reader and its copy's restore writer."""

    def __init__(self, entry: Entry, msg_type: str):
        self.entry = entry
        self.msg_type = msg_type
        self.reader: Any = None
        self.writer: Any = None
        self.topic = ''                 # the writer's topic: the live process's restore topic
        self.cls: Any = None
        self.requests: Any = None
        self.latched: Any = None
        self.recent: Deque[tuple] = deque(maxlen=REMEMBERED_REQUESTS)   # taken, by its key


class StateRelay:
    def __init__(self, node: Node, catalogue: Mapping[str, Entry],
                 msg_types: Mapping[str, str], log: Callable[[str, str], None]):
        self._node = node
        self._log = log
        self._relays = {name: _Relay(e, msg_types.get(name, ''))
                        for name, e in catalogue.items() if e.state_topic and e.startable}
        # The readers live on a node no executor spins: taken by ``drain``, never called back.
        self._watch: Optional[Node] = Node(
            f'{node.get_name()}_state', context=node.context,
            start_parameter_services=False) if self._relays else None
        self._learnt_at = -float('inf')
        for relay in self._relays.values():
            if relay.msg_type:
                self._open(relay)

    @property
    def nodes(self) -> Tuple[str, ...]:
        return tuple(self._relays)

    def _open(self, relay: _Relay) -> None:
        try:
            cls = message_class(relay.msg_type)
        except EndpointError as e:
            self._log('error', f'{relay.entry.name}: its state cannot be kept: {e}')
            relay.msg_type = ''
            return
        assert self._watch is not None
        relay.reader = self._watch.create_subscription(
            cls, relay.entry.state_topic, lambda _m: None, READER_QOS, raw=True)
        relay.cls = cls
        relay.requests = self._watch.create_subscription(
            cls, relay.entry.restore_input, lambda _m: None, REQUEST_QOS, raw=True)
        relay.latched = self._watch.create_subscription(
            cls, relay.entry.restore_input, lambda _m: None, LATCHED_REQUEST_QOS, raw=True)
        self._log('info', f'{relay.entry.name}: keeping its state from '
                          f'{relay.entry.state_topic} ({relay.msg_type}); each copy started here '
                          f'takes it on a topic of its own under {relay.entry.restore_topic}')

    def _learn_types(self, now: float) -> None:
        waiting = [r for r in self._relays.values() if r.reader is None and not r.msg_type]
        if not waiting or now - self._learnt_at < LEARN_PERIOD_S:
            return
        self._learnt_at = now
        types = dict(self._node.get_topic_names_and_types())
        for relay in waiting:
            found = types.get(relay.entry.state_topic) or []
            if len(found) == 1:
                relay.msg_type = found[0]
                self._open(relay)

    def drain(self, now: float) -> Tuple[List[Heard], List[Tuple[str, bytes]]]:
        """The messages heard on each state topic since the last drain (the latest only), and
        those published by others on each node's own restore topic (every one)."""
        self._learn_types(now)
        heard: List[Heard] = []
        requests: List[Tuple[str, bytes]] = []
        for name, relay in self._relays.items():
            if relay.reader is None:
                continue
            with relay.reader.handle:
                taken = relay.reader.handle.take_message(relay.reader.msg_type, True)
            if taken is not None:
                info = taken[1] if len(taken) > 1 and isinstance(taken[1], dict) else {}
                heard.append((name, taken[0],
                              int(info.get('publication_sequence_number', -1))))
            for reader in (relay.requests, relay.latched):
                requests += [(name, data) for data in self._take_requests(relay, reader)]
        return heard, requests

    def _take_requests(self, relay: _Relay, reader: Any) -> List[bytes]:
        """What others published on the node's restore topic, once each (a latched writer's
        message comes through both readers), history replayed on a late match left out."""
        out: List[bytes] = []
        with reader.handle:
            for _ in range(5):
                taken = reader.handle.take_message(reader.msg_type, True)
                if taken is None:
                    break
                data = taken[0]
                info = taken[1] if len(taken) > 1 and isinstance(taken[1], dict) else {}
                key = (info.get('source_timestamp'), info.get('publication_sequence_number'),
                       data)
                if key in relay.recent:
                    continue
                relay.recent.append(key)
                sent, received = info.get('source_timestamp'), info.get('received_timestamp')
                if sent and received and (received - sent) / 1e9 > REQUEST_REPLAY_S:
                    self._log('info', f'{relay.entry.name}: a message on '
                                      f'{relay.entry.restore_input} sent '
                                      f'{(received - sent) / 1e9:.1f} s ago reached this agent '
                                      'only now (a latched writer matched late): not taken as '
                                      'its state')
                    continue
                out.append(data)
        return out

    def _writer(self, name: str, topic: str) -> Any:
        """The node's writer, on ``topic`` (made anew when the live process changed)."""
        relay = self._relays.get(name)
        if relay is None or relay.cls is None:
            return None
        if relay.topic != topic:
            if relay.writer is not None:
                self._node.destroy_publisher(relay.writer)
            relay.writer = self._node.create_publisher(relay.cls, topic, WRITER_QOS)
            relay.topic = topic
        return relay.writer

    def ready(self, name: str, topic: str) -> bool:
        """Whether a hand-over can go out now: the process subscribes to its restore topic."""
        writer = self._writer(name, topic)
        return writer is not None and writer.get_subscription_count() > 0

    def send(self, name: str, topic: str, data: bytes) -> None:
        self._writer(name, topic).publish(data)

    def delivered(self, name: str, topic: str) -> bool:
        """Whether the process's reader acknowledged what was sent (waits ACK_WAIT at most)."""
        writer = self._writer(name, topic)
        return writer is not None and writer.wait_for_all_acked(ACK_WAIT)

    def destroy(self) -> None:
        for relay in self._relays.values():
            if relay.writer is not None:
                self._node.destroy_publisher(relay.writer)
        self._relays.clear()
        if self._watch is not None:
            self._watch.destroy_node()          # and its readers
            self._watch = None
