"""The project's one blocking stop: SIGINT, a grace, then SIGKILL, for one child or several at
once (real processes)."""

import os
import signal
import subprocess
import sys
import time

from anyscale_manager.agent.procs import stop_all, stop_popen

POLITE = 'import time\nwhile True: time.sleep(0.05)'
STUBBORN = ('import signal, sys, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n'
            'print("ready", flush=True)\nwhile True: time.sleep(0.05)')


def start(code):
    return subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)


def test_stop_all_interrupts_every_child_and_kills_only_the_stubborn_one():
    polite, stubborn = start(POLITE), start(STUBBORN)
    assert stubborn.stdout.readline().strip() == 'ready'    # its SIGINT is ignored from here
    t0 = time.monotonic()
    codes = stop_all([polite, stubborn], 1.0)
    took = time.monotonic() - t0
    assert codes[0] not in (None, -signal.SIGKILL)           # ended by its SIGINT
    assert codes[1] == -signal.SIGKILL
    assert took >= 1.0                                       # the stubborn one had its grace


def test_stop_popen_escalates_to_sigkill_after_the_grace():
    stubborn = start(STUBBORN)
    assert stubborn.stdout.readline().strip() == 'ready'
    assert stop_popen(stubborn, 0.5) == -signal.SIGKILL


TREE = ('import subprocess, sys, time\n'
        'child = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; '
        'g = subprocess.Popen([sys.executable, \\"-c\\", \\"import time; time.sleep(60)\\"], '
        'start_new_session=True); print(g.pid, flush=True); time.sleep(60)"], '
        'stdout=subprocess.PIPE, text=True)\n'
        'print(child.pid, child.stdout.readline().strip(), flush=True)\n'
        'time.sleep(60)')


def test_descendants_are_the_live_tree_the_one_that_left_the_session_included():
    """A node's child and grandchild, the grandchild in a session of its own: both are found
    (by the children files, and by psutil where the kernel has none), nothing else."""
    from anyscale_manager.agent import procs
    leader = start(TREE)
    child = grandchild = None
    try:
        child, grandchild = (int(x) for x in leader.stdout.readline().split())
        assert set(procs.descendants(leader.pid)) == {child, grandchild}
        assert procs.descendants(grandchild) == ()
        procs.CHILDREN_FILES, was = False, procs.CHILDREN_FILES
        try:
            assert set(procs.descendants(leader.pid)) == {child, grandchild}
        finally:
            procs.CHILDREN_FILES = was
        assert procs.descendants(999999999) == ()
    finally:
        stop_all([leader], 0.5)
        for pid in (p for p in (child, grandchild) if p is not None):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
