"""The Δ rule: when a connection is below its freq_min, for how long, and whether past Δ.

This module owns the rule: the probes, the decider (its constraint check and its Δ timer), the
status view, /diagnostics, the test-bed's observer and judge, the soak, the simulator, the
benches and the demo all judge a connection with it, so every figure means the same thing.
Whether a connection is monitored at all is the model's fact (``Connection.monitored``: both
thresholds set); whether it pins both its ends to the master is another
(``Connection.pins_both_ends``, Δ = 0), never read here as a tolerance.

The rule, on the arrival times a subscriber lives through (``T = 1/freq_min + a``, ``a`` the
stall allowance, ``STALL_ALLOWANCE_S``):

* **Silence.** Once the subscriber has gone longer than ``T`` without a message, the
  connection is below freq_min, from ``last arrival + T`` until the next arrival. A stopped
  topic therefore reads below (and 0 Hz) after ``T``, not after a window average has decayed.
  The allowance forgives a receiver that was not scheduled for a moment (a loaded 2-core
  scale, a batch taken late); it is the only slack in the rule.
* **Real intervals.** A topic that keeps arriving, but too slowly, is below while the lower
  median of its intervals within the last ``window_s`` (each counted as at most ``T``, at least
  two of them) is longer than ``1/freq_min``. The median ignores the one long interval that
  ended an outage, so a recovered topic is judged on its new intervals at once, and a topic at
  2 Hz against a 5 Hz minimum stays below between its messages.

A stretch below runs from its first instant to the arrival that ends it; an outage (the gap
between two messages) of ``Δ + 1/freq_min + 0.1 s`` is therefore always longer than Δ below
freq_min, and one of ``Δ + 1/freq_min - 0.1 s`` never is. Δ is exceeded when a stretch lasts
longer than Δ (``past_delta``; so Δ = 0 tolerates no stretch at all).

Where only rates are known (a reading, the simulator's world), a rate is below when it is under
freq_min (``rate_below``) and a stretch runs from the first such instant (``stretch_start``).
The decider times each connection from its readings with ``DeltaTracker`` (``below_start``: a
missing or stale reading is 0 Hz from when it went missing), and every connection's judgement
at one instant is a ``ConnectionVerdict``.
"""

import math
from collections import deque
from dataclasses import dataclass
from typing import Deque, Dict, Iterable, List, Mapping, Optional, Tuple

from ..model.types import DeciderSettings, Deployment, frozen_map
from ..protocol import ERROR, OK, WARN
from .observations import ConnectionObs, Observations, is_fresh

# A receiver stall forgiven before silence counts: far below any Δ worth setting, above the
# 50 ms batches in which the probes take their messages and the scheduling stalls of a
# loaded scale (a 40 Hz topic on the test-bed's CPU-capped robot waits up to ~0.17 s at
# times); below 0.1 s, so that an outage of Δ + 1/freq_min + 0.1 s is always a violation.
STALL_ALLOWANCE_S = 0.09
DEFAULT_WINDOW_S = 2.0


def min_period_s(freq_min_hz: Optional[float]) -> float:
    """The longest interval between messages at freq_min; infinite without a freq_min above 0
    (nothing is ever below it)."""
    return 1.0 / freq_min_hz if freq_min_hz is not None and freq_min_hz > 0 else math.inf


def rate_below(freq_min_hz: Optional[float], rate_hz: float, slack_hz: float = 0.0) -> bool:
    """Whether a rate reads below freq_min (by more than ``slack_hz``); never without one."""
    return freq_min_hz is not None and rate_hz < freq_min_hz - slack_hz


def past_delta(below_for_s: float, tolerance_s: Optional[float]) -> bool:
    """Whether a stretch below freq_min of ``below_for_s`` exceeds Δ: it lasts longer than Δ
    (Δ = 0 tolerates no stretch at all; without a Δ, none is ever past it)."""
    return tolerance_s is not None and below_for_s > tolerance_s


def stretch_start(since: Optional[float], now: float, below: bool) -> Optional[float]:
    """The stretch below open at ``now``: it began at ``since``, or now if it opens now; None
    once the connection is no longer below."""
    if not below:
        return None
    return now if since is None else since


def time_below(since: Optional[float], now: float) -> float:
    """How long the stretch below that began at ``since`` has lasted at ``now`` (0 if none)."""
    return 0.0 if since is None else max(0.0, now - since)


@dataclass(frozen=True)
class ConnectionVerdict:
    """One connection's judgement by the Δ rule at one instant."""

    below_for_s: float = 0.0      # length of the open stretch below freq_min (0 when none)
    level: int = OK               # OK, WARN (below, within Δ), ERROR (below for longer than Δ)
    silent: bool = False          # nothing heard for longer than 1/freq_min + the allowance
    ended_below_s: float = 0.0    # longest stretch that ended since the previous verdict

    @classmethod
    def judge(cls, below_for_s: float, tolerance_s: Optional[float],
              below: Optional[bool] = None, *, silent: bool = False,
              ended_below_s: float = 0.0) -> 'ConnectionVerdict':
        """The verdict on a stretch below of ``below_for_s`` against Δ = ``tolerance_s``;
        ``below`` says whether the connection is below at all (default: a stretch longer
        than 0 is open)."""
        if below is None:
            below = below_for_s > 0.0
        level = OK if not below else ERROR if past_delta(below_for_s, tolerance_s) else WARN
        return cls(below_for_s if below else 0.0, level, silent, ended_below_s)

    @property
    def below(self) -> bool:
        """Below freq_min now (within Δ or past it)."""
        return self.level in (WARN, ERROR) or self.below_for_s > 0.0

    @property
    def past_delta(self) -> bool:
        return self.level == ERROR


def _check(value: Optional[float], what: str, allow_zero: bool) -> Optional[float]:
    return None if value is None else _number(value, what, allow_zero)


def _number(value: float, what: str, allow_zero: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f'{what} must be a {"non-negative" if allow_zero else "positive"} '
                         f'number, got {value!r}')
    return float(value)


class DeltaJudge:
    """The Δ rule (see the module) for one connection, fed its arrivals as they come.

    ``add(t)`` records an arrival; ``verdict(now)`` judges at ``now``. Times are seconds on one
    monotonic clock of the caller's choosing; nothing here reads a clock. ``started`` is when
    listening began: a connection never heard is silent from ``started + T``. Without a
    freq_min (an unmonitored connection) every verdict is OK.
    """

    def __init__(self, freq_min_hz: Optional[float], tolerance_s: Optional[float],
                 started: float = 0.0, window_s: float = DEFAULT_WINDOW_S,
                 stall_allowance_s: float = STALL_ALLOWANCE_S):
        self.freq_min_hz = _check(freq_min_hz, 'freq_min_hz', allow_zero=True)
        self.tolerance_s = _check(tolerance_s, 'tolerance_s', allow_zero=True)
        self.window_s = _number(window_s, 'window_s', allow_zero=False)
        self.stall_allowance_s = _number(stall_allowance_s, 'stall_allowance_s',
                                         allow_zero=True)
        self.period_s = min_period_s(self.freq_min_hz)
        self.silence_s = self.period_s + self.stall_allowance_s
        self._last = started              # the last arrival, or when listening began
        self._heard = False
        # (end time, at most 1/freq_min) of each interval ending within the window, and how
        # many of them are that short: the lower median is longer than 1/freq_min exactly when
        # no more than (n - 1) // 2 of the n intervals are short (no sorting per message).
        self._intervals: Deque[Tuple[float, bool]] = deque()
        self._short = 0
        self._since: Optional[float] = None
        self._ended: List[Tuple[float, float]] = []

    @property
    def monitored(self) -> bool:
        """Whether this judge has a freq_min to be below (``min_period_s`` is finite)."""
        return math.isfinite(self.period_s)

    def add(self, t: float) -> None:
        """One message heard at ``t`` (a clock going backwards is clamped)."""
        if not self.monitored:
            return
        t = max(t, self._last)
        if t - self._last > self.silence_s and self._since is None:
            self._since = self._last + self.silence_s
        if self._heard:
            # A publisher at exactly freq_min is not below it by a rounding error.
            short = t - self._last <= self.period_s * (1.0 + 1e-9)
            self._intervals.append((t, short))
            self._short += short
        self._last, self._heard = t, True
        horizon = t - self.window_s
        while self._intervals and self._intervals[0][0] < horizon:
            self._short -= self._intervals.popleft()[1]
        n = len(self._intervals)
        slow = n >= 2 and self._short <= (n - 1) // 2
        if self._since is not None and not slow:
            self._ended.append((self._since, t))
            self._since = None
        elif self._since is None and slow:
            self._since = t

    def below_since(self, now: float) -> Optional[float]:
        """Start of the stretch below freq_min open at ``now``, or None."""
        if not self.monitored:
            return None
        if self._since is not None:
            return self._since
        if now - self._last > self.silence_s:
            return self._last + self.silence_s
        return None

    def take_ended(self) -> List[Tuple[float, float]]:
        """The stretches below that ended since the last call, oldest first."""
        ended, self._ended = self._ended, []
        return ended

    def verdict(self, now: float) -> ConnectionVerdict:
        since = self.below_since(now)
        ended = max((b - a for a, b in self.take_ended()), default=0.0)
        return ConnectionVerdict.judge(time_below(since, now), self.tolerance_s,
                                       since is not None,
                                       silent=now - self._last > self.silence_s,
                                       ended_below_s=ended)


def below_spans(arrivals: Iterable[float], freq_min_hz: Optional[float], start: float,
                end: float, window_s: float = DEFAULT_WINDOW_S,
                stall_allowance_s: float = STALL_ALLOWANCE_S) -> List[Tuple[float, float]]:
    """Every stretch below freq_min in [start, end] of a topic heard at ``arrivals`` (sorted),
    by the same rule as ``DeltaJudge``; listening began at ``start``, and a stretch still open
    at ``end`` closes there. Arrivals before ``start`` (up to a window's worth) set the
    intervals the first judgement sees."""
    if not math.isfinite(min_period_s(freq_min_hz)):
        return []
    times = list(arrivals)
    before = [t for t in times if start - window_s <= t < start]
    judge = DeltaJudge(freq_min_hz, None, before[0] if before else start, window_s,
                       stall_allowance_s)
    spans: List[Tuple[float, float]] = []
    for t in before:
        judge.add(t)
    judge.take_ended()
    for t in times:
        if start <= t <= end:
            judge.add(t)
    spans.extend(judge.take_ended())
    open_since = judge.below_since(end)
    if open_since is not None and open_since < end:
        spans.append((open_since, end))
    return [(max(a, start), b) for a, b in spans if b > start]


# --- the decider's Δ timer, from the probes' readings -------------------------------------

def below_start(reading: Optional[ConnectionObs], now: float, settings: DeciderSettings,
                heard_from: float, start: Optional[float] = None,
                unjudged_until: float = -math.inf) -> Optional[float]:
    """Start of a connection's stretch below freq_min at ``now``, from its latest reading
    (None: not below), continuing the stretch that began at ``start``.

    A fresh reading its probe judged below opens (or continues) the stretch, and the probe's
    own ``below_for_s`` can only move its start earlier (the probe saw the drop before the
    reading arrived); a fresh reading not judged below closes it. A missing or stale reading is
    0 Hz from the moment it went missing: its stamp plus ``observation_max_age_s``, or for a
    connection never reported ``heard_from`` (when listening began; -inf: missing at once)
    plus that age, and never before ``unjudged_until`` (the last time it was not judged).
    """
    if reading is not None and is_fresh(reading.stamp, now, settings):
        if not reading.below:
            return None
        probe_start = reading.stamp - max(0.0, reading.below_for_s)
        return min(probe_start, now) if start is None else min(start, probe_start)
    missing_from = max((reading.stamp if reading is not None else heard_from)
                       + settings.observation_max_age_s, unjudged_until)
    if now >= missing_from:
        return missing_from if start is None else min(start, missing_from)
    return start


class DeltaTracker:
    """Continuous time each monitored connection has spent below its freq_min, by
    ``below_start`` on each update's readings.

    Driven by observation times, not a wall clock; a connection never reported is heard from
    the tracker's first update. A connection in ``obs.unjudged_connections`` (its probe's agent
    silent or just restarted) is not timed: its timer is reset, and a reading still missing
    afterwards counts as missing from the last update that did not judge it.
    """

    def __init__(self, deployment: Deployment):
        self.deployment = deployment
        self._since: Dict[str, float] = {}       # connection -> start of its time below
        self._unjudged_at: Dict[str, float] = {}  # connection -> last update that skipped it
        self._started: Optional[float] = None

    @property
    def started(self) -> Optional[float]:
        return self._started

    def update(self, obs: Observations, settings: DeciderSettings) -> Mapping[str, float]:
        now = obs.now
        if self._started is None:
            self._started = now
        out: Dict[str, float] = {}
        for c in self.deployment.connections:
            if not c.monitored:
                continue
            if c.name in obs.unjudged_connections:
                self._unjudged_at[c.name] = now
                self._since.pop(c.name, None)
                out[c.name] = 0.0
                continue
            start = below_start(obs.connections.get(c.name), now, settings, self._started,
                                self._since.get(c.name),
                                self._unjudged_at.get(c.name, -math.inf))
            if start is None:
                self._since.pop(c.name, None)
            else:
                self._since[c.name] = start
            out[c.name] = time_below(start, now)
        return frozen_map(out)
