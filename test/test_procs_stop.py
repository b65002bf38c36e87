"""The project's one blocking stop: SIGINT, a grace, then SIGKILL, for one child or several at
once (real processes)."""

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
