"""Driving one lifecycle (managed) node to the state its scale wants: pure and clock-free.

The agent sets a goal: ``ACTIVE`` where the layout places the node, ``INACTIVE`` for a standby
copy, ``FINALIZED`` before it signals the process to stop (None: hold, as for a copy adopted
before its state is known). ``next_request(now, reachable)`` says which service call to make
(``get_state`` or one ``change_state`` transition); the caller makes it and hands back the answer
(``answered_state``, ``answered_change``) or its absence (``next_request`` notices the deadline).

A change_state that timed out may still have happened (ros-navigation/navigation2#6556), and a
refused one leaves the node in its previous state or, after an error, unconfigured or
finalized: after either, the state is read again with get_state before anything else. Refusals
and time-outs are counted; each is retried after a backoff that doubles, and after
``max_failures`` in a row the driver gives up (``failed``): the caller restarts the process or,
when the goal was to finalize it, signals it anyway. Reaching the goal clears the count.
"""

from dataclasses import dataclass
from typing import Callable, Dict, Iterable, List, Optional, Set, Tuple, Union

from ..protocol import LIVE_STATES, LifecycleState, ProcState

UNKNOWN = LifecycleState.UNKNOWN
UNCONFIGURED = LifecycleState.UNCONFIGURED
INACTIVE = LifecycleState.INACTIVE
ACTIVE = LifecycleState.ACTIVE
FINALIZED = LifecycleState.FINALIZED
PRIMARY = (UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED)
GOALS = (ACTIVE, INACTIVE, FINALIZED)
# A copy that answers one of these may be serving whoever asked (an adopted copy too).
MAY_SERVE = (ACTIVE, LifecycleState.ACTIVATING, LifecycleState.DEACTIVATING)

# lifecycle_msgs/msg/Transition ids, and the primary state each one ends in when it succeeds.
TRANSITIONS = {
    'configure': (1, INACTIVE), 'cleanup': (2, UNCONFIGURED), 'activate': (3, ACTIVE),
    'deactivate': (4, INACTIVE), 'unconfigured_shutdown': (5, FINALIZED),
    'inactive_shutdown': (6, FINALIZED), 'active_shutdown': (7, FINALIZED),
}

# The next transition from each primary state towards each goal. Towards FINALIZED the node is
# deactivated and cleaned up first, as nav2's lifecycle manager does, so its own teardown runs.
_PATH = {
    ACTIVE: {UNCONFIGURED: 'configure', INACTIVE: 'activate'},
    INACTIVE: {UNCONFIGURED: 'configure', ACTIVE: 'deactivate'},
    FINALIZED: {ACTIVE: 'deactivate', INACTIVE: 'cleanup', UNCONFIGURED: 'unconfigured_shutdown'},
}


def next_transition(state: LifecycleState, goal: LifecycleState) -> Optional[str]:
    """The transition to ask for from primary ``state`` towards ``goal`` (None: there, or no
    way there, as from finalized)."""
    if goal not in _PATH:
        raise ValueError(f'unknown lifecycle goal {goal!r} (expected one of {", ".join(GOALS)})')
    return _PATH[goal].get(state)


def _ask(reachable: Union[bool, Callable[[], bool]]) -> bool:
    return reachable() if callable(reachable) else bool(reachable)


def label_state(label: str) -> LifecycleState:
    """The state a get_state answer labels; UNKNOWN for a label outside the ROS 2 lifecycle
    state machine, which is looked at again like a transition in progress."""
    try:
        return LifecycleState(label)
    except ValueError:
        return UNKNOWN


@dataclass(frozen=True)
class Request:
    """One service call to make: ``kind`` 'get' (get_state) or 'change' (``transition``)."""

    serial: int
    kind: str
    transition: str
    sent: float
    deadline: float

    @property
    def transition_id(self) -> int:
        return TRANSITIONS[self.transition][0]


class Driver:
    """The lifecycle state machine of one copy, as seen through its services."""

    def __init__(self, name: str, change_timeout_s: float, get_timeout_s: float = 1.0,
                 backoff_s: float = 0.5, backoff_max_s: float = 8.0, max_failures: int = 3):
        self.name = name
        self.change_timeout_s = change_timeout_s
        self.get_timeout_s = get_timeout_s
        self.backoff_s = backoff_s
        self.backoff_max_s = backoff_max_s
        self.max_failures = max_failures
        self.goal: Optional[LifecycleState] = None
        self.events: List[Tuple[str, str]] = []     # (level, text), drained by the caller
        self._serial = 0
        self.reset()

    def reset(self) -> None:
        """A new process (started or adopted): nothing is known of it yet."""
        self.state: LifecycleState = UNKNOWN
        self.pending: Optional[Request] = None
        self.failures = 0
        self.retry_at = 0.0
        self.problem = ''       # why the last transition failed ('' when none did)
        self._check = True      # read the state before asking for any transition
        self.check_at = 0.0     # not before then
        self._activated = False     # asked to activate, or seen active, since last seen not

    # --- what the caller asks ---------------------------------------------------------------
    def set_goal(self, goal: Optional[LifecycleState]) -> None:
        if goal is not None and goal not in GOALS:
            raise ValueError(f'unknown lifecycle goal {goal!r}')
        if goal != self.goal:
            self.goal = goal
            self.failures = 0
            self.retry_at = 0.0

    @property
    def at_goal(self) -> bool:
        return self.goal is not None and self.state == self.goal

    @property
    def failed(self) -> bool:
        """It gave up: ``max_failures`` refusals or time-outs in a row."""
        return self.failures >= self.max_failures

    @property
    def may_be_active(self) -> bool:
        """Whether the copy may be serving: it is active, or it was asked to activate (or was
        active) and has not been seen inactive since: an activation not answered yet or timed
        out, an 'activating' or 'deactivating' answer, an error being processed."""
        return self.state == ACTIVE or self._activated

    @property
    def known(self) -> bool:
        return self.state != UNKNOWN

    @property
    def settled(self) -> bool:
        """Nothing to ask nor wait for: its state known, at its goal (or none set), no call
        out, no retry due."""
        return (self.pending is None and not self._check and not self.failed
                and (self.goal is None or self.state == self.goal))

    def next_request(self, now: float,
                     reachable: Union[bool, Callable[[], bool]]) -> Optional[Request]:
        """The call to make now, if any (the caller makes it at once); None while one is out,
        while the services are not reachable, in a backoff, at the goal, or after giving up.
        ``reachable`` may be a function: it is asked only when a call would be made (a look
        at the ROS graph, which a copy at its goal does not need at each step)."""
        if self.pending is not None:
            if now < self.pending.deadline:
                return None
            self._timed_out(now)
        if self.failed:
            return None
        if self._check:
            if now < self.check_at or not _ask(reachable):
                return None
            return self._send('get', '', now, self.get_timeout_s)
        if self.goal is None or now < self.retry_at:
            return None
        transition = next_transition(self.state, self.goal)
        if transition is None and self.state == self.goal:
            return None
        if not _ask(reachable):
            return None
        if transition is None:
            if self.state != self.goal:     # finalized, with a live goal: only a restart helps
                self.failures = self.max_failures - 1
                self._fail(now, f'it is {self.state} and cannot become {self.goal}', check=False)
            return None
        return self._send('change', transition, now, self.change_timeout_s)

    # --- answers -----------------------------------------------------------------------------
    def answered_state(self, serial: int, label: str, now: float) -> None:
        if not self._is_pending(serial):
            return
        self.pending = None
        self.state = label_state(label)
        self._note_state()
        self._check = self.state not in PRIMARY
        if self._check:
            # A transition in progress (another client's, or ours that timed out): look again.
            self.check_at = now + self.backoff_s
        if self.at_goal:
            self.failures = 0
            self.problem = ''

    def answered_change(self, serial: int, success: bool, now: float) -> None:
        if not self._is_pending(serial):
            return
        request = self.pending
        self.pending = None
        if success:
            self.state = TRANSITIONS[request.transition][1]
            self._note_state()
            if self.at_goal:
                self.failures = 0
                self.problem = ''
            return
        self._fail(now, f'{request.transition} refused by the node')

    def lost(self, serial: int, why: str, now: float) -> None:
        """The call could not be made or its answer was lost (not a time-out)."""
        if not self._is_pending(serial):
            return
        request = self.pending
        self.pending = None
        if request.kind == 'change':
            self._fail(now, f'{request.transition} failed: {why}')
        else:
            self._check = True
            self.check_at = now + self.backoff_s

    # --- internals ---------------------------------------------------------------------------
    def _note_state(self) -> None:
        if self.state in MAY_SERVE:
            self._activated = True
        elif self.state in (UNCONFIGURED, INACTIVE, FINALIZED):
            self._activated = False

    def _send(self, kind: str, transition: str, now: float, timeout_s: float) -> Request:
        if transition == 'activate':
            self._activated = True
        self._serial += 1
        self.pending = Request(self._serial, kind, transition, now, now + timeout_s)
        return self.pending

    def _is_pending(self, serial: int) -> bool:
        return self.pending is not None and self.pending.serial == serial

    def _timed_out(self, now: float) -> None:
        request = self.pending
        self.pending = None
        if request.kind == 'get':
            # Not answered yet: a process still starting, or its services not matched yet.
            self._check = True
            self.check_at = now
            return
        self._fail(now, f'{request.transition} not answered within {self.change_timeout_s:g} s '
                        '(it may still have happened: checking with get_state)')

    def _fail(self, now: float, why: str, check: bool = True) -> None:
        self.failures += 1
        self.problem = why
        self._check = check
        self.check_at = now
        delay = min(self.backoff_s * 2 ** (self.failures - 1), self.backoff_max_s)
        self.retry_at = now + delay
        tail = ('; giving up' if self.failed else
                f'; retry {self.failures} of {self.max_failures - 1} in {delay:g} s')
        self.events.append(('warn' if not self.failed else 'error',
                            f'{self.name}: lifecycle: {why}{tail}'))


def report(state: ProcState, ready: bool, reason: str, driver: Driver) -> tuple:
    """(state, ready, reason, lifecycle label) of a lifecycle copy for the agent's report:
    RUNNING and ready only while active (what serves), STANDBY for a live copy kept
    inactive, STARTING on its way to active, STOPPING on its way out."""
    if state not in LIVE_STATES:
        return state, False, reason, driver.state if state == ProcState.STOPPING else None
    if driver.failed:
        reason = f'lifecycle: {driver.problem}'
    elif driver.problem:
        reason = f'lifecycle (retrying): {driver.problem}'
    if driver.state == ACTIVE and driver.goal != FINALIZED:
        return ProcState.RUNNING, True, reason, driver.state
    if driver.goal == FINALIZED:
        return ProcState.STOPPING, False, reason, driver.state
    if driver.goal == INACTIVE or (driver.goal is None and driver.state == INACTIVE):
        return ProcState.STANDBY, False, reason, driver.state
    return ProcState.STARTING, False, reason, driver.state


def goals(names: Iterable[str], want: Set[str], standby_here: Iterable[str], has_layout: bool,
          live: Iterable[str]) -> Tuple[Dict[str, Optional[LifecycleState]], Set[str]]:
    """The goal of each lifecycle copy on this scale, and the nodes whose process must run.

    ``want``: the nodes the layout places here; ``standby_here``: those it keeps a standby
    copy of here; ``live``: the lifecycle copies running now. A placed copy is made active, a
    standby one inactive, any other finalized. Before the first layout (a restarted agent
    adopting its copies) a live copy keeps the state it reports (goal None) until the layout
    says otherwise. An inactive copy's process runs too."""
    standby = set(standby_here)
    out: Dict[str, Optional[LifecycleState]] = {
        n: ACTIVE if n in want else INACTIVE if n in standby else FINALIZED for n in names}
    run = set(want)
    if not has_layout:
        kept = set(live) & set(out)
        out.update({n: None for n in kept})
        run |= kept
    run |= {n for n, g in out.items() if g == INACTIVE}
    return out, run
