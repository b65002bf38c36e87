"""The agent process around its node: the scale it is for, where it keeps its state and logs,
its warden, the signals it acts on, its restart in place and its last stop. No ROS here."""

import os
import re
import signal
import socket
import sys
import threading
import time
from typing import Callable, FrozenSet, List, Mapping, Optional, Sequence, Tuple

from ..model.types import AgentSettings, Deployment
from ..model.discovery import domain_of, server_port, uses_servers
from . import ports
from .discovery import DiscoveryError, server_argv
from .supervisor import Supervisor
from .warden import spawn as spawn_warden, warden_port

SCALE_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
STOP, RESTART = 'stop', 'restart'
# Across a restart in place: the descriptors of the sockets bound to the old participant's DDS
# ports. A participant that takes the ports of one its peers knew is left unmatched by those
# that missed its goodbye (agent/ports.py); the new agent's must take others.
HELD_PORTS_ENV = 'ANYSCALE_AGENT_HELD_PORTS'


def scale_from_args(args: Sequence[str]) -> Optional[str]:
    """The ``scale`` parameter given with -p/--param in the ROS arguments (the last one wins).

    The node's name depends on the scale, so it is read before the node exists.
    """
    found = None
    in_ros = False
    items = list(args)
    for i, arg in enumerate(items):
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg in ('-p', '--param') and i + 1 < len(items):
            name, sep, value = items[i + 1].partition(':=')
            if sep and name.rsplit(':', 1)[-1] == 'scale':
                found = value.strip().strip('\'"')
    return found


def places(settings: AgentSettings, deployment: str, scale: str,
           environ: Mapping[str, str]) -> Tuple[str, str]:
    """(the path of the agent's state and lock files without their suffix, its log folder):
    under agent.state_dir and agent.log_dir, else under ROS_HOME and ROS_LOG_DIR as ROS does."""
    home = environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')
    state_dir = settings.state_dir or os.path.join(home, 'anyscale_manager')
    log_root = settings.log_dir or os.path.join(
        environ.get('ROS_LOG_DIR') or os.path.join(home, 'log'), 'anyscale_manager')
    return (os.path.join(state_dir, f'agent_{deployment}_{scale}'),
            os.path.join(log_root, deployment, scale))


def start_warden(deployment: Deployment, scale: str, supervisor: Supervisor, stem: str,
                 log_dir: str) -> List[Tuple[str, str]]:
    """Start the scale's warden (agent/warden.py): the heartbeat echo and the fencing of these
    nodes, in a process that outlives the agent. One per state file: an agent restarted in
    place, or by systemd, finds it running. What happened, as (level, text) log lines."""
    s, d = deployment.agent, deployment
    if scale != d.master.name:
        supervisor.fenceable = frozenset(
            n for n in supervisor.names if set(d.allowed_scales(n)) - {scale})
    supervisor.save()       # who this agent is, before the warden reads it
    port = warden_port(d, scale)
    log = os.path.join(log_dir, 'warden.log')
    lines: List[Tuple[str, str]] = []
    server: List[str] = []
    if uses_servers(d):
        try:
            server = server_argv(d, scale, os.environ)
        except DiscoveryError as e:
            lines.append(('error', f'{e}: this scale runs no discovery server; its processes '
                                   "find the others through the other scales' servers only "
                                   '(not while a link is cut)'))
    try:
        pid = spawn_warden(stem + '.json', scale, d.name, d.scale(scale).host, port,
                           s.adopt_grace_s, s.restart_grace_s, s.fence_grace_s, log,
                           d.security.key_file, s.warden_priority, server)
    except OSError as e:
        # The nodes still run and are supervised; what is lost is said.
        return [('error', f'cannot start the warden ({e.strerror or e}; log {log}): the master '
                          'hears no heartbeat from this scale (its link counts as down) and '
                          'nothing stops these nodes if this agent dies')]
    if pid is None:
        return lines
    return lines + [('info', f'warden started: pid {pid}, heartbeats on UDP '
                             f'{d.scale(scale).host}:{port} (log {log})'
                             + (f'; it keeps the discovery server on port '
                                f'{server_port(d, scale, domain_of(os.environ))} running'
                                if server else ''))]


class Signals:
    """SIGINT and SIGTERM ask to stop every node, SIGHUP to restart in place.

    The handlers only note the signal; the loop acts on it between two callbacks (``take``). A
    handler runs between any two bytecodes of the main thread, maybe inside a callback that
    holds a monitor's lock: stopping the nodes from there deadlocked once (a SIGINT logged
    "shutting down" and stopped nothing).

    Python runs a handler only when the main thread runs bytecode, not while it waits in the
    executor. ``wake_with`` gives a wake the loop's executor answers (a one-shot timer's
    reset): Python's C-level handler writes each signal's number to a socket (the wakeup fd)
    at once, and a thread blocked on that socket calls the wake, so the loop can wait for its
    callbacks as long as it likes and still take a signal within milliseconds.
    """

    def __init__(self):
        self._noted: List[str] = []
        self._wake: Optional[Callable[[], None]] = None
        self._socket: Optional[socket.socket] = None

    def install(self) -> None:
        signal.signal(signal.SIGINT, lambda signum, frame: self._noted.append(STOP))
        signal.signal(signal.SIGTERM, lambda signum, frame: self._noted.append(STOP))
        signal.signal(signal.SIGHUP, lambda signum, frame: self._noted.append(RESTART))
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        self._socket = writer           # kept open for as long as the process lives
        threading.Thread(target=self._listen, args=(reader,), name='signal-wake',
                         daemon=True).start()

    def wake_with(self, wake: Callable[[], None]) -> None:
        """Call ``wake()`` (from another thread) whenever a signal arrives from now on."""
        self._wake = wake

    def _listen(self, reader: socket.socket) -> None:
        while True:
            try:
                if not reader.recv(64):
                    return
            except OSError:
                return
            wake = self._wake
            if wake is not None:
                try:
                    wake()
                except Exception:   # the node is being destroyed: the loop sees the signal
                    pass

    def take(self) -> List[str]:
        """The requests noted since the last call, in order: at most two stops (a second one
        kills every node at once; more add nothing)."""
        out: List[str] = []
        while self._noted:
            kind = self._noted.pop(0)
            if kind == RESTART or out.count(STOP) < 2:
                out.append(kind)
        return out


def own_dds_ports() -> FrozenSet[int]:
    """The participant-range UDP ports this process binds (its DDS participant's, and those a
    PortHold of it holds)."""
    return ports.unicast_ports([os.getpid()], ports.domain_of(os.environ))


def restart_in_place(participant_ports: FrozenSet[int] = frozenset(),
                     also: Optional[ports.PortHold] = None) -> None:
    """Replace this process with a new agent: same pid, same command line, the code installed
    now. The nodes stay its children (in sessions of their own) and the new agent adopts them
    from the state file; ``systemctl reload`` with ``ExecReload=/bin/kill -HUP $MAINPID``
    (docs/agent.md). ``participant_ports``: ``own_dds_ports()`` read before the participant
    was deleted; those it freed are bound and passed on, with the sockets ``also`` holds, so
    that the new agent's participant takes others (``held_ports``)."""
    hold = ports.PortHold()
    hold.hold(participant_ports - own_dds_ports(), time.monotonic())
    held = hold.sockets() + (also.sockets() if also is not None else [])
    # Nothing of this process but stdin, stdout and stderr may reach the new one: a DDS socket
    # or lock file kept open would look like a live participant to the others.
    for entry in os.listdir('/proc/self/fd'):
        fd = int(entry)
        if fd > 2:
            try:
                os.set_inheritable(fd, False)
            except OSError:
                pass                 # the listing's own descriptor, already closed
    fds = []
    for s in held:
        os.set_inheritable(s.fileno(), True)
        fds.append(str(s.fileno()))
    if fds:
        os.environ[HELD_PORTS_ENV] = ','.join(fds)
    # A second SIGHUP before the new process has its handler would end it (the default
    # action): ignored until then (an ignored signal stays ignored across exec).
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    sys.stdout.flush()
    sys.stderr.flush()
    argv = list(getattr(sys, 'orig_argv', None) or [sys.executable] + sys.argv)
    os.execv(sys.executable, argv)


def held_ports() -> List[int]:
    """The descriptors of the ports the process this one replaced held for it (a restart in
    place), taken out of the environment so that no node inherits the variable."""
    fds = []
    for item in os.environ.pop(HELD_PORTS_ENV, '').split(','):
        if item.strip().isdigit():
            fds.append(int(item))
    return fds


def stop_offline(supervisor: Supervisor, deadline_s: float) -> None:
    """Stop what still runs without ROS (the context is gone): graces still apply."""
    end = time.monotonic() + deadline_s
    supervisor.stop_all(time.monotonic())
    while not supervisor.all_stopped() and time.monotonic() < end:
        supervisor.step(time.monotonic())
        time.sleep(0.05)
    if supervisor.all_stopped():
        supervisor.stopped = True      # the warden has nothing left to guard
        supervisor.save()
