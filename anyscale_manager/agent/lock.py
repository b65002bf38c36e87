"""One agent per scale and machine: an exclusive lock on a file of its state folder.

A second agent would start every node twice. The lock is an flock, released by the system
when its holder exits however it exits; the file holds the holder's pid, for people.
"""

import fcntl
import os
from typing import IO


class LockError(RuntimeError):
    """Why the lock cannot be taken, said in one line."""


def take_lock(path: str, holder: str) -> IO[str]:
    """Lock ``path`` (made with its folder) for this process and write its pid there; held
    while the returned file is open. ``holder`` names the one process that may hold it
    ("agent for scale 'a' of 'demo'"), for the error."""
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        f = open(path, 'a+')
    except OSError as e:
        # Without its lock and state file an agent could start every node twice, or lose
        # track of them when it restarts: it starts nothing.
        raise LockError(f'cannot use the state folder {os.path.dirname(path)} (lock '
                        f'{path}): {e.strerror or e}; set agent.state_dir to a writable '
                        'folder') from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise LockError(f'another {holder} runs on this machine (it holds {path}); not '
                        'starting a second one') from None
    try:
        f.seek(0)
        f.truncate()
        f.write(f'{os.getpid()}\n')
        f.flush()
    except OSError:
        pass        # the pid is for people (a full disk); the lock is the flock
    return f


def release_lock(f: IO[str]) -> None:
    try:
        f.close()
    except OSError:
        pass    # its pid line could not be flushed (a full disk); closed all the same
