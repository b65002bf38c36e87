"""One subscription per topic and QoS in a process, its messages handed to every reader.

Every message a subscription takes costs the executor a dispatch (about 0.2 ms of Python here,
whatever the callback does). On the master scale the agent, its link monitor and the decider
read the same topics (the agents' reports, the layout): three subscriptions took every report
three times. ``Readers`` gives a process one subscription per (topic, message type, QoS) and
calls each reader's callback in turn; one that raises is logged and the others still get the
message.

The subscriptions belong to the process's longest-lived node (``open``: the agent's). A reader
that subscribes before it (the master's decider, built first) is attached when it opens; a
reader that goes (``drop``, the decider at a stop) is detached, and a subscription nobody reads
any more is destroyed.
"""

import traceback
from typing import Any, Callable, Dict, List, Optional, Tuple

from rclpy.node import Node
from rclpy.qos import QoSProfile

Key = Tuple[str, Any, Tuple]


def _qos_key(profile: QoSProfile) -> Tuple:
    return (profile.history, profile.depth, profile.reliability, profile.durability)


class Readers:
    def __init__(self):
        self._owner: Optional[Node] = None
        self._subs: Dict[Key, Any] = {}
        self._callbacks: Dict[Key, List[Tuple[object, Callable]]] = {}
        self._qos: Dict[Key, QoSProfile] = {}

    def open(self, owner: Node) -> None:
        """The node that owns the subscriptions; those asked for before it are made now."""
        self._owner = owner
        for key in list(self._callbacks):
            self._make(key)

    def subscribe(self, reader: object, msg_type: Any, topic: str, profile: QoSProfile,
                  callback: Callable) -> None:
        """``callback(msg)`` for every message of ``topic``; ``reader`` names it for ``drop``."""
        key = (topic, msg_type, _qos_key(profile))
        self._qos[key] = profile
        self._callbacks.setdefault(key, []).append((reader, callback))
        if self._owner is not None and key not in self._subs:
            self._make(key)

    def drop(self, reader: object) -> None:
        """Stop calling ``reader``; destroy what nobody reads any more."""
        for key in list(self._callbacks):
            left = [(r, c) for r, c in self._callbacks[key] if r is not reader]
            self._callbacks[key] = left
            if not left:
                del self._callbacks[key]
                sub = self._subs.pop(key, None)
                if sub is not None and self._owner is not None:
                    self._owner.destroy_subscription(sub)

    def count(self) -> int:
        """How many subscriptions the process holds through this object."""
        return len(self._subs)

    def _make(self, key: Key) -> None:
        if key in self._subs:
            return
        topic, msg_type, _ = key
        self._subs[key] = self._owner.create_subscription(
            msg_type, topic, lambda msg, key=key: self._deliver(key, msg), self._qos[key])

    def _deliver(self, key: Key, msg: Any) -> None:
        for _, callback in list(self._callbacks.get(key, ())):
            try:
                callback(msg)
            except Exception:  # noqa: B902 - one reader's bug must not starve the others
                self._owner.get_logger().error(
                    f'a reader of {key[0]} failed:\n{traceback.format_exc()}')


def subscribe(node: Node, readers: Optional[Readers], reader: object, msg_type: Any,
              topic: str, profile: QoSProfile, callback: Callable) -> None:
    """Through ``readers`` when the process shares them, else a subscription of ``node``'s."""
    if readers is None:
        node.create_subscription(msg_type, topic, callback, profile)
    else:
        readers.subscribe(reader, msg_type, topic, profile, callback)


__all__ = ['Readers', 'subscribe']
