"""Learning of a node's exit the moment it happens, not at the next tick.

Each process the supervisor starts or adopts gets a pidfd (Linux 5.3+), and one thread blocked on
it; when the process ends the thread calls ``wake``, which the agent turns into an rclpy guard
condition: the supervisor's next step runs at once and finds the exit (its own poll reaps
it), and the agent reports it at once. A pidfd, unlike SIGCHLD, also works for an adopted
process that is not our child, and needs no signal handler (Python runs those only between
bytecodes of the main thread, which sits in the executor's wait). Without pidfd support the
tick's poll still finds every exit, one tick later.
"""

import os
import select
import threading
from typing import Callable


class ExitWatcher:
    """Calls ``wake()`` from a thread of its own each time a watched process ends."""

    def __init__(self, wake: Callable[[], None]):
        self._wake = wake

    @staticmethod
    def supported() -> bool:
        return hasattr(os, 'pidfd_open')

    def watch(self, pid: int) -> bool:
        """Watch ``pid``; False when it cannot be (gone already, or no pidfd here)."""
        if pid <= 0 or not self.supported():
            return False
        try:
            fd = os.pidfd_open(pid)
        except OSError:
            return False
        threading.Thread(target=self._wait, args=(fd,), name=f'exit-watch-{pid}',
                         daemon=True).start()
        return True

    def _wait(self, fd: int) -> None:
        try:
            select.select([fd], [], [])
        except (OSError, ValueError):
            pass
        finally:
            os.close(fd)
        try:
            self._wake()
        except Exception:       # the agent is shutting down: nothing to wake
            pass
