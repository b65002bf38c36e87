"""One decider per deployment: what a decider concludes from another one's layouts.

Pure, clocks passed in. A rival is another decider id publishing layouts of this deployment
(authenticated when there is a key). It is live when its last message arrived within
``lease_s`` and either its stamp is within ``lease_s`` of this clock or it published again
while we listened (a live decider re-publishes every ``lease_s / 3``; a latched message of a
frozen one is old). The rule, the same seen from both sides: the decider that started first
(``started``, then ``id`` to break a tie) keeps the deployment; a decider that finds a live
older one stops (exit 2), before it publishes anything when it finds it while starting. So two
deciders never both publish for longer than one re-publication period once they hear each other.
"""

from dataclasses import dataclass
from typing import Dict, List, Optional

from ..protocol import DeciderIdentity


def older(a: DeciderIdentity, b: DeciderIdentity) -> bool:
    """Whether ``a`` keeps the deployment against ``b``."""
    return (a.started, a.id) < (b.started, b.id)


@dataclass
class _Heard:
    identity: DeciderIdentity
    received: float     # monotonic, ours
    stamp: float        # its wall clock
    first_seq: Optional[int]
    last_seq: Optional[int]


class RivalWatch:
    def __init__(self, me: DeciderIdentity, lease_s: float):
        self.me = me
        self.lease_s = lease_s
        self._heard: Dict[str, _Heard] = {}

    def heard(self, other: DeciderIdentity, seq: Optional[int], stamp: float,
              now: float) -> None:
        if other.id == self.me.id:
            return
        h = self._heard.get(other.id)
        if h is None:
            if len(self._heard) > 64:     # bounded: drop the stalest
                del self._heard[min(self._heard, key=lambda k: self._heard[k].received)]
            self._heard[other.id] = _Heard(other, now, stamp, seq, seq)
            return
        h.identity, h.received, h.stamp, h.last_seq = other, now, stamp, seq

    def live(self, now: float, now_wall: float) -> List[DeciderIdentity]:
        out = []
        for h in self._heard.values():
            if now - h.received > self.lease_s:
                continue
            advanced = (h.first_seq is not None and h.last_seq is not None
                        and h.last_seq > h.first_seq)
            if advanced or abs(now_wall - h.stamp) <= self.lease_s:
                out.append(h.identity)
        return sorted(out, key=lambda i: (i.started, i.id))

    def must_stop(self, now: float, now_wall: float, started: bool) -> Optional[str]:
        """Why this decider must stop (exit 2), or None. ``started``: it publishes already."""
        rivals = self.live(now, now_wall)
        if not started and rivals:
            r = rivals[0]
            return (f'another decider of this deployment is live: {r.describe()}, started at '
                    f'{r.started:.3f}; not starting a second one (stop it first, or wait '
                    f'{self.lease_s:g} s after it stopped)')
        first = [r for r in rivals if older(r, self.me)]
        if first:
            r = first[0]
            return (f'another decider of this deployment publishes: {r.describe()}, started at '
                    f'{r.started:.3f}, before this one ({self.me.started:.3f}); the first one '
                    'keeps the deployment, this one stops')
        return None

    def younger(self, now: float, now_wall: float) -> List[DeciderIdentity]:
        """Live rivals that started after this decider (they are to stop)."""
        return [r for r in self.live(now, now_wall) if older(self.me, r)]
