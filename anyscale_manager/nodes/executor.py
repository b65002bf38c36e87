"""The executor the agent spins on.

rclpy's default executor rebuilds its wait set in Python at every wake-up; an agent has a dozen
probe subscriptions fed at 10-40 Hz, and that was most of its CPU, taken from the weak scale it
runs on (the test-bed robot agent: 18-19 % of a core, 6 % with this one). The events executor
dispatches from C++. It is new in Jazzy's rclpy (``rclpy.experimental``); where it is missing,
the default one is used.
"""

import gc
from typing import Optional

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
    collector would have done (the same thresholds, youngest generation first).

    What is alive by then (the modules, the message classes, the nodes and their entities) is
    moved out of the collector's sight (``gc.freeze``): it lives as long as the program, and a
    full collection that walked it took 17 ms each time, under 2 us once it is frozen
    (``bench/bench_gc_freeze.py``: the agent's and the decider's modules, 40 publishers and 40
    subscriptions). Later objects are collected as before."""
    gc.disable()
    gc.collect()
    gc.freeze()


def collect_due() -> None:
    """The collection the automatic collector would run now, if any (see above)."""
    counts, thresholds = gc.get_count(), gc.get_threshold()
    generation = -1
    for g in range(3):
        if thresholds[g] and counts[g] > thresholds[g]:
            generation = g
    if generation >= 0:
        gc.collect(generation)


__all__ = ['collect_between_callbacks', 'collect_due', 'make_executor']
