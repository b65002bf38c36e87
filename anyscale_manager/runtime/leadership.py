"""Who decides: one leading decider per deployment, and hot standbys ready to take over.

Pure, clocks passed in (``now``: monotonic seconds). Every decider beats on /anyscale/decider
every ``beat_s`` with its identity, role and term; the leader also publishes the layouts, and a
standby only listens (to the leader's layouts and events and to every report the leader reads).

- **Start.** A decider starts as a standby. It leads once it has heard no leader for
  ``discovery_s`` since its start; hearing one, it stays a standby.
- **Takeover.** A standby takes the lead when the last leader it heard has been silent for
  ``takeover_s``, plus two beats per live standby that started before it (the first one started
  goes first; the others then hear it lead and stay standbys). A standby that has heard a
  leader only through its layouts (a latched one arrives before the beats, whose discovery is
  separate), never its beats, waits until ``discovery_s`` after its own start as well.
- **Term.** A decider that takes the lead takes a term above every term it has heard (beats,
  layouts, the agents' reports), and every layout carries it: agents refuse a lower term than
  the one they follow (agent/authority.py), so a leader that comes back after a takeover
  commands nothing. It steps down when it hears a live leader of a higher term (or of its own
  term that started before it), or any higher term at all (an agent's report can carry the
  new leader's term before its beats arrive): it stands by, and takes over again, above every
  term heard, ``takeover_s`` later if no leader beats (an agent that follows a decider now
  gone).
- **Stall.** A leader commands only within ``takeover_s`` less DELIVERY_S (0.3 s of 0.4) of its
  own last beat: one that could not beat for longer (SIGSTOP, a paused VM, a starved process)
  may have been taken over, so it steps down and listens before anything else it would
  publish. A standby takes over only ``takeover_s`` after the leader's last beat *arrived*:
  as long as a beat arrives within DELIVERY_S of being sent, the old leader's last command
  precedes the new leader's first (the beat it sends on resuming can arrive late, after the
  standby's silence began). A leader that stepped down goes after every live standby when
  no leader beats (two beats each, one more, and twice DELIVERY_S): the standby's silence
  began at its last beat as leader, before its own step-down. A leader that knew
  of no other decider when it stalled (none heard within ``lease_s`` before its last beat) and
  stalled for less than ``discovery_s`` cannot have been overtaken (a decider that never heard
  it listens ``discovery_s``), and keeps leading.
"""

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from ..protocol import DeciderIdentity

LEADER, STANDBY = 'leader', 'standby'
MAX_PEERS = 64
RANK_BEATS = 2          # a standby waits this many beats more per live standby older than it
# How late a beat may arrive at another decider: a leader counts as stalled after
# takeover_s less this (at most a third of takeover_s) without a beat. Its beat after a stall
# can reach a standby that much after the standby's own takeover_s of silence began.
DELIVERY_S = 0.1


def older(a: DeciderIdentity, b: DeciderIdentity) -> bool:
    """Whether ``a`` started before ``b`` (the id breaks a tie): both sides compute the same."""
    return (a.started, a.id) < (b.started, b.id)


def outranks(a: Tuple[int, DeciderIdentity], b: Tuple[int, DeciderIdentity]) -> bool:
    """Whether leader ``a`` = (term, identity) keeps the lead against leader ``b``."""
    return a[0] > b[0] or a[0] == b[0] and older(a[1], b[1])


@dataclass
class Peer:
    identity: DeciderIdentity
    role: str
    term: int
    generation: int
    received: float


@dataclass(frozen=True)
class Change:
    """A change of role or term this decider must act on."""

    role: str
    term: int
    reason: str
    # On a takeover: the leader last heard (its layouts are the ones to continue from).
    previous: Optional[Peer] = None


class Leadership:
    def __init__(self, me: DeciderIdentity, *, beat_s: float, takeover_s: float,
                 discovery_s: float, lease_s: float, started: float, alone_wait_s: float = 0.0):
        self.me = me
        self.beat_s, self.takeover_s = beat_s, takeover_s
        # How long a leader alone waits between two looks at who listens (its quiet time).
        self.alone_wait_s = alone_wait_s
        self.discovery_s, self.lease_s = discovery_s, lease_s
        self.started = started
        self.role = STANDBY
        self.term = 0
        self.max_term = 0                   # the highest term heard anywhere
        self.peers: Dict[str, Peer] = {}
        self.leader: Optional[Peer] = None  # the leader last heard (as a standby)
        self.quiet_since: Optional[float] = None    # when a leader was last known to live
        self.beats_heard = False                    # a leader's beat, not only its layouts
        self.last_beat: Optional[float] = None      # our own last beat
        # A leader nobody listens to (no other decider, no status view): its beats go to no
        # one, and a gap between them of up to alone_wait_s is no stall anyone could take over
        # in (``alone``). A longer one is: a standby may have started and found no beat.
        self.alone = False
        self.stall_s = takeover_s - min(DELIVERY_S, takeover_s / 3.0)
        self.deposed = False        # stepped down: goes after every live standby
        self.takeovers = 0

    # --- what is heard --------------------------------------------------------------------
    def heard_beat(self, identity: DeciderIdentity, role: str, term: int, generation: int,
                   now: float, *, layout: bool = False) -> Optional[Change]:
        """A beat (or, with ``layout``, a layout: a leader's word too) of another decider."""
        if identity.id == self.me.id:
            return None
        if role == LEADER and not layout:
            self.beats_heard = True
        self.max_term = max(self.max_term, term)
        if identity.id not in self.peers and len(self.peers) >= MAX_PEERS:
            del self.peers[min(self.peers, key=lambda k: self.peers[k].received)]
        peer = Peer(identity, role, term, generation, now)
        self.peers[identity.id] = peer
        if role != LEADER:
            return None
        if self.role == LEADER:
            if outranks((term, identity), (self.term, self.me)):
                return self._step_down(now, f'decider {identity.describe()} leads at term '
                                            f'{term} (this one at term {self.term})')
            return None
        if not layout:
            # A leader beats: the race after a step-down is over. A layout does not end it: a
            # latched one of a gone leader can arrive now.
            self.deposed = False
        if self.leader is None or self.leader.identity.id == identity.id \
                or outranks((term, identity), (self.leader.term, self.leader.identity)) \
                or now - self.leader.received > self.takeover_s:
            self.leader = peer
        self.quiet_since = now if self.quiet_since is None else max(self.quiet_since, now)
        return None

    def heard_term(self, term: Optional[int]) -> None:
        """A term seen in a layout or an agent's report."""
        if term is not None:
            self.max_term = max(self.max_term, term)

    # --- the clock ------------------------------------------------------------------------
    def check(self, now: float) -> Optional[Change]:
        """Before a beat and before anything this decider would command: the change of role or
        term that is due now, if any."""
        if self.role == LEADER:
            last = self.last_beat
            if last is not None and now - last > self._stall_limit():
                # The deciders known when the stall began: a stall longer than lease_s would
                # otherwise forget them all (their beats stamped before it).
                known = any(p.received >= last - self.lease_s for p in self.peers.values())
                if known or now - last >= self.discovery_s:
                    return self._step_down(now, f'could not beat for {now - last:.2f} s '
                                                f'(> {self.stall_s:.2f} s: takeover_s '
                                                f'{self.takeover_s:g} s less the delivery of a '
                                                'beat): another decider may lead now')
            if self.max_term > self.term:
                # Another decider led at a higher term since this one took its own: it may
                # lead now (its beats can arrive after an agent's report of its term). Stand
                # by; if no leader beats, this one takes over above it after takeover_s.
                return self._step_down(now, f"term {self.max_term} heard above this leader's "
                                            f'term {self.term}')
            return None
        wait = self.due_in(now)
        if wait is not None and wait <= 0:
            return self._lead(now)
        return None

    def beaten(self, now: float) -> None:
        """This decider's beat went out at ``now``."""
        self.last_beat = now

    def listened(self, listened: bool, now: float) -> None:
        """Whether another reads the beats now, told after ``check`` has judged the time since
        the last wake. A leader that was alone counts as having beaten until now: nobody could
        have taken over, so its quiet time is no stall; one that was listened to and stalled
        has been judged (stepped down) before it may count as alone."""
        if self.alone:
            self.last_beat = now
        self.alone = not listened and self.role == LEADER

    def _stall_limit(self) -> float:
        """The longest time since the last beat (or, alone, the last look at who listens) that
        is no stall: a leader alone looks every alone_wait_s. A leader stopped or starved for
        longer, alone when it stopped, may have been taken over by a standby started
        meanwhile: it neither commands nor leads on until its beat thread has judged that."""
        return self.stall_s + (self.alone_wait_s if self.alone else 0.0)

    def may_command(self, now: float) -> bool:
        return self.role == LEADER and self.last_beat is not None \
            and now - self.last_beat <= self._stall_limit()

    # --- views ----------------------------------------------------------------------------
    def live_leader(self, now: float) -> Optional[Peer]:
        live = [p for p in self.peers.values()
                if p.role == LEADER and now - p.received <= self.takeover_s]
        best = None
        for p in live:
            if best is None or outranks((p.term, p.identity), (best.term, best.identity)):
                best = p
        return best

    def others(self, now: float) -> List[Peer]:
        """Other deciders heard within ``lease_s``, first started first."""
        return sorted((p for p in self.peers.values() if now - p.received <= self.lease_s),
                      key=lambda p: (p.identity.started, p.identity.id))

    def standbys_before(self, now: float) -> int:
        return sum(1 for p in self.peers.values() if p.role == STANDBY
                   and now - p.received <= self.takeover_s and older(p.identity, self.me))

    def due_in(self, now: float) -> Optional[float]:
        """Seconds until this standby takes the lead (<= 0: now); None while a leader lives."""
        if self.role == LEADER or self.live_leader(now) is not None:
            return None
        if self.deposed:
            # A leader that stepped down (a stall, a higher term) lets any standby take over
            # first: the standby's silence began at this one's last beat as leader, earlier
            # than its own step-down, and the beat of the standby that took over must have
            # time to arrive.
            live = sum(1 for p in self.peers.values()
                       if p.role == STANDBY and now - p.received <= self.takeover_s)
            rank = RANK_BEATS * self.beat_s * (live + 1) + 2 * DELIVERY_S
        else:
            rank = RANK_BEATS * self.beat_s * self.standbys_before(now)
        base = self.started + self.discovery_s
        if self.quiet_since is not None:
            # A leader whose beats have not been heard yet is not a silent one: until then,
            # not before discovery_s after the start.
            floor = -math.inf if self.beats_heard else base
            base = max(floor, self.quiet_since + self.takeover_s)
        return base + rank - now

    # --- transitions ----------------------------------------------------------------------
    def _lead(self, now: float) -> Change:
        previous = self.leader
        self.term = max(self.max_term, self.term) + 1
        self.max_term = self.term
        self.role = LEADER
        self.deposed = False
        self.last_beat = now
        if previous is None:
            since = self.started if self.quiet_since is None else self.quiet_since
            reason = (f'no leading decider heard in {now - since:.1f} s: this one leads at '
                      f'term {self.term}')
        else:
            self.takeovers += 1
            reason = (f'decider {previous.identity.describe()} (term {previous.term}) silent '
                      f'for {now - previous.received:.2f} s: this one takes over at term '
                      f'{self.term}')
        return Change(LEADER, self.term, reason, previous)

    def _step_down(self, now: float, why: str) -> Change:
        self.role = STANDBY
        self.deposed = True
        self.leader = None
        self.quiet_since = now
        return Change(STANDBY, self.term, why + ': standing by')


__all__ = ['Change', 'LEADER', 'Leadership', 'Peer', 'STANDBY', 'older', 'outranks']
