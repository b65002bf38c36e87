"""The agent of one scale: starts and stops the deployment's nodes there, and hosts its monitors.

    ros2 run anyscale_manager agent --ros-args --params-file DEPLOYMENT.yaml -p scale:=NAME

Glue only: the catalogue, the supervisor and the move-order rules live in anyscale_manager.agent.
The node subscribes to the latched layout and to the other agents' reports, publishes its own
report (latched) on every change and at ``agent.heartbeat_rate_hz``, and drives the supervisor
from a timer. A lifecycle node is driven through its own copy's services (agent/lifecycle.py):
configured once started, active where the layout places it, inactive as a standby copy, and
finalized before its process is signalled. SIGINT or SIGTERM stops every node it runs (SIGINT,
SIGTERM, SIGKILL with the configured graces) while it keeps reporting, then it exits 0; a second
signal skips the graces.
"""

import array
import fcntl
import os
import re
import secrets
import signal
import sys
import time
import traceback
from typing import Any, Dict, List, Optional, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String

from . import qos
from .executor import make_executor
from .lifecycle_client import CopyClients
from .throttled_log import ThrottledLog
from .. import protocol
from .. import protocol_auth as auth
from ..agent import lifecycle as lc
from ..agent.authority import describe, Follower
from ..agent.catalogue import build_catalogue, Entry
from ..agent.exits import ExitWatcher
from ..agent.warden import spawn as spawn_warden, warden_port
from ..agent.host import this_host
from ..agent.reconcile import Reconciler
from ..agent.supervisor import Supervisor
from ..model.loader import DeploymentError, load_from_parameters
from ..protocol import LIVE_STATES, ProcState
from ..runtime.hosts import HostBook
from ..interrupt import restore_ctrl_c

try:
    from . import monitors as _monitors
    _MONITORS_MISSING = ''
except ImportError as exc:   # a broken install: the agent still supervises without monitors
    _monitors = None
    _MONITORS_MISSING = str(exc)

TICK_S = 0.1
# While a node is stopping the loop runs this often: a stop_before_start move waits until the
# old copy is seen gone here (and reported) before the other scale starts the new one.
STOPPING_TICK_S = 0.02
EXIT_WAKE_S = 0.001          # the one-shot wake after a node exits (agent/exits.py)
SCALE_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
# A layout that names unknown nodes or scales is logged entry by entry up to this many.
MAX_LAYOUT_WARNINGS = 5
UNSIGNED = ('layouts are not signed and anyone on this ROS domain can move or stop the nodes '
            'of this scale (anyscale-manager keygen; docs/decider.md, security)')


class AgentError(RuntimeError):
    """A reason the agent cannot run, said in one line."""


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


def _plain(value: Any) -> Any:
    if isinstance(value, array.array):
        return list(value)
    return value


def _ros_home() -> str:
    return os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')


class AgentNode(Node):
    def __init__(self, scale: str, **kwargs):
        super().__init__(f'anyscale_agent_{scale}',
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        self._lock_file = None
        self._monitors: List[Any] = []
        self._watch: Optional[Node] = None
        self._lifecycle: Dict[str, CopyClients] = {}
        try:
            self._setup(scale)
        except Exception:
            self._release_lock()
            self.destroy_node()
            raise

    # --- construction ---------------------------------------------------------------------
    def _setup(self, scale: str) -> None:
        flat = {name: _plain(p.value) for name, p in self.get_parameters_by_prefix('').items()}
        self.deployment = load_from_parameters(flat)
        d = self.deployment
        if scale not in d.scale_names:
            raise AgentError(f'scale {scale!r} is not a scale of deployment {d.name!r} '
                             f'(scales: {", ".join(d.scale_names)})')
        self.scale = scale
        self.settings = d.agent
        key = auth.load_key(d.security.key_file) if d.security.key_file else None
        self._key = key
        self._gate = auth.LayoutGate(key, d.security.replay_window_s)
        # Peers' reports and the decider's objective also start and stop things here (a
        # handover lets go on a peer's ready report; a remote scale stops its nodes when the
        # master goes silent): with a key they are checked like layouts.
        self._state_gate = auth.Gate(key, d.security.replay_window_s)
        self._objective_gate = auth.Gate(key, d.security.replay_window_s)
        self._instance = secrets.token_hex(8)
        self._seq = 0
        # The machine this agent runs on, and the one each other scale's agent reports: on a
        # shared machine the scale monitor measures this agent's own processes.
        self._host_id, self._host_name = this_host()
        self._hosts = HostBook()
        self._bad = ThrottledLog(self.get_logger())    # bad input: one line per kind and 10 s
        self._follower = Follower(d.decider.lease_s)
        state_dir = self.settings.state_dir or os.path.join(_ros_home(), 'anyscale_manager')
        log_root = self.settings.log_dir or os.path.join(
            os.environ.get('ROS_LOG_DIR') or os.path.join(_ros_home(), 'log'),
            'anyscale_manager')
        self.log_dir = os.path.join(log_root, d.name, scale)
        stem = os.path.join(state_dir, f'agent_{d.name}_{scale}')
        self._take_lock(stem + '.lock')

        self.catalogue: Dict[str, Entry] = build_catalogue(d, scale)
        for entry in self.catalogue.values():
            if entry.problem:
                self.get_logger().error(f'{entry.name}: {entry.problem}')
        self.supervisor = Supervisor(self.catalogue, self.settings, self.log_dir,
                                     state_path=stem + '.json',
                                     identity={'deployment': d.name, 'scale': scale})
        self.reconciler = Reconciler(d, scale, self.catalogue,
                                     readiness_timeout_s=self.settings.readiness_timeout_s,
                                     agent_timeout_s=d.decider.agent_timeout_s)
        s = self.settings
        self._lifecycle = {
            name: CopyClients(self, entry.services,
                              lc.Driver(name, change_timeout_s=s.lifecycle_timeout_s,
                                        backoff_s=max(s.restart_backoff_s, 0.1),
                                        backoff_max_s=max(s.restart_backoff_max_s, 0.1)),
                              time.monotonic, self._tick)
            for name, entry in self.catalogue.items() if entry.lifecycle and entry.startable}
        self._lifecycle_pid: Dict[str, int] = {}
        self._finalize_since: Dict[str, float] = {}
        self._wall_offset = time.time() - time.monotonic()
        # A node's exit wakes a step at once (agent/exits.py): a crash is reported, and a
        # standby copy elsewhere can take over, without waiting for the tick. The wake is a
        # one-shot timer reset from the watcher's thread (the events executor has no guard
        # conditions); it fires within a millisecond.
        self._exit_wake = self.create_timer(EXIT_WAKE_S, self._on_exit)
        self._exit_wake.cancel()
        self.supervisor.watch_exit = ExitWatcher(self._exit_wake.reset).watch
        for note in self.supervisor.adopt(time.monotonic()):
            if note.startswith('state file'):       # unreadable, or not this agent's
                self.get_logger().warn(f'adoption: {note}')
            else:
                self.get_logger().info(f'adoption: {note}')
        self._shutdown_requested = 0
        self.restarting = False
        self._shutdown_at = 0.0
        self._probe_names: Optional[tuple] = None
        self._published_view: Dict[str, tuple] = {}
        self._last_waiting: Dict[str, str] = {}

        self._state_pub = self.create_publisher(String, protocol.TOPIC_AGENT_STATE, qos.LATCHED)
        # Several writers on each (every agent; a rival decider): a reader of depth 1 keeps one
        # sample for all of them, and a peer's report that lands beside another is lost until
        # its next heartbeat (a stop_before_start move then waited one report period).
        self.create_subscription(String, protocol.TOPIC_LAYOUT, self._on_layout,
                                 qos.LATCHED_READER)
        self.create_subscription(String, protocol.TOPIC_AGENT_STATE, self._on_agent_state,
                                 qos.LATCHED_READER)
        if scale != d.master.name:
            # The decider's output at each of its steps: word from the master scale, which a
            # remote scale cut off from it no longer gets (see Reconciler).
            self.reconciler.heard_master(time.monotonic())
            self.create_subscription(String, protocol.TOPIC_OBJECTIVE, self._on_objective, 10)
        # One timer drives the loop, at STOPPING_TICK_S while a node is stopping (_tick).
        self._tick_s = TICK_S
        self._tick_timer = self.create_timer(TICK_S, self._tick)
        self.create_timer(1.0 / self.settings.heartbeat_rate_hz, self._publish_state)
        self._start_monitors()
        self._start_warden(stem)
        self.get_logger().info(
            f'agent for scale {scale!r} of {d.name!r}: catalogue '
            f'{", ".join(self.catalogue) or "(empty)"}; logs in {self.log_dir}')
        if key is None:
            self.get_logger().warn(f'security.key_file is not set: {UNSIGNED}')
        self._tick()

    def _start_warden(self, stem: str) -> None:
        """The scale's warden (agent/warden.py): the heartbeat echo and the fencing of these
        nodes, in a process that outlives this one. One per state file: an agent restarted
        in place, or by systemd, finds it running."""
        s, d = self.settings, self.deployment
        if self.scale != d.master.name:
            self.supervisor.fenceable = frozenset(
                n for n in self.catalogue if set(d.allowed_scales(n)) - {self.scale})
        self.supervisor.save()       # who this agent is, before the warden reads it
        port = warden_port(d, self.scale)
        log = os.path.join(self.log_dir, 'warden.log')
        try:
            pid = spawn_warden(stem + '.json', self.scale, d.name, d.scale(self.scale).host,
                               port, s.adopt_grace_s, s.restart_grace_s, s.fence_grace_s, log,
                               d.security.key_file, s.warden_priority)
        except OSError as e:
            # The nodes still run and are supervised; what is lost is said.
            self.get_logger().error(
                f'cannot start the warden ({e.strerror or e}; log {log}): the master hears no '
                'heartbeat from this scale (its link counts as down) and nothing stops these '
                'nodes if this agent dies')
            return
        if pid is not None:
            self.get_logger().info(f'warden started: pid {pid}, heartbeats on UDP '
                                   f'{d.scale(self.scale).host}:{port} (log '
                                   f'{os.path.join(self.log_dir, "warden.log")})')

    def _take_lock(self, path: str) -> None:
        """One agent per scale and machine: a second one would start every node twice."""
        try:
            os.makedirs(os.path.dirname(path), exist_ok=True)
            f = open(path, 'a+')
        except OSError as e:
            # Without its lock and state file an agent could start every node twice, or lose
            # track of them when it restarts: it starts nothing.
            raise AgentError(f'cannot use the state folder {os.path.dirname(path)} (lock '
                             f'{path}): {e.strerror or e}; set agent.state_dir to a writable '
                             'folder') from None
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            raise AgentError(f'another agent for scale {self.scale!r} of '
                             f'{self.deployment.name!r} runs on this machine (it holds {path}); '
                             'not starting a second one') from None
        try:
            f.seek(0)
            f.truncate()
            f.write(f'{os.getpid()}\n')
            f.flush()
        except OSError:
            pass        # the pid is for people (a full disk); the lock is the flock
        self._lock_file = f

    def _release_lock(self) -> None:
        if self._lock_file is not None:
            try:
                self._lock_file.close()
            except OSError:
                pass    # its pid line could not be flushed (a full disk); closed all the same
            self._lock_file = None

    def _start_monitors(self) -> None:
        if _monitors is None:
            self.get_logger().warn(f'monitors not available ({_MONITORS_MISSING}); '
                                   'this agent supervises nodes only')
            return
        d, scale = self.deployment, self.scale
        # One signer for the monitors' topics (a key: signed; else plain JSON, as before).
        sealer = auth.Sealer(self._key, f'agent {scale}')
        builders = (('ScaleMonitor', lambda cls: cls(self, d, scale, pids=self._serving_pids,
                                                     own_pids=self._supervised_pids,
                                                     shared_with=self._shared_with,
                                                     sealer=sealer)),
                    ('LinkMonitor', lambda cls: cls(self, d, scale, sealer=sealer)),
                    ('ProbeManager', lambda cls: cls(self, d, scale,
                                                     watch_node=self._handover_node(),
                                                     sealer=sealer)))
        for name, build in builders:
            cls = getattr(_monitors, name, None)
            if cls is None:
                self.get_logger().warn(f'monitors.{name} not available; not hosted')
                continue
            try:
                monitor = build(cls)
            except Exception as e:   # a monitor must never take the supervision down
                self.get_logger().error(f'cannot start {name}: {e!r}')
                continue
            self._monitors.append(monitor)
            if name == 'ProbeManager':
                self._probes = monitor

    def _handover_node(self) -> Optional[Node]:
        """A node no executor spins, whose subscriptions the probes read themselves (with the
        message info the events executor does not hand out): who wrote, for handovers."""
        if self._watch is None:
            self._watch = Node(f'{self.get_name()}_handover', context=self.context,
                               start_parameter_services=False)
        return self._watch

    # --- inputs ---------------------------------------------------------------------------
    def _on_layout(self, msg: String) -> None:
        try:
            layout = protocol.Layout.from_json(msg.data, protocol.TOPIC_LAYOUT)
        except protocol.ProtocolError as e:
            self._bad.error('layout: malformed', f'ignored a layout message: {e}')
            return
        if layout.deployment != self.deployment.name:
            self._bad.warn('layout: another deployment',
                           f'ignored a layout of deployment {layout.deployment!r:.60}, not '
                           f'{self.deployment.name!r}', interval_s=60.0)
            return
        now = time.monotonic()
        why = self._gate.check(msg.data, layout, time.time())
        if why:
            self._bad.error('layout: refused', f'dropped layout generation {layout.generation} '
                            f'of decider {describe(layout.decider)}: {why}')
            return
        follow = self._follower.consider(layout.decider, now, layout.term)
        if not follow.accept:
            self.get_logger().warn(follow.reason, throttle_duration_sec=10.0)
            return
        if follow.reason:
            self.get_logger().info(follow.reason)
        # The decider runs on the master scale: its layout, even one latched and delivered
        # when the link comes back, is word from there now. Counted before the layout is
        # applied, so that the first tick after it does not take the silence before it for a
        # cut and stop what the layout just placed here.
        self.reconciler.heard_master(now)
        if not follow.switched and layout.generation == self.reconciler.generation:
            return      # the followed decider's re-publication: its lease, nothing new
        verdict = self.reconciler.apply_layout(layout, now, new_decider=follow.switched)
        for w in verdict.warnings[:MAX_LAYOUT_WARNINGS]:
            self.get_logger().warn(w)
        if len(verdict.warnings) > MAX_LAYOUT_WARNINGS:
            self.get_logger().warn(f'layout generation {layout.generation}: '
                                   f'{len(verdict.warnings) - MAX_LAYOUT_WARNINGS} more entries '
                                   'ignored (not listed)')
        if verdict.applied:
            mine = sorted(n for n, s in self.reconciler.assignments.items() if s == self.scale)
            self.get_logger().info(f'layout generation {layout.generation} applied '
                                   f'({layout.reason or "no reason given"}); here: '
                                   f'{", ".join(mine) or "nothing"}')
            self._tick()
            # The new generation is news for the others even when nothing here changed.
            self._publish_state()

    def _on_agent_state(self, msg: String) -> None:
        try:
            state = protocol.AgentState.from_json(msg.data, protocol.TOPIC_AGENT_STATE)
        except protocol.ProtocolError as e:
            self._bad.warn('agent_state: malformed', f'ignored an agent state message: {e}')
            return
        if state.scale == self.scale and state.instance == self._instance:
            return                                      # our own report
        why = self._state_gate.check_from(msg.data, f'{state.scale}/{state.instance}',
                                          state.seq, state.stamp, time.time())
        if why:
            self._bad.error('agent_state: refused', f'dropped an agent state claiming scale '
                            f'{state.scale!r:.60}: {why}')
            return
        warning = self.reconciler.peer_state(state, time.monotonic())
        if warning:
            self._bad.warn('agent_state: not a peer', warning)
        elif state.scale != self.scale:
            self._hosts.heard(state.scale, state.host_id, state.host, time.monotonic())
            self._tick()

    def _on_objective(self, msg: String) -> None:
        try:
            objective = protocol.Objective.from_json(msg.data, protocol.TOPIC_OBJECTIVE)
        except protocol.ProtocolError as e:
            self._bad.warn('objective: malformed', f'ignored an objective message: {e}')
            return
        why = self._objective_gate.check_from(msg.data, objective.decider, objective.seq,
                                              objective.stamp, time.time())
        if why:
            self._bad.error('objective: refused', f'dropped an objective message: {why}')
            return
        self.reconciler.heard_master(time.monotonic())

    # --- the loop -------------------------------------------------------------------------
    def _visible_counts(self) -> Dict[str, int]:
        counts: Dict[str, int] = {}
        for name, ns in self.get_node_names_and_namespaces():
            full = (ns.rstrip('/') + '/' + name)
            for key in {name, full} if ns in ('', '/') else {full}:
                counts[key] = counts.get(key, 0) + 1
        return counts

    def _serving(self) -> set:
        """Nodes that serve here now: a live plain process, or a lifecycle copy that is active
        or being activated (not one whose state is not known yet)."""
        out = set()
        sup = self.supervisor
        for name in sup.active():
            clients = self._lifecycle.get(name)
            if clients is None:
                out.add(name)
            elif sup.state(name) != ProcState.STOPPING:
                d = clients.driver
                if d.state == lc.ACTIVE or (d.known and d.goal == lc.ACTIVE and not d.failed):
                    out.add(name)
        return out

    def _supervised_pids(self) -> List[int]:
        """Every live process this agent supervises: serving, standby or stopping copies."""
        return list(self.supervisor.pids().values())

    def _shared_with(self) -> tuple:
        """The other scales whose agents, heard within agent_timeout_s, run on this machine."""
        return self._hosts.sharing(self.scale, self._host_id, time.monotonic(),
                                   self.deployment.decider.agent_timeout_s)

    def _serving_pids(self) -> Dict[str, int]:
        """The pids of the copies that serve: an inactive standby copy's CPU is not its node's."""
        serving = self._serving()
        return {n: pid for n, pid in self.supervisor.pids().items() if n in serving}

    def _on_exit(self) -> None:
        self._exit_wake.cancel()
        self._tick()

    def _tick(self) -> None:
        now = time.monotonic()
        sup = self.supervisor
        self._bad.flush()
        probes = getattr(self, '_probes', None)
        if probes is not None:
            probes.poll_writers(now)
        if self._shutdown_requested:
            want: set = set()
            goals = {n: lc.FINALIZED for n in self._lifecycle}
        else:
            placed = self.reconciler.desired(now, self._serving(), heard_here=self._heard_here)
            live = [n for n in self._lifecycle if sup.state(n) in LIVE_STATES]
            goals, want = lc.goals(self._lifecycle, placed, self.reconciler.standby_here,
                                   self.reconciler.has_layout, live)
            waiting = self.reconciler.waiting
            for node, why in waiting.items():
                if self._last_waiting.get(node) != why.split(' (')[0]:
                    self.get_logger().info(f'{node}: {why}')
            self._last_waiting = {n: w.split(' (')[0] for n, w in waiting.items()}
        want |= {n for n, g in goals.items() if g == lc.FINALIZED and self._finalizing(n, now)}
        sup.set_wanted(want, now)
        self._sync_drivers()
        for name, goal in goals.items():
            driver = self._lifecycle[name].driver
            # A copy whose state is not known yet (just started, or adopted) is only asked
            # for it: activating or deactivating it blind could leave two copies serving.
            driver.set_goal(goal if driver.known or goal == lc.FINALIZED else None)
        counts = self._visible_counts() if len(self._lifecycle) < len(self.catalogue) else {}

        def visible(entry: Entry) -> bool:
            if entry.lifecycle:
                # Up once it answers get_state on its own services.
                return entry.name in self._lifecycle and self._lifecycle[entry.name].driver.known
            # A copy still running on another scale has the same name: count ours.
            elsewhere = self.reconciler.copies_elsewhere(entry.name, now)
            return counts.get(entry.ros_name, 0) > elsewhere

        changed = sup.step(now, visible)
        self._sync_drivers()
        self._drive_lifecycles(now)
        self._log_events()
        # Answers to lifecycle requests arrive between ticks: compare with what was last
        # published, not with the start of this tick.
        view = self._lifecycle_view()
        if changed or view != self._published_view:
            self._published_view = view
            self._publish_state()
        self._update_probes()
        stopping = any(sup.state(n) == ProcState.STOPPING for n in sup.names)
        tick_s = STOPPING_TICK_S if stopping else TICK_S
        if tick_s != self._tick_s:
            self._tick_s = tick_s
            self._tick_timer.timer_period_ns = round(tick_s * 1e9)
            self._tick_timer.reset()

    def _lifecycle_view(self) -> Dict[str, tuple]:
        return {n: (c.driver.state, c.driver.goal, c.driver.failed)
                for n, c in self._lifecycle.items()}

    def _finalizing(self, name: str, now: float) -> bool:
        """Whether a lifecycle copy that must stop keeps its process a while longer: until it
        is finalized, its driver gave up, or lifecycle_timeout_s has passed since it was asked
        (a node that does not answer is signalled all the same)."""
        if self.supervisor.state(name) not in LIVE_STATES:
            self._finalize_since.pop(name, None)
            return False
        driver = self._lifecycle[name].driver
        since = self._finalize_since.setdefault(name, now)
        if driver.state == lc.FINALIZED or driver.failed \
                or now - since > self.settings.lifecycle_timeout_s:
            return False
        return True

    def _sync_drivers(self) -> None:
        """A new process (started, restarted or gone) starts its driver afresh."""
        pids = self.supervisor.pids()
        for name, clients in self._lifecycle.items():
            pid = pids.get(name, 0)
            if self._lifecycle_pid.get(name, 0) != pid:
                self._lifecycle_pid[name] = pid
                clients.driver.reset()
                self._finalize_since.pop(name, None)

    def _drive_lifecycles(self, now: float) -> None:
        sup = self.supervisor
        for name, clients in self._lifecycle.items():
            driver = clients.driver
            if sup.state(name) not in LIVE_STATES:
                continue
            if driver.failed and driver.goal in (lc.ACTIVE, lc.INACTIVE):
                sup.restart(name, now, f'its lifecycle did not reach {driver.goal}: '
                                       f'{driver.problem}')
                continue
            clients.poll()
            for level, text in driver.events:
                sup.events.append((level, text))
            driver.events.clear()

    def _heard_here(self, node: str, since: float) -> Optional[bool]:
        """Whether this scale has heard, since ``since``, a newly started writer (the node's
        copy elsewhere) on every output of ``node`` that it watches; None when it watches
        none."""
        probes = getattr(self, '_probes', None)
        if probes is None:
            return None
        probed = set(probes.connections)
        joined = [probes.writer_joined_since(c.name, since) for c in self.deployment.connections
                  if c.publisher == node and c.name in probed]
        joined = [j for j in joined if j is not None]
        return all(joined) if joined else None

    def _log_events(self) -> None:
        log = self.get_logger()
        for level, text in self.supervisor.events:
            # rclpy refuses one call site with changing severities: one call per level.
            if level == 'error':
                log.error(text)
            elif level == 'warn':
                log.warn(text)
            else:
                log.info(text)
        self.supervisor.events.clear()

    def _update_probes(self) -> None:
        probes = getattr(self, '_probes', None)
        if probes is None:
            return
        here = self._serving()
        for n in self.deployment.nodes:
            if not n.managed and self.deployment.allowed_scales(n.name) == (self.scale,):
                here.add(n.name)
        names = tuple(c.name for c in self.deployment.connections if c.subscriber in here)
        if names != self._probe_names:
            self._probe_names = names
            try:
                probes.set_connections(names)
            except Exception as e:
                self.get_logger().error(f'ProbeManager.set_connections failed: {e!r}')

    def report(self) -> protocol.AgentState:
        nodes = {}
        for name, r in self.supervisor.reports().items():
            since = r.since + self._wall_offset if r.since else 0.0
            state, ready, reason, label = r.state, r.ready, r.exit_reason, None
            clients = self._lifecycle.get(name)
            if clients is not None:
                state, ready, reason, label = lc.report(r.state, r.ready, r.exit_reason,
                                                        clients.driver)
            nodes[name] = protocol.NodeReport(state=state, pid=r.pid, since=since,
                                              restarts=r.restarts, ready=ready,
                                              exit_reason=reason, lifecycle=label)
        return protocol.AgentState(scale=self.scale, generation=self.reconciler.generation,
                                   stamp=time.time(), nodes=nodes,
                                   decider=self._follower.followed_id, term=self._follower.term,
                                   instance=self._instance,
                                   host_id=self._host_id or None, host=self._host_name or None)

    def _publish_state(self) -> None:
        state = self.report()
        self._seq += 1
        state.seq = self._seq
        self._state_pub.publish(String(data=auth.seal(self._key, state)))

    # --- shutdown -------------------------------------------------------------------------
    def request_shutdown(self) -> None:
        self._shutdown_requested += 1
        now = time.monotonic()
        if self._shutdown_requested == 1:
            self.get_logger().info('shutting down: stopping every node of this scale')
            self._shutdown_at = now
            self._tick()       # lifecycle nodes are finalized first, then signalled
        else:
            self.get_logger().warn('second shutdown request: killing every node now')
            self.supervisor.kill_all(now)

    def request_restart(self) -> None:
        """SIGHUP: restart in place, leaving every node running (``main`` re-executes the
        agent, which adopts them from the state file)."""
        if self._shutdown_requested:
            self.get_logger().warn('restart requested while shutting down: ignored')
            return
        self.get_logger().info('restarting in place: the nodes of this scale keep running and '
                               'are adopted by the new agent process (same pid)')
        self.restarting = True
        # The warden waits restart_grace_s for the new process, not adopt_grace_s.
        self.supervisor.restarting = True
        self.supervisor.save()

    @property
    def finished(self) -> bool:
        return bool(self._shutdown_requested) and self.supervisor.all_stopped()

    def finish_offline(self, deadline_s: float) -> None:
        """Stop what still runs without ROS (the context is gone): graces still apply."""
        end = time.monotonic() + deadline_s
        self.supervisor.stop_all(time.monotonic())
        while not self.supervisor.all_stopped() and time.monotonic() < end:
            self.supervisor.step(time.monotonic())
            time.sleep(0.05)
        if self.supervisor.all_stopped():
            self.supervisor.stopped = True      # the warden has nothing left to guard
            self.supervisor.save()

    def destroy_node(self) -> None:
        for monitor in self._monitors:
            try:
                monitor.destroy()
            except Exception as e:
                self.get_logger().error(f'destroying {type(monitor).__name__}: {e!r}')
        self._monitors = []
        for clients in self._lifecycle.values():
            clients.destroy()
        self._lifecycle = {}
        if self._watch is not None:
            self._watch.destroy_node()
            self._watch = None
        self._release_lock()
        super().destroy_node()


def main(args: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    argv = list(sys.argv if args is None else args)
    scale = scale_from_args(argv)
    if not scale:
        print('agent: the scale parameter is required: '
              '--ros-args --params-file DEPLOYMENT.yaml -p scale:=NAME', file=sys.stderr)
        return 2
    if not SCALE_RE.match(scale):
        print(f'agent: scale {scale!r} is not a valid scale name', file=sys.stderr)
        return 2
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as e:   # rcl refuses the arguments or the parameters file
        print(f'agent: cannot start on scale {scale!r}: {e}', file=sys.stderr)
        return 2
    node = None
    executor = None
    # The handlers only note the signal; the loop acts on it between two callbacks. A handler
    # runs between any two bytecodes of the main thread, maybe inside a callback that holds a
    # monitor's lock: stopping the nodes from there deadlocked once (a SIGINT logged "shutting
    # down" and stopped nothing).
    signals: List[str] = []

    def on_signal(signum, frame):
        signals.append('stop')

    def on_restart(signum, frame):
        signals.append('restart')

    def act() -> None:
        stops = 0
        while signals:
            kind = signals.pop(0)
            if kind == 'restart':
                node.request_restart()
            elif stops < 2:         # a second one kills every node at once
                stops += 1
                node.request_shutdown()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGHUP, on_restart)
    try:
        try:
            node = AgentNode(scale)
        except (DeploymentError, AgentError, ValueError) as e:
            print(f'agent: cannot start on scale {scale!r}:\n{e}', file=sys.stderr)
            return 2
        act()
        executor = make_executor()
        executor.add_node(node)
        while rclpy.ok() and not node.finished and not node.restarting:
            act()
            if node.finished or node.restarting:
                break
            try:
                executor.spin_once(timeout_sec=TICK_S)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception:   # a bug in one callback must not orphan or stop the nodes
                node.get_logger().error('callback failed:\n' + traceback.format_exc())
        if node.finished:
            node._publish_state()    # the final report: everything stopped
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            if node.restarting:
                try:
                    node.supervisor.save()   # what runs now, for the new process to adopt
                except OSError as e:         # the last start or stop recorded it already
                    node.get_logger().error(f'cannot update the state file: {e}')
            else:
                s = node.settings
                node.finish_offline(s.sigint_grace_s + s.sigterm_grace_s + 5.0)
            node.destroy_node()
        if executor is not None:
            executor.shutdown()
        rclpy.try_shutdown()
    if node is not None and node.restarting:
        # The DDS participant is deleted now, not left to exit (exec runs no destructor): the
        # others drop it at once, and its shared-memory ports are closed as they should be. A
        # participant left undeleted made the new process deaf, one restart in about twenty:
        # its peers went on writing to the old process's shared-memory port, and the new agent
        # saw neither its layout nor its nodes.
        rclpy.get_default_context().destroy()
        restart_in_place()
    return 0


def restart_in_place() -> None:
    """Replace this process with a new agent: same pid, same command line, the code installed
    now. The nodes stay its children (in sessions of their own) and the new agent adopts them
    from the state file; ``systemctl reload`` with ``ExecReload=/bin/kill -HUP $MAINPID``
    (docs/agent.md)."""
    # Nothing of this process but stdin, stdout and stderr may reach the new one: a DDS socket
    # or lock file kept open would look like a live participant to the others.
    for entry in os.listdir('/proc/self/fd'):
        fd = int(entry)
        if fd > 2:
            try:
                os.set_inheritable(fd, False)
            except OSError:
                pass                 # the listing's own descriptor, already closed
    # A second SIGHUP before the new process has its handler would end it (the default
    # action): ignored until then (an ignored signal stays ignored across exec).
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    sys.stdout.flush()
    sys.stderr.flush()
    argv = list(getattr(sys, 'orig_argv', None) or [sys.executable] + sys.argv)
    os.execv(sys.executable, argv)


if __name__ == '__main__':
    sys.exit(main())
