"""Whose layouts an agent follows: exactly one decider, changed only when its lease lapses.

Pure, clock passed in. The followed decider re-publishes its layout at least every
``lease_s / 3``; each message of it renews the lease. A layout of another decider is refused
while the lease holds, and accepted (the agent then follows its sender) once the followed one
has been silent for ``lease_s``, or when the agent follows none yet. A layout that names no
decider (an older decider, or a plain script) counts as one anonymous decider. Generations are
compared within one decider only: a new decider's first layout is taken whatever its number.
"""

from dataclasses import dataclass
from typing import Optional

from ..protocol import DeciderIdentity

ANONYMOUS = ''


@dataclass(frozen=True)
class FollowVerdict:
    accept: bool
    switched: bool       # the sender is a decider not followed before (its generations restart)
    reason: str          # why, for the log ('' for a plain renewal)


def describe(identity: Optional[DeciderIdentity]) -> str:
    return 'without identity (anonymous)' if identity is None else identity.describe()


class Follower:
    def __init__(self, lease_s: float):
        self.lease_s = lease_s
        self.followed: Optional[DeciderIdentity] = None
        self.followed_id: Optional[str] = None    # None: none yet; ANONYMOUS: one without id
        self.heard: Optional[float] = None

    def silent_for(self, now: float) -> Optional[float]:
        return None if self.heard is None else now - self.heard

    def consider(self, sender: Optional[DeciderIdentity], now: float) -> FollowVerdict:
        """Whether a (checked, well-formed, this deployment's) layout of ``sender`` counts."""
        sender_id = ANONYMOUS if sender is None else sender.id
        if self.followed_id == sender_id:
            self.heard = now if self.heard is None else max(self.heard, now)
            return FollowVerdict(True, False, '')
        if self.followed_id is None:
            self._follow(sender, sender_id, now)
            return FollowVerdict(True, True, f'following decider {describe(sender)}')
        silent = now - self.heard
        if silent >= self.lease_s:
            old = describe(self.followed)
            self._follow(sender, sender_id, now)
            return FollowVerdict(True, True, f'decider {old} silent for {silent:.1f} s (lease '
                                             f'{self.lease_s:g} s): following decider '
                                             f'{describe(sender)}')
        return FollowVerdict(False, False, f'layout of decider {describe(sender)} ignored: '
                                           f'following {describe(self.followed)}, heard '
                                           f'{silent:.1f} s ago (another decider is followed '
                                           f'only after {self.lease_s:g} s of silence)')

    def _follow(self, sender: Optional[DeciderIdentity], sender_id: str, now: float) -> None:
        self.followed, self.followed_id, self.heard = sender, sender_id, now
