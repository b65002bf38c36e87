"""The executor the agent spins on.

rclpy's default executor rebuilds its wait set in Python at every wake-up; an agent has a dozen
probe subscriptions fed at 10-40 Hz, and that was most of its CPU, taken from the weak scale it
runs on (the test-bed robot agent: 18-19 % of a core, 6 % with this one). The events executor
dispatches from C++. It is new in Jazzy's rclpy (``rclpy.experimental``); where it is missing,
the default one is used.
"""

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


__all__ = ['make_executor']
