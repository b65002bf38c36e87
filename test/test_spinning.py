"""The tests' one wait (spinning.py), driven by a fake executor: no context, no DDS."""

import subprocess
import sys

import pytest

from processes import LoggedProcess
from spinning import spin_for, spin_until


class FakeExecutor:
    """Counts its spins; each runs ``work`` (what a callback would do)."""

    def __init__(self, work=lambda: None):
        self.spins = 0
        self.work = work

    def spin_once(self, timeout_sec):
        self.spins += 1
        self.work()


def test_returns_the_conditions_value_once_true():
    ex = FakeExecutor()
    assert spin_until(ex, lambda: ex.spins >= 3 and 'ready', 5.0, 'three spins') == 'ready'
    assert ex.spins == 3


def test_a_condition_already_true_spins_nothing():
    ex = FakeExecutor()
    assert spin_until(ex, lambda: [1], 5.0, 'anything') == [1]
    assert ex.spins == 0


def test_a_timeout_names_what_was_awaited_and_shows_the_state():
    with pytest.raises(AssertionError) as failed:
        spin_until(FakeExecutor(), lambda: False, 0.05, 'the first layout',
                   state=lambda: {'layouts': 0})
    text = str(failed.value)
    assert text.startswith('timed out after 0.05 s waiting for the first layout')
    assert "state: {'layouts': 0}" in text


def test_a_timeout_may_be_allowed_and_gives_the_last_value():
    assert spin_until(FakeExecutor(), lambda: [], 0.05, 'an answer', required=False) == []


def test_spin_for_spins_the_whole_time():
    ex = FakeExecutor()
    spin_for(ex, 0.05)
    assert ex.spins >= 1


def test_tick_is_called_at_its_period_before_spinning():
    calls = []
    ex = FakeExecutor()
    spin_until(ex, lambda: ex.spins >= 5, 5.0, 'five spins', tick=lambda: calls.append(1),
               tick_every_s=60.0)
    assert calls == [1]                   # once at the start, then not again within 60 s
    spin_until(ex, lambda: ex.spins >= 10, 5.0, 'ten spins', tick=lambda: calls.append(1),
               tick_every_s=0.0)
    assert len(calls) == 1 + 5


def test_a_watched_process_ending_ends_the_wait_with_every_output(tmp_path):
    quick = LoggedProcess(tmp_path / 'quick.out',
                          [sys.executable, '-c', 'print("bye from quick")'], None)
    quick.proc.wait(30)
    slow = LoggedProcess(tmp_path / 'slow.out', [sys.executable, '-c',
                                                 'import time; print("slow here", flush=True);'
                                                 ' time.sleep(60)'], None)
    try:
        procs = [('quick', quick), ('slow', slow)]
        # Not watched: the wait goes on to its deadline.
        with pytest.raises(AssertionError, match='timed out after 0.1 s'):
            spin_until(FakeExecutor(), lambda: False, 0.1, 'x', procs, watch=('slow',))
        with pytest.raises(AssertionError) as failed:
            spin_until(FakeExecutor(), lambda: False, 60.0, 'the decider leading', procs,
                       watch=True)
        text = str(failed.value)
        assert text.startswith('quick exited while waiting for the decider leading')
        assert '--- quick (exit 0)\nbye from quick' in text
        assert '--- slow (running)' in text
    finally:
        slow.stop()


def test_an_exited_popens_pipe_is_read_a_running_ones_is_not():
    done = subprocess.Popen([sys.executable, '-c', 'print("the end")'],
                            stdout=subprocess.PIPE, text=True)
    done.wait(30)
    running = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'],
                               stdout=subprocess.PIPE)
    try:
        with pytest.raises(AssertionError) as failed:
            spin_until(FakeExecutor(), lambda: False, 60.0, 'a layout',
                       {'decider': done, 'other': running}, watch=True)
        text = str(failed.value)
        assert '--- decider (exit 0)\nthe end' in text
        assert '--- other (running)\n(still running: output not read)' in text
    finally:
        running.kill()
        running.wait()
        running.stdout.close()
        done.stdout.close()
