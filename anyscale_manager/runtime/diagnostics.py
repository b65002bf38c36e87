"""How often a status goes out on /diagnostics: once a second, as ROS's diagnostic_updater
publishes, and at once when its level changes (an error is never held back). The project's own
topics carry every reading at its own rate; /diagnostics is for people and aggregators, and
each status there costs its publisher a message of a dozen key-value pairs. Pure, clock
passed in.
"""

from typing import Dict, Tuple

PERIOD_S = 1.0


class DiagnosticsGate:
    """Per status name: whether a status of ``level`` is due now."""

    def __init__(self, period_s: float = PERIOD_S):
        if not period_s >= 0.0:
            raise ValueError(f'a diagnostics period must be >= 0 s, got {period_s!r}')
        self.period_s = period_s
        self._last: Dict[str, Tuple[int, float]] = {}      # name -> (level, sent at)

    def due(self, name: str, level: int, now: float) -> bool:
        """Whether to publish status ``name`` at ``level`` now: its first, a change of level,
        or a period since the last one sent. A True answer counts as sent."""
        last = self._last.get(name)
        if last is not None and last[0] == level and now - last[1] < self.period_s:
            return False
        self._last[name] = (level, now)
        return True


__all__ = ['DiagnosticsGate', 'PERIOD_S']
