"""The agent of one scale: starts and stops the deployment's nodes there, and hosts its monitors.

    ros2 run anyscale_manager agent --ros-args --params-file DEPLOYMENT.yaml -p scale:=NAME

Glue only: what the agent decides and does is its turn (agent/turn.py), beside the catalogue,
the supervisor and the move-order rules in anyscale_manager.agent. The node decodes and checks
the latched layout, the other agents' reports and the decider's objective and hands them to the
turn, runs the turn's steps from a timer, and publishes its report (latched) when the turn asks
and at ``agent.heartbeat_rate_hz``. A lifecycle node is driven through its own copy's services
(agent/lifecycle.py): configured once started, active where the layout places it, inactive as a
standby copy, and finalized before its process is signalled. SIGINT or SIGTERM stops every node
it runs (SIGINT, SIGTERM, SIGKILL with the configured graces) while it keeps reporting, then it
exits 0; a second signal skips the graces.
"""
import array
import os
import secrets
import sys
import time
import traceback
from typing import IO, Any, Callable, Dict, List, Optional, Tuple

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String

from . import qos
from .agent_monitors import AgentMonitors
from .executor import collect_between_callbacks, collect_due, make_executor
from .steady_loop import release_timers, serve_timers, steady_timer
from .lifecycle_client import CopyClients
from .readers import Readers
from .log_lines import log_at
from .state_relay import StateRelay
from .throttled_log import ThrottledLog
from .. import protocol
from .. import protocol_auth as auth
from ..agent.authority import describe
from ..agent.catalogue import build_catalogue, Entry
from ..agent.claims import HostClaims
from ..agent.discovery import apply_client_setup, DiscoveryError, server_argv
from ..agent.exits import ExitWatcher
from ..agent.ledger import Ledger, LedgerError
from ..agent.host import this_host
from ..agent.lock import LockError, release_lock, take_lock
from ..agent.process import (held_ports, own_dds_ports, places, restart_in_place, RESTART,
                             scale_from_args, SCALE_RE, Signals, start_warden, STOP, stop_offline)
from ..agent.supervisor import Supervisor
from ..agent.turn import AgentInputs, AgentOutput, AgentTurn, name_counts, TICK_S
from ..model.capacity import claim_lease_s
from ..model.discovery import uses_servers
from ..model.loader import DeploymentError, load_from_parameters
from ..model.params_file import refuse_bad_params_files
from ..interrupt import restore_ctrl_c
from .shutdown import shut_rclpy_down

EXIT_WAKE_S = 0.001          # the one-shot wake after a node exits (agent/exits.py)
LOOP_WAIT_S = 1.0            # the longest wait for a callback; a signal wakes it at once
REPORT_LATE_PERIODS = 3.0    # a report this many periods after the last is said to be late
UNSIGNED = ('layouts are not signed and anyone on this ROS domain can move or stop the nodes '
            'of this scale (anyscale-manager keygen; docs/decider.md, security)')


class AgentError(RuntimeError):
    """A reason the agent cannot run, said in one line."""


def _plain(value: Any) -> Any:
    if isinstance(value, array.array):
        return list(value)
    return value


class AgentNode(Node):
    def __init__(self, scale: str, readers: Optional[Readers] = None, **kwargs):
        super().__init__(f'anyscale_agent_{scale}',
                         automatically_declare_parameters_from_overrides=True, **kwargs)
        # The process's shared subscriptions (nodes/readers.py): this node owns them, and the
        # master's decider, built before it, reads through them too.
        self.readers = readers if readers is not None else Readers()
        self.readers.open(self)
        self._lock_file: Optional[IO[str]] = None
        self._hosted: Optional[AgentMonitors] = None
        self._relay: Optional[StateRelay] = None
        self._probes: Any = None
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
        if uses_servers(d):
            try:
                server_argv(d, scale, os.environ)
            except DiscoveryError as e:
                # A scale without its server leaves every other scale's processes pinging it.
                raise AgentError(f'discovery.mode server: {e}') from None
        key = auth.load_key(d.security.key_file) if d.security.key_file else None
        self._key = key
        self._gate = auth.LayoutGate(key, d.security.replay_window_s)
        # Peers' reports and the decider's objective also start and stop things here (a
        # handover lets go on a peer's ready report; a remote scale stops its nodes when the
        # master goes silent): with a key they are checked like layouts.
        self._state_gate = auth.Gate(key, d.security.replay_window_s)
        self._objective_gate = auth.Gate(key, d.security.replay_window_s)
        self._seq = 0
        self._report_s = 1.0 / self.settings.heartbeat_rate_hz
        self._reported_at = time.monotonic()
        self._bad = ThrottledLog(self.get_logger())    # bad input: one line per kind and 10 s
        stem, self.log_dir = places(self.settings, d.name, scale, os.environ)
        self._lock_file = take_lock(stem + '.lock', f'agent for scale {scale!r} of {d.name!r}')

        self.catalogue: Dict[str, Entry] = build_catalogue(d, scale)
        for entry in self.catalogue.values():
            if entry.problem:
                self.get_logger().error(f'{entry.name}: {entry.problem}')
        self.supervisor = Supervisor(self.catalogue, self.settings, self.log_dir,
                                     state_path=stem + '.json',
                                     identity={'deployment': d.name, 'scale': scale})
        # The machine this agent runs on, and the one each other scale's agent reports: on a
        # shared machine the scale monitor measures this agent's own processes.
        host_id, host_name = this_host()
        self.turn = AgentTurn(d, scale, self.catalogue, self.supervisor,
                              instance=secrets.token_hex(8),
                              wall_offset=time.time() - time.monotonic(),
                              host_id=host_id, host_name=host_name)
        self.reconciler = self.turn.reconciler
        if d.scale(scale).shared:
            try:
                ledger = Ledger(os.path.dirname(stem), d.name, claim_lease_s(d))
            except LedgerError as e:
                raise AgentError(f'scales.{scale}.shared: {e}') from None
            self.turn.claims = HostClaims(ledger, d, scale)
        self._lifecycle = {
            name: CopyClients(self, self.catalogue[name].services, driver, time.monotonic,
                              self._tick)
            for name, driver in self.turn.drivers.items()}
        # A node's exit wakes a step at once (agent/exits.py): a crash is reported, and a
        # standby copy elsewhere can take over, without waiting for the tick. The wake is a
        # one-shot timer reset from the watcher's thread (the events executor has no guard
        # conditions); it fires within a millisecond.
        self._exit_wake = self.create_timer(EXIT_WAKE_S, self._on_exit)
        self._exit_wake.cancel()
        self.supervisor.watch_exit = ExitWatcher(self._exit_wake.reset).watch
        self._act(self.turn.begin(time.monotonic()))

        self._state_pub = self.create_publisher(String, protocol.TOPIC_AGENT_STATE, qos.LATCHED)
        # Several writers on each (every agent; a rival decider): a reader of depth 1 keeps one
        # sample for all of them, and a peer's report that lands beside another is lost until
        # its next heartbeat (a stop_before_start move then waited one report period).
        self.readers.subscribe(self, String, protocol.TOPIC_LAYOUT, qos.LATCHED_READER,
                               self._signed('layout', protocol.Layout, protocol.TOPIC_LAYOUT,
                                            'a layout message', self._check_layout,
                                            self.turn.on_layout, malformed='error'))
        self.readers.subscribe(self, String, protocol.TOPIC_AGENT_STATE, qos.LATCHED_READER,
                               self._signed('agent_state', protocol.AgentState,
                                            protocol.TOPIC_AGENT_STATE, 'an agent state message',
                                            self._check_state, self.turn.on_agent_state))
        if scale != d.master.name:
            # The decider's output at each of its steps: word from the master scale, which a
            # remote scale cut off from it no longer gets (see Reconciler).
            self.create_subscription(String, protocol.TOPIC_OBJECTIVE, self._signed(
                'objective', protocol.Objective, protocol.TOPIC_OBJECTIVE,
                'an objective message', self._check_objective, self.turn.on_objective), 10)
        # One timer drives the loop at the period each step asks for: TICK_S while something is
        # under way, STOPPING_TICK_S while a node stops, the next deadline (IDLE_TICK_S at
        # most) when nothing is; every input that changes what runs steps at once.
        self._tick_s = TICK_S
        self._tick_timer = steady_timer(self, TICK_S, self._tick)
        steady_timer(self, self._report_s, self._on_report_timer)
        # One signer for the monitors' topics (a key: signed; else plain JSON, as before).
        self._hosted = AgentMonitors(self, d, scale, auth.Sealer(key, f'agent {scale}'),
                                     self.turn.serving_pids, self.turn.supervised_pids,
                                     lambda: self.turn.shared_with(time.monotonic()))
        self._probes = self._hosted.probes
        # The state of the nodes that declare one, kept here and handed to a copy that serves.
        self._relay = StateRelay(self, self.catalogue,
                                 {n: d.state_msg_type(n) for n in self.turn.states.specs},
                                 self._log)
        # Each state reader keeps one message: taken every TICK_S, whatever the step's period
        # (a step at TICK_S for that alone was most of an idle agent's work).
        self._requests: List[Tuple[str, bytes]] = []
        if self._relay.nodes:
            steady_timer(self, TICK_S, self._take_states)
        for level, text in start_warden(d, scale, self.supervisor, stem, self.log_dir):
            self._log(level, text)
        self.get_logger().info(
            f'agent for scale {scale!r} of {d.name!r}: catalogue '
            f'{", ".join(self.catalogue) or "(empty)"}; logs in {self.log_dir}')
        if key is None:
            self.get_logger().warn(f'security.key_file is not set: {UNSIGNED}')
        self._tick()

    def _release_lock(self) -> None:
        if self._lock_file is not None:
            release_lock(self._lock_file)
            self._lock_file = None

    # --- inputs ---------------------------------------------------------------------------
    def _signed(self, kind: str, cls: Any, topic: str, what: str,
                check: Callable[[str, Any, float], Optional[str]],
                handle: Callable[[Any, float], AgentOutput],
                malformed: str = 'warn') -> Callable[[String], None]:
        """The callback of a signed topic: decode a ``cls`` message, ``check`` it ('' to go
        on; why it is dropped; None: dropped, said already or not worth saying), then hand it to
        the turn's ``handle``. Bad input is logged once per kind and interval."""
        def take(msg: String) -> None:
            try:
                message = cls.from_json(msg.data, topic)
            except protocol.ProtocolError as e:
                self._note(malformed, f'{kind}: malformed: {protocol.error_kind(str(e))}',
                           f'ignored {what}: {e}')
                return
            why = check(msg.data, message, time.time())
            if why is None:
                return
            if why:
                self._bad.error(f'{kind}: refused: {auth.refusal_kind(why)}', why)
                return
            self._act(handle(message, time.monotonic()))
        return take

    def _check_layout(self, text: str, layout: protocol.Layout, wall: float) -> Optional[str]:
        if layout.deployment != self.deployment.name:
            self._bad.warn('layout: another deployment',
                           f'ignored a layout of deployment {layout.deployment!r:.60}, not '
                           f'{self.deployment.name!r}', interval_s=60.0)
            return None
        why = self._gate.check(text, layout, wall)
        return why and (f'dropped layout generation {layout.generation} of decider '
                        f'{describe(layout.decider)}: {why}')

    def _check_state(self, text: str, state: protocol.AgentState, wall: float) -> Optional[str]:
        if self.turn.is_own(state):
            return None
        why = self._state_gate.check_from(text, f'{state.scale}/{state.instance}', state.seq,
                                          state.stamp, wall)
        return why and f'dropped an agent state claiming scale {state.scale!r:.60}: {why}'

    def _check_objective(self, text: str, objective: protocol.Objective,
                         wall: float) -> Optional[str]:
        why = self._objective_gate.check_from(text, objective.decider, objective.seq,
                                              objective.stamp, wall)
        return why and f'dropped an objective message: {why}'

    # --- the loop -------------------------------------------------------------------------
    def _on_exit(self) -> None:
        self._exit_wake.cancel()
        self._tick()

    def _take_states(self) -> None:
        """The states heard since the last take, into the turn's book; a state set by others
        (a pose set in RViz) steps the agent at once, which hands it on."""
        if self._relay is None:
            return
        now = time.monotonic()
        heard, requests = self._relay.drain(now)
        for level, text in self.turn.hear_states(heard, now):
            self._log(level, text)
        if requests:
            self._requests.extend(requests)
            self._tick()

    def _on_report_timer(self) -> None:
        self._report_late(time.monotonic(), 'at its period')
        self._publish_state()

    def _report_late(self, now: float, where: str) -> bool:
        """Whether the periodic report is more than REPORT_LATE_PERIODS periods after the last
        one, said when it is: the peers count this agent silent after agent_timeout_s, and the
        line tells a late report from a lost one."""
        gap = now - self._reported_at
        if gap <= REPORT_LATE_PERIODS * self._report_s:
            return False
        self.get_logger().warning(
            f'the report is {gap:.1f} s after the last one (every {self._report_s:g} s, '
            f'agent.heartbeat_rate_hz): {where}', throttle_duration_sec=5.0)
        return True

    def _tick(self) -> None:
        now = time.monotonic()
        self._bad.flush()
        if self._report_late(now, 'sent from the step, the periodic report not sent'):
            self._publish_state()
        probes = self._probes
        if probes is not None:
            probes.poll_writers()
        graph = self.get_node_names_and_namespaces() if self.turn.watches_graph else ()
        heard, requests = self._relay.drain(now) if self._relay is not None else ((), [])
        requests, self._requests = self._requests + list(requests), []
        self._act(self.turn.step(now, AgentInputs(
            wall=time.time(), visible=name_counts(graph),
            poll=lambda name: self._lifecycle[name].poll(),
            writer_joined=None if probes is None else probes.writer_joined_since,
            probed=() if probes is None else frozenset(probes.connections),
            heard=heard, requests=requests, restore=self._relay)))

    def _act(self, out: AgentOutput) -> None:
        """Log, publish and reschedule what the turn asks for."""
        for level, text in out.logs:
            self._log(level, text)
        for kind, level, text in out.notes:
            self._note(level, kind, text)
        if out.report is not None:
            self._publish_state(out.report)
        if out.probe_connections is not None and self._probes is not None:
            try:
                self._probes.set_connections(out.probe_connections)
            except Exception as e:
                self.get_logger().error(f'ProbeManager.set_connections failed: {e!r}')
        if out.tick_s is not None and out.tick_s != self._tick_s:
            self._tick_s = out.tick_s
            self._tick_timer.timer_period_ns = round(out.tick_s * 1e9)
            self._tick_timer.reset()
        if out.step:
            self._tick()

    def _log(self, level: str, text: str) -> None:
        log_at(self.get_logger(), level, text)

    def _note(self, level: str, kind: str, text: str) -> None:
        (self._bad.error if level == 'error' else self._bad.warn)(kind, text)

    def _publish_state(self, state: Optional[protocol.AgentState] = None) -> None:
        if state is None:
            state = self.turn.report(time.time())
        self._seq += 1
        state.seq = self._seq
        self._state_pub.publish(String(data=auth.seal(self._key, state)))
        self._reported_at = time.monotonic()

    # --- shutdown -------------------------------------------------------------------------
    def on_signals(self, kinds: List[str]) -> None:
        """Stop every node (SIGINT, SIGTERM; a second one skips the graces) or restart in
        place, leaving every node running (SIGHUP: ``main`` re-executes the agent, which adopts
        them from the state file)."""
        for kind in kinds:
            self._act(self.turn.request_restart() if kind == RESTART
                      else self.turn.request_shutdown(time.monotonic()))

    @property
    def restarting(self) -> bool:
        return self.turn.restarting

    @property
    def finished(self) -> bool:
        return self.turn.finished

    def destroy_node(self) -> None:
        if self._hosted is not None:
            self._hosted.destroy()
            self._hosted = self._probes = None
        for clients in self._lifecycle.values():
            clients.destroy()
        self._lifecycle = {}
        if self._relay is not None:
            self._relay.destroy()
            self._relay = None
        self._release_lock()
        super().destroy_node()


def main(args: Optional[List[str]] = None) -> int:
    return run(args, 'agent')


def run(args: Optional[List[str]], program: str,
        guest: Optional[Callable[[str, Readers], Node]] = None) -> int:
    """The agent's process. ``guest``: given the scale and the process's shared subscriptions
    (nodes/readers.py), another node for this process, built
    before the agent starts anything and spun by its executor until a stop is asked, then
    destroyed first (the master's decider: nodes/master.py); it raises AgentError to refuse."""
    restore_ctrl_c()
    argv = list(sys.argv if args is None else args)
    scale = scale_from_args(argv)
    if not scale:
        print(f'{program}: the scale parameter is required: '
              '--ros-args --params-file DEPLOYMENT.yaml -p scale:=NAME', file=sys.stderr)
        return 2
    if not SCALE_RE.match(scale):
        print(f'{program}: scale {scale!r} is not a valid scale name', file=sys.stderr)
        return 2
    if refuse_bad_params_files(program, argv):    # said with its line, not as rcl words it
        return 2
    # A restart in place: the old participant's ports, still bound, until this one has others.
    carried = held_ports()
    # discovery.mode server: a client of the deployment's discovery servers (before it joins).
    apply_client_setup(program, argv, super_client=True)
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as e:   # rcl refuses the arguments or the parameters file
        print(f'{program}: cannot start on scale {scale!r}: {e}', file=sys.stderr)
        return 2
    node = None
    other: Optional[Node] = None
    executor = None
    signals = Signals()
    signals.install()
    # The periodic jobs of the agent, its monitors and a guest: run by this loop, not by rclpy
    # timers (steady_loop.SteadyLoop).
    loop = serve_timers(rclpy.get_default_context())
    try:
        try:
            readers = Readers()
            other = guest(scale, readers) if guest is not None else None
            node = AgentNode(scale, readers)
        except (DeploymentError, AgentError, LockError, ValueError) as e:
            print(f'{program}: cannot start on scale {scale!r}:\n{e}', file=sys.stderr)
            return 2
        if carried:
            hold = node.supervisor.port_hold
            kept = hold.adopt(carried, time.monotonic())
            node.get_logger().info(
                "restarted in place: the previous participant's DDS ports "
                f'{", ".join(map(str, kept)) or "(none)"} held for {hold.hold_s:g} s, so that '
                'this one took others')
        # The loop waits for callbacks until a signal wakes it (Signals.wake_with): a wait
        # of TICK_S woke the process ten times a second with nothing to do.
        signal_wake = node.create_timer(EXIT_WAKE_S, lambda: signal_wake.cancel())
        signal_wake.cancel()
        signals.wake_with(signal_wake.reset)
        executor = make_executor()
        executor.add_node(node)
        if other is not None:
            executor.add_node(other)
        collect_between_callbacks()
        while rclpy.ok():
            collect_due()
            taken = signals.take()
            if other is not None and STOP in taken:
                # A stop: the guest goes first (a decider must not answer the nodes' stop).
                executor.remove_node(other)
                readers.drop(other)
                loop.drop(other)
                other.destroy_node()
                other = None
            node.on_signals(taken)
            if node.finished or node.restarting:
                break
            try:
                executor.spin_once(timeout_sec=loop.wait_s(LOOP_WAIT_S))
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception:   # a bug in one callback must not orphan or stop the nodes
                node.get_logger().error('callback failed:\n' + traceback.format_exc())
            loop.run_due(lambda e: node.get_logger().error(
                'a periodic job failed:\n' + ''.join(traceback.format_exception(e))))
        if node.finished:
            node._publish_state()    # the final report: everything stopped
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        release_timers(rclpy.get_default_context())
        if other is not None:
            other.destroy_node()
        if node is not None:
            if node.restarting:
                try:
                    node.supervisor.save()   # what runs now, for the new process to adopt
                except OSError as e:         # the last start or stop recorded it already
                    node.get_logger().error(f'cannot update the state file: {e}')
            else:
                s = node.settings
                stop_offline(node.supervisor, s.sigint_grace_s + s.sigterm_grace_s + 5.0)
            node.destroy_node()
        restarting = node is not None and node.restarting
        # The participant's ports (and those the supervisor holds), read before it goes.
        before = own_dds_ports() if restarting else frozenset()
        if executor is not None:
            executor.shutdown()
        shut_rclpy_down()
    if restarting:
        # The DDS participant is deleted now, not left to exit (exec runs no destructor): the
        # others drop it at once, and its shared-memory ports are closed as they should be. A
        # participant left undeleted made the new process deaf, one restart in about twenty:
        # its peers went on writing to the old process's shared-memory port, and the new agent
        # saw neither its layout nor its nodes.
        # Its ports are held across the exec (agent/process.py HELD_PORTS_ENV): those its peers
        # knew it by, that missed its goodbye, would leave a new participant there unmatched.
        rclpy.get_default_context().destroy()
        restart_in_place(before, node.supervisor.port_hold)
    return 0


if __name__ == '__main__':
    sys.exit(main())
