"""One log line per kind of bad input and interval, with a count of the lines held back.

Pure: any logger with ``warning`` and ``error`` (rclpy's, or a test's), the clock passed in. A
broken or hostile publisher can send thousands of bad messages a second. Each kind of bad input
(a key the caller picks from a fixed set, never from the message: a topic and what was wrong with
it) is logged at once the first time; then, for ``interval_s``, it is only counted, and one line
says how many were held back and the last reason. rclpy's ``throttle_duration_sec`` throttles
per call site rather than per topic, and counts nothing.
"""

import time
from dataclasses import dataclass
from typing import Callable, Dict, Optional

DEFAULT_INTERVAL_S = 10.0
# Above what a node's keys can number (its topics times the kinds of bad input,
# protocol.DECODE_ERRORS and protocol_auth.REFUSALS): a kind is forgotten only past it, and
# what it held back is said first.
MAX_KINDS = 512


@dataclass
class _Kind:
    logged_at: float
    interval_s: float
    level: str
    held: int = 0
    last: str = ''


class ThrottledLog:
    def __init__(self, logger, interval_s: float = DEFAULT_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic):
        self._logger = logger
        self.interval_s = interval_s
        self._clock = clock
        self._kinds: Dict[str, _Kind] = {}
        self.total = 0            # every bad input noted, logged or held back

    def warn(self, key: str, text: str, interval_s: Optional[float] = None) -> None:
        self._note(key, 'warn', text, interval_s)

    def error(self, key: str, text: str, interval_s: Optional[float] = None) -> None:
        self._note(key, 'error', text, interval_s)

    def _note(self, key: str, level: str, text: str, interval_s: Optional[float]) -> None:
        now = self._clock()
        self.total += 1
        kind = self._kinds.get(key)
        if kind is not None and now - kind.logged_at < kind.interval_s:
            kind.held += 1
            kind.last = text
            return
        if kind is None:
            if len(self._kinds) >= MAX_KINDS:
                oldest = min(self._kinds, key=lambda k: self._kinds[k].logged_at)
                gone = self._kinds.pop(oldest)
                if gone.held:
                    self._emit(gone.level, gone.last + self._held_note(gone, now))
            kind = self._kinds[key] = _Kind(now, interval_s or self.interval_s, level)
        line = text + self._held_note(kind, now)
        kind.logged_at, kind.held, kind.level = now, 0, level
        self._emit(level, line)

    def flush(self) -> None:
        """Say how many were held back, for each kind whose interval is over."""
        now = self._clock()
        for kind in self._kinds.values():
            if kind.held and now - kind.logged_at >= kind.interval_s:
                line = kind.last + self._held_note(kind, now)
                kind.logged_at, kind.held = now, 0
                self._emit(kind.level, line)

    @staticmethod
    def _held_note(kind: _Kind, now: float) -> str:
        if not kind.held:
            return ''
        return f' [{kind.held} more like this in the last {now - kind.logged_at:.0f} s]'

    def _emit(self, level: str, line: str) -> None:
        # rclpy refuses one call site with changing severities: one call per level.
        if level == 'error':
            self._logger.error(line)
        else:
            self._logger.warning(line)
