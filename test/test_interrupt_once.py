"""A node's cleanup after Ctrl-C survives the supervisor's repeated SIGINT (interrupt_once),
through rclpy's own signal handler: real processes, no DDS traffic."""

import subprocess
import sys

import pytest

SCRIPT = '''
import os, signal, sys
{setup}
{init}
try:
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(10 ** 7):
        pass
    print('not interrupted')
    sys.exit(3)
except KeyboardInterrupt:
    os.kill(os.getpid(), signal.SIGINT)      # the supervisor repeats itself during cleanup
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(10 ** 6):
        pass
    {shutdown}
    print('cleaned up')
'''
ONCE = 'from anyscale_manager.interrupt import interrupt_once\ninterrupt_once()'
RCLPY_INIT = 'import rclpy\nrclpy.init()'
RCLPY_SHUTDOWN = 'rclpy.try_shutdown()'


def run(setup, with_rclpy):
    code = SCRIPT.format(setup=setup, init=RCLPY_INIT if with_rclpy else '',
                         shutdown=RCLPY_SHUTDOWN if with_rclpy else 'pass')
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize('with_rclpy', [False, True])
def test_the_first_sigint_interrupts_and_later_ones_do_not(with_rclpy):
    done = run(ONCE, with_rclpy)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == 'cleaned up'
    assert 'Traceback' not in done.stderr


def test_without_it_a_repeated_sigint_breaks_the_cleanup():
    """The case it exists for: Python's own handler raises again inside the cleanup."""
    done = run('', False)
    assert done.returncode != 0
    assert 'Traceback' in done.stderr and 'cleaned up' not in done.stdout


HANDED_OVER = '''
import os, signal, sys, time
import rclpy
from anyscale_manager.interrupt import interrupt_once, rclpy_stops_on_sigint
interrupt_once()
rclpy.init()
rclpy_stops_on_sigint()
try:
    os.kill(os.getpid(), signal.SIGINT)
    end = time.monotonic() + 10.0
    while rclpy.ok() and time.monotonic() < end:
        for _ in range(1000):
            pass
except KeyboardInterrupt:
    print('raised')
    sys.exit(3)
print('context shut down' if not rclpy.ok() else 'still running')
os.kill(os.getpid(), signal.SIGINT)          # the supervisor repeats itself during cleanup
for _ in range(10 ** 6):
    pass
rclpy.try_shutdown()
print('cleaned up')
'''


def test_once_rclpy_stops_on_sigint_it_is_not_raised_as_well():
    """After ``rclpy_stops_on_sigint``: rclpy's handler shuts the context down (the spin ends
    there) and no KeyboardInterrupt lands in the middle of whatever runs; a repeated SIGINT is
    ignored."""
    done = subprocess.run([sys.executable, '-c', HANDED_OVER], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.split() == ['context', 'shut', 'down', 'cleaned', 'up']
    assert 'Traceback' not in done.stderr


STOP_ASKED = '''
import os, signal, time
import rclpy
from anyscale_manager.interrupt import interrupt_once, rclpy_stops_on_sigint, stop_asked
from anyscale_manager.nodes.shutdown import shut_rclpy_down
interrupt_once()
rclpy.init()
rclpy_stops_on_sigint()
print(stop_asked())
os.kill(os.getpid(), signal.SIGINT)
end = time.monotonic() + 10.0
while not stop_asked() and time.monotonic() < end:
    time.sleep(0.01)
print(stop_asked())
shut_rclpy_down()
'''


def test_a_sigint_is_seen_by_stop_asked_beside_rclpys_handler():
    """The decider's spin loop ends on its own word (``stop_asked``) as well as on the context
    that rclpy's handler shuts down."""
    done = subprocess.run([sys.executable, '-c', STOP_ASKED], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.split() == ['False', 'True']


class _HandlerThreadFirst:
    """Stand-in for a timing that cannot be forced: rclpy's signal-handler thread shuts the
    context down between ``try_shutdown``'s ``ok()`` check and its own shutdown."""

    def __init__(self, real):
        self.real = real
        self.raced = False

    def __enter__(self):
        return self.real.__enter__()

    def __exit__(self, *exc):
        return self.real.__exit__(*exc)

    def ok(self):
        was_ok = self.real.ok()
        if was_ok and not self.raced:
            self.raced = True
            self.real.shutdown()
        return was_ok

    def __getattr__(self, name):
        return getattr(self.real, name)


def _raced_context():
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    ctx._Context__context = _HandlerThreadFirst(ctx._Context__context)
    return ctx


def test_a_shutdown_that_finds_the_handler_thread_was_first_is_a_shutdown():
    """The race that made a stopping node fail at its last line ("rcl_shutdown already called
    on the given context"): try_shutdown alone raises it, shut_rclpy_down ends shut down."""
    import rclpy
    from anyscale_manager.nodes.shutdown import shut_rclpy_down
    bare = _raced_context()
    with pytest.raises(RuntimeError, match='already called'):
        rclpy.try_shutdown(context=bare)
    ctx = _raced_context()
    shut_rclpy_down(context=ctx)
    assert not ctx.ok()
