"""A child process of a test with its output in a file, stopped by signal with a deadline."""

import signal
import subprocess


class LoggedProcess:
    def __init__(self, out_path, argv, env):
        self.out = out_path
        self.argv = list(argv)
        with open(self.out, 'wb') as f:
            self.proc = subprocess.Popen(self.argv, env=env, stdout=f,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def text(self):
        return self.out.read_text(errors='replace')

    def stop(self, sig=signal.SIGINT, timeout=20.0, must_exit=False):
        """Signal it and wait; past the timeout it is killed, and the exit code is None, or
        with ``must_exit`` an AssertionError with its output."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            if must_exit:
                raise AssertionError(f'{self.argv[0]} did not exit within {timeout} s:\n'
                                     f'{self.text()}') from None
            return None
