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
