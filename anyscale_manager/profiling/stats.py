"""Pure statistics of a profile: a topic's rate as the runtime's probes read it, and CPU.

Nothing here reads a clock: every method takes ``now`` (seconds on one monotonic clock), as
``runtime/rates.py`` does, so a unit test drives it with hand-written times.

A topic's rate is read the way the agents' probes read it once the deployment runs: a
``RateWindow`` over the probes' window (``monitoring.probe_window_s``, 2 s by default), read
once a second. The decider judges ``freq_min_hz`` and ``tolerance_s`` against exactly such
readings, so thresholds suggested from them (``suggest.py``) hold for the run that was watched.
"""

import math
import statistics
from dataclasses import dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from ..model.types import MonitorSettings
from ..runtime.cpu import ProcessGroupCpu
from ..runtime.rates import RateWindow

READING_PERIOD_S = 1.0
PROBE_WINDOW_S = MonitorSettings().probe_window_s


def _statistic(of: Callable[[Sequence[float]], float]) -> property:
    """A statistic of a series' readings, 0 when there are none."""
    return property(lambda series: of(series.readings) if series.readings else 0.0)


@dataclass(frozen=True)
class Series:
    """Readings of one figure, one a period, and their statistics in the readings' unit."""

    readings: Tuple[float, ...]

    lowest = _statistic(min)
    highest = _statistic(max)
    median = _statistic(statistics.median)
    mean = _statistic(statistics.fmean)


@dataclass(frozen=True)
class RateSummary(Series):
    """What one topic did during the watch: its rate readings (Hz), one a period from the
    second arrival."""

    messages: int                      # arrivals counted
    reading_period_s: float
    window_s: float
    total_bytes: int                   # serialized bytes of every arrival
    max_bytes: int                     # the largest message

    @property
    def mean_bytes(self) -> float:
        return self.total_bytes / self.messages if self.messages else 0.0

    def longest_below_s(self, threshold_hz: float) -> float:
        """The longest stretch of consecutive readings below ``threshold_hz``, in seconds."""
        return longest_run_below(self.readings, threshold_hz) * self.reading_period_s


def longest_run_below(values: Sequence[float], threshold: float) -> int:
    """The length of the longest run of consecutive values below ``threshold``."""
    best = run = 0
    for v in values:
        run = run + 1 if v < threshold else 0
        best = max(best, run)
    return best


class TopicMeter:
    """Arrivals of one topic (with their serialized sizes) and its rate readings."""

    def __init__(self, window_s: float = PROBE_WINDOW_S,
                 reading_period_s: float = READING_PERIOD_S):
        if not (isinstance(reading_period_s, (int, float)) and math.isfinite(reading_period_s)
                and reading_period_s > 0):
            raise ValueError(f'reading_period_s must be a positive number, got '
                             f'{reading_period_s!r}')
        self.window = RateWindow(window_s)
        self.reading_period_s = float(reading_period_s)
        self.readings: List[float] = []
        self.max_bytes = 0

    @property
    def messages(self) -> int:
        return self.window.count

    def add(self, now: float, nbytes: int) -> None:
        """One message of ``nbytes`` serialized bytes arrived at ``now``."""
        self.window.add(now, nbytes)
        self.max_bytes = max(self.max_bytes, int(nbytes))

    def sample(self, now: float) -> Optional[float]:
        """Take one reading (call once a reading period); None before the second arrival, when
        the topic has no rate yet: a topic whose subscription was matched late is not read as
        slow before its first messages."""
        if self.window.count < 2:
            return None
        rate = self.window.rate_hz(now)
        self.readings.append(rate)
        return rate

    def summary(self) -> RateSummary:
        return RateSummary(messages=self.window.count, readings=tuple(self.readings),
                           reading_period_s=self.reading_period_s,
                           window_s=self.window.window_s, total_bytes=self.window.total_bytes,
                           max_bytes=self.max_bytes)


@dataclass(frozen=True)
class CpuSummary(Series):
    """CPU of one process (with its descendants) in cores of this host: 1.0 = one core busy."""

    def share(self, parts: int) -> 'CpuSummary':
        """This process's CPU split evenly over ``parts`` nodes that share it."""
        return CpuSummary(tuple(r / parts for r in self.readings)) if parts > 1 else self


class CpuMeter:
    """Per process: CPU seconds per wall second of the process and its descendants, one
    reading per ``update`` after the first (which only primes)."""

    def __init__(self):
        self._counter = ProcessGroupCpu()
        self.readings: Dict[int, List[float]] = {}

    def update(self, now: float, samples: Mapping[int, Mapping[int, float]]) -> None:
        """``samples``: process id -> {pid of it or a descendant: cumulative CPU seconds}."""
        rates = self._counter.update(now, {str(pid): per_pid for pid, per_pid in samples.items()})
        for key, rate in rates.items():
            self.readings.setdefault(int(key), []).append(rate)

    def summary(self, pid: int) -> Optional[CpuSummary]:
        readings = self.readings.get(pid)
        return CpuSummary(tuple(readings)) if readings else None


def round_sig(value: float, digits: int = 3, mode: str = 'nearest') -> float:
    """``value`` to ``digits`` significant digits, rounded to the nearest, 'down' or 'up'."""
    if value == 0 or not math.isfinite(value):
        return value
    exponent = digits - 1 - math.floor(math.log10(abs(value)))
    scaled = value * 10 ** exponent if exponent >= 0 else value / 10 ** -exponent
    # A value a hair off a round number (9.999999999 from float arithmetic) is that number.
    nearest = round(scaled)
    if abs(scaled - nearest) < 1e-9 * max(1.0, abs(scaled)):
        scaled = nearest
    if mode == 'down':
        scaled = math.floor(scaled)
    elif mode == 'up':
        scaled = math.ceil(scaled)
    else:
        scaled = round(scaled)
    return scaled / 10 ** exponent if exponent >= 0 else float(scaled * 10 ** -exponent)
