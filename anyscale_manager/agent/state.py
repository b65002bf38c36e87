"""A node's state on one scale: the latest message of its state topic, kept here, and handed
to a copy of the node that this scale's agent is about to make serve (docs/lifecycle.md, state).

Every agent of a scale that may run a node with ``state:`` keeps the latest message heard on the
node's state topic (``heard``), so a serving copy's last state is already on every scale that may
take over when it dies. A copy that is to serve here (activated, started cold, restarted in
place) is handed that message on its own restore input before it serves (``hand``), once per
spell of serving; a copy with nothing heard yet starts as it would without a state, and that is
said. Pure and clock-free: the agent's ROS side takes the messages and publishes the hand-over.
"""

from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Tuple

from ..model.types import StateSpec

# (level, text): one log line of the agent's.
Line = Tuple[str, str]
# Two writers on a state topic: backward steps of the sequence numbers within this window.
TWO_WRITERS_WINDOW_S = 2.0
TWO_WRITERS_STEPS = 2
TWO_WRITERS_REPEAT_S = 60.0
# A state set by others on the restore topic (a pose set in RViz) stays the state to hand over
# for this long against what the serving copy publishes: that copy takes the set state when its
# own loop gets to it (1 s late on the test-bed's capped robot), and until then it publishes
# from the state it had. Handing one of those to a copy taking over would drop what was set.
SET_HOLD_S = 3.0


@dataclass(frozen=True)
class Held:
    """The latest state message of one node, serialised as it came."""

    data: bytes
    heard_at: float          # monotonic, when it was received here


@dataclass(frozen=True)
class Handover:
    """What to hand a copy before it serves: ``data`` (None: nothing heard yet) and its age."""

    node: str
    copy: int                # the copy's pid: one hand-over per copy and spell of serving
    data: Optional[bytes]
    age_s: Optional[float]


@dataclass
class Pending:
    """A hand-over under way: sent once the copy's restore input is matched.
    ``awaiting_first``: no state heard yet, the copy waits for the first (bounded by the turn,
    agent/turn.py FIRST_STATE_WAIT_S); ``since`` then counts that wait, and the restore input's
    from when the state came."""

    copy: int
    since: float
    sent: bool = False
    awaiting_first: bool = False


class StateBook:
    """The latest state of each stateful node a scale may run, and the copies handed it."""

    def __init__(self, specs: Mapping[str, StateSpec], max_bytes: int, stale_s: float):
        self.specs = dict(specs)
        self.max_bytes = max_bytes
        self.stale_s = stale_s
        self._held: Dict[str, Held] = {}
        self._handed: Dict[str, int] = {}          # node -> the copy handed its state
        self._pending: Dict[str, Pending] = {}
        self._too_big: Dict[str, bool] = {}
        self._last_seq: Dict[str, int] = {}
        self._backward: Dict[str, List[float]] = {}
        self._two_writers_said: Dict[str, float] = {}
        self._set_at: Dict[str, float] = {}         # node -> when a state was set by others

    def heard(self, node: str, data: bytes, now: float, seq: int = -1) -> List[Line]:
        """A state message of ``node`` received here (``seq``: its writer's sequence number,
        -1 unknown). Returns what to log: a message over the bound, once per node; two writers
        sending the node's state at once, once a minute."""
        if node not in self.specs:
            return []
        out: List[Line] = []
        if len(data) > self.max_bytes:
            if not self._too_big.get(node):
                self._too_big[node] = True
                kept = self._held.get(node)
                out.append(('warn', f'{node}: a state message on {self.specs[node].topic} of '
                                    f'{len(data)} bytes is over agent.state_max_bytes = '
                                    f'{self.max_bytes}: not kept (the copy that takes over gets '
                                    + (f'the last one that fitted, {len(kept.data)} bytes)'
                                       if kept else 'none)')))
            return out
        self._too_big[node] = False
        out += self._writers(node, seq, now)
        set_at = self._set_at.get(node)
        if set_at is not None and now - set_at < SET_HOLD_S:
            return out                 # possibly from before the serving copy took the set one
        self._held[node] = Held(data, now)
        return out

    def set_by_others(self, node: str, data: bytes, now: float) -> List[Line]:
        """A state published on the node's restore topic by someone else (a pose set in RViz):
        the node's state from now on, kept against the serving copy's output for
        ``SET_HOLD_S``."""
        if node not in self.specs:
            return []
        if len(data) > self.max_bytes:
            return [('warn', f'{node}: a message on {self.specs[node].restore} of {len(data)} '
                             f'bytes is over agent.state_max_bytes = {self.max_bytes}: not kept')]
        self._held[node] = Held(data, now)
        self._set_at[node] = now
        return []

    def _writers(self, node: str, seq: int, now: float) -> List[Line]:
        """Sequence numbers that step back more than once in a short window come from two
        writers at once (a copy that restarted steps back once)."""
        if seq < 0:
            return []
        last = self._last_seq.get(node)
        self._last_seq[node] = seq
        if last is None or seq > last:
            return []
        steps = [t for t in self._backward.get(node, []) if now - t <= TWO_WRITERS_WINDOW_S]
        steps.append(now)
        self._backward[node] = steps
        said = self._two_writers_said.get(node)
        if len(steps) < TWO_WRITERS_STEPS or (said is not None
                                              and now - said < TWO_WRITERS_REPEAT_S):
            return []
        self._two_writers_said[node] = now
        return [('warn', f'{node}: two writers send its state on {self.specs[node].topic} at '
                         'once (two serving copies, or another node on that topic): the latest '
                         'message heard is kept, whichever wrote it')]

    def latest(self, node: str) -> Optional[Held]:
        return self._held.get(node)

    def age_s(self, node: str, now: float) -> Optional[float]:
        held = self._held.get(node)
        return None if held is None else max(0.0, now - held.heard_at)

    def needs(self, node: str, copy: int) -> bool:
        """Whether copy ``copy`` of ``node`` is still to be handed the state before it serves."""
        return node in self.specs and copy > 0 and self._handed.get(node) != copy

    def handover(self, node: str, copy: int, now: float) -> Tuple[Handover, List[Line]]:
        """What to hand copy ``copy`` now, and what to log about it."""
        held = self._held.get(node)
        topic = self.specs[node].restore
        if held is None:
            return Handover(node, copy, None, None), [
                ('info', f'{node}: no state heard yet on {self.specs[node].topic}: the copy '
                         f'(pid {copy}) starts from its own')]
        age = max(0.0, now - held.heard_at)
        if self._set_at.get(node) == held.heard_at and age < SET_HOLD_S:
            return Handover(node, copy, held.data, age), [
                ('info', f'{node}: the state set on {topic} {age:.2f} s ago handed to the copy '
                         f'(pid {copy})')]
        if age > self.stale_s:
            return Handover(node, copy, held.data, age), [
                ('warn', f'{node}: its last state is {age:.1f} s old (over agent.state_stale_s '
                         f'= {self.stale_s:g} s: the serving copy stopped sending it); handed '
                         f'to the copy (pid {copy}) on {topic} all the same')]
        return Handover(node, copy, held.data, age), [
            ('info', f'{node}: state of {age:.2f} s ago handed to the copy (pid {copy}) on '
                     f'{topic}')]

    def handed(self, node: str, copy: int) -> None:
        """The copy has its state (or was told there is none): it may serve."""
        self._handed[node] = copy
        self._pending.pop(node, None)

    # --- hand-overs in progress ----------------------------------------------------------------
    def begin(self, node: str, copy: int, now: float) -> 'Pending':
        """Copy ``copy`` of ``node`` is to be handed its state before it serves: the hand-over
        stays pending until it is ``handed``, or gives up after a time (``expired``). What is
        handed is the latest state when it is sent (``handover``)."""
        current = self._pending.get(node)
        if current is None or current.copy != copy:
            current = self._pending[node] = Pending(copy, now)
        return current

    def pending(self) -> List['Pending']:
        return list(self._pending.values())

    def pending_for(self, node: str) -> Optional['Pending']:
        return self._pending.get(node)

    def expired(self, now: float, timeout_s: float) -> List[Line]:
        """Hand-overs that waited ``timeout_s`` for the copy's restore input: the copy serves
        without its state rather than not at all."""
        out: List[Line] = []
        for node, p in list(self._pending.items()):
            if not p.awaiting_first and now - p.since > timeout_s:
                out.append(('warn', f'{node}: its copy (pid {p.copy}) did not take its '
                                    f'state on {self.specs[node].restore} (remapped to its own '
                                    f'topic) within {timeout_s:g} s: it serves from its own '
                                    'state (does it subscribe to its restore topic while '
                                    'inactive? docs/lifecycle.md, state)'))
                self.handed(node, p.copy)
        return out

    def stood_down(self, node: str) -> None:
        """The node's copy here no longer serves: its next spell is handed the state again."""
        self._handed.pop(node, None)
        self._pending.pop(node, None)
