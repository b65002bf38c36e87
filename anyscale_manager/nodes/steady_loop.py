"""The periodic work of a process that spins its own loop (the agent's, the decider's): jobs
the loop runs between two callbacks of its executor, not rclpy timers (``SteadyLoop``).

A node's code asks for ``steady_timer(node, period_s, callback)`` and gets a job of the loop
that serves its context (``serve_timers``), or a plain rclpy timer where none does (a node spun
by another executor, in a test); ``destroy_steady`` undoes either.
"""

import time
from typing import Callable, Dict, List, Optional


class LoopTimer:
    """A periodic job run by the spinning loop (``SteadyLoop``), with what the package uses of
    an rclpy timer: ``timer_period_ns`` (read and set: from the next call on), ``reset()``
    (next call one period from now), ``cancel()``, ``is_canceled()``,
    ``time_until_next_call()``. Used from the loop's thread only."""

    def __init__(self, loop: 'SteadyLoop', node, period_s: float, callback: Callable[[], None]):
        self._loop, self.node, self.callback = loop, node, callback
        self.timer_period_ns = round(period_s * 1e9)
        self.canceled = False
        self.next_at = time.monotonic() + period_s

    def reset(self) -> None:
        self.canceled = False
        self.next_at = time.monotonic() + self.timer_period_ns / 1e9

    def cancel(self) -> None:
        self.canceled = True

    def is_canceled(self) -> bool:
        return self.canceled

    def time_until_next_call(self) -> Optional[int]:
        if self.canceled:
            return None
        return max(0, round((self.next_at - time.monotonic()) * 1e9))

    def destroy(self) -> None:
        self._loop.remove(self)


class SteadyLoop:
    """The periodic jobs of a process that spins its own loop (the agent's, the decider's),
    run by that loop between two callbacks of the executor rather than by rclpy timers.

    rclpy's events executor (Jazzy, 7.1) queues a dispatch of a ready timer at every update of
    its timers that runs before the first dispatch does (each reset of any timer queues one),
    and rcl moves a timer a period ahead at each dispatch: on a busy loop a 0.5 s timer was
    called 33 times at once, then not for 12.5 s while the loop sat idle
    (test/test_steady_loop.py). On a robot booting under its CPU quota the agents' reports
    and connection status went quiet for 1.5-8 s that way and their deciders counted them gone.
    Setting such a timer back (a reset) queues another update, which dispatches the other ready
    timers again: no repair from inside holds. Here a job is due at its period on the monotonic
    clock, missed periods are skipped (as rcl does), and the loop waits in the executor no longer
    than until the next job is due: a job runs once a period, ahead of a backlog of messages."""

    SLACK_S = 0.0005        # a wait may end this much early

    def __init__(self):
        self._timers: List[LoopTimer] = []

    def timer(self, node, period_s: float, callback: Callable[[], None]) -> LoopTimer:
        timer = LoopTimer(self, node, period_s, callback)
        self._timers.append(timer)
        return timer

    def remove(self, timer: LoopTimer) -> None:
        if timer in self._timers:
            self._timers.remove(timer)

    def drop(self, node) -> None:
        """Forget every job of ``node`` (before it is destroyed)."""
        self._timers = [t for t in self._timers if t.node is not node]

    def wait_s(self, most_s: float) -> float:
        """How long the loop may wait for a callback: until the next job is due, ``most_s``
        at most."""
        now = time.monotonic()
        due = min((t.next_at for t in self._timers if not t.canceled), default=now + most_s)
        return min(most_s, max(0.0, due - now))

    def run_due(self, failed: Callable[[BaseException], None]) -> None:
        """Run every job due now, in the order they were made; ``failed`` is told of an
        exception of one, and the others run."""
        now = time.monotonic()
        for timer in list(self._timers):
            if timer.canceled or now < timer.next_at - self.SLACK_S \
                    or timer not in self._timers:
                continue
            period = timer.timer_period_ns / 1e9
            timer.next_at += period
            if timer.next_at <= now:
                timer.next_at = now + period
            try:
                timer.callback()
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as e:      # noqa: B902 - one job's bug stops no other
                failed(e)


_LOOPS: Dict[int, SteadyLoop] = {}      # id(rclpy context) -> its process's loop


def serve_timers(context) -> SteadyLoop:
    """From now on the steady timers of nodes of ``context`` are jobs of the returned loop,
    which the caller runs (``wait_s``, ``run_due``) until ``release_timers``."""
    loop = SteadyLoop()
    _LOOPS[id(context)] = loop
    return loop


def release_timers(context) -> None:
    _LOOPS.pop(id(context), None)


def steady_timer(node, period_s: float, callback: Callable[[], None], **kwargs):
    """A periodic timer of ``node``: a job of its process's SteadyLoop where one serves its
    context (the agent's and the decider's processes), else ``node.create_timer(period_s,
    callback, **kwargs)`` (a node spun by another executor, in a test)."""
    loop = _LOOPS.get(id(node.context))
    if loop is not None:
        return loop.timer(node, period_s, callback)
    return node.create_timer(period_s, callback, **kwargs)


def destroy_steady(node, timer) -> None:
    """Undo ``steady_timer``."""
    if isinstance(timer, LoopTimer):
        timer.destroy()
    else:
        node.destroy_timer(timer)


__all__ = ['LoopTimer', 'SteadyLoop', 'destroy_steady', 'release_timers', 'serve_timers',
           'steady_timer']
