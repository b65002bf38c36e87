"""An input's silences as the node that takes it lives them, for its log.

Pure: the caller passes the time at which its callback ran. The probes and the test-bed's
observer measure a connection from their own processes; only the subscriber itself can say
whether it went without its input (a node starved of CPU runs its callbacks late, whatever the
network did). A gap is said when it is longer than ``floor_s`` and ``factor`` times the input's
usual interval (a running mean), one line per ``every_s`` at most, with a count of the others.
"""

from typing import Optional

FLOOR_S = 0.15
FACTOR = 4.0
EVERY_S = 10.0


class InputGaps:
    def __init__(self, floor_s: float = FLOOR_S, factor: float = FACTOR,
                 every_s: float = EVERY_S):
        self.floor_s = floor_s
        self.factor = factor
        self.every_s = every_s
        self._last: Optional[float] = None
        self._usual: Optional[float] = None        # running mean of the intervals (s)
        self._said_at: Optional[float] = None
        self._held = 0
        self._held_longest = 0.0

    def heard(self, now: float) -> Optional[str]:
        """One input taken at ``now``; a line to log when it ended a gap worth saying."""
        last, self._last = self._last, now
        if last is None:
            return None
        gap = now - last
        usual = self._usual
        self._usual = gap if usual is None else 0.9 * usual + 0.1 * min(gap, 10.0 * usual)
        if usual is None or gap <= max(self.floor_s, self.factor * usual):
            return None
        if self._said_at is not None and now - self._said_at < self.every_s:
            self._held += 1
            self._held_longest = max(self._held_longest, gap)
            return None
        line = f'no input for {gap:.2f} s (usually every {usual:.3f} s)'
        if self._held:
            line += (f'; {self._held} more gaps in the last {now - self._said_at:.0f} s, the '
                     f'longest {self._held_longest:.2f} s')
        self._said_at, self._held, self._held_longest = now, 0, 0.0
        return line


__all__ = ['InputGaps']
