"""Periodic jobs of the agent's and the decider's processes (nodes/steady_loop.py):
rclpy's events executor dispatches a ready timer once per queued timer update and rcl moves it a
period ahead at each dispatch, so a plain timer on a busy loop is called many times at once and
then not for as many periods; a job of the loop runs once a period, also after a busy stretch.
Real rclpy, real timers, this process only."""

import time

import pytest

from anyscale_manager.nodes.executor import EventsExecutor, make_executor
from anyscale_manager.nodes.steady_loop import (LoopTimer, release_timers, serve_timers,
                                                steady_timer)
from spinning import RosContext

pytestmark = [pytest.mark.timeout(60),
              pytest.mark.skipif(EventsExecutor is None, reason='rclpy has no events executor')]

PERIOD_S = 0.5
BUSY_S = 2.0        # a loop kept busy this long: each turn 0.3 s of work and 5 timer resets
IDLE_S = 3.0        # then idle this long


def test_a_loop_job_keeps_its_period_through_a_busy_loop_where_a_timer_does_not():
    with RosContext(make_executor) as ros:
        node = ros.node('timers')
        plain, steady = [], []
        node.create_timer(PERIOD_S, lambda: plain.append(time.monotonic()))
        loop = serve_timers(ros.context)
        try:
            job = steady_timer(node, PERIOD_S, lambda: steady.append(time.monotonic()))
        finally:
            release_timers(ros.context)
        assert isinstance(job, LoopTimer)
        # No loop serves the context any more: a plain rclpy timer.
        plain_again = steady_timer(node, 60.0, lambda: None)
        assert not isinstance(plain_again, LoopTimer) and hasattr(plain_again, 'handle')
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
        failures = []
        while time.monotonic() - began < BUSY_S + IDLE_S:
            ros.executor.spin_once(timeout_sec=loop.wait_s(0.1))
            loop.run_due(failures.append)
        ended = time.monotonic()
    assert failures == []

    def report(calls):
        return [round(t - began, 2) for t in calls]
    quiet_after = BUSY_S + 0.3
    # What the executor does to a plain timer here (if it no longer does, SteadyLoop may go).
    gaps = [b - a for a, b in zip(plain, plain[1:] + [ended])]
    assert max(gaps) > 2 * PERIOD_S and min(gaps) < 0.01, report(plain)
    # A job of the loop: never twice at once, and never silent longer than a period and a busy
    # turn (0.3 s; a late call keeps the grid, so the next one comes sooner).
    gaps = [b - a for a, b in zip(steady, steady[1:])]
    assert min(gaps) >= 0.15, report(steady)
    assert max(gaps + [ended - steady[-1]]) <= PERIOD_S + 0.35, report(steady)
    idle = [t - began for t in steady if t - began > quiet_after]
    assert len(idle) >= (BUSY_S + IDLE_S - quiet_after) / PERIOD_S - 1, report(steady)


def test_a_loop_job_is_reset_cancelled_and_its_period_changed_as_a_timer_is():
    with RosContext(make_executor) as ros:
        node = ros.node('loop_jobs')
        loop = serve_timers(ros.context)
        try:
            calls = []
            job = steady_timer(node, 0.2, lambda: calls.append(time.monotonic()))
            assert 0.15e9 < job.time_until_next_call() <= 0.2e9
            assert loop.wait_s(1.0) <= 0.2
            job.cancel()
            assert job.is_canceled() and job.time_until_next_call() is None
            assert loop.wait_s(1.0) == 1.0
            job.timer_period_ns = 50_000_000
            job.reset()
            began = time.monotonic()
            while len(calls) < 3:
                assert time.monotonic() - began < 5.0, calls
                time.sleep(loop.wait_s(0.1))
                loop.run_due(pytest.fail)
            assert calls[0] - began >= 0.05 - loop.SLACK_S
            loop.drop(node)
            assert loop.wait_s(1.0) == 1.0
        finally:
            release_timers(ros.context)


def test_a_job_that_raises_is_told_and_the_others_run():
    loop = serve_timers(object())
    seen, told = [], []

    class Node:
        context = None

    def bad():
        raise ValueError('boom')
    jobs = [loop.timer(Node(), 0.01, bad), loop.timer(Node(), 0.01, lambda: seen.append(1))]
    for job in jobs:
        job.next_at = time.monotonic() - 1      # both due now
    loop.run_due(told.append)
    assert seen == [1] and [str(e) for e in told] == ['boom']
