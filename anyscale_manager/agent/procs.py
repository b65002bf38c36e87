"""Small Linux process helpers: session members, identity, signal descriptions."""

import os
import signal
from typing import List, Optional, Tuple

import psutil


def describe_exit(returncode: Optional[int]) -> str:
    """A Popen return code in words: 'exited with status 3', 'killed by SIGKILL (Killed)'."""
    if returncode is None:
        return 'exit status unknown'
    if returncode >= 0:
        return f'exited with status {returncode}'
    number = -returncode
    try:
        name = signal.Signals(number).name
    except ValueError:
        name = f'signal {number}'
    text = signal.strsignal(number) or ''
    return f'killed by {name} ({text})' if text else f'killed by {name}'


def _stat(pid: int) -> Optional[Tuple[str, int, int]]:
    """(state, process group, session) of a pid from /proc, or None when it is gone."""
    try:
        with open(f'/proc/{pid}/stat', 'rb') as f:
            data = f.read()
    except OSError:
        return None
    # The command name may hold spaces and parentheses: fields start after the last ')'.
    rest = data[data.rfind(b')') + 2:].split()
    try:
        return rest[0].decode(), int(rest[2]), int(rest[3])
    except (IndexError, ValueError):
        return None


def session_members(sid: int) -> List[int]:
    """Live (non-zombie) processes of a session or process group led by ``sid``."""
    out = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        st = _stat(int(entry))
        if st is None or st[0] in ('Z', 'X'):
            continue
        if st[1] == sid or st[2] == sid:
            out.append(int(entry))
    return out


def signal_session(sid: int, sig: int, extra: Tuple[int, ...] = ()) -> int:
    """Send ``sig`` to the group and to every member of the session; return how many got it."""
    try:
        os.killpg(sid, sig)
    except (ProcessLookupError, PermissionError):
        pass
    count = 0
    for pid in set(session_members(sid)) | set(extra):
        try:
            os.kill(pid, sig)
            count += 1
        except (ProcessLookupError, PermissionError):
            pass
    return count


def descendants(pid: int) -> Tuple[int, ...]:
    """Every descendant of a process now (children that left the session included)."""
    try:
        return tuple(p.pid for p in psutil.Process(pid).children(recursive=True))
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return ()


def create_time(pid: int) -> Optional[float]:
    try:
        return psutil.Process(pid).create_time()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None


def alive(pid: int, started: float) -> bool:
    """The process with this pid and start time is alive (not a zombie)."""
    try:
        proc = psutil.Process(pid)
        if abs(proc.create_time() - started) > 0.05:
            return False
        return proc.status() != psutil.STATUS_ZOMBIE
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return False


def environ_value(pid: int, name: str) -> Optional[str]:
    try:
        return psutil.Process(pid).environ().get(name)
    except (psutil.NoSuchProcess, psutil.AccessDenied, OSError):
        return None
