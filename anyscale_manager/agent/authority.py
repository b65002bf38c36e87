"""Whose layouts an agent follows: exactly one decider, fenced by its leadership term.

Pure, clock passed in. Every layout carries its decider's term (runtime/leadership.py; absent:
0). An agent follows one decider and the highest term it has seen from the deciders it followed:

- a layout of the followed decider counts (a re-publication renews its lease);
- a layout of another decider at a higher term counts at once, and the agent follows it (a
  standby that took over; its generations restart);
- one at the same term (above 0) counts when its decider started before the followed one (two
  that took the lead together: both sides keep the older);
- any other is refused while the followed decider's lease holds (its last message within
  ``lease_s``): a leader that comes back after a takeover (a lower term) commands nothing;
- once the followed one has been silent for ``lease_s``, or before the agent follows any, a
  layout counts whatever its term (a lone decider restarted with no memory of terms).

A layout that names no decider (an older decider, a plain script) counts as one anonymous
decider at term 0. Generations are compared within one decider only: a new decider's first
layout is taken whatever its number.
"""

from dataclasses import dataclass
from typing import Optional

from ..protocol import DeciderIdentity
from ..runtime.leadership import older

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
        self.term = 0                             # the followed decider's term
        self.heard: Optional[float] = None

    def silent_for(self, now: float) -> Optional[float]:
        return None if self.heard is None else now - self.heard

    def consider(self, sender: Optional[DeciderIdentity], now: float,
                 term: Optional[int] = None) -> FollowVerdict:
        """Whether a (checked, well-formed, this deployment's) layout of ``sender`` counts."""
        sender_id = ANONYMOUS if sender is None else sender.id
        term = term or 0
        if self.followed_id == sender_id:
            self.heard = now if self.heard is None else max(self.heard, now)
            self.term = max(self.term, term)
            return FollowVerdict(True, False, '')
        if self.followed_id is None:
            self._follow(sender, sender_id, term, now)
            return FollowVerdict(True, True, f'following decider {describe(sender)} (term '
                                             f'{term})')
        old = describe(self.followed)
        if term > self.term:
            why = (f'decider {describe(sender)} leads at term {term}, above term {self.term} '
                   f'of decider {old}: following it')
            self._follow(sender, sender_id, term, now)
            return FollowVerdict(True, True, why)
        if term == self.term > 0 and sender is not None and self.followed is not None \
                and older(sender, self.followed):
            why = (f'decider {describe(sender)} leads at term {term} like decider {old} and '
                   'started before it: following it')
            self._follow(sender, sender_id, term, now)
            return FollowVerdict(True, True, why)
        silent = now - self.heard
        if silent >= self.lease_s:
            self._follow(sender, sender_id, term, now)
            return FollowVerdict(True, True, f'decider {old} silent for {silent:.1f} s (lease '
                                             f'{self.lease_s:g} s): following decider '
                                             f'{describe(sender)} (term {term})')
        return FollowVerdict(False, False, f'layout of decider {describe(sender)} (term {term}) '
                                           f'ignored: following {old} (term {self.term}), '
                                           f'heard {silent:.1f} s ago (a lower term, or another '
                                           f'decider at this term, is followed only after '
                                           f'{self.lease_s:g} s of silence)')

    def _follow(self, sender: Optional[DeciderIdentity], sender_id: str, term: int,
                now: float) -> None:
        self.followed, self.followed_id, self.heard, self.term = sender, sender_id, now, term
