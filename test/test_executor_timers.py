"""A periodic timer on the events executor the agent and the decider spin on (nodes/executor.py,
steady_timer): while the loop is busy and other timers are reset, the executor dispatches a ready
timer once per queued update and rcl moves it a period ahead at each dispatch; a plain timer is
then called many times at once and not again for as many periods, a steady one once a period.
Real rclpy, real timers, this process only."""

import time

import pytest

from anyscale_manager.nodes.executor import EventsExecutor, make_executor, steady_timer
from spinning import RosContext

pytestmark = [pytest.mark.timeout(60),
              pytest.mark.skipif(EventsExecutor is None, reason='rclpy has no events executor')]

PERIOD_S = 0.5
BUSY_S = 2.0        # a loop kept busy this long: each turn 0.3 s of work and 5 timer resets
IDLE_S = 3.0        # then idle this long


def test_a_steady_timer_keeps_its_period_through_a_busy_loop():
    with RosContext(make_executor) as ros:
        node = ros.node('timers')
        plain, steady = [], []
        node.create_timer(PERIOD_S, lambda: plain.append(time.monotonic()))
        steady_timer(node, PERIOD_S, lambda: steady.append(time.monotonic()))
        other = node.create_timer(60.0, lambda: None)
        began = time.monotonic()

        def busy():
            if time.monotonic() - began > BUSY_S:
                return
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                pass
            for _ in range(5):
                other.reset()
        node.create_timer(0.1, busy)
        while time.monotonic() - began < BUSY_S + IDLE_S:
            ros.executor.spin_once(timeout_sec=0.1)

    def report(calls):
        return [round(t - began, 2) for t in calls]
    quiet_after = BUSY_S + 0.3
    # What the executor does to a plain timer here (if it no longer does, steady_timer may go).
    assert max(b - a for a, b in zip(plain, plain[1:])) > 2 * PERIOD_S \
        or len(plain) > 2 * (BUSY_S + IDLE_S) / PERIOD_S, report(plain)
    # A steady one: never twice within half a period, and once a period once the loop is idle.
    assert min(b - a for a, b in zip(steady, steady[1:])) >= PERIOD_S / 2, report(steady)
    idle = [t - began for t in steady if t - began > quiet_after]
    assert idle and idle[0] - quiet_after <= PERIOD_S + 0.1, report(steady)
    assert max(b - a for a, b in zip(idle, idle[1:])) <= PERIOD_S + 0.1, report(steady)
    assert len(idle) >= (BUSY_S + IDLE_S - quiet_after) / PERIOD_S - 1, report(steady)
