"""The warden: one small process per scale that outlives its agent.

    python -m anyscale_manager.agent.warden --state FILE --scale NAME --deployment NAME
        --host HOST --port PORT [--adopt-grace S] [--restart-grace S] [--fence-grace S]
        [--key-file FILE]

The agent starts it (once: a second warden of the same state file exits at once) and it does
two things an agent cannot do for itself, because both must hold while the agent is dead or
replacing itself:

- **The heartbeat echo.** The link monitor of each link's watching end (the master, or the
  first of two remote scales) sends a UDP datagram to the far end's warden (``warden_port``)
  and times the answer: the link's round trip, loss, queueing
  delay and up/down. The answer also says how the scale's agent is (``alive``, ``restarting``,
  ``gone`` or ``fenced``, and for how long), so a dead or restarting agent is never taken for a
  cut link, and a cut link is still one (no answer at all). With the deployment's key, beats
  and echoes carry an HMAC (protocol_auth) and anything unsigned or forged is dropped; an echo
  names the monitor that sent the beat (a random id of that process) and the beat's number, so
  an echo recorded earlier answers nothing now.
- **Fencing.** A node must not outlive its agent unsupervised. The warden reads the agent's
  state file (its pid and start time, and every node it runs); when the agent is gone and no
  successor has written that file within ``adopt_grace_s`` (``restart_grace_s`` after the agent
  said it restarts in place), it stops those nodes: SIGINT to each session, SIGKILL after
  ``fence_grace_s``. The decider places them elsewhere only once the echo says ``fenced``
  (docs/agent.md, fencing): never two copies serving. An agent that stops cleanly says so in
  its state file, and the warden leaves.

No ROS here: a plain process with a UDP socket, a few megabytes.
"""

import argparse
import fcntl
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence, Tuple

from . import priority as realtime
from .. import protocol_auth as auth
from ..interrupt import restore_ctrl_c

ALIVE, RESTARTING, GONE, FENCED = 'alive', 'restarting', 'gone', 'fenced'
AGENT_STATES = (ALIVE, RESTARTING, GONE, FENCED)
LOOP_S = 0.25           # the loop wakes at once for a beat or the agent's death
MISSING_S = 5.0          # a state folder removed this long ago: the deployment is gone
MAX_DATAGRAM = 512


def warden_port(deployment: Any, scale: str) -> int:
    """The UDP port of ``scale``'s warden (Deployment.scale_port)."""
    return deployment.scale_port(scale)


@dataclass
class AgentView:
    """What the state file says of the agent."""

    pid: int = 0
    start_ticks: Optional[int] = None           # its start, clock ticks since boot
    restarting: bool = False
    stopped: bool = False
    nodes: Tuple[Tuple[int, int], ...] = ()     # (pid, start in ticks) of each node to fence


class Verdict:
    """The warden's judgement of its agent, with the clock passed in (tested without
    processes). ``step`` returns True when the nodes must be fenced now."""

    def __init__(self, adopt_grace_s: float, restart_grace_s: float):
        self.adopt_grace_s = adopt_grace_s
        self.restart_grace_s = restart_grace_s
        self.state = ALIVE
        self.since = 0.0
        self._gone_at: Optional[float] = None
        self._announced = False

    def step(self, now: float, alive: bool, restarting: bool) -> bool:
        if alive:
            self._gone_at = None
            self._announced = restarting
            self._set(RESTARTING if restarting else ALIVE, now)
            return False
        if self.state == FENCED:
            return False
        if self._gone_at is None:
            self._gone_at = now
            self._announced = self._announced or restarting
            self._set(RESTARTING if self._announced else GONE, now)
        grace = self.restart_grace_s if self._announced else self.adopt_grace_s
        if now - self._gone_at >= grace:
            self._set(FENCED, now)
            return True
        return False

    def _set(self, state: str, now: float) -> None:
        if state != self.state:
            self.state, self.since = state, now


class AgentWatch:
    """Whether the agent process named in the state file lives: a pidfd that the warden's
    wait includes (its death wakes the loop at once), checked against the process's start time
    when it is first followed (a reused pid is not the agent; ``procs.start_ticks``)."""

    def __init__(self) -> None:
        self._fd: Optional[int] = None
        self._dead = True

    def follow(self, pid: int, started: Optional[int]) -> None:
        from . import procs
        self.close()
        self._dead = True
        if pid <= 0:
            return
        try:
            fd = os.pidfd_open(pid)
        except (OSError, AttributeError):
            return
        if started is not None and not procs.alive(pid, started):
            os.close(fd)
            return
        self._fd, self._dead = fd, False

    def fds(self) -> List[int]:
        return [] if self._fd is None or self._dead else [self._fd]

    def alive(self) -> bool:
        if self._fd is not None and not self._dead:
            ready, _, _ = select.select([self._fd], [], [], 0)
            self._dead = bool(ready)
        return not self._dead

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def read_state(path: str) -> Optional[AgentView]:
    """The agent's state file, or None if it cannot be read now (being replaced, absent). A
    file written under another boot names nothing alive. Starts are read as clock ticks since
    boot; a file of an earlier version has only wall-clock starts, matched against the live
    processes as that version did (``procs.recorded_start``)."""
    from . import procs
    try:
        with open(path, encoding='utf-8') as f:
            data = json.load(f)
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    if procs.another_boot(data.get('boot_id')):
        return AgentView()
    nodes = []
    for rec in (data.get('nodes') or {}).values():
        if isinstance(rec, dict) and isinstance(rec.get('pid'), int) and rec['pid'] > 1 \
                and rec.get('fence'):
            ticks = procs.recorded_start(rec['pid'], rec.get('start_ticks'), rec.get('started'))
            if ticks is not None:
                nodes.append((rec['pid'], ticks))
    pid = data.get('agent_pid')
    pid = pid if isinstance(pid, int) and not isinstance(pid, bool) else 0
    started = None
    if pid > 0 and (data.get('agent_start_ticks') is not None
                    or data.get('agent_started') is not None):
        started = procs.recorded_start(pid, data.get('agent_start_ticks'),
                                       data.get('agent_started'))
        pid = pid if started is not None else 0       # gone, or another process now
    return AgentView(pid=pid, start_ticks=started,
                     restarting=data.get('restarting') is True,
                     stopped=data.get('stopped') is True, nodes=tuple(nodes))


def _datagram(data: bytes, deployment: str, key: Optional[bytes]) -> Optional[dict]:
    """The JSON object of one datagram of this deployment (signed with ``key`` when there is
    one), or None."""
    if len(data) > MAX_DATAGRAM:
        return None
    try:
        text = data.decode('utf-8')
        obj = json.loads(text)
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(obj, dict) or obj.get('d') != deployment:
        return None
    if key is not None and auth.check_signature(key, text):
        return None
    return obj


def _encode(obj: dict, key: Optional[bytes]) -> bytes:
    if key is not None:
        obj['auth'] = auth.sign(key, obj)
    return json.dumps(obj, separators=(',', ':'), sort_keys=True).encode()


def answer(request: bytes, deployment: str, scale: str, state: str, for_s: float,
           key: Optional[bytes] = None) -> Optional[bytes]:
    """The echo of one heartbeat datagram, or None for anything that is not one addressed to
    this scale of this deployment (signed, when there is a key)."""
    beat = _datagram(request, deployment, key)
    if beat is None or beat.get('to') != scale:
        return None
    seq, monitor = beat.get('seq'), beat.get('m', '')
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0 \
            or not isinstance(monitor, str) or len(monitor) > 64:
        return None
    return _encode({'d': deployment, 'from': scale, 'm': monitor, 'seq': seq, 'agent': state,
                    'for_s': round(max(0.0, for_s), 3)}, key)


def parse_echo(data: bytes, deployment: str, key: Optional[bytes] = None,
               monitor: str = '') -> Optional[Tuple[str, int, str, float]]:
    """(scale, seq, agent state, for how long) of an echo of a beat of ``monitor``, or None
    if it is not one (or, with a key, not signed with it)."""
    echo = _datagram(data, deployment, key)
    if echo is None or echo.get('m', '') != monitor:
        return None
    scale, seq, state, for_s = (echo.get('from'), echo.get('seq'), echo.get('agent'),
                                echo.get('for_s'))
    if not isinstance(scale, str) or not isinstance(seq, int) or isinstance(seq, bool) \
            or state not in AGENT_STATES or not isinstance(for_s, (int, float)):
        return None
    return scale, seq, state, float(for_s)


def beat(deployment: str, scale: str, seq: int, key: Optional[bytes] = None,
         monitor: str = '') -> bytes:
    """A heartbeat of ``monitor`` (a random id of the sending process) to ``scale``."""
    return _encode({'d': deployment, 'to': scale, 'm': monitor, 'seq': seq}, key)


def fence(nodes: Tuple[Tuple[int, int], ...], grace_s: float,
          say: Callable[[str], None]) -> int:
    """Stop every node still alive (same pid and start): SIGINT to its session, SIGKILL
    after ``grace_s``. Returns how many were stopped."""
    from . import procs
    live = [(pid, started) for pid, started in nodes if procs.alive(pid, started)]
    for pid, _ in live:
        procs.signal_session(pid, signal.SIGINT)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(procs.alive(p, s) for p, s in live):
        time.sleep(0.02)
    for pid, started in live:
        if procs.alive(pid, started) or procs.session_members(pid):
            procs.signal_session(pid, signal.SIGKILL)
    say(f'fenced {len(live)} node process(es): ' + ', '.join(str(p) for p, _ in live))
    return len(live)


def run(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    key = None
    if args.key_file:
        try:
            key = auth.load_key(args.key_file)
        except auth.KeyFileError as e:
            say(f'{e}: not started')
            return 2
    lock_path = args.state + '.warden'
    lock = open(lock_path, 'a+')
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        say(f'another warden guards {args.state}: leaving')
        return 0
    lock.seek(0)
    lock.truncate()
    lock.write(f'{os.getpid()}\n')
    lock.flush()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((args.host, args.port))
    except OSError as e:
        say(f'cannot listen for heartbeats on UDP {args.host}:{args.port} ({e.strerror or e}): '
            f'another process holds the port; give scale {args.scale} a free one '
            f'(scales.{args.scale}.port, or monitoring.bandwidth_probe_port for the base of '
            'the derived ones)')
        return 2
    sock.setblocking(False)
    prioritise(args.priority, args.scale, say)
    args.keeper = keeper(args, say)
    watch = AgentWatch()
    verdict = Verdict(args.adopt_grace, args.restart_grace)
    view = AgentView()
    mtime = None
    missing_since: Optional[float] = None
    fencing: Optional[threading.Thread] = None
    say(f'guarding scale {args.scale} ({args.state}); heartbeats on UDP '
        f'{args.host}:{args.port}')
    while True:
        now = time.monotonic()
        if args.keeper is not None:
            try:
                args.keeper.step(now)
            except Exception as e:   # noqa: B902 - the heartbeats and the fencing come first
                say(f'the discovery server could not be started: {e!r}; trying again')
                args.keeper.due = now + args.keeper.backoff
        try:
            stat = os.stat(args.state)
            missing_since = None
            if stat.st_mtime_ns != mtime:
                fresh = read_state(args.state)
                if fresh is not None:
                    if (fresh.pid, fresh.start_ticks) != (view.pid, view.start_ticks):
                        watch.follow(fresh.pid, fresh.start_ticks)
                    view, mtime = fresh, stat.st_mtime_ns
        except OSError:
            missing_since = now if missing_since is None else missing_since
            if not os.path.isdir(os.path.dirname(args.state) or '.') \
                    and now - missing_since > MISSING_S:
                say('the state folder is gone: nothing left to guard, leaving')
                return 0
        alive = watch.alive()
        if view.stopped and not alive:
            say('the agent stopped cleanly (its nodes with it): leaving')
            return 0
        before = verdict.state
        if verdict.step(now, alive, view.restarting):
            say(f'agent pid {view.pid} gone with no successor: stopping its nodes')
            # In a thread: the heartbeats are answered meanwhile (a warden that stops
            # answering would make the link look cut).
            fencing = threading.Thread(target=fence, args=(view.nodes, args.fence_grace, say),
                                       daemon=True)
            fencing.start()
        elif verdict.state != before:
            say(f'agent pid {view.pid}: {verdict.state}')
        # 'fenced' only once the nodes are stopped.
        state = GONE if fencing is not None and fencing.is_alive() else verdict.state
        ready, _, _ = select.select([sock] + watch.fds(), [], [], LOOP_S)
        ready = [r for r in ready if r is sock]
        while ready:
            try:
                data, peer = sock.recvfrom(MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                break
            reply = answer(data, args.deployment, args.scale, state,
                           time.monotonic() - verdict.since, key)
            if reply is not None:
                try:
                    sock.sendto(reply, peer)
                except OSError:
                    pass
            ready, _, _ = select.select([sock], [], [], 0)


def keeper(args: argparse.Namespace, say: Callable[[str], None]):
    """The discovery server this warden keeps running (agent/discovery.py), if any: it lives
    as long as the warden, so a restarted or dead agent leaves the scale's discovery as it
    was."""
    if not getattr(args, 'discovery_server', ''):
        return None
    from .discovery import ServerKeeper, server_environment
    argv = json.loads(args.discovery_server)
    log = getattr(args, 'discovery_log', '') or os.path.join(os.path.dirname(args.state),
                                                             'discovery.log')
    return ServerKeeper(argv, server_environment(os.environ), log, say)


def prioritise(priority: int, scale: str, say: Callable[[str], None]) -> bool:
    """Answer heartbeats ahead of the scale's workload. The echo is the proof that the link
    works: one that waits for a core behind a loaded scale's processes arrives as late as a
    cut link's would, and the watching end moves nodes away for nothing. Real-time round
    robin at ``priority`` (the warden sleeps in select and does little when awake); without
    the privilege it says so once and keeps the normal priority."""
    if priority <= 0:
        return False
    why = realtime.set_realtime(0, priority)
    if why is not None:
        say(f'heartbeats answered at normal priority: real-time priority {priority} refused '
            f'({why}); a fully loaded {scale} can then answer late enough to read as a cut. '
            f'{realtime.advice("warden_priority")}')
        return False
    say(f'heartbeats answered at real-time priority {priority} (SCHED_RR)')
    return True


def spawn(state_path: str, scale: str, deployment: str, host: str, port: int,
          adopt_grace_s: float, restart_grace_s: float, fence_grace_s: float,
          log_path: str, key_file: str = '', priority: int = 0,
          discovery_server: Sequence[str] = ()) -> Optional[int]:
    """Start the warden of this state file unless one runs; its pid, or None if one did.
    ``discovery_server``: the command of the scale's discovery server, which it keeps running
    (its log beside the warden's)."""
    try:
        with open(state_path + '.warden', 'a+') as f:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(f, fcntl.LOCK_UN)
    except BlockingIOError:
        return None
    argv = [sys.executable, '-m', 'anyscale_manager.agent.warden', '--state', state_path,
            '--scale', scale, '--deployment', deployment, '--host', host, '--port', str(port),
            '--adopt-grace', str(adopt_grace_s), '--restart-grace', str(restart_grace_s),
            '--fence-grace', str(fence_grace_s)]
    if key_file:
        argv += ['--key-file', key_file]
    if priority > 0:
        argv += ['--priority', str(priority)]
    if discovery_server:
        argv += ['--discovery-server', json.dumps(list(discovery_server)), '--discovery-log',
                 os.path.join(os.path.dirname(log_path) or '.', 'discovery.log')]
    os.makedirs(os.path.dirname(log_path) or '.', exist_ok=True)
    with open(log_path, 'ab') as log:
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True,
                                close_fds=True)
    return proc.pid


def main(argv: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    ap = argparse.ArgumentParser(prog='anyscale_manager.agent.warden',
                                 description=__doc__.split('\n')[0])
    ap.add_argument('--state', required=True, help="the agent's state file")
    ap.add_argument('--scale', required=True)
    ap.add_argument('--deployment', required=True)
    ap.add_argument('--host', required=True)
    ap.add_argument('--port', type=int, required=True)
    ap.add_argument('--adopt-grace', type=float, default=5.0)
    ap.add_argument('--restart-grace', type=float, default=10.0)
    ap.add_argument('--fence-grace', type=float, default=0.5)
    ap.add_argument('--key-file', default='', help="the deployment's key: signed heartbeats")
    ap.add_argument('--priority', type=int, default=0,
                    help='real-time (SCHED_RR) priority to answer heartbeats at; 0: normal')
    ap.add_argument('--discovery-server', default='',
                    help="the scale's DDS discovery server to keep running, as a JSON list "
                         '(its command and arguments)')
    ap.add_argument('--discovery-log', default='', help="the discovery server's log")
    args = ap.parse_args(argv)
    args.keeper = None

    def say(text: str) -> None:
        print(f'[warden {args.scale}] {time.strftime("%H:%M:%S")} {text}', flush=True)
    try:
        return run(args, say)
    except KeyboardInterrupt:
        return 0
    finally:
        if args.keeper is not None:
            args.keeper.stop()


if __name__ == '__main__':
    signal.signal(signal.SIGHUP, signal.SIG_IGN)     # the agent's reload is not ours
    sys.exit(main())


__all__ = ['AGENT_STATES', 'ALIVE', 'FENCED', 'GONE', 'RESTARTING', 'AgentView', 'Verdict',
           'answer', 'beat', 'fence', 'main', 'parse_echo', 'read_state', 'spawn',
           'warden_port']
