"""The Δ rule: when a connection is below its freq_min, and for how long, from its arrivals.

This is the one judge of the package: the probes, the decider (through the probes' readings),
the status view, /diagnostics, the test-bed's observer, the soak, the benches and the demo all
judge a connection with it, so every figure means the same thing.

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
longer than Δ (so Δ = 0 tolerates no stretch at all).
"""

import math
from collections import deque
from dataclasses import dataclass
from typing import Deque, Iterable, List, Optional, Tuple

from ..protocol import ERROR, OK, WARN

# A receiver stall forgiven before silence counts: far below any Δ worth setting, above the
# 50 ms batches in which the probes take their messages and the scheduling stalls of a
# loaded scale (a 40 Hz topic on the test-bed's CPU-capped robot waits up to ~0.17 s at
# times); below 0.1 s, so that an outage of Δ + 1/freq_min + 0.1 s is always a violation.
STALL_ALLOWANCE_S = 0.09
DEFAULT_WINDOW_S = 2.0


@dataclass(frozen=True)
class ConnectionVerdict:
    """One connection's judgement by the Δ rule at one instant."""

    below_for_s: float            # length of the open stretch below freq_min (0 when none)
    level: int                    # OK, WARN (below, within Δ), ERROR (below for longer than Δ)
    silent: bool                  # nothing heard for longer than 1/freq_min + the allowance
    ended_below_s: float = 0.0    # longest stretch that ended since the previous verdict


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
        self.freq_min_hz = _check(freq_min_hz, 'freq_min_hz', allow_zero=True) or None
        self.tolerance_s = _check(tolerance_s, 'tolerance_s', allow_zero=True)
        self.window_s = _number(window_s, 'window_s', allow_zero=False)
        self.stall_allowance_s = _number(stall_allowance_s, 'stall_allowance_s',
                                         allow_zero=True)
        self.period_s = 1.0 / self.freq_min_hz if self.freq_min_hz else math.inf
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
        return self.freq_min_hz is not None

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
        below = 0.0 if since is None else max(0.0, now - since)
        ended = max((b - a for a, b in self.take_ended()), default=0.0)
        if since is None:
            level = OK
        else:
            tolerance = math.inf if self.tolerance_s is None else self.tolerance_s
            level = ERROR if below > tolerance else WARN
        return ConnectionVerdict(below, level, now - self._last > self.silence_s, ended)


def below_spans(arrivals: Iterable[float], freq_min_hz: Optional[float], start: float,
                end: float, window_s: float = DEFAULT_WINDOW_S,
                stall_allowance_s: float = STALL_ALLOWANCE_S) -> List[Tuple[float, float]]:
    """Every stretch below freq_min in [start, end] of a topic heard at ``arrivals`` (sorted),
    by the same rule as ``DeltaJudge``; listening began at ``start``, and a stretch still open
    at ``end`` closes there. Arrivals before ``start`` (up to a window's worth) set the
    intervals the first judgement sees."""
    if freq_min_hz is None or freq_min_hz <= 0:
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
