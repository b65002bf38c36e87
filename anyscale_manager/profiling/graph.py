"""What the profile saw of the ROS graph, and what it leaves out. Pure: snapshots in.

Left out: hidden nodes (a name starting with ``_``, as ``ros2 node list`` hides them), the
project's own nodes (the decider, agents and their handover nodes, ``status``, the test-bed's
observer, the profiler itself), hidden topics (a token starting with ``_``), the topics every
node has (``/rosout``, ``/parameter_events``) and the project's topics (``/anyscale/...``).
"""

import re
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Set, Tuple

from .. import protocol

# The names the project's nodes take (nodes/decider.py NODE_NAME, nodes/agent.py
# 'anyscale_agent_<scale>' and '<that>_state', nodes/status.py 'anyscale_status_<pid>',
# testbed/observer.py, and profiling/watch.py 'anyscale_profile_<pid>').
PROJECT_NODE_RE = re.compile(
    r'^anyscale_(decider|agent_[A-Za-z0-9_]+|status_[0-9]+|testbed_observer|profile_[0-9]+)$')
INFRASTRUCTURE_TOPICS = frozenset({'/rosout', '/parameter_events'})
MSG_TYPE_RE = re.compile(r'^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$')
PUB, SUB = 'publisher', 'subscription'


def full_name(name: str, namespace: str) -> str:
    """'/ns/name' from a node's name and namespace ('/' is the root)."""
    ns = namespace.rstrip('/')
    return f'{ns}/{name}' if ns.startswith('/') or not ns else f'/{ns}/{name}'


def base_name(full: str) -> str:
    return full.rstrip('/').rsplit('/', 1)[-1]


def namespace_of(full: str) -> str:
    ns = full.rstrip('/').rsplit('/', 1)[0]
    return ns or '/'


def is_hidden_node(full: str) -> bool:
    return base_name(full).startswith('_')


def is_project_node(full: str) -> bool:
    return bool(PROJECT_NODE_RE.match(base_name(full)))


def kept_node(full: str) -> bool:
    return not is_hidden_node(full) and not is_project_node(full)


def skipped_topic(topic: str) -> str:
    """Why ``topic`` is left out of the profile ('' when it is kept)."""
    if topic in INFRASTRUCTURE_TOPICS:
        return 'every node has it'
    if topic == protocol.PREFIX or topic.startswith(protocol.PREFIX + '/'):
        return "the project's own topic"
    if any(token.startswith('_') for token in topic.split('/') if token):
        return 'hidden'
    return ''


@dataclass(frozen=True)
class Endpoint:
    """One publisher or subscription as the graph reports it."""

    node: str                 # the node's full name, '/ns/name'
    topic: str
    msg_type: str             # 'pkg/msg/Type'
    kind: str                 # PUB or SUB
    gid: bytes = b''          # the DDS endpoint GUID (16 bytes with Fast DDS)
    reliable: bool = True
    transient_local: bool = False


@dataclass(frozen=True)
class Edge:
    """One connection: a topic from one publisher node to one subscriber node."""

    topic: str
    publisher: str
    subscriber: str
    msg_type: str


@dataclass(frozen=True)
class TopicPlan:
    """How the profiler subscribes to a topic: its type, and QoS every publisher matches."""

    topic: str
    msg_type: str
    reliable: bool            # every publisher is reliable: a reliable reader loses nothing
    transient_local: bool     # every publisher is transient local: the latched sample comes too
    types: Tuple[str, ...] = ()   # every type its publishers declare (more than one: a problem)


@dataclass
class NodeSeen:
    first_s: float
    last_s: float
    copies: int = 1           # the most processes seen at once under this name


@dataclass
class GraphSeen:
    """The union of the graph snapshots taken during the watch."""

    nodes: Dict[str, NodeSeen] = field(default_factory=dict)
    endpoints: Set[Endpoint] = field(default_factory=set)

    def add(self, now: float, nodes: Iterable[str], endpoints: Iterable[Endpoint]) -> None:
        """One snapshot: every node's full name (a name twice: two nodes of that name) and
        every endpoint of every topic."""
        counts: Dict[str, int] = {}
        for name in nodes:
            counts[name] = counts.get(name, 0) + 1
        for name, copies in counts.items():
            seen = self.nodes.get(name)
            if seen is None:
                self.nodes[name] = NodeSeen(now, now, copies)
            else:
                seen.last_s = now
                seen.copies = max(seen.copies, copies)
        self.endpoints.update(endpoints)

    def kept_nodes(self) -> List[str]:
        """Every node kept in the profile, sorted; a node seen only through its endpoints
        counts too."""
        names = set(self.nodes) | {e.node for e in self.endpoints}
        return sorted(n for n in names if kept_node(n))

    def edges(self) -> List[Edge]:
        """One edge per (topic, publisher node, subscriber node) between kept nodes."""
        pubs: Dict[str, Dict[str, str]] = {}
        subs: Dict[str, Set[str]] = {}
        for e in self.endpoints:
            if skipped_topic(e.topic) or not kept_node(e.node):
                continue
            if e.kind == PUB:
                pubs.setdefault(e.topic, {}).setdefault(e.node, e.msg_type)
            else:
                subs.setdefault(e.topic, set()).add(e.node)
        out = [Edge(topic, pub, sub, msg_type)
               for topic, writers in pubs.items() for pub, msg_type in writers.items()
               for sub in subs.get(topic, ()) if sub != pub]
        return sorted(out, key=lambda e: (e.topic, e.publisher, e.subscriber))

    def topic_plans(self) -> Dict[str, TopicPlan]:
        """The topics of the edges, each with the QoS that matches every publisher seen."""
        wanted = {e.topic for e in self.edges()}
        writers: Dict[str, List[Endpoint]] = {}
        for e in self.endpoints:
            if e.topic in wanted and e.kind == PUB:
                writers.setdefault(e.topic, []).append(e)
        out = {}
        for topic, ends in sorted(writers.items()):
            types = tuple(sorted({e.msg_type for e in ends}))
            out[topic] = TopicPlan(topic=topic, msg_type=types[0],
                                   reliable=all(e.reliable for e in ends),
                                   transient_local=all(e.transient_local for e in ends),
                                   types=types)
        return out

    def gids(self, node: str) -> Set[bytes]:
        return {e.gid for e in self.endpoints if e.node == node and e.gid}

    def publishes(self, node: str) -> List[str]:
        return sorted({e.topic for e in self.edges() if e.publisher == node})

    def subscribes(self, node: str) -> List[str]:
        return sorted({e.topic for e in self.edges() if e.subscriber == node})

    def publishes_type(self, node: str, msg_type: str) -> bool:
        """Whether ``node`` publishes a topic of ``msg_type``, whoever listens (a lifecycle
        node's transition events go to its manager, often no node of the profile)."""
        return any(e.node == node and e.kind == PUB and e.msg_type == msg_type
                   for e in self.endpoints)

    def seen(self, node: str) -> Optional[NodeSeen]:
        return self.nodes.get(node)
