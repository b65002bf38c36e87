"""Small Linux process helpers: session members, identity, signal descriptions."""

import os
import signal
import subprocess
import time
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

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


_TICKS = os.sysconf('SC_CLK_TCK')


def _read(path: str) -> Optional[bytes]:
    """A small /proc file's bytes, or None if it cannot be read (the process is gone). A raw
    os.read: a Python file object costs about as much again as the read itself."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return os.read(fd, 65536)
    except OSError:
        return None
    finally:
        os.close(fd)


def memory_percent() -> float:
    """The share of the machine's memory in use, as psutil.virtual_memory().percent has it
    ((MemTotal - MemAvailable) / MemTotal, /proc/meminfo), read in a tenth of its time."""
    data = _read('/proc/meminfo')
    total = available = None
    for line in (data or b'').split(b'\n'):
        if line.startswith(b'MemTotal:'):
            total = int(line.split()[1])
        elif line.startswith(b'MemAvailable:'):
            available = int(line.split()[1])
            break
    if not total or available is None:
        return float(psutil.virtual_memory().percent)
    return round(100.0 * (total - available) / total, 1)


def _stat_fields(pid: int) -> Optional[List[bytes]]:
    """The fields of /proc/PID/stat after the command name (state first), or None if gone."""
    data = _read(f'/proc/{pid}/stat')
    if data is None:
        return None
    # The command name may hold spaces and parentheses: fields start after the last ')'.
    return data[data.rfind(b')') + 2:].split()


def _entry(rest: Optional[List[bytes]]) -> Optional[Tuple[int, float]]:
    """(parent pid, user + system CPU seconds) from stat fields; None for a zombie or gone."""
    try:
        if rest[0] in (b'Z', b'X'):
            return None
        return int(rest[1]), (int(rest[11]) + int(rest[12])) / _TICKS
    except (TypeError, IndexError, ValueError):
        return None


def _stat(pid: int) -> Optional[Tuple[str, int, int]]:
    """(state, process group, session) of a pid from /proc, or None when it is gone."""
    rest = _stat_fields(pid)
    try:
        return rest[0].decode(), int(rest[2]), int(rest[3])
    except (TypeError, IndexError, ValueError):
        return None


def process_table() -> Dict[int, Tuple[int, float]]:
    """pid -> (parent pid, cumulative user + system CPU seconds) of every live process, read
    in one pass over /proc (zombies left out)."""
    out: Dict[int, Tuple[int, float]] = {}
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        found = _entry(_stat_fields(int(entry)))
        if found is not None:
            out[int(entry)] = found
    return out


def _children_files() -> bool:
    """Whether this kernel lists each thread's children (/proc/PID/task/TID/children,
    CONFIG_PROC_CHILDREN)."""
    return os.path.exists(f'/proc/{os.getpid()}/task/{os.getpid()}/children')


CHILDREN_FILES = _children_files()


def tree_table(roots: Iterable[int], known: Iterable[int] = (), all_threads: bool = True
               ) -> Dict[int, Tuple[int, float]]:
    """``process_table`` of the processes in the trees of ``roots`` only: each root and its
    descendants, found through the children each thread lists, so that a sample reads a few
    files per process of the trees rather than every process of the machine (a robot has a
    few hundred, kernel threads included: 1-8 ms a pass, twice a second). Where the kernel
    lists no children, the whole table.

    ``all_threads`` False reads the children of each process's main thread only, and reads
    ``known`` (the processes of an earlier full pass) as well: a ROS process has a dozen or
    more threads, so this reads two files a process instead of one per thread; a child
    started by another thread since the full pass is found at the next one."""
    if not CHILDREN_FILES:
        return process_table()
    out: Dict[int, Tuple[int, float]] = {}
    todo = [pid for pid in roots if isinstance(pid, int) and pid > 0]
    if not all_threads:
        todo.extend(known)
    while todo:
        pid = todo.pop()
        if pid in out:
            continue
        found = _entry(_stat_fields(pid))
        if found is None:
            continue
        out[pid] = found
        if all_threads:
            try:
                threads = os.listdir(f'/proc/{pid}/task')
            except OSError:
                continue
        else:
            threads = (pid,)
        # A child belongs to the thread that started it (a process's other threads start
        # children too); once that thread ends, to another thread of the process.
        for tid in threads:
            data = _read(f'/proc/{pid}/task/{tid}/children')
            if data:
                todo.extend(int(child) for child in data.split())
    return out


def tree_cpu_seconds(table: Mapping[int, Tuple[int, float]], leaders: Mapping[str, int]
                     ) -> Dict[str, Dict[int, float]]:
    """name -> {pid: cumulative CPU seconds} of each leader and all its descendants, from one
    process table; a leader that is gone gives an empty map."""
    children: Dict[int, List[int]] = {}
    for child, (parent, _) in table.items():
        children.setdefault(parent, []).append(child)
    out: Dict[str, Dict[int, float]] = {}
    for name, pid in leaders.items():
        tree: Dict[int, float] = {}
        todo = [pid] if pid in table else []
        while todo:
            current = todo.pop()
            if current not in tree:
                tree[current] = table[current][1]
                todo.extend(children.get(current, ()))
        out[name] = tree
    return out


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
    """Every live descendant of a process now (children that left the session included):
    through the children each thread lists (``tree_table``), a few files a process of the
    tree where psutil reads every process of the machine; an agent looks at each step of a
    stopping node (STOPPING_TICK_S)."""
    if CHILDREN_FILES:
        return tuple(child for child in tree_table([pid]) if child != pid)
    try:
        children = psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        return ()
    return tuple(p.pid for p in children if _live(p))


def _live(p: psutil.Process) -> bool:
    try:
        return p.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def create_time(pid: int) -> Optional[float]:
    """When ``pid`` started, on the wall clock (seconds since the epoch): for people and for
    state files read by earlier versions, never to tell a process apart (see ``start_ticks``)."""
    try:
        return psutil.Process(pid).create_time()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None


def start_ticks(pid: int) -> Optional[int]:
    """When ``pid`` started, in clock ticks since boot (/proc/PID/stat, field 22), or None when
    it is gone. With the pid it names one process for as long as the machine runs. A start
    time on the wall clock does not: it is the boot time plus these ticks, and the boot time
    moves whenever the clock is stepped (a robot's first NTP fix after a boot without a
    real-time clock, a paused or migrated virtual machine), after which every recorded process
    would read as gone."""
    rest = _stat_fields(pid)
    try:
        return int(rest[19])
    except (TypeError, IndexError, ValueError):
        return None


def age_s(ticks: int) -> float:
    """Seconds since a process that started at ``ticks`` (``start_ticks``) started."""
    return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / _TICKS)


def wall_start(ticks: int) -> float:
    """A start in ticks (``start_ticks``) on the wall clock, as ``create_time`` gives it: what
    state-file readers of earlier versions compare."""
    return psutil.boot_time() + ticks / _TICKS


def another_boot(recorded: object) -> bool:
    """Whether a state file's ``boot_id`` names a boot other than this one (its processes are
    then all gone, whatever their pids and ticks). A file without one (an earlier version), or
    whose writer could not read it, is taken as of this boot."""
    mine = boot_id()
    return bool(recorded) and bool(mine) and recorded != mine


def boot_id() -> str:
    """This boot's identity (the kernel's random boot id), '' where it cannot be read."""
    try:
        with open('/proc/sys/kernel/random/boot_id', encoding='ascii') as f:
            return f.read().strip()
    except OSError:
        return ''


def alive(pid: int, ticks: int) -> bool:
    """The process with this pid and start (``start_ticks``) is alive (not a zombie)."""
    rest = _stat_fields(pid)
    try:
        return rest[0] not in (b'Z', b'X') and int(rest[19]) == ticks
    except (TypeError, IndexError, ValueError):
        return False


def recorded_start(pid: int, ticks: object, wall: object) -> Optional[int]:
    """The start of process ``pid`` as a state file recorded it, in ticks (``start_ticks``).
    A file of an earlier version has only its start on the wall clock, ``wall``: then the
    live process's ticks if its wall-clock start is within 0.05 s of it (that version's
    rule), else None (gone, or another process)."""
    if isinstance(ticks, int) and not isinstance(ticks, bool):
        return ticks if ticks >= 0 else None
    if isinstance(wall, (int, float)) and not isinstance(wall, bool):
        live = start_ticks(pid)          # one read of /proc: the same process throughout
        if live is not None and abs(wall_start(live) - wall) <= 0.05:
            return live
    return None


def reap(pid: int) -> Optional[Tuple[bool, Optional[int]]]:
    """For a child of this process: (True, its return code as Popen gives it) once it has
    ended, collecting it; (False, None) while it has not (a multi-threaded process killed is
    collectable only once all its threads are gone). None when ``pid`` is not a child of ours
    (a process adopted from an agent that was killed is init's child)."""
    try:
        got, status = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return None
    if got == 0:
        return False, None
    return True, os.waitstatus_to_exitcode(status)


def environ_value(pid: int, name: str, exec_wait_s: float = 0.0) -> Optional[str]:
    """``name`` in the environment ``pid`` was started with. A child forked but not yet exec'd
    (its spawner killed in between) still shows its spawner's environment: up to
    ``exec_wait_s`` is given for the exec when the name is missing."""
    deadline = time.monotonic() + exec_wait_s
    while True:
        try:
            value = psutil.Process(pid).environ().get(name)
        except (psutil.NoSuchProcess, psutil.AccessDenied, OSError):
            return None
        if value is not None or time.monotonic() >= deadline:
            return value
        time.sleep(0.02)


def stop_popen(proc: 'subprocess.Popen', sigint_grace_s: float,
               sigterm_grace_s: Optional[float] = None, *, session: bool = True,
               kill_wait_s: float = 5.0) -> Optional[int]:
    """Stop a child as ROS expects: SIGINT, then SIGTERM after ``sigint_grace_s`` (skipped when
    ``sigterm_grace_s`` is None), then SIGKILL after ``sigterm_grace_s``; to its whole session
    when it was started in one of its own (``start_new_session=True``), else to it alone.
    Returns its exit status (None if even SIGKILL did not end it within ``kill_wait_s``). The
    one blocking escalation of the project, for the test-bed, the benches and the tests; the
    agent runs the same steps without blocking, one state per ``Supervisor.step``."""
    steps = [(signal.SIGINT, sigint_grace_s)]
    if sigterm_grace_s is not None:
        steps.append((signal.SIGTERM, sigterm_grace_s))
    steps.append((signal.SIGKILL, kill_wait_s))
    for sig, grace in steps:
        if proc.poll() is not None:
            break
        try:
            if session:
                os.killpg(proc.pid, sig)
            else:
                os.kill(proc.pid, sig)
        except ProcessLookupError:
            pass
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


def stop_all(popens: 'Sequence[subprocess.Popen]', sigint_grace_s: float, *,
             session: bool = True, kill_wait_s: float = 5.0) -> List[Optional[int]]:
    """``stop_popen`` for several children at once: SIGINT to every one, one shared grace for
    all of them to exit, then SIGKILL to what is left; their exit statuses, in order."""
    def signal_each(sig: int) -> None:
        for proc in popens:
            if proc.poll() is None:
                try:
                    (os.killpg if session else os.kill)(proc.pid, sig)
                except ProcessLookupError:
                    pass

    def wait_each(until: float) -> None:
        for proc in popens:
            try:
                proc.wait(max(0.0, until - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    signal_each(signal.SIGINT)
    wait_each(time.monotonic() + sigint_grace_s)
    signal_each(signal.SIGKILL)
    wait_each(time.monotonic() + kill_wait_s)
    return [proc.poll() for proc in popens]
