"""The system clock on the monotonic one: DDS and the kernel stamp on the first, the monitors
judge on the second."""

import time
from typing import Callable


def clock_offset_s(attempts: int = 5, monotonic: Callable[[], float] = time.monotonic,
                   wall: Callable[[], float] = time.time) -> float:
    """System clock minus monotonic clock, from the tightest of a few readings of the system
    clock between two of the monotonic one: a thread preempted between two plain reads (a
    loaded machine, tens of milliseconds) would shift a whole batch of arrivals by that much."""
    best_width, best = float('inf'), 0.0
    for _ in range(attempts):
        before = monotonic()
        stamp = wall()
        after = monotonic()
        if after - before < best_width:
            best_width, best = after - before, stamp - (before + after) / 2.0
        if best_width < 1e-4:
            break
    return best
