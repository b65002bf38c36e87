"""Pure statistics of the monitors: rate windows, heartbeats, writers (the Δ rule is
runtime/delta.py; a link's bandwidth, runtime/bandwidth.py).

Nothing here reads a clock or touches ROS: every method takes ``now`` (seconds on one monotonic
clock of the caller's choosing), so the same classes run in the probes, in the simulator and in
unit tests with a hand-written clock.
"""

import math
from collections import deque
from typing import Deque, Dict, List, Optional

from .delta import min_period_s


def _positive(value: float, what: str) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) \
            or not math.isfinite(value) or value <= 0:
        raise ValueError(f'{what} must be a positive number, got {value!r}')
    return float(value)


class RateWindow:
    """Message rate and bytes per second of one topic over a time window.

    Arrivals older than ``window_s`` are forgotten, except that the last two arrivals are always
    kept so that a topic slower than the window (0.5 Hz in a 2 s window) still reads its rate
    instead of flickering between 0 and a guess. The rate is the least-squares slope of arrival
    count against arrival time over the kept arrivals: exact for a periodic publisher (a count
    over the window would be off by up to one message) and, unlike ``(n - 1) / span``, hardly
    moved by a receiver stall that stamps a batch late at an edge of the window. Once the silence
    since the last arrival grows longer than the mean interval (plus ``stall_allowance_s``, so
    that a receiver busy for a moment does not read as a slower topic), the open gap counts as
    an interval in progress, ``n / (span + gap)``, so the rate decays smoothly; it reads 0 once
    nothing arrived for
    ``max(window_s, 2 x the last interval)``: a fast topic that stops reads 0 within one window,
    a slow one is declared stopped after missing about two of its own periods.
    """

    def __init__(self, window_s: float, stall_allowance_s: float = 0.1):
        self.window_s = _positive(window_s, 'window_s')
        if not 0.0 <= stall_allowance_s < self.window_s:
            raise ValueError(f'stall_allowance_s must be in [0, window_s), '
                             f'got {stall_allowance_s!r}')
        self.stall_allowance_s = stall_allowance_s
        self._times: Deque[float] = deque()
        self._sizes: Deque[int] = deque()
        self._bytes = 0
        self.count = 0            # every arrival ever recorded
        self.total_bytes = 0

    def add(self, now: float, nbytes: int = 0) -> None:
        """Record one arrival of ``nbytes`` at ``now`` (a clock going backwards is clamped)."""
        if self._times and now < self._times[-1]:
            now = self._times[-1]
        nbytes = max(0, int(nbytes))
        self._times.append(now)
        self._sizes.append(nbytes)
        self._bytes += nbytes
        self.count += 1
        self.total_bytes += nbytes
        self._trim(now)

    def _trim(self, now: float) -> None:
        horizon = now - self.window_s
        while len(self._times) > 2 and self._times[0] < horizon:
            self._times.popleft()
            self._bytes -= self._sizes.popleft()

    def last_arrival(self) -> Optional[float]:
        return self._times[-1] if self._times else None

    def rate_hz(self, now: float) -> float:
        self._trim(now)
        n = len(self._times)
        if n < 2:
            return 0.0
        first, last = self._times[0], self._times[-1]
        silence = now - last
        last_interval = last - self._times[-2]
        if silence > max(self.window_s, 2.0 * last_interval):
            return 0.0
        span = last - first
        if span <= 0.0:
            # Several arrivals with one stamp: fall back to a count over the window.
            return n / self.window_s
        mean_interval = span / (n - 1)
        gap = max(mean_interval, silence - self.stall_allowance_s)
        return min(self._slope(), n / (span + gap))

    def _slope(self) -> float:
        """Least-squares arrivals per second over the kept arrivals.

        Equal to (n - 1) / span for evenly spaced arrivals, but a receiver stall at an edge of
        the window (a batch of messages stamped late, all at once) moves it by a small fraction
        of what it moves the end-to-end ratio.
        """
        times = self._times
        n = len(times)
        if n == 2:
            return 1.0 / (times[1] - times[0])
        t0 = times[0]
        mean_t = sum(t - t0 for t in times) / n
        mean_k = (n - 1) / 2.0
        cov = var = 0.0
        for k, t in enumerate(times):
            d = t - t0 - mean_t
            cov += d * (k - mean_k)
            var += d * d
        return cov / var if var > 0.0 else (n - 1) / (times[-1] - t0)

    def bytes_per_s(self, now: float) -> float:
        rate = self.rate_hz(now)
        if rate <= 0.0:
            return 0.0
        return rate * self._bytes / len(self._times)

    def recent_bytes_per_s(self, now: float, span_s: float) -> float:
        """Bytes per second that arrived in the last ``span_s`` (at most the window): what a
        link delivers now, where ``bytes_per_s`` still remembers the window's older part."""
        span_s = min(_positive(span_s, 'span_s'), self.window_s)
        total = 0
        for t, size in zip(reversed(self._times), reversed(self._sizes)):
            if t <= now - span_s:
                break
            total += size
        return total / span_s

    def reset(self) -> None:
        self._times.clear()
        self._sizes.clear()
        self._bytes = 0


class HeartbeatTracker:
    """Round-trip time, loss and up/down of one link from numbered heartbeats.

    Down follows BFD's detection rule: the link is down once no echo has arrived for
    ``misses_down`` heartbeat periods and at least ``misses_down`` beats have been sent since the
    last one; it is up again at the first valid echo. Before any echo it is down (nothing proves
    it works). The count of beats matters when the judging process itself stalls (a loaded
    scale, a paused machine): it sent no beats meanwhile, and the echoes of those it did send
    wait in its queue, so its silence then is no evidence against the link. A
    beat counts as lost when its echo has not come back within ``misses_down`` periods; loss is
    the fraction lost among the last ``loss_window`` beats whose fate is known. Echoes of unknown
    or forgotten sequence numbers are ignored; the round-trip time is computed from our own send
    record, never from a value carried by the echo.

    Queueing delay is how a full link shows first: its queue grows before anything is lost. It is
    the round-trip time beyond the base (the least seen among the last ``base_window`` echoes),
    as reached by ``agree`` of the last ``recent`` beats, an unanswered beat counting as waiting
    since it was sent (a lower bound that keeps growing if it was dropped). One late echo (a
    scheduling hiccup on a loaded scale) does not make it; a queue that holds every beat does.
    Nor does a stall of the judge itself: a beat sent more than ``stall_s`` after its period
    (the process was starved, and the echoes of the beats before it were read late, as late as
    a full queue would return them) starts the judgement afresh from that beat.
    """

    def __init__(self, period_s: float, misses_down: int, loss_window: int = 40,
                 base_window: int = 240, recent: int = 4, agree: int = 3,
                 stall_s: float = math.inf):
        self.period_s = _positive(period_s, 'period_s')
        self.stall_s = stall_s if stall_s == math.inf else _positive(stall_s, 'stall_s')
        self._judged_from = -math.inf      # beats sent earlier say nothing of a queue
        if not isinstance(misses_down, int) or misses_down < 1:
            raise ValueError(f'misses_down must be an integer >= 1, got {misses_down!r}')
        if loss_window < 1:
            raise ValueError(f'loss_window must be >= 1, got {loss_window!r}')
        if base_window < loss_window:
            raise ValueError(f'base_window must be >= loss_window ({loss_window}), got '
                             f'{base_window!r}')
        if not 1 <= agree <= recent:
            raise ValueError(f'need 1 <= agree <= recent, got agree={agree!r}, '
                             f'recent={recent!r}')
        self.misses_down = misses_down
        self.loss_window = loss_window
        self.recent = recent
        self.agree = agree
        self._sent: Dict[int, float] = {}          # seq -> send time, pending beats
        self._fates: Deque[bool] = deque(maxlen=loss_window)   # True = answered
        self._rtts: Deque[float] = deque(maxlen=base_window)    # of the answered beats
        self._last: Deque[list] = deque(maxlen=recent)   # [seq, sent, rtt or None]
        self._next_seq = 0
        self._sent_since_echo = 0
        # Send times of the beats since the last echo (the last few): a beat is evidence of
        # silence only once it has had a period to be answered.
        self._pending_times: Deque[float] = deque(maxlen=max(8, 2 * misses_down))
        self.last_echo: Optional[float] = None
        self.last_rtt_s: Optional[float] = None

    @property
    def timeout_s(self) -> float:
        return self.misses_down * self.period_s

    def next_beat(self, now: float) -> int:
        """Register a beat sent at ``now`` and return its sequence number."""
        if self._last and now - self._last[-1][1] > self.period_s + self.stall_s:
            self._judged_from = now
        seq = self._next_seq
        self._next_seq += 1
        self._sent[seq] = now
        self._sent_since_echo += 1
        self._pending_times.append(now)
        self._last.append([seq, now, None])
        self._expire(now)
        return seq

    def echo(self, now: float, seq: int) -> Optional[float]:
        """Register the echo of ``seq``; return its round-trip time, or None if not ours."""
        sent = self._sent.pop(seq, None) if isinstance(seq, int) else None
        if sent is None or now < sent:
            return None
        rtt = now - sent
        self._fates.append(True)
        self._rtts.append(rtt)
        for entry in self._last:
            if entry[0] == seq:
                entry[2] = rtt
        self.last_rtt_s = rtt
        if self.last_echo is None or now >= self.last_echo:
            # ``now`` is when the echo arrived, which can be before beats this process has
            # sent since (it read the echo late): those are still waiting for an answer.
            self.last_echo = now
            later = [t for t in self._pending_times if t > now]
            self._pending_times.clear()
            self._pending_times.extend(later)
            self._sent_since_echo = sum(1 for t in self._sent.values() if t > now)
        return rtt

    def _expire(self, now: float) -> None:
        deadline = now - self.timeout_s
        for seq in [s for s, t in self._sent.items() if t < deadline]:
            del self._sent[seq]
            self._fates.append(False)

    def up(self, now: float, allowance_s: float = 0.0) -> bool:
        """Down once no echo came for ``misses_down`` periods and ``misses_down`` beats were
        sent since, spread over at least half their periods: beats sent in one burst by a
        process that was not scheduled (its timer catching up) prove nothing yet.
        ``allowance_s`` more silence is allowed while the watcher knows why the echoes are
        late (its own bandwidth probe filling the link's queue)."""
        if self.last_echo is None:
            return False
        if now - self.last_echo <= self.timeout_s + max(0.0, allowance_s) \
                or self._sent_since_echo < self.misses_down:
            return True
        times = self._pending_times
        return times[-1] - times[0] < 0.5 * (self.misses_down - 1) * self.period_s

    def silence(self, now: float) -> str:
        """What a down verdict rests on, in words: how long without an echo, how many beats went
        unanswered, and how regularly they were sent (beats far apart mean this process was not
        scheduled, not that the link lost them)."""
        if self.last_echo is None:
            return f'no echo yet ({self._sent_since_echo} beats sent)'
        text = (f'no echo for {now - self.last_echo:.2f} s, {self._sent_since_echo} beats '
                'unanswered')
        pending = sorted(t for t in self._sent.values() if t > self.last_echo)
        gaps = [b - a for a, b in zip(pending, pending[1:])]
        if gaps:
            text += (f', sent {min(gaps):.2f}-{max(gaps):.2f} s apart (period '
                     f'{self.period_s:g} s)')
        return text

    def loss(self, now: float) -> float:
        self._expire(now)
        if not self._fates:
            return 0.0
        return sum(1 for f in self._fates if not f) / len(self._fates)

    def base_rtt_s(self) -> Optional[float]:
        """The least round-trip time among the recent echoes: the link with an empty queue."""
        return min(self._rtts) if self._rtts else None

    def queueing_delay_s(self, now: float, since: float = -math.inf) -> Optional[float]:
        """Delay beyond the base reached by ``agree`` of the last ``recent`` beats; None until
        that many beats were sent at or after ``since`` (e.g. the link's return, or the end of
        a throughput probe that filled the queue on purpose) or before any echo."""
        base = self.base_rtt_s()
        since = max(since, self._judged_from)
        beats = [e for e in self._last if e[1] >= since]
        if base is None or len(beats) < self.recent:
            return None
        waits = sorted((e[2] if e[2] is not None else now - e[1]) for e in beats)
        return max(0.0, waits[self.recent - self.agree] - base)

    def rtt_s(self) -> Optional[float]:
        """Median round-trip time of the last ``loss_window`` answered beats (robust to one
        late echo)."""
        if not self._rtts:
            return None
        ordered = sorted(list(self._rtts)[-self.loss_window:])
        mid = len(ordered) // 2
        return ordered[mid] if len(ordered) % 2 else 0.5 * (ordered[mid - 1] + ordered[mid])


class WriterStreams:
    """Tells the writers of one topic apart by their publication sequence numbers.

    Each DDS writer numbers its messages 1, 2, 3, ...; ROS 2 hands that number to a subscriber
    (``publication_sequence_number`` in the message info) but not who sent it. A message whose
    number follows some stream's last one continues the nearest such stream (of several as
    near, the one heard last); one that follows none (at or below every stream's last number)
    comes from a writer that started later than all of them: a new stream. A copy of a node
    started elsewhere for a handover thus shows at
    its first message heard here, its numbers starting near 1 where the old copy's are far past
    that. Losses and interleaving do not matter. A stream not heard for ``forget_s`` is dropped
    (a stopped writer), so that a new copy is not taken for the continuation of an old one.
    """

    def __init__(self, forget_s: float = 3.0, max_streams: int = 16):
        self.forget_s = _positive(forget_s, 'forget_s')
        self.max_streams = max_streams
        self._streams: List[List[float]] = []     # [last number, last heard]
        self._joined: Deque[float] = deque(maxlen=max_streams)   # when a later writer appeared

    def add(self, now: float, seq: object) -> None:
        """One message heard at ``now`` with publication sequence number ``seq`` (ignored when
        the middleware does not give one)."""
        if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
            return
        self._streams = [s for s in self._streams if now - s[1] <= self.forget_s]
        before = [s for s in self._streams if s[0] < seq]
        if before:
            # The nearest number; of streams as near, the one heard last. A writer that stopped
            # during a handover is remembered for forget_s: when the new copy's numbers reach
            # where it stopped, the tie must not hand the new copy's messages to it (that kept
            # the stopped writer "live" and counted two senders for seconds after a handover).
            stream = min(before, key=lambda s: (seq - s[0], -s[1]))
            stream[0], stream[1] = seq, now
            return
        if self._streams:
            self._joined.append(now)
        self._streams.append([seq, now])
        if len(self._streams) > self.max_streams:
            self._streams.remove(min(self._streams, key=lambda s: s[1]))

    @property
    def streams(self) -> int:
        return len(self._streams)

    def live(self, now: float, within_s: float) -> int:
        """How many writers were heard in the last ``within_s``."""
        return sum(1 for s in self._streams if now - s[1] <= within_s)

    def together_at(self, now: float, within_s: float) -> Optional[float]:
        """The last time two of the writers heard in the last ``within_s`` had both been heard
        (the second latest of their last messages), None with fewer than two."""
        heard = sorted((s[1] for s in self._streams if now - s[1] <= within_s), reverse=True)
        return heard[1] if len(heard) >= 2 else None

    def joined_since(self, since: float) -> bool:
        """Whether a writer that started later than the others was first heard at or after
        ``since``."""
        return any(t >= since for t in self._joined)


def live_window_s(freq_min_hz: Optional[float], forget_s: float) -> float:
    """How recently a writer must have been heard to count as sending: two of its periods at
    the connection's minimum rate, at least 0.5 s, at most ``forget_s`` (the streams' own
    memory, ``WriterStreams.forget_s``)."""
    return min(forget_s, max(0.5, 2.0 * min_period_s(freq_min_hz)))


def two_senders_past(senders_for_s: Optional[float], bound_s: float) -> bool:
    """Whether two or more writers have been heard at once for longer than ``bound_s``
    (monitoring.duplicate_sender_s): the one rule the probes, the decider and the status view
    judge a reading's ``senders_for_s`` by."""
    return (senders_for_s or 0.0) > bound_s


class SenderOverlap:
    """How long two or more writers of one topic have been heard at once, from the live
    writers read at each reading (``WriterStreams.live`` and ``WriterStreams.together_at``).

    The overlap runs from the first reading with two live writers to the last time two were
    both heard (``together_at``), not to the reading: a writer counts as live for a window
    after its last message (``live_window_s``), and that window is not time heard at once."""

    def __init__(self) -> None:
        self._since: Optional[float] = None

    def update(self, now: float, live: int, together_at: Optional[float] = None) -> float:
        if live < 2:
            self._since = None
            return 0.0
        last = now if together_at is None else min(now, together_at)
        if self._since is None:
            self._since = last
        return max(0.0, last - self._since)
