"""The executor the agent spins on.

rclpy's default executor rebuilds its wait set in Python at every wake-up; an agent has a dozen
probe subscriptions fed at 10-40 Hz, and that was most of its CPU, taken from the weak scale it
runs on (the test-bed robot agent: 18-19 % of a core, 6 % with this one). The events executor
dispatches from C++. It is new in Jazzy's rclpy (``rclpy.experimental``); where it is missing,
the default one is used.
"""

import gc
import time
from typing import Callable, Optional

from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor

try:
    from rclpy.experimental import EventsExecutor
except ImportError:         # an older Jazzy rclpy
    EventsExecutor = None


def make_executor(context: Optional[Context] = None) -> Executor:
    if EventsExecutor is not None:
        return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def collect_between_callbacks() -> None:
    """Python's cyclic garbage collection, run from the spin loop between two callbacks rather
    than wherever an allocation triggers it. Triggered inside a callback, it runs within the
    events executor's C++ dispatch, and a collected rclpy object's finalizer can then wait on
    what that dispatch holds: a decider started in a chaos soak hung until it was killed, its
    thread in "Garbage-collecting" under the executor's EventHandler.__exit__. Called once where a
    program's loop begins; ``collect_due`` after each turn of the loop does what the automatic
    collector would have done (the same thresholds, youngest generation first)."""
    gc.disable()


def collect_due() -> None:
    """The collection the automatic collector would run now, if any (see above)."""
    counts, thresholds = gc.get_count(), gc.get_threshold()
    generation = -1
    for g in range(3):
        if thresholds[g] and counts[g] > thresholds[g]:
            generation = g
    if generation >= 0:
        gc.collect(generation)


def steady_timer(node, period_s: float, callback: Callable[[], None], **kwargs):
    """``node.create_timer(period_s, callback, **kwargs)`` whose callback runs once a period,
    however often the executor dispatches it.

    rclpy's events executor (Jazzy, 7.1) queues a dispatch of a ready timer at every update of
    its timers that runs before the first dispatch does (any timer's reset queues an update,
    and so does each dispatch), and rcl advances a timer by one period at each dispatch: on a
    busy loop a 0.5 s timer was called 33 times at once, then not for 12.5 s while the loop sat
    idle (test/test_executor_timers.py; the robot agents' reports and connection status went
    quiet for 1.5-8 s after a boot under a saturated CPU quota). Here a dispatch less than half
    a period after the last call is not passed on, and a timer left more than a period ahead
    is set back to one period from now. The period is the timer's own at each call (a caller
    may change ``timer_period_ns``)."""
    timer = None
    last = [-float('inf')]

    def fire() -> None:
        now = time.monotonic()
        try:
            if now - last[0] >= timer.timer_period_ns / 2e9:
                last[0] = now
                callback()
        finally:
            left = timer.time_until_next_call()
            if left is not None and left > timer.timer_period_ns:
                timer.reset()

    timer = node.create_timer(period_s, fire, **kwargs)
    return timer


__all__ = ['collect_between_callbacks', 'collect_due', 'make_executor', 'steady_timer']
