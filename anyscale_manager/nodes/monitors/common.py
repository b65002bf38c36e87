"""What the monitors share: QoS profiles, the publishers of a project topic and of
/diagnostics, message types by name, settings checks, and one timer's cadence of jobs."""

import importlib
import re
import time
from typing import Callable, List, Mapping, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import String

from .. import qos
from ... import protocol as p
from ...protocol_auth import Sealer
from ...model.types import Deployment
from ...runtime.diagnostics import DiagnosticsGate

PROBE_QOS = qos.PROBE
STATUS_QOS = qos.STATUS
LATCHED_QOS = qos.LATCHED_READER
DIAGNOSTICS_QOS = STATUS_QOS
_TYPE_RE = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*)/(?:(msg)/)?([A-Za-z_][A-Za-z0-9_]*)$')


def import_message_class(type_name: str):
    """'pkg/msg/Type' (or 'pkg/Type') -> the message class; ValueError naming what failed."""
    match = _TYPE_RE.match(type_name or '')
    if not match:
        raise ValueError(f'message type {type_name!r:.80} is not of the form pkg/msg/Type')
    pkg, _, name = match.groups()
    try:
        module = importlib.import_module(f'{pkg}.msg')
    except ImportError as e:
        raise ValueError(f'message type {type_name}: cannot import {pkg}.msg ({e})') from None
    cls = getattr(module, name, None)
    if cls is None or not hasattr(cls, 'get_fields_and_field_types'):
        raise ValueError(f'message type {type_name}: {pkg}.msg has no message {name}')
    return cls


def status(name: str, level: int, message: str, hardware_id: str,
           values: Mapping[str, object]) -> DiagnosticStatus:
    s = DiagnosticStatus()
    s.level = bytes([level])
    s.name = name
    s.message = message
    s.hardware_id = hardware_id
    s.values = [KeyValue(key=str(k), value=_fmt(v)) for k, v in values.items()]
    return s


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f'{value:.6g}'
    return '' if value is None else str(value)


class Publishers:
    """A monitor's project-topic publisher plus the shared /diagnostics publisher."""

    def __init__(self, node, topic: str, sealer: Optional[Sealer] = None):
        self.node = node
        self._gate = DiagnosticsGate()
        self.topic = topic
        self.sealer = sealer or Sealer(None, '')
        self.own = node.create_publisher(String, topic, STATUS_QOS)
        self.diagnostics = node.create_publisher(DiagnosticArray, p.TOPIC_DIAGNOSTICS,
                                                 DIAGNOSTICS_QOS)

    def send(self, message: p.Message) -> None:
        self.own.publish(String(data=self.sealer.seal(message)))

    def diagnostics_due(self, name: str, level: int) -> bool:
        """Whether status ``name`` at ``level`` goes out now (runtime/diagnostics.py): build it
        only then."""
        return self._gate.due(name, level, time.monotonic())

    def send_diagnostics(self, statuses: List[DiagnosticStatus]) -> None:
        """Publish ``statuses``, each built after ``diagnostics_due`` said yes."""
        if not statuses:
            return
        array = DiagnosticArray()
        array.header.stamp = self.node.get_clock().now().to_msg()
        array.status = statuses
        self.diagnostics.publish(array)

    def destroy(self) -> None:
        self.node.destroy_publisher(self.own)
        self.node.destroy_publisher(self.diagnostics)


class Cadence:
    """Periodic jobs served by one timer that ticks every ``tick_s``: a job runs at the first
    tick within half a tick of its due time, then is due one period later; periods missed
    while the executor was busy are skipped, as rcl skips a timer's.

    One timer per monitor: rclpy's events executor manages the timers of a clock in a list it
    scans at every wake-up, and says so in the log from 8 timers on; every monitor and the
    agent itself share the agent node's clock.
    """

    def __init__(self, tick_s: float, start: float):
        if not tick_s > 0:
            raise ValueError(f'a cadence needs a positive tick, got {tick_s!r}')
        self.tick_s = tick_s
        self._start = start
        self._jobs: List[list] = []       # [period_s, due, job], in the order they were added

    def every(self, period_s: float, job: Callable[[], None]) -> None:
        """Run ``job`` every ``period_s`` (at least a tick), the first time one period in."""
        if not period_s >= self.tick_s:
            raise ValueError(f'a job every {period_s!r} s is faster than the tick of its '
                             f'cadence, {self.tick_s:g} s')
        self._jobs.append([period_s, self._start + period_s, job])

    def due(self, job: Callable[[], None]) -> float:
        """When ``job`` is next due."""
        return next(entry[1] for entry in self._jobs if entry[2] == job)

    def retick(self, tick_s: float) -> None:
        """Tick every ``tick_s`` from now on; no job may be faster. Due times stand."""
        if not tick_s > 0 or any(period < tick_s for period, _, _ in self._jobs):
            raise ValueError(f'a cadence cannot tick every {tick_s!r} s with jobs every '
                             f'{", ".join(f"{j[0]:g}" for j in self._jobs)} s')
        self.tick_s = tick_s

    def run(self, now: float) -> None:
        """Run, in the order they were added, the jobs due at ``now``. Each is rescheduled
        before it runs: one that raises does not run twice, and the rest run at the next tick."""
        slack = self.tick_s / 2
        for entry in self._jobs:
            period_s, due, job = entry
            if now < due - slack:
                continue
            due += period_s
            entry[1] = due if due > now else now + period_s
            job()


# An unchanged status (LinkStatus, ConnectionStatus) goes out this often at most, and a third
# of the decider's observation_max_age_s at least (a reading that old counts as missing); a
# change of what its readers act on at once.
STATUS_REFRESH_S = 1.0


def refresh_s(deployment: Deployment, period_s: float) -> float:
    """How often a monitor publishing every ``period_s`` at most sends an unchanged status."""
    return max(period_s, min(STATUS_REFRESH_S, deployment.decider.observation_max_age_s / 3.0))


def connection_status_refresh_s(deployment: Deployment, scale: str, period_s: float) -> float:
    """How often ``scale``'s probes, taking readings every ``period_s``, send unchanged ones:
    the master at ``refresh_s``, a remote scale never later than the next reading (0.0: every
    reading goes out), for its readings of the connections crossing a link are the delivery
    evidence of the link's monitor at the other end (ProbeManager)."""
    return refresh_s(deployment, period_s) if scale == deployment.master.name else 0.0


def period_of(rate_hz: float, what: str) -> float:
    if not rate_hz > 0:
        raise ValueError(f'monitoring.{what} must be positive, got {rate_hz!r}')
    return 1.0 / rate_hz


def scale_of(deployment: Deployment, scale: str):
    try:
        return deployment.scale(scale)
    except KeyError:
        raise ValueError(f'deployment {deployment.name!r} has no scale {scale!r} '
                         f'(scales: {", ".join(deployment.scale_names)})') from None
