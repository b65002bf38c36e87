"""The agent's signals: noted by the handlers, taken by the loop, and waking a loop that waits
in the executor (agent/process.py Signals). Each case runs in a process of its own: the
handlers and the wakeup fd belong to a process's main thread."""

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent('''
    import os, signal, sys, threading, time
    from anyscale_manager.agent.process import RESTART, STOP, Signals

    signals = Signals()
    signals.install()
    woke = threading.Event()
    signals.wake_with(woke.set)
    sent = []

    def send(sig):
        time.sleep(0.2)
        sent.append(time.monotonic())
        os.kill(os.getpid(), sig)

    for sig, kind in ((signal.SIGTERM, STOP), (signal.SIGHUP, RESTART)):
        woke.clear()
        threading.Thread(target=send, args=(sig,)).start()
        # The main thread waits in C as the agent's loop waits in the executor: only the
        # wake can end this wait early (a lock wait resumes after a handler runs).
        if not woke.wait(10.0):
            print('no wake for', sig.name)
            sys.exit(1)
        print('woke', sig.name, round(time.monotonic() - sent[-1], 3))
        deadline = time.monotonic() + 5.0
        taken = []
        while not taken and time.monotonic() < deadline:
            taken = signals.take()
            time.sleep(0.01)
        if taken != [kind]:
            print('took', taken, 'for', sig.name)
            sys.exit(1)
    print('ok')
''')


def test_a_signal_wakes_a_loop_that_waits_and_is_taken_once():
    done = subprocess.run([sys.executable, '-c', SCRIPT], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip().endswith('ok'), done.stdout
