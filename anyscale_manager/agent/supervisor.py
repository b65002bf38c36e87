"""Process supervision on one scale: start, stop, restart and adopt the catalogue's nodes.

No ROS and no decisions here: the caller says which nodes it wants running (``set_wanted``) and
drives the supervisor with ``step(now, visible)``, passing its monotonic clock and a predicate
telling whether a catalogue entry's node is visible in the ROS graph. Each node runs in a
session and process group of its own (its pid is the group id), with the catalogue's explicit
environment, its output appended to a log file of its own. Stopping sends SIGINT to the whole
group, then SIGTERM after ``sigint_grace_s``, then SIGKILL after ``sigterm_grace_s``; a node that
dies unasked is reported with its exit reason, whatever is left of its group is killed, and it
is restarted after a backoff that doubles up to ``restart_backoff_max_s``. A state file records
what runs, so that a restarted agent adopts its nodes (pid, process start in clock ticks since
boot, the boot and a per-start token must all match) instead of starting them twice.

Processes only: a lifecycle node's states (a standby copy is a live, inactive process) are the
caller's (agent/lifecycle.py); its ``visible`` predicate says when such a process answers.
"""

import json
import os
import signal
import subprocess
import uuid
from dataclasses import dataclass, field
from typing import Callable, Dict, FrozenSet, Iterable, List, Mapping, Optional, Tuple

from . import ports, priority, procs, shm
from .catalogue import ENV_INSTANCE, Entry, restore_remap
from .log_tail import last_line
from ..model.types import AgentSettings
from ..protocol import LIVE_STATES, NodeReport, ProcState

STATE_VERSION = 1
# A state file records a few lines per node: anything much larger is not one of ours.
MAX_STATE_BYTES = 1 << 20
LOG_ROTATE_BYTES = 10 * 1024 * 1024
ACTIVE = (ProcState.STARTING, ProcState.RUNNING, ProcState.STOPPING)
# A node's DDS ports are looked for this often after its start, for this long (_note_ports).
PORTS_EVERY_S, PORTS_LOOK_S = 0.25, 30.0
# A crashed or unstartable node, waiting for its restart.
DOWN = (ProcState.BACKOFF, ProcState.FAILED)


@dataclass
class _Proc:
    entry: Entry
    state: ProcState = ProcState.STOPPED
    wanted: bool = False
    popen: Optional[subprocess.Popen] = None
    pid: int = 0
    start_ticks: int = 0          # process start, clock ticks since boot (procs.start_ticks)
    started_wall: float = 0.0     # ... on the wall clock when first recorded (see save)
    instance: str = ''
    since: float = 0.0
    restarts: int = 0
    ready: bool = False
    exit_reason: str = ''
    exit_code: Optional[int] = None
    log_tail: str = ''
    ready_deadline: float = 0.0
    running_since: float = 0.0
    backoff_s: float = 0.0
    restart_at: float = 0.0
    stop_phase: int = 0           # 0 SIGINT sent, 1 SIGTERM sent, 2 SIGKILL sent
    stop_deadline: float = 0.0
    strays: Tuple[int, ...] = ()  # descendants that may have left the session
    log_path: str = ''
    adopted: bool = False
    raised: bool = False          # a critical node, raised to real-time once settled (priority.py)
    failed_spawns: int = 0
    history: List[str] = field(default_factory=list)
    ports: FrozenSet[int] = frozenset()  # its participants' unicast ports (agent/ports.py)
    ports_next: float = 0.0               # when to look for them (while none are found)...
    ports_until: float = 0.0              # ...until then: a process without DDS has none


class Supervisor:
    """Runs the catalogue's nodes on one scale; see the module docstring."""

    def __init__(self, catalogue: Mapping[str, Entry], settings: AgentSettings, log_dir: str,
                 state_path: str = '', identity: Optional[Mapping[str, str]] = None):
        self.settings = settings
        self.log_dir = log_dir
        self.state_path = state_path
        self.identity = dict(identity or {})      # deployment and scale, written to the state
        self._procs: Dict[str, _Proc] = {n: _Proc(entry=e) for n, e in catalogue.items()}
        self._ghosts: Dict[str, _Proc] = {}       # adopted, not in the catalogue: being stopped
        self.events: List[Tuple[str, str]] = []   # (level, text), drained by the caller
        self._dirty = False
        self._save_failures = 0                   # writes of the state file failed in a row
        self.shm_dir = shm.SHM_DIR                # where Fast DDS keeps its port files
        # A killed node's DDS ports, held a few seconds so its replacement is heard at once.
        self.port_hold = ports.PortHold()
        # Called with each pid started or adopted: the agent watches it (agent/exits.py) so that
        # an exit wakes the next step at once instead of waiting for the tick.
        self.watch_exit: Callable[[int], object] = lambda pid: None
        # What the scale's warden reads of this agent (agent/warden.py): who it is, and whether
        # it restarts in place now or has stopped every node and left.
        self.agent_start_ticks = procs.start_ticks(os.getpid())
        self.agent_started_wall = procs.create_time(os.getpid())
        self.boot_id = procs.boot_id()
        self.restarting = False
        self.stopped = False
        # The nodes the warden stops when this agent dies: those a decider could start
        # elsewhere (on the master scale none: the decider keeps its layout while the master's
        # agent is silent, and a node only this scale may run has no other copy to meet).
        self.fenceable: frozenset = frozenset()
        self.realtime = priority.Realtime(settings.critical_priority)

    # --- queries --------------------------------------------------------------------------
    @property
    def names(self) -> Tuple[str, ...]:
        return tuple(self._procs)

    def reports(self) -> Dict[str, NodeReport]:
        """Each node's report as it goes on the wire, but ``since`` on the caller's monotonic
        clock (the agent's turn puts it on the wall clock, agent/turn.py node_reports)."""
        return {n: NodeReport(state=p.state, pid=p.pid if p.state in ACTIVE else 0,
                              since=p.since, restarts=p.restarts, ready=p.ready,
                              exit_reason=p.exit_reason, exit_code=p.exit_code,
                              log_tail=p.log_tail or None)
                for n, p in self._procs.items()}

    def state(self, name: str) -> ProcState:
        return self._procs[name].state

    def active(self) -> Tuple[str, ...]:
        """Nodes with a live process here (starting, running or stopping)."""
        return tuple(n for n, p in self._procs.items() if p.state in ACTIVE)

    def adopted(self, name: str) -> bool:
        """``name`` runs in a process this agent adopted (started by an agent before it)."""
        p = self._procs.get(name)
        return p is not None and p.adopted and p.state in ACTIVE

    def pids(self) -> Dict[str, int]:
        """Live nodes' pids."""
        return {n: p.pid for n, p in self._procs.items() if p.state in ACTIVE and p.pid}

    def instances(self) -> Dict[str, str]:
        """Live nodes' per-start tokens (ENV_INSTANCE)."""
        return {n: p.instance for n, p in self._procs.items()
                if p.state in ACTIVE and p.pid and p.instance}

    def dds_ports(self, name: str) -> FrozenSet[int]:
        """The unicast ports found of the node's live participants (empty until found)."""
        return self._procs[name].ports

    def wanted(self) -> Tuple[str, ...]:
        return tuple(n for n, p in self._procs.items() if p.wanted)

    def all_stopped(self) -> bool:
        return not self._ghosts and all(p.state not in ACTIVE for p in self._procs.values())

    def log_path(self, name: str) -> str:
        return os.path.join(self.log_dir, f'{name}.log')

    # --- commands -------------------------------------------------------------------------
    def set_wanted(self, names: Iterable[str], now: float) -> None:
        """Start the named nodes and stop every other; names outside the catalogue are refused."""
        wanted = set(names)
        unknown = wanted - set(self._procs)
        if unknown:
            raise KeyError(f'not in the catalogue: {", ".join(sorted(unknown))}')
        for name, p in self._procs.items():
            if name in wanted:
                if not p.wanted:
                    p.wanted = True
                    p.backoff_s = 0.0
                    if p.state not in ACTIVE:
                        self._spawn(p, now)
            elif p.wanted:
                p.wanted = False
                self._begin_stop(p, now)

    def start(self, name: str, now: float) -> None:
        self.set_wanted(set(self.wanted()) | {name}, now)

    def restart(self, name: str, now: float, why: str) -> bool:
        """Replace the live process of ``name`` with a fresh one at the next step, without
        backoff: for a copy alive but unusable (its lifecycle stuck). False if it is not live."""
        p = self._procs.get(name)
        if p is None or p.state not in LIVE_STATES or not p.pid:
            return False
        procs.signal_session(p.pid, signal.SIGKILL, p.strays)
        if p.popen is not None:
            try:
                p.popen.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                pass
        self._event('warn', f'{name}: pid {p.pid} restarted: {why}')
        self._gone(p, now, f'restarted: {why}', restart_at=now)
        return True

    def stop(self, name: str, now: float) -> None:
        self.set_wanted(set(self.wanted()) - {name}, now)

    def stop_all(self, now: float) -> None:
        self.set_wanted((), now)

    def kill_all(self, now: float) -> None:
        """Skip the graces: SIGKILL every group now (a second shutdown request)."""
        self.set_wanted((), now)
        for p in list(self._procs.values()) + list(self._ghosts.values()):
            if p.state == ProcState.STOPPING and p.stop_phase < 2:
                p.stop_phase = 2
                p.stop_deadline = now
                procs.signal_session(p.pid, signal.SIGKILL, p.strays)

    # --- the loop -------------------------------------------------------------------------
    def step(self, now: float, visible: Callable[[Entry], bool] = lambda entry: False) -> bool:
        """Advance every node's state machine; True when a report changed."""
        before = self.reports()
        self.port_hold.release(now)
        for p in self._procs.values():
            self._step_one(p, now, visible)
        for name, p in list(self._ghosts.items()):
            self._step_stopping(p, now)
            if p.state != ProcState.STOPPING:
                del self._ghosts[name]
                self._dirty = True
        changed = self.reports() != before
        if changed or self._dirty:
            self._dirty = False
            self.save()
        return changed

    @property
    def settled(self) -> bool:
        """Whether no process is on its way but at a time ``next_due`` knows: each is up and
        seen ready, stopped as wanted, or waits for its restart; none is stopping, and the
        state file is written. Then only those times and what happens to the processes (an
        exit, a new set of wanted nodes) give a step work."""
        if self._ghosts or self._dirty:
            return False
        return all((p.state == ProcState.RUNNING and p.ready) or p.state in DOWN
                   or (p.state == ProcState.STOPPED and not p.wanted)
                   for p in self._procs.values())

    def next_due(self, now: float) -> Optional[float]:
        """The earliest time a step has work that no exit nor input brings: a node restarted
        after its backoff, its DDS ports looked for again (every PORTS_EVERY_S from its start
        until found, PORTS_LOOK_S at most), held ports released, a critical node raised to
        real-time priority once settled (None: no such work)."""
        due = [p.ports_next for p in self._procs.values()
               if p.state in LIVE_STATES and not p.ports and p.ports_next <= p.ports_until
               and now <= p.ports_until]
        due += [p.restart_at for p in self._procs.values() if p.state in DOWN and p.wanted]
        due += [p.running_since + priority.SETTLE_S for p in self._procs.values()
                if self._to_raise(p)]
        release = self.port_hold.next_release()
        if release is not None:
            due.append(release)
        return min(due, default=None)

    def unseen(self) -> Tuple[str, ...]:
        """Live processes not seen ready yet: those a step looks for in the ROS graph."""
        return tuple(n for n, p in self._procs.items() if p.state in LIVE_STATES
                     and not (p.state == ProcState.RUNNING and p.ready))

    def _step_one(self, p: _Proc, now: float, visible: Callable[[Entry], bool]) -> None:
        if p.state in LIVE_STATES:
            if p.state == ProcState.RUNNING \
                    and now - p.running_since >= self.settings.restart_backoff_max_s:
                # A long healthy run: its next crash, this one included, is not part of a loop
                # (judged here, not left to a step between, which an idle agent may not take).
                p.backoff_s = 0.0
            code, gone = self._leader_exit(p)
            if gone:
                self._crashed(p, now, code)
                if p.wanted and p.state in DOWN and now >= p.restart_at:
                    # No backoff: started again in this step, not the next; until it is up its
                    # report keeps the crash's reason (the decider hears of the crash by it
                    # and by the restart count).
                    crash = p.exit_reason, p.exit_code, p.log_tail
                    self._restart_now(p, now)
                    if p.state == ProcState.STARTING:
                        p.exit_reason, p.exit_code, p.log_tail = crash
                return
            if not p.ports and p.ports_next <= now <= p.ports_until:
                self._note_ports(p, now)
            seen = bool(visible(p.entry))
            if p.state == ProcState.STARTING:
                if seen:
                    self._set(p, ProcState.RUNNING, now, ready=True, reason='')
                    p.running_since = now
                elif now >= p.ready_deadline:
                    self._set(p, ProcState.RUNNING, now, ready=False,
                              reason=f'not visible in the ROS graph as {p.entry.ros_name!r} '
                                     f'within {self.settings.readiness_timeout_s:g} s')
                    p.running_since = now
                    self._event('warn', f'{p.entry.name}: {p.exit_reason}')
            else:
                # Readiness latches for the life of the process: a graph view that blinks while
                # another copy leaves must not make a handed-over node look lost.
                if seen and not p.ready:
                    p.ready = True
                    p.exit_reason = ''
            if self._to_raise(p) and now - p.running_since >= priority.SETTLE_S:
                self._raise(p)
        elif p.state == ProcState.STOPPING:
            self._step_stopping(p, now)
        elif p.state in DOWN:
            if p.wanted and now >= p.restart_at:
                self._restart_now(p, now)

    def _to_raise(self, p: _Proc) -> bool:
        return (p.entry.critical and p.state == ProcState.RUNNING and p.ready and not p.raised
                and self.realtime.priority > 0 and not self.realtime.refused)

    def _raise(self, p: _Proc) -> None:
        """critical_priority: a critical node, once settled, runs at real-time priority."""
        p.raised = True
        said = self.realtime.raise_node(p.entry.name, p.pid)
        if said:
            self._event('warn' if self.realtime.refused else 'info', said)

    def _step_stopping(self, p: _Proc, now: float) -> None:
        code, gone = self._leader_exit(p)
        if not gone:
            p.strays = tuple(set(p.strays) | set(procs.descendants(p.pid)))
        members = procs.session_members(p.pid) if p.pid else []
        strays = [s for s in p.strays if procs.start_ticks(s) is not None]
        if gone and not members and not strays:
            reason = 'stopped' if code is None else f'stopped ({procs.describe_exit(code)})'
            if p.stop_phase >= 1:
                reason += f' after {("SIGTERM", "SIGKILL")[min(p.stop_phase, 2) - 1]}'
            if p.stop_phase >= 2:
                self._hold_ports(p, now)        # killed: it could not say goodbye
            p.ports = frozenset()
            self._set(p, ProcState.STOPPED, now, ready=False, reason=reason)
            p.pid = 0
            p.popen = None
            self._dirty = True
            if p.wanted:            # wanted again while it was stopping
                self._spawn(p, now)
            return
        if now < p.stop_deadline:
            return
        if p.stop_phase == 0:
            p.stop_phase = 1
            p.stop_deadline = now + self.settings.sigterm_grace_s
            self._event('warn', f'{p.entry.name}: still running {self.settings.sigint_grace_s:g}'
                                ' s after SIGINT, sending SIGTERM')
            procs.signal_session(p.pid, signal.SIGTERM, p.strays)
        else:
            if p.stop_phase == 1:
                self._event('warn', f'{p.entry.name}: still running '
                                    f'{self.settings.sigterm_grace_s:g} s after SIGTERM, '
                                    'sending SIGKILL')
            p.stop_phase = 2
            p.stop_deadline = now + 1.0
            procs.signal_session(p.pid, signal.SIGKILL, p.strays)

    # --- transitions ----------------------------------------------------------------------
    def _set(self, p: _Proc, state: ProcState, now: float, ready: bool, reason: str) -> None:
        if state != p.state:
            p.since = now
        p.state = state
        p.ready = ready
        p.exit_reason = reason
        # An exit's code and log line go with the reason it gave (``_crashed`` sets them).
        p.exit_code, p.log_tail = None, ''

    def _event(self, level: str, text: str) -> None:
        self.events.append((level, text))

    def _open_log(self, p: _Proc):
        os.makedirs(self.log_dir, exist_ok=True)
        path = self.log_path(p.entry.name)
        try:
            if os.path.getsize(path) > LOG_ROTATE_BYTES:
                os.replace(path, path + '.1')
        except OSError:
            pass
        p.log_path = path
        return open(path, 'ab', buffering=0)

    def _spawn(self, p: _Proc, now: float) -> None:
        entry = p.entry
        if not entry.startable:
            self._set(p, ProcState.FAILED, now, ready=False, reason=entry.problem or 'no argv')
            p.restart_at = now + self.settings.restart_backoff_max_s
            self._event('error', f'{entry.name}: cannot start: {p.exit_reason}')
            return
        # A port file left empty by a participant killed while starting would hang this one
        # in rclpy.init() (agent/shm.py): cleared before every start.
        shm.remove_broken_port_files(self.shm_dir, say=lambda text: self._event('warn', text))
        p.instance = uuid.uuid4().hex
        env = dict(entry.env)
        env[ENV_INSTANCE] = p.instance
        log = None
        try:
            log = self._open_log(p)
            log.write(f'--- {entry.name}: starting {" ".join(entry.argv)}\n'.encode())
        except OSError as e:
            # An unwritable log folder or a full disk must not keep a node from serving.
            if log is not None:
                log.close()
                log = None
            p.log_path = os.devnull
            self._event('error', f'{entry.name}: cannot write its log file '
                                 f'{self.log_path(entry.name)} ({e.strerror or e}); starting it '
                                 'with its output discarded')
        try:
            # start_new_session: its own session and process group, away from the agent's
            # terminal, so a Ctrl-C meant for the agent does not reach it and the group can be
            # signalled as one.
            # node_nice: the node runs below the agent and the decider, so a node that takes
            # all the CPU it gets (a CPU-bound one on a weak robot) cannot starve the monitors,
            # heartbeats and probes that judge it. A critical node (in a tolerance-0
            # connection: it may never be below its minimum) is not niced by node_nice: on a
            # saturated scale it runs beside the agent, ahead of the heavy nodes that may move.
            # A node's own nice adds to the rest. nice(1) execs the node: same pid.
            # A node with a state gets a restore input of this process's own (catalogue.py).
            argv = list(entry.argv) + list(restore_remap(entry, p.instance))
            niceness = min(19, (0 if entry.critical else self.settings.node_nice) + entry.nice)
            if niceness:
                argv = ['nice', '-n', str(niceness)] + argv
            p.popen = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL,
                                       stdout=subprocess.DEVNULL if log is None else log,
                                       stderr=subprocess.STDOUT,
                                       start_new_session=True, close_fds=True)
        except OSError as e:
            self._spawn_failed(p, now, f'cannot start {entry.argv[0]}: {e.strerror or e}')
            return
        finally:
            if log is not None:
                log.close()
        p.pid = p.popen.pid
        self.watch_exit(p.pid)
        p.start_ticks = procs.start_ticks(p.pid) or 0
        p.started_wall = procs.create_time(p.pid) or 0.0
        p.adopted = False
        p.raised = False
        p.strays = ()
        p.ports, p.ports_next, p.ports_until = frozenset(), now, now + PORTS_LOOK_S
        p.failed_spawns = 0
        p.ready_deadline = now + self.settings.readiness_timeout_s
        self._set(p, ProcState.STARTING, now, ready=False, reason='')
        self._event('info', f'{entry.name}: started pid {p.pid} (log {p.log_path})')
        # Recorded at once: an agent killed right now must still find it when it comes back.
        self.save()

    def _restart_now(self, p: _Proc, now: float) -> None:
        p.restarts += 1
        self._spawn(p, now)

    def _spawn_failed(self, p: _Proc, now: float, reason: str) -> None:
        p.failed_spawns += 1
        p.popen = None
        p.pid = 0
        self._set(p, ProcState.FAILED, now, ready=False, reason=reason)
        p.restart_at = now + self._next_backoff(p)
        self._event('error', f'{p.entry.name}: {reason}')

    def _next_backoff(self, p: _Proc) -> float:
        """The delay before this restart, and the next one's: none for the first crash (of a
        new node, or after a healthy run of ``restart_backoff_max_s``), then
        ``restart_backoff_s`` doubling up to ``restart_backoff_max_s``: a crash loop is held
        back, a single crash costs only the restart."""
        delay = max(p.backoff_s, 0.0)
        low = self.settings.restart_backoff_s
        p.backoff_s = min(max(delay * 2, low), self.settings.restart_backoff_max_s)
        return delay

    def _leader_exit(self, p: _Proc) -> Tuple[Optional[int], bool]:
        """(return code or None, whether the node's leader process is gone)."""
        if p.popen is not None:
            code = p.popen.poll()
            return code, code is not None
        if not p.pid:
            return None, True
        # An adopted process is still our child when this agent re-executed itself (a restart
        # in place): it is gone once reaped, and then its exit status is known.
        reaped = procs.reap(p.pid)
        if reaped is not None:
            ended, code = reaped
            return code, ended
        return None, not procs.alive(p.pid, p.start_ticks)

    def _crashed(self, p: _Proc, now: float, code: Optional[int]) -> None:
        reason = procs.describe_exit(code)
        if p.adopted and code is None:
            reason = 'exited (adopted process, exit status unknown)'
        # Whatever the node left behind goes with it: no orphans.
        left = procs.signal_session(p.pid, signal.SIGKILL, p.strays)
        if left:
            reason += f'; killed {left} leftover process{"es" if left > 1 else ""}'
        delay = self._next_backoff(p)
        self._gone(p, now, reason, restart_at=now + delay)
        # An adopted process writes where the agent that started it opened its log: here.
        log = p.log_path or self.log_path(p.entry.name)
        tail = last_line(log) if log != os.devnull else ''
        self._event('error', f'{p.entry.name}: crashed: {reason}; restarting in {delay:g} s '
                             f'(restart {p.restarts + 1})'
                             + (f'; its last log line: {tail}' if tail else ''))
        if not p.wanted:
            self._set(p, ProcState.STOPPED, now, ready=False, reason=reason)
        p.exit_code, p.log_tail = code, tail

    def _gone(self, p: _Proc, now: float, reason: str, restart_at: float) -> None:
        """The process is gone (killed or exited): back off until ``restart_at``."""
        self._hold_ports(p, now)
        p.popen = None
        p.pid = 0
        self._set(p, ProcState.BACKOFF, now, ready=False, reason=reason)
        p.restart_at = restart_at
        self._dirty = True

    def _note_ports(self, p: _Proc, now: float) -> None:
        """Read the unicast ports of the node's participants (agent/ports.py). Looked for
        every PORTS_EVERY_S from its start until found, for at most PORTS_LOOK_S (not once it
        is visible: the graph still shows a killed copy for seconds)."""
        pids = set(procs.session_members(p.pid)) | set(p.strays) | {p.pid}
        p.ports = ports.unicast_ports(pids, ports.domain_of(p.entry.env))
        p.ports_next = now + PORTS_EVERY_S

    def _hold_ports(self, p: _Proc, now: float) -> None:
        if p.ports:
            held = self.port_hold.hold(p.ports, now)
            if held:
                self._event('info', f'{p.entry.name}: holding its DDS ports '
                                    f'{", ".join(map(str, held))} for '
                                    f'{self.port_hold.hold_s:g} s, so that its next start '
                                    'takes fresh ones')
        p.ports = frozenset()

    def _begin_stop(self, p: _Proc, now: float) -> None:
        if p.state in DOWN:
            self._set(p, ProcState.STOPPED, now, ready=False, reason=p.exit_reason)
            return
        if p.state not in LIVE_STATES:
            return
        p.strays = tuple(set(p.strays) | set(procs.descendants(p.pid)))
        self._set(p, ProcState.STOPPING, now, ready=False, reason='')
        p.stop_phase = 0
        p.stop_deadline = now + self.settings.sigint_grace_s
        procs.signal_session(p.pid, signal.SIGINT, p.strays)
        self._event('info', f'{p.entry.name}: stopping pid {p.pid} (SIGINT)')

    # --- the state file -------------------------------------------------------------------
    def save(self) -> None:
        """Record every live node so that a restarted agent can adopt it."""
        if not self.state_path:
            return
        nodes = {}
        for name, p in list(self._procs.items()) + list(self._ghosts.items()):
            if p.state in ACTIVE and p.pid:
                # 'started' (the wall clock, as first read) is for a warden of an earlier
                # version only: it compares it with its own reading of the process's start.
                nodes[name] = {'pid': p.pid, 'start_ticks': p.start_ticks,
                               'started': p.started_wall, 'instance': p.instance,
                               'argv': list(p.entry.argv), 'restarts': p.restarts,
                               'stopping': p.state == ProcState.STOPPING,
                               'fence': name in self.fenceable}
        data = dict(self.identity, version=STATE_VERSION, boot_id=self.boot_id,
                    agent_pid=os.getpid(), agent_start_ticks=self.agent_start_ticks,
                    agent_started=self.agent_started_wall,
                    restarting=self.restarting, stopped=self.stopped, nodes=nodes)
        tmp = f'{self.state_path}.{os.getpid()}.tmp'
        try:
            os.makedirs(os.path.dirname(self.state_path) or '.', exist_ok=True)
            with open(tmp, 'w', encoding='utf-8') as f:
                json.dump(data, f, indent=1, sort_keys=True)
            os.replace(tmp, self.state_path)
        except OSError as e:
            # What runs keeps running; only a restarted agent would not adopt it. Said once,
            # retried at every step until it works.
            try:
                os.unlink(tmp)
            except OSError:
                pass
            self._dirty = True
            self._save_failures += 1
            if self._save_failures == 1:
                self._event('error', f'cannot write the state file {self.state_path} '
                                     f'({e.strerror or e}); the nodes keep running, but an agent '
                                     'restarted now would not adopt them')
            return
        if self._save_failures:
            self._event('info', f'state file {self.state_path} written again (after '
                                f'{self._save_failures} failed writes)')
            self._save_failures = 0

    def adopt(self, now: float) -> List[str]:
        """Take over the nodes a previous agent recorded; return what was done, in words.

        A recorded process is ours only if the boot, its pid, its start (ticks since boot) and
        the per-start token in its environment all match: a reused pid is never signalled. A
        file of an earlier version has no ticks: its wall-clock start is checked as that version
        did (``procs.recorded_start``). An adopted node whose argv no
        longer matches the catalogue, or that is no longer in it, is stopped.
        """
        notes: List[str] = []
        if not self.state_path or not os.path.exists(self.state_path):
            return notes
        try:
            with open(self.state_path, encoding='utf-8') as f:
                text = f.read(MAX_STATE_BYTES + 1)
            if len(text) > MAX_STATE_BYTES:
                raise ValueError(f'over {MAX_STATE_BYTES} bytes')
            data = json.loads(text)
            if not isinstance(data, dict):
                raise ValueError('not a JSON object')
            if data.get('version') != STATE_VERSION:
                raise ValueError(f'version {str(data.get("version"))[:20]}, this agent reads '
                                 f'version {STATE_VERSION}')
            nodes = data.get('nodes')
            if not isinstance(nodes, dict):
                raise ValueError('no map of nodes')
        except OSError as e:
            notes.append(f'state file {self.state_path} unreadable ({e.strerror or e}); '
                         'adopting nothing')
            return notes
        except (ValueError, RecursionError) as e:
            # Kept aside for a person to read: the next save would overwrite it.
            aside = self.state_path + '.unreadable'
            try:
                os.replace(self.state_path, aside)
            except OSError:
                aside = ''
            notes.append(f'state file {self.state_path} unreadable ({str(e)[:200]}); adopting '
                         f'nothing{f", kept as {aside}" if aside else ""}')
            return notes
        for k in ('deployment', 'scale'):
            if k in self.identity and data.get(k) != self.identity[k]:
                notes.append(f'state file {self.state_path} is for {k} {data.get(k)!r}, not '
                             f'{self.identity[k]!r}; adopting nothing')
                return notes
        if procs.another_boot(data.get('boot_id')):
            notes.append(f'state file {self.state_path} was written before this machine last '
                         'booted: what it records is gone; adopting nothing')
            return notes
        for name, rec in nodes.items():
            try:
                pid, instance = int(rec['pid']), str(rec['instance'])
                argv = tuple(str(a) for a in rec['argv'])
                if rec.get('start_ticks') is None:
                    float(rec['started'])               # written by an earlier version
                elif procs.recorded_start(pid, rec['start_ticks'], None) is None:
                    raise ValueError(rec['start_ticks'])
            except (KeyError, TypeError, ValueError, OverflowError):
                notes.append(f'{name[:60]}: malformed state record; ignored')
                continue
            started = procs.recorded_start(pid, rec.get('start_ticks'), rec.get('started')) \
                if pid > 1 else None
            if started is None or not procs.alive(pid, started):
                notes.append(f'{name}: recorded pid {pid} is gone')
                continue
            if procs.environ_value(pid, ENV_INSTANCE, exec_wait_s=0.5) != instance:
                notes.append(f'{name}: pid {pid} is another process now (token differs); '
                             'left alone')
                continue
            p = self._procs.get(name)
            if p is None:
                # Ours, but no longer in the catalogue: stop it, never restart it.
                ghost = _Proc(entry=Entry(name=name, argv=argv))
                self._take(ghost, pid, started, instance, now, rec)
                self._begin_stop(ghost, now)
                self._ghosts[name] = ghost
                notes.append(f'{name}: pid {pid} is not in the catalogue; stopping it')
                continue
            self._take(p, pid, started, instance, now, rec)
            if argv != p.entry.argv or rec.get('stopping') or rec.get('standby'):
                p.wanted = False
                self._begin_stop(p, now)
                notes.append(f'{name}: adopted pid {pid} runs an outdated command or was being '
                             'stopped; stopping it')
            else:
                p.wanted = True
                notes.append(f'{name}: adopted pid {pid}')
        self._dirty = True
        return notes

    def _take(self, p: _Proc, pid: int, started: int, instance: str, now: float,
              rec: Mapping) -> None:
        p.pid = pid
        p.start_ticks = started
        wall = rec.get('started')
        p.started_wall = float(wall) if isinstance(wall, (int, float)) \
            and not isinstance(wall, bool) else procs.wall_start(started)
        p.instance = instance
        p.popen = None
        p.adopted = True
        p.raised = False
        p.ports, p.ports_next, p.ports_until = frozenset(), now, now + PORTS_LOOK_S
        self.watch_exit(pid)
        if rec.get('standby'):
            # Recorded frozen (SIGSTOP) by an agent of an earlier version: it must run to stop.
            procs.signal_session(pid, signal.SIGCONT, procs.descendants(pid))
        restarts = rec.get('restarts', 0)
        p.restarts = restarts if isinstance(restarts, int) and 0 <= restarts < 2 ** 31 else 0
        p.backoff_s = 0.0
        p.ready_deadline = now + self.settings.readiness_timeout_s
        self._set(p, ProcState.STARTING, now, ready=False, reason='')
        # Report the process's own start on the caller's clock.
        p.since = now - procs.age_s(started)
