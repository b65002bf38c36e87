"""The decider node: ``ros2 run anyscale_manager decider --ros-args --params-file FILE.yaml``.

Glue only. It rebuilds the deployment from its parameters, checks and feeds what the agents and
monitors publish into the decider's turn (runtime/turn.py), runs that turn once per
``decider.period_s`` (and at once on a cut, a crash or a shrinking link) and publishes what it
returns: the desired layout (latched, with a generation number and the leadership term), every
decision with its reason, the cost function, the plan-against-reality check and its own health
on /diagnostics. It also keeps what only a live process has: its identity, key and beat.

Several deciders of one deployment may run: one leads, the others stand by
(runtime/leadership.py). A standby hears everything the leader hears, follows its layouts and
decisions, publishes only its beat and diagnostics, and takes over within ``takeover_s`` of the
leader's silence from the leader's last layout.
"""

import faulthandler
import os
import secrets
import signal
import socket
import sys
import threading
import time
import traceback
from dataclasses import fields
from typing import Any, Dict, List, Optional

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String

from . import qos
from .decider_beat import BeatThread, alone_wait_s
from .executor import collect_between_callbacks, collect_due, make_executor
from .steady_loop import destroy_steady, release_timers, serve_timers, steady_timer
from .log_lines import log_at
from .readers import Readers, subscribe
from .throttled_log import ThrottledLog
from .. import protocol as p
from .. import protocol_auth as auth
from ..agent.discovery import apply_client_setup
from ..model.advice import UNSIGNED
from ..model.loader import DeploymentError, load_from_parameters
from ..model.params_file import refuse_bad_params_files
from ..model.sections import settings_with
from ..model.types import DeciderSettings, Deployment
from ..runtime.diagnostics import DiagnosticsGate
from ..runtime.leadership import LEADER, STANDBY, Change, Leadership
from ..runtime.layout import LayoutError
from ..runtime.turn import DeciderTurn, TurnOutput
from ..interrupt import ignore_interrupts, interrupt_once, rclpy_stops_on_sigint, \
    restore_ctrl_c, stop_asked
from .shutdown import shut_rclpy_down

NODE_NAME = 'anyscale_decider'

LATCHED = qos.LATCHED
AGENT_STATE_QOS = qos.LATCHED_READER
EVENTS_QOS = qos.EVENTS
MONITOR_QOS = qos.MONITOR_READER

# decider.* parameters a person may change while it runs (model/types.py declares each once:
# its meaning, range and unit).
LIVE = {f.name: f.metadata for f in fields(DeciderSettings) if f.metadata.get('live')}


def describe(name: str) -> ParameterDescriptor:
    """The ROS descriptor of a live decider setting: its meaning, unit and range."""
    meta = LIVE[name]
    check = meta['check']
    text = meta['help'] + (f' ({check["unit"]})' if check.get('unit') else '')
    if check.get('low_open'):
        text += f'; above {check["low"]:g}'
    descriptor = ParameterDescriptor(description=text, dynamic_typing=True)
    if 'low' in check:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(check['low']), to_value=float(check['high']), step=0.0)]
    elif 'choices' in check:
        descriptor.additional_constraints = 'one of ' + ', '.join(check['choices'])
    return descriptor


class _Locked:
    """An object whose every method runs under a lock (the leadership, shared with the beat
    thread); plain attributes are read as they are."""

    def __init__(self, obj, lock):
        self._obj, self._lock = obj, lock

    def __getattr__(self, name: str):
        value = getattr(self._obj, name)
        if not callable(value):
            return value
        lock = self._lock

        def locked(*args, **kwargs):
            with lock:
                return value(*args, **kwargs)
        return locked


class DeciderNode(Node):
    """One decider per deployment, on the master scale."""

    def __init__(self, *, parameter_overrides: Optional[List[Parameter]] = None,
                 clock=time.monotonic, readers: Optional[Readers] = None, **kwargs):
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True,
                         parameter_overrides=parameter_overrides, **kwargs)
        self._now = clock
        flat = {name: self.get_parameter(name).value
                for name in self.list_parameters([], 0).names}
        self.deployment: Deployment = load_from_parameters(flat)
        self.settings = self.deployment.decider
        self._declare_descriptors()

        started = self._now()
        self.started = started
        self.core = DeciderTurn(self.deployment, self.settings, started)
        self._rejected = 0
        self._bad = ThrottledLog(self.get_logger())   # bad input: one line per kind and 10 s
        self._link_lost = False
        self._crash_heard = False
        self.host = socket.gethostname()
        self.identity = p.DeciderIdentity(id=secrets.token_hex(8), host=self.host[:256],
                                          pid=os.getpid(), started=time.time())
        security = self.deployment.security
        self.key = auth.load_key(security.key_file) if security.key_file else None
        self.gate = auth.LayoutGate(self.key, security.replay_window_s)
        self.state_gate = auth.Gate(self.key, security.replay_window_s)
        # The monitors' topics, each with its own replay guard (a sender numbers its messages
        # across topics), and this decider's own events and plan checks.
        self.status_gates = {topic: auth.StatusGate(self.key, security.replay_window_s)
                             for topic in (p.TOPIC_SCALE_STATUS, p.TOPIC_LINK_STATUS,
                                           p.TOPIC_CONNECTION_STATUS)}
        self.sealer = auth.Sealer(self.key, f'decider {self.identity.id}')
        self.objective_seq = 0
        s = self.settings
        # Every callback runs under this lock, and so does the beat thread's work
        # (nodes/decider_beat.py): one thread at a time in the decider's state.
        self._lock = threading.RLock()
        self.lead = _Locked(Leadership(self.identity, beat_s=s.beat_s, takeover_s=s.takeover_s,
                                       discovery_s=s.discovery_s, lease_s=s.lease_s,
                                       started=started, alone_wait_s=alone_wait_s(s)),
                            self._lock)
        self.beat_gate = auth.StatusGate(self.key, security.replay_window_s)
        self.seq = 0
        # decider id -> its last layout (a standby takes over from the leader's)
        self._layouts: Dict[str, p.Layout] = {}
        self._followers: Dict[str, Optional[str]] = {}    # scale -> decider its agent follows
        self._stood_by_for: Optional[tuple] = None         # (leader id, term) said in the log
        # A standby publishes its beat and diagnostics only; layouts, events, the objective
        # and the plan check come from the leader.
        self.pub_layout = self.create_publisher(String, p.TOPIC_LAYOUT, LATCHED)
        self.pub_events = self.create_publisher(String, p.TOPIC_EVENTS, EVENTS_QOS)
        self.pub_objective = self.create_publisher(String, p.TOPIC_OBJECTIVE, 10)
        self.pub_plan = self.create_publisher(String, p.TOPIC_PLAN_CHECK, 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, p.TOPIC_DIAGNOSTICS, 10)
        self._diag_gate = DiagnosticsGate()
        for topic, callback, profile in (
                (p.TOPIC_EVENTS, self._on_event, EVENTS_QOS),
                (p.TOPIC_LAYOUT, self._on_layout, qos.LATCHED_READER),
                (p.TOPIC_AGENT_STATE, self._on_agent_state, AGENT_STATE_QOS),
                (p.TOPIC_SCALE_STATUS, self._on_scale_status, MONITOR_QOS),
                (p.TOPIC_LINK_STATUS, self._on_link_status, MONITOR_QOS),
                (p.TOPIC_CONNECTION_STATUS, self._on_connection_status, MONITOR_QOS)):
            # Through the process's shared subscriptions in `master` (nodes/readers.py).
            subscribe(self, readers, self, String, topic, profile, self._locked(callback))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._locked(self._after_set_parameters))
        self.timer = steady_timer(self, self.settings.period_s, self._locked(self._on_timer))
        # The lease of the agents' follow rule: re-published well within it.
        self.renew_timer = steady_timer(self, self.settings.lease_s / 3.0,
                                        self._locked(self._renew))
        self.beat = BeatThread(self, self._lock)
        self.beat.start()
        if self.key is None:
            self.get_logger().warn(f'security.key_file is not set: {UNSIGNED}')
        self.get_logger().info(
            f'decider {self.identity.describe()}: listening {self.settings.discovery_s:g} s for '
            'a leading decider of this deployment (hearing one, it stands by)')
        self.get_logger().info(
            f'deployment {self.deployment.name!r}: {len(self.deployment.scales)} scales, '
            f'{len(self.deployment.nodes)} nodes, migratable: '
            f'{", ".join(self.deployment.migratable_nodes) or "none"}; first layout '
            f'{self.settings.initial_layout!r}, waiting up to {self.settings.agent_timeout_s:g} s '
            f'for the agents to report what runs')

    def destroy_node(self) -> None:
        self.beat.stop()
        super().destroy_node()

    # --- parameters ---------------------------------------------------------------------------
    def _declare_descriptors(self) -> None:
        for f in fields(DeciderSettings):
            if f.name not in LIVE:
                continue
            name = f'decider.{f.name}'
            descriptor = describe(f.name)
            if self.has_parameter(name):
                self.set_descriptor(name, descriptor)
            else:
                value = getattr(self.settings, f.name)
                self.declare_parameter(name, value, descriptor)

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        changes = {}
        for prm in params:
            section, _, key = prm.name.partition('.')
            if section != 'decider' or '.' in key:
                return SetParametersResult(
                    successful=False,
                    reason=f'{prm.name}: the deployment is fixed while the decider runs; '
                           'restart it with a new parameters file')
            if prm.type_ == Parameter.Type.NOT_SET:
                return SetParametersResult(successful=False,
                                           reason=f'{prm.name}: cannot be undeclared')
            changes[key] = prm.value
        try:
            settings_with(self.settings, changes)
        except ValueError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: List[Parameter]) -> None:
        changes = {prm.name.partition('.')[2]: prm.value for prm in params
                   if prm.name.startswith('decider.')}
        try:
            new = settings_with(self.settings, changes)
        except ValueError:
            return                     # refused before; nothing changed
        old, self.settings = self.settings, new
        self.core.update_settings(new)
        if new.period_s != old.period_s:
            self.timer.cancel()
            destroy_steady(self, self.timer)
            self.timer = steady_timer(self, new.period_s, self._locked(self._on_timer))
        for key in changes:
            self._event('settings', '', '', '', f'decider.{key} = {changes[key]!r}')

    # --- intake -------------------------------------------------------------------------------
    def _intake(self, msg: Any, cls: type, topic: str, handle) -> None:
        try:
            decoded = cls.from_json(msg.data, topic)
            gate = self.status_gates.get(topic)
            why = gate.check(msg.data, decoded, time.time()) if gate is not None else ''
            if why:
                raise p.ProtocolError(f'dropped: {why}')
            handle(decoded, self._now())
        except (p.ProtocolError, ValueError, KeyError, TypeError) as e:
            self._rejected += 1
            self._bad.warn(f'{topic}: {auth.refusal_kind(str(e))}',
                           f'ignored a message on {topic}: {e}')
        except Exception as e:  # noqa: B902 - a message must never stop the decider
            self._rejected += 1
            self._bad.error(topic + ': failed',
                            f'ignored a message on {topic} ({type(e).__name__}: {e})')

    def _on_agent_state(self, msg: String) -> None:
        self._intake(msg, p.AgentState, p.TOPIC_AGENT_STATE,
                     lambda state, now: self._agent_state(state, now, msg.data))
        if self._crash_heard:
            # A serving copy just crashed: a standby copy elsewhere can take over before the
            # connections it feeds notice, so decide now rather than at the next period.
            self._crash_heard = False
            self._tick()

    def _agent_state(self, state: p.AgentState, now: float, text: str = '') -> None:
        why = self.state_gate.check_from(text, f'{state.scale}/{state.instance}', state.seq,
                                         state.stamp, time.time())
        if why:
            raise p.ProtocolError(f'agent state claiming scale {state.scale!r:.60}: {why}')
        book = self.core.book
        book.agent_state(state, now)
        self.lead.heard_term(state.term)
        if self.core.layout is not None and any(
                book.crashes.get((state.scale, node), (None,))[0] == now
                for node, scale in self.core.policy.layout.items() if scale == state.scale):
            self._crash_heard = True
        # An agent that follows another decider (one that just stopped: for one lease; or a
        # forger's anonymous layout) is said once. No re-publication above its generation: two
        # deciders each out-counting the other's generation never settle.
        if state.scale in self.deployment.scale_names \
                and self._followers.get(state.scale, '?') != state.decider:
            self._followers[state.scale] = state.decider
            if self.lead.role == LEADER and state.decider != self.identity.id:
                who = 'no decider' if state.decider is None else (
                    'an anonymous layout' if state.decider == '' else f'decider {state.decider}')
                self.get_logger().info(
                    f'the agent of {state.scale} follows {who} (generation '
                    f'{state.generation}, term {state.term}), not this one ({self.identity.id}, '
                    f'term {self.lead.term}); it follows this one at a higher term, or once '
                    f'that one has been silent for {self.settings.lease_s:g} s')

    def _on_layout(self, msg: String) -> None:
        """Layouts of other deciders: a leader's (kept: a standby continues from it; one of a
        higher term makes a leader step down), or foreign or malformed (said, throttled, never
        answered by re-deciding)."""
        try:
            layout = p.Layout.from_json(msg.data, p.TOPIC_LAYOUT)
        except p.ProtocolError as e:
            self._rejected += 1
            self._bad.warn(f'layout: malformed: {p.error_kind(str(e))}',
                           f'ignored a malformed layout: {e}')
            return
        if layout.decider is not None and layout.decider.id == self.identity.id:
            return                                  # our own
        if layout.deployment != self.deployment.name:
            # Another deployment's decider on this domain: harmless, said once a minute.
            self._bad.warn('layout: another deployment',
                           f'ignored a layout of deployment {layout.deployment!r:.60}, not '
                           f'{self.deployment.name!r} (deployments should not share a ROS '
                           'domain)', interval_s=60.0)
            return
        if self._refused_by(self.gate, msg.data, layout, 'layout', 'a layout claiming to be of '
                            f'this deployment (generation {layout.generation})'):
            return
        if layout.decider is None:
            self._rejected += 1
            self._bad.warn(
                'layout: anonymous',
                f'ignored a layout of this deployment without a decider identity (generation '
                f'{layout.generation}: an older decider or a plain script); agents that '
                'follow this decider ignore it too')
            return
        if layout.decider.id not in self._layouts and len(self._layouts) >= 64:
            self._layouts.pop(next(iter(self._layouts)))
        self._layouts[layout.decider.id] = layout
        # A layout is its decider's word that it leads at its term, as its beat is.
        change = self.lead.heard_beat(layout.decider, LEADER, layout.term or 0,
                                      layout.generation, self._now(), layout=True)
        if change is not None:
            self._role_changed(change)
        self._say_standing_by()

    def _refused_by(self, gate, text: str, message, kind: str, described: str) -> bool:
        """Whether ``gate`` drops ``message``; a drop is said, throttled per reason."""
        why = gate.check(text, message, time.time())
        if why:
            self._rejected += 1
            self._bad.warn(f'{kind}: refused: {auth.refusal_kind(why)}',
                           f'ignored {described}: {why}')
        return bool(why)

    def heard_beat_text(self, text: str, now: float) -> None:
        """One beat taken by the beat thread (under the lock): decoded, checked, heard, and a
        change of role it causes acted on."""
        try:
            beat = p.DeciderBeat.from_json(text, p.TOPIC_DECIDER)
        except p.ProtocolError as e:
            self._rejected += 1
            self._bad.warn(f'beat: malformed: {p.error_kind(str(e))}',
                           f'ignored a malformed decider beat: {e}')
            return
        if beat.decider.id == self.identity.id or beat.deployment != self.deployment.name:
            return
        if self._refused_by(self.beat_gate, text, beat, 'beat',
                            'a decider beat claiming to be of this deployment'):
            return
        change = self.lead.heard_beat(beat.decider, beat.role, beat.term, beat.generation, now)
        if change is not None:
            self._role_changed(change)
        self._say_standing_by()

    def _locked(self, callback):
        """``callback`` run under the decider's lock (the beat thread's work runs under it)."""
        def run(*args):
            with self._lock:
                return callback(*args)
        return run

    def _say_standing_by(self) -> None:
        leader = self.lead.leader
        if self.lead.role == STANDBY and leader is not None \
                and (leader.identity.id, leader.term) != self._stood_by_for:
            self._stood_by_for = (leader.identity.id, leader.term)
            self.get_logger().info(f'standing by for decider {leader.identity.describe()} '
                                   f'(term {leader.term})')

    def _on_event(self, msg: String) -> None:
        """The leader's decisions: a standby keeps their hysteresis for after a takeover."""
        if self.lead.role != STANDBY:
            return
        try:
            event = p.Event.from_json(msg.data, p.TOPIC_EVENTS)
        except p.ProtocolError:
            return                    # the status view and the leader say it; not ours
        if self.key is not None and auth.check_signature(self.key, msg.data):
            return
        self.core.heard_decision(event.kind, event.node, event.from_scale, self._now())

    def _on_scale_status(self, msg: String) -> None:
        self._intake(msg, p.ScaleStatus, p.TOPIC_SCALE_STATUS, self.core.book.scale_status)

    def _on_link_status(self, msg: String) -> None:
        self._intake(msg, p.LinkStatus, p.TOPIC_LINK_STATUS, self._link_status)
        if self._link_lost:
            # A link just went down or shrank: the nodes beyond it must come back before their
            # connections' tolerance runs out, so decide now rather than at the next period.
            self._link_lost = False
            self._tick()

    def _link_status(self, status: p.LinkStatus, now: float) -> None:
        if self.core.book.link_status(status, now) and self.core.layout is not None:
            self._link_lost = True

    def _on_connection_status(self, msg: String) -> None:
        self._intake(msg, p.ConnectionStatus, p.TOPIC_CONNECTION_STATUS,
                     self.core.book.connection_status)

    # --- the loop -----------------------------------------------------------------------------
    def check_role(self, now: float) -> None:
        change = self.lead.check(now)
        if change is not None:
            self._role_changed(change)

    def _role_changed(self, change: Change) -> None:
        now = self._now()
        log = self.get_logger()
        if change.role == STANDBY:
            log.warning(change.reason)
            self._diagnostics(p.OK, f'standing by (term {change.term}): {change.reason}')
            return
        log.info(change.reason)
        previous = change.previous
        heard = None if previous is None else self._layouts.get(previous.identity.id)
        out = self.core.lead(now, change.reason, took_over=previous is not None,
                             heard=None if heard is None else (heard.generation,
                                                               dict(heard.assignments)))
        if out is not None:
            self._emit(out)
        self._tick()

    def _on_timer(self) -> None:
        self.beat.executor_alive = self._now()      # the executor turns: the beat may go on
        self._tick()

    def _tick(self) -> None:
        self._bad.flush()
        now = self._now()
        try:
            self.check_role(now)
            if not self.lead.may_command(now):
                self._standby_diagnostics(now)
                return
            self._turn(now)
        except Exception as e:  # noqa: B902 - report, keep the last layout, try again
            self.get_logger().error(f'decider turn failed: {type(e).__name__}: {e}',
                                    throttle_duration_sec=5.0)
            self._diagnostics(p.ERROR, f'turn failed: {e}')

    def _standby_diagnostics(self, now: float) -> None:
        leader = self.lead.live_leader(now)
        if leader is not None:
            message = (f'standing by for decider {leader.identity.describe()} (term '
                       f'{leader.term})')
        else:
            due = self.lead.due_in(now)
            message = 'standing by: no leader heard' + (
                f'; leads in {max(due, 0.0):.1f} s' if due is not None else '')
        self._diagnostics(p.OK, message, {'generation': self.core.generation})

    def _turn(self, now: float) -> None:
        self._emit(self.core.turn(now))

    def _emit(self, out: TurnOutput) -> None:
        """Publish and log what a turn returned, in its order."""
        for generation, assignments, reason in out.layouts:
            self._send_layout(generation, assignments, reason)
        for event in out.events:
            self._event(*event)
        log = self.get_logger()
        for level, text in out.logs:
            log_at(log, level, text)
        if out.objective is not None:
            perf, integral, elapsed = out.objective
            self.objective_seq += 1
            self.pub_objective.publish(String(data=auth.seal(self.key, p.Objective(
                stamp=time.time(), perf_map=perf, integral=integral, elapsed_s=elapsed,
                decider=self.identity.id, seq=self.objective_seq))))
        if out.plan is not None:
            checked = out.plan
            self._publish(self.pub_plan, p.PlanCheck(
                stamp=time.time(), overall_deviation=checked.overall_deviation,
                nodes={n: p.PlanNode(expected_hz=c.expected_hz, measured_hz=c.measured_hz,
                                     expected_performance=c.expected_performance,
                                     measured_performance=c.measured_performance,
                                     deviation=c.deviation) for n, c in checked.nodes.items()},
                overloaded=dict(checked.overloaded)))
        self._diagnostics(out.level, out.message, out.values)

    # --- publishing ---------------------------------------------------------------------------
    def _publish(self, pub, message: p.Message) -> None:
        if pub is not None:
            pub.publish(String(data=self.sealer.seal(message)))

    def _send_layout(self, generation: int, assignments: Dict[str, str], reason: str) -> None:
        if not self.lead.may_command(self._now()):
            return         # stalled past takeover_s, or standing by: another may lead now
        self.seq += 1
        layout = p.Layout(
            generation=generation, deployment=self.deployment.name,
            assignments=dict(assignments), reason=reason, stamp=time.time(),
            decider=self.identity, seq=self.seq, term=self.lead.term)
        self.pub_layout.publish(String(data=auth.seal(self.key, layout)))

    def _renew(self) -> None:
        """The same layout again, newly stamped and numbered: the agents' lease on us."""
        now = self._now()
        self.check_role(now)
        if self.core.layout is not None and self.lead.may_command(now):
            self._send_layout(self.core.generation, self.core.layout, self.core.reason)

    def _event(self, kind: str, node: str, from_scale: str, to_scale: str, reason: str,
               generation: Optional[int] = None) -> None:
        if self.lead.role != LEADER:
            return
        self._publish(self.pub_events, p.Event(
            stamp=time.time(), kind=kind, node=node, from_scale=from_scale, to_scale=to_scale,
            reason=reason, generation=self.core.generation if generation is None else generation))

    def _diagnostics(self, level: int, message: str,
                     values: Optional[Dict[str, object]] = None) -> None:
        if self.pub_diag is None:
            return
        name = (f'{NODE_NAME}: {self.deployment.name}' if self.lead.role == LEADER else
                f'{NODE_NAME} (standby {self.identity.id}): {self.deployment.name}')
        # Once a second, and at once on a change of level or role (runtime/diagnostics.py):
        # built only then.
        if not self._diag_gate.due(name, level, self._now()):
            return
        status = DiagnosticStatus(level=bytes([level]), name=name, message=message[:500],
                                  hardware_id=self.host)
        values = dict(values or self.core.values(self._now()))
        values.update({'messages ignored': self._rejected, 'decider': self.identity.describe(),
                       'messages signed': self.key is not None, 'role': self.lead.role,
                       'term': self.lead.term, 'takeovers': self.lead.takeovers,
                       'other deciders': ', '.join(f'{o.identity.id} ({o.role})' for o in
                                                   self.lead.others(self._now())) or 'none'})
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(array)


def main(args=None) -> int:
    restore_ctrl_c()
    # A parameters file rcl cannot read: said with its line and what was expected, not as
    # rcl's parser words it.
    if refuse_bad_params_files('anyscale_manager decider', sys.argv if args is None else args):
        return 2
    # discovery.mode server: a client of the deployment's discovery servers (before it joins).
    apply_client_setup('anyscale_manager decider', sys.argv if args is None else args)
    # A SIGINT shuts rclpy's context down (its handler) and is not also raised as
    # KeyboardInterrupt: raised in the middle of an rclpy call, that came out as a RuntimeError
    # ("Unable to convert call argument '0' to Python object") while the context was still up,
    # and the decider exited 1 with a traceback instead of stopping cleanly.
    interrupt_once()
    # SIGUSR1 writes every thread's stack to stderr (the decider's log): what a decider that
    # does not stop is doing (the test-bed's teardown asks before it kills one).
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        rclpy.init(args=args)
    except Exception as e:  # noqa: B902 - rcl refuses the arguments or the parameters file
        print(f'anyscale_manager decider: cannot start: {e}', file=sys.stderr)
        return 2
    rclpy_stops_on_sigint()
    node = None
    code = 0
    # The turns and the lease's renewals: jobs of this loop, not rclpy timers
    # (steady_loop.SteadyLoop).
    loop = serve_timers(rclpy.get_default_context())
    try:
        node = DeciderNode()
        executor = make_executor()
        executor.add_node(node)
        collect_between_callbacks()

        def failed(e: BaseException) -> None:
            node.get_logger().error(
                'a periodic job failed:\n' + ''.join(traceback.format_exception(e)))
        while rclpy.ok() and not stop_asked():
            executor.spin_once(timeout_sec=loop.wait_s(1.0))
            loop.run_due(failed)
            collect_due()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # SIGINT can shut the context down while rclpy takes a message ("Unable to convert
        # call argument '0' to Python object" from take_message). Stopping was asked for, so
        # it is a clean stop; while the context is up it is a real error.
        if rclpy.ok():
            raise
    except (DeploymentError, LayoutError, auth.KeyFileError) as e:
        print(f'anyscale_manager decider: {e}', file=sys.stderr)
        code = 2
    finally:
        ignore_interrupts()          # a repeated SIGINT must not break the cleanup
        release_timers(rclpy.get_default_context())
        if node is not None:
            node.destroy_node()
        shut_rclpy_down()
    return code


if __name__ == '__main__':
    sys.exit(main())
