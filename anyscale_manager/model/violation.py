"""A broken constraint, one type for the planners' layout check and the runtime's constraints."""

from dataclasses import dataclass
from typing import Tuple


@dataclass(frozen=True)
class Violation:
    """One broken constraint, with a reason a person can read.

    ``kind``: the planners' placement, residence, coresidence, cpu, bandwidth, no_link,
    setting; the runtime's frequency, cpu, bandwidth, link_down, stale. ``nodes``: the nodes
    off the master whose return would address it (the runtime's; the planners leave it empty).
    """

    kind: str
    subject: str                   # the node, connection, scale or link concerned
    reason: str
    nodes: Tuple[str, ...] = ()

    def __str__(self) -> str:
        return self.reason
