"""The monitors an agent hosts inside its own node: scale CPU, the link, connection probes.

Glue only: each class reads the world (psutil, cgroups, DDS arrivals, sockets), feeds the pure
statistics of ``runtime.rates`` and ``runtime.cpu`` with ``time.monotonic()`` and publishes the
results on the project's topics and on ``/diagnostics``. Each monitor runs its callbacks in its
own mutually exclusive callback group, so a multi-threaded executor never runs two of one
monitor's callbacks at once.
"""

import importlib
import json
import math
import os
import re
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Set, Tuple

import psutil
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_msgs.msg import String

from . import qos
from .. import protocol as p
from ..agent import procs
from ..model.types import Connection, Deployment
from ..runtime import cpu as cpu_math
from ..runtime.rates import (BandwidthEstimate, HeartbeatTracker, RateWindow,
                             ToleranceTracker, WriterStreams, crossing_connections,
                             steady_throughput_bps, used_kbps)

PROBE_QOS = qos.PROBE
STATUS_QOS = qos.STATUS
HEARTBEAT_QOS = qos.HEARTBEAT
LATCHED_QOS = qos.LATCHED_READER
DIAGNOSTICS_QOS = STATUS_QOS

PROBE_MAGIC = b'ASBWPRB1'            # 8 bytes, then the requested duration in ms (uint32)
PROBE_MAX_DURATION_S = 2.0           # the server never receives longer than this
PROBE_CHUNK = 64 * 1024
PROBE_RECV_BYTES = 1 << 20
TYPE_RESOLVE_PERIOD_S = 1.0
WATCHDOG_SLACK_S = 0.002
_TYPE_RE = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*)/(?:(msg)/)?([A-Za-z_][A-Za-z0-9_]*)$')


# --- shared helpers ---------------------------------------------------------------------------

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


class _Publishers:
    """A monitor's project-topic publisher plus the shared /diagnostics publisher."""

    def __init__(self, node, topic: str):
        self.node = node
        self.topic = topic
        self.own = node.create_publisher(String, topic, STATUS_QOS)
        self.diagnostics = node.create_publisher(DiagnosticArray, p.TOPIC_DIAGNOSTICS,
                                                 DIAGNOSTICS_QOS)

    def send(self, message: p.Message) -> None:
        self.own.publish(String(data=message.to_json()))

    def send_diagnostics(self, statuses: List[DiagnosticStatus]) -> None:
        if not statuses:
            return
        array = DiagnosticArray()
        array.header.stamp = self.node.get_clock().now().to_msg()
        array.status = statuses
        self.diagnostics.publish(array)

    def destroy(self) -> None:
        self.node.destroy_publisher(self.own)
        self.node.destroy_publisher(self.diagnostics)


def _period(rate_hz: float, what: str) -> float:
    if not rate_hz > 0:
        raise ValueError(f'monitoring.{what} must be positive, got {rate_hz!r}')
    return 1.0 / rate_hz


def _scale_of(deployment: Deployment, scale: str):
    try:
        return deployment.scale(scale)
    except KeyError:
        raise ValueError(f'deployment {deployment.name!r} has no scale {scale!r} '
                         f'(scales: {", ".join(deployment.scale_names)})') from None


# --- scale monitor ----------------------------------------------------------------------------

class _SystemCpu:
    """Cumulative busy CPU seconds of the scale: its cgroup when a quota confines it, else the
    whole machine; and the CPUs (``cores``) that busy time is spread over."""

    def __init__(self, pid: int):
        self.cgroup_usage_path: Optional[str] = None
        self.usage_scale = 1.0
        quota = None
        try:
            with open(f'/proc/{pid}/cgroup') as f:
                groups = cpu_math.parse_proc_cgroup(f.read())
        except OSError:
            groups = {}
        cpu_path = groups.get('cpu')
        if cpu_path and cpu_path != '/':
            base = self._mount('cpu', cpu_path)
            quota = cpu_math.quota_cores_v1(_read(os.path.join(base, 'cpu.cfs_quota_us')),
                                            _read(os.path.join(base, 'cpu.cfs_period_us')))
            acct = self._mount('cpuacct', groups.get('cpuacct', cpu_path))
            if quota is not None and os.path.exists(os.path.join(acct, 'cpuacct.usage')):
                self.cgroup_usage_path = os.path.join(acct, 'cpuacct.usage')
                self.usage_scale = 1e-9
        elif '' in groups and groups[''] != '/' and 'cpu' not in groups:
            base = os.path.join('/sys/fs/cgroup', groups[''].lstrip('/'))
            quota = cpu_math.quota_cores_v2(_read(os.path.join(base, 'cpu.max')))
            if quota is not None and os.path.exists(os.path.join(base, 'cpu.stat')):
                self.cgroup_usage_path = os.path.join(base, 'cpu.stat')
                self.usage_scale = 1e-6
        if self.cgroup_usage_path is None:
            quota = None
        self.cores = cpu_math.effective_cores(psutil.cpu_count(logical=True) or 1, quota)

    @staticmethod
    def _mount(controller: str, path: str) -> str:
        for root in (f'/sys/fs/cgroup/{controller}', '/sys/fs/cgroup/cpu,cpuacct',
                     '/sys/fs/cgroup/cpuacct,cpu'):
            candidate = os.path.join(root, path.lstrip('/'))
            if os.path.isdir(candidate):
                return candidate
        return os.path.join(f'/sys/fs/cgroup/{controller}', path.lstrip('/'))

    def busy_seconds(self) -> Optional[float]:
        if self.cgroup_usage_path is not None:
            text = _read(self.cgroup_usage_path)
            if self.cgroup_usage_path.endswith('cpu.stat'):
                for line in text.splitlines():
                    if line.startswith('usage_usec '):
                        text = line.split()[1]
                        break
            try:
                return int(text.strip()) * self.usage_scale
            except ValueError:
                return None
        t = psutil.cpu_times()
        idle = t.idle + getattr(t, 'iowait', 0.0)
        # On Linux guest time is already inside user time.
        total = sum(t) - getattr(t, 'guest', 0.0) - getattr(t, 'guest_nice', 0.0)
        return total - idle

    @property
    def source(self) -> str:
        return self.cgroup_usage_path or 'psutil.cpu_times'


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ''


class ScaleMonitor:
    """Publishes protocol.ScaleStatus on TOPIC_SCALE_STATUS and a scale DiagnosticStatus."""

    def __init__(self, node, deployment: Deployment, scale: str,
                 pids: Callable[[], Mapping[str, int]]):
        self._node = node
        self._scale = _scale_of(deployment, scale)
        self._pids = pids
        period = _period(deployment.monitoring.scale_rate_hz, 'scale_rate_hz')
        self._system = _SystemCpu(os.getpid())
        self._total = cpu_math.CpuCounter()
        self._procs = cpu_math.ProcessGroupCpu()
        self._out = _Publishers(node, p.TOPIC_SCALE_STATUS)
        self._group = MutuallyExclusiveCallbackGroup()
        self.last: Optional[p.ScaleStatus] = None
        self._sample()     # prime every counter now, so the first tick already has a reading
        self._timer = node.create_timer(period, self._tick, callback_group=self._group)
        node.get_logger().info(
            f'scale monitor for {self._scale.name}: {self._system.cores:g} CPUs worth '
            f'{self._scale.capacity_cpu:g} reference-core percent, from {self._system.source}')

    def _sample(self) -> Tuple[Optional[float], Dict[str, float]]:
        now = time.monotonic()
        busy = self._system.busy_seconds()
        total = None if busy is None else self._total.update(now, busy)
        try:
            pids = dict(self._pids())
        except Exception as e:  # the agent's callback; never let it kill the monitor
            self._node.get_logger().warning(f'scale monitor: pids() failed: {e}',
                                            throttle_duration_sec=10.0)
            pids = {}
        # One pass over /proc for every node (a process tree per node): walking each node's
        # tree with psutil rescans /proc once per node, which was half the agent's CPU.
        leaders = {name: pid for name, pid in pids.items() if isinstance(pid, int) and pid > 0}
        samples = procs.tree_cpu_seconds(procs.process_table(), leaders) if leaders else {}
        return total, self._procs.update(now, samples)

    def _ref(self, core_seconds_per_s: float) -> float:
        return cpu_math.reference_percent(core_seconds_per_s, self._scale.capacity_cpu,
                                          self._system.cores)

    def _tick(self) -> None:
        total, by_node = self._sample()
        if total is None:
            return
        capacity = self._scale.capacity_cpu
        cpu_total = min(self._ref(total), capacity)
        message = p.ScaleStatus(
            scale=self._scale.name, stamp=time.time(), cpu_total=cpu_total,
            capacity_cpu=capacity,
            cpu_by_node={name: self._ref(v) for name, v in sorted(by_node.items())},
            mem_percent=float(psutil.virtual_memory().percent),
            load_1m=float(os.getloadavg()[0]))
        self.last = message
        self._out.send(message)
        level = p.WARN if cpu_total >= 0.9 * capacity else p.OK
        text = (f'CPU {cpu_total:.0f} of {capacity:.0f}' +
                (' (near capacity)' if level == p.WARN else ''))
        values = {'cpu_total': cpu_total, 'capacity_cpu': capacity,
                  'mem_percent': message.mem_percent, 'load_1m': message.load_1m}
        values.update({f'cpu.{k}': v for k, v in message.cpu_by_node.items()})
        self._out.send_diagnostics([status(f'anyscale/scale/{self._scale.name}', level, text,
                                           self._scale.host, values)])

    def destroy(self) -> None:
        self._node.destroy_timer(self._timer)
        self._out.destroy()


# --- connection probes ------------------------------------------------------------------------

@dataclass
class _TopicProbe:
    """One raw subscription, shared by every probed connection on the topic."""

    topic: str
    window: RateWindow
    declared_type: str = ''
    subscription: object = None
    type_name: str = ''
    msg_class: object = None
    watch: object = None       # a second subscription, polled: who wrote (handovers)
    writers: WriterStreams = field(default_factory=WriterStreams)
    problem: str = ''          # why there is no subscription yet
    fatal: bool = False        # the type cannot be used here: no reading at all
    users: Set[str] = field(default_factory=set)


class ProbeManager:
    """Raw-subscription probes for the connections whose subscriber runs on this scale.

    With a ``watch_node`` (a node no executor spins), the topics of connections whose publisher
    is migratable get a second subscription there, read by ``poll_writers``: it takes each
    message with its info, whose publication sequence number tells a newly started writer from
    the old one (``WriterStreams``). The agent asks ``writer_joined_since`` before it lets a
    moving node's old copy go. (The events executor the agent spins on does not hand message
    info to callbacks, hence the polling.)
    """

    def __init__(self, node, deployment: Deployment, scale: str, watch_node=None):
        self._node = node
        self._watch_node = watch_node
        self._migratable = frozenset(deployment.migratable_nodes)
        self._deployment = deployment
        self._scale = _scale_of(deployment, scale)
        settings = deployment.monitoring
        self._window_s = settings.probe_window_s
        RateWindow(self._window_s)       # validates the window before anything is created
        period = _period(settings.probe_publish_rate_hz, 'probe_publish_rate_hz')
        self._topics: Dict[str, _TopicProbe] = {}
        self._probes: Dict[str, Tuple[Connection, ToleranceTracker]] = {}
        self._out = _Publishers(node, p.TOPIC_CONNECTION_STATUS)
        self._group = MutuallyExclusiveCallbackGroup()
        self._lock = threading.Lock()
        self.last: Optional[p.ConnectionStatus] = None
        self._timer = node.create_timer(period, self._publish, callback_group=self._group)
        self._resolver = node.create_timer(TYPE_RESOLVE_PERIOD_S, self._resolve_pending,
                                           callback_group=self._group)

    @property
    def connections(self) -> Tuple[str, ...]:
        return tuple(sorted(self._probes))

    def set_connections(self, names: Iterable[str]) -> None:
        """Probe exactly these connections from now on; unknown names change nothing."""
        names = list(names)
        unknown = [n for n in names if n not in {c.name for c in self._deployment.connections}]
        if unknown:
            raise ValueError(f'set_connections: deployment {self._deployment.name!r} has no '
                             f'connection {", ".join(repr(n) for n in unknown)}')
        wanted = {n: self._deployment.connection(n) for n in names}
        with self._lock:
            for name in [n for n in self._probes if n not in wanted]:
                conn, _ = self._probes.pop(name)
                self._release(conn.topic, name)
            for name, conn in wanted.items():
                if name in self._probes:
                    continue
                self._probes[name] = (conn, ToleranceTracker(conn.freq_min_hz, conn.tolerance_s))
                self._attach(conn)

    def _resolve(self, topic: str) -> str:
        try:
            return self._node.resolve_topic_name(topic)
        except Exception:
            return topic

    def _attach(self, conn: Connection) -> None:
        topic = self._resolve(conn.topic)
        probe = self._topics.get(topic)
        if probe is None:
            probe = _TopicProbe(topic, RateWindow(self._window_s), declared_type=conn.msg_type)
            self._topics[topic] = probe
            self._subscribe(probe)
        elif conn.msg_type and probe.declared_type and conn.msg_type != probe.declared_type:
            self._node.get_logger().warning(
                f'connection {conn.name}: declares {conn.msg_type} on {topic}, another '
                f'connection on it declares {probe.declared_type}; probing with the latter')
        probe.users.add(conn.name)
        self._ensure_watch(probe)

    def _ensure_watch(self, probe: _TopicProbe) -> None:
        if self._watch_node is None or probe.watch is not None or probe.msg_class is None:
            return
        if not any(self._deployment.connection(n).publisher in self._migratable
                   for n in probe.users):
            return
        probe.watch = self._watch_node.create_subscription(
            probe.msg_class, probe.topic, lambda _msg: None, PROBE_QOS, raw=True)

    def _release(self, topic: str, name: str) -> None:
        topic = self._resolve(topic)
        probe = self._topics.get(topic)
        if probe is None:
            return
        probe.users.discard(name)
        if not probe.users:
            if probe.subscription is not None:
                self._node.destroy_subscription(probe.subscription)
            if probe.watch is not None:
                self._watch_node.destroy_subscription(probe.watch)
            del self._topics[topic]

    def _subscribe(self, probe: _TopicProbe) -> None:
        type_name = probe.declared_type
        if not type_name:
            types = dict(self._node.get_topic_names_and_types()).get(probe.topic)
            if not types:
                probe.problem = f'waiting for a publisher on {probe.topic} to learn its type'
                return
            type_name = types[0]
        try:
            cls = import_message_class(type_name)
        except ValueError as e:
            probe.problem, probe.fatal = str(e), True
            self._node.get_logger().error(f'probe on {probe.topic}: {e}')
            return
        window = probe.window

        def on_message(raw: bytes, window=window) -> None:
            window.add(time.monotonic(), len(raw))

        probe.subscription = self._node.create_subscription(
            cls, probe.topic, on_message, PROBE_QOS, callback_group=self._group, raw=True)
        probe.type_name, probe.problem, probe.fatal = type_name, '', False
        probe.msg_class = cls
        self._ensure_watch(probe)

    def _resolve_pending(self) -> None:
        with self._lock:
            for probe in self._topics.values():
                if probe.subscription is None and not probe.fatal:
                    self._subscribe(probe)

    def poll_writers(self, now: float, limit: int = 200) -> None:
        """Read what the watch subscriptions hold: who wrote each message (see the class)."""
        with self._lock:
            watched = [(p.watch, p.writers) for p in self._topics.values() if p.watch is not None]
        for subscription, writers in watched:
            try:
                with subscription.handle:
                    for _ in range(limit):
                        taken = subscription.handle.take_message(subscription.msg_type, True)
                        if taken is None:
                            break
                        info = taken[1] if len(taken) > 1 else None
                        writers.add(now, info.get('publication_sequence_number')
                                    if isinstance(info, dict) else None)
            except Exception:   # destroyed meanwhile: its topic is no longer probed
                continue

    def writer_joined_since(self, name: str, since: float) -> Optional[bool]:
        """Whether connection ``name``'s topic was heard from a writer that started later than
        the others, first at or after ``since`` (a copy of its publisher started elsewhere);
        None when this scale does not watch it. Needs ``poll_writers`` called often."""
        with self._lock:
            conn = self._probes.get(name)
            probe = self._topics.get(self._resolve(conn[0].topic)) if conn else None
            if probe is None or probe.watch is None:
                return None
            return probe.writers.joined_since(since)

    def readings(self, now: float) -> Dict[str, Tuple[p.ConnectionReading, str]]:
        """Connection -> (reading, note) for every probe that can measure; advances Δ."""
        out = {}
        with self._lock:
            for name, (conn, tracker) in sorted(self._probes.items()):
                probe = self._topics[self._resolve(conn.topic)]
                if probe.fatal:
                    continue
                rate = probe.window.rate_hz(now)
                verdict = tracker.update(now, rate)
                reading = p.ConnectionReading(rate_hz=rate,
                                              bytes_per_s=probe.window.bytes_per_s(now),
                                              below_for_s=verdict.below_for_s,
                                              level=verdict.level)
                out[name] = (reading, probe.problem)
        return out

    def _publish(self) -> None:
        now = time.monotonic()
        readings = self.readings(now)
        message = p.ConnectionStatus(scale=self._scale.name, stamp=time.time(),
                                     connections={k: r for k, (r, _) in readings.items()})
        self.last = message
        self._out.send(message)
        statuses = []
        with self._lock:
            probes = sorted(self._probes.items())
        for name, (conn, _) in probes:
            values = {'topic': conn.topic, 'publisher': conn.publisher,
                      'subscriber': conn.subscriber, 'freq_min_hz': conn.freq_min_hz,
                      'tolerance_s': conn.tolerance_s}
            if name not in readings:
                probe = self._topics.get(self._resolve(conn.topic))
                problem = probe.problem if probe else 'no probe'
                statuses.append(status(f'anyscale/connection/{name}', p.STALE, problem,
                                       self._scale.host, values))
                continue
            reading, note = readings[name]
            values.update({'rate_hz': reading.rate_hz, 'bytes_per_s': reading.bytes_per_s,
                           'below_for_s': reading.below_for_s})
            statuses.append(status(f'anyscale/connection/{name}', reading.level,
                                   _describe(conn, reading, note), self._scale.host, values))
        self._out.send_diagnostics(statuses)

    def destroy(self) -> None:
        self._node.destroy_timer(self._timer)
        self._node.destroy_timer(self._resolver)
        with self._lock:
            for probe in self._topics.values():
                if probe.subscription is not None:
                    self._node.destroy_subscription(probe.subscription)
                if probe.watch is not None:
                    self._watch_node.destroy_subscription(probe.watch)
            self._topics.clear()
            self._probes.clear()
        self._out.destroy()


def _describe(conn: Connection, reading: p.ConnectionReading, note: str) -> str:
    text = f'{reading.rate_hz:.3g} Hz'
    if conn.freq_min_hz is not None:
        if reading.level == p.OK:
            text += f' (freq_min {conn.freq_min_hz:g} Hz)'
        else:
            text += (f', below freq_min {conn.freq_min_hz:g} Hz for {reading.below_for_s:.1f} s'
                     f' (tolerance {conn.tolerance_s:g} s)')
    return f'{text}; {note}' if note else text


# --- link monitor -----------------------------------------------------------------------------

def probe_throughput(host: str, port: int, duration_s: float,
                     timeout_s: float = 3.0) -> float:
    """Send a bulk TCP burst to a probe server for ``duration_s``; its measured bytes/s.

    The receiver times the transfer and answers with one JSON line; the sender keeps the pipe
    full until that answer arrives, so the measurement is bounded by the receiver's clock and
    not by how much the local socket buffers swallowed. Raises OSError or ValueError.
    """
    duration_ms = int(min(max(duration_s, 0.05), PROBE_MAX_DURATION_S) * 1000)
    deadline = time.monotonic() + duration_ms / 1000.0 + timeout_s
    chunk = bytes(PROBE_CHUNK)
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        sock.sendall(PROBE_MAGIC + struct.pack('!I', duration_ms))
        sock.setblocking(False)
        reply = b''
        while time.monotonic() < deadline:
            readable, writable, _ = select.select([sock], [sock], [], 0.2)
            if readable:
                data = sock.recv(4096)
                if not data:
                    break
                reply += data
                if b'\n' in reply or len(reply) > 4096:
                    break
                continue
            if writable:
                try:
                    sock.send(chunk)
                except (BlockingIOError, InterruptedError):
                    pass
        else:
            raise OSError(f'throughput probe to {host}:{port} timed out')
        # Reset rather than close gracefully: what is still in the send buffer must not keep
        # the link busy after the measurement.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
    try:
        answer = json.loads(reply.split(b'\n', 1)[0].decode('ascii'))
        bps = float(answer['bytes_per_s'])
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        raise ValueError(f'throughput probe to {host}:{port}: bad answer {reply[:60]!r}') \
            from None
    if not bps > 0:
        raise ValueError(f'throughput probe to {host}:{port}: {answer.get("error", "no data")}')
    return bps


def _drain_ready(conn: socket.socket, buffer: bytearray) -> int:
    """Read, without waiting, whatever is already buffered; return its size."""
    total = 0
    timeout = conn.gettimeout()
    conn.setblocking(False)
    try:
        while True:
            n = conn.recv_into(buffer)
            if not n:
                break
            total += n
    except (BlockingIOError, InterruptedError):
        pass
    finally:
        conn.settimeout(timeout)
    return total


class ProbeServer:
    """The remote end of the throughput probe: receives one bounded burst at a time."""

    def __init__(self, host: str, port: int, logger=None):
        self._logger = logger
        self._sock = socket.create_server((host, port), reuse_port=False)
        self._sock.settimeout(0.5)
        self.address = self._sock.getsockname()[:2]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name='anyscale-bw-probe',
                                        daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            with conn:
                try:
                    self._receive(conn)
                except OSError as e:
                    if self._logger is not None:
                        self._logger.warning(f'throughput probe: {e}',
                                             throttle_duration_sec=60.0)

    def _receive(self, conn: socket.socket) -> None:
        conn.settimeout(2.0)
        header = b''
        while len(header) < 12:
            data = conn.recv(12 - len(header))
            if not data:
                return
            header += data
        if header[:8] != PROBE_MAGIC:
            return         # not ours: drop the connection without an answer
        duration = min(max(struct.unpack('!I', header[8:])[0] / 1000.0, 0.05),
                       PROBE_MAX_DURATION_S)
        samples: List[Tuple[float, int]] = []
        received = 0
        first = None
        buffer = bytearray(PROBE_RECV_BYTES)
        while True:
            n = conn.recv_into(buffer)
            now = time.monotonic()
            if not n:
                break
            received += n
            if first is None:
                first = now
                samples.append((now, received))
                continue
            if now - first >= duration:
                # What the kernel already holds arrived before now: count it with this sample,
                # or a receiver that was descheduled for a moment would read a slower link.
                received += _drain_ready(conn, buffer)
                samples.append((now, received))
                break
            samples.append((now, received))
        bps = steady_throughput_bps(samples)
        answer = {'bytes': received, 'bytes_per_s': bps or 0.0,
                  'duration_s': 0.0 if first is None else samples[-1][0] - first}
        conn.sendall(json.dumps(answer).encode('ascii') + b'\n')
        conn.shutdown(socket.SHUT_WR)
        # Drain what the sender still had in flight until it closes, so our answer is not
        # discarded by a reset.
        end = time.monotonic() + 2.0
        try:
            while time.monotonic() < end and conn.recv(PROBE_CHUNK):
                pass
        except OSError:
            pass

    def close(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(timeout=2.0)


@dataclass
class _Remote:
    scale: object
    link_name: str
    beats: HeartbeatTracker
    bandwidth: Optional[BandwidthEstimate]
    was_up: bool = False
    probing: bool = False
    congested: bool = False
    delay_s: Optional[float] = None
    quiet_since: float = -math.inf     # beats sent earlier say nothing of congestion
    watchdog: object = None
    result: Optional[Tuple[float, Optional[float], str, float]] = None  # done, bps, error, used


class LinkMonitor:
    """Master: heartbeats, RTT, loss, up/down and bandwidth of the link to each remote.
    Remote: echoes the heartbeats addressed to it and serves the throughput probe."""

    def __init__(self, node, deployment: Deployment, scale: str):
        self._node = node
        self._deployment = deployment
        self._scale = _scale_of(deployment, scale)
        settings = deployment.monitoring
        self._period = _period(settings.heartbeat_rate_hz, 'heartbeat_rate_hz')
        self._group = MutuallyExclusiveCallbackGroup()
        self._log = node.get_logger()
        self._timers = []
        self._subs = []
        self._server: Optional[ProbeServer] = None
        self._remotes: Dict[str, _Remote] = {}
        self._lock = threading.Lock()
        self.last: Dict[str, p.LinkStatus] = {}
        if self._scale.is_master:
            self._start_master(settings)
        else:
            self._start_remote(settings)

    # master side ----------------------------------------------------------------------------
    def _start_master(self, settings) -> None:
        for remote in self._deployment.remote_scales:
            link = self._deployment.link_between(self._scale.name, remote.name)
            estimate = None
            if link is not None:
                # A link that looks congested is probed at once, but the probe fills at most a
                # tenth of its time.
                estimate = BandwidthEstimate(
                    settings.bandwidth_probe_interval_s, link.bandwidth_kbps,
                    urgent_gap_s=10.0 * settings.bandwidth_probe_duration_s)
            self._remotes[remote.name] = _Remote(
                remote, link.name if link else f'{self._scale.name}-{remote.name}',
                HeartbeatTracker(self._period, settings.heartbeat_misses_down), estimate)
        self._readings: Dict[Tuple[str, str], Tuple[float, float]] = {}  # (scale, conn) -> B/s, at
        self._running: Dict[str, Dict[str, str]] = {}          # scale -> node -> scale
        self._beat_pub = self._node.create_publisher(String, p.TOPIC_HEARTBEAT, HEARTBEAT_QOS)
        self._out = _Publishers(self._node, p.TOPIC_LINK_STATUS)
        self._subs.append(self._node.create_subscription(
            String, p.TOPIC_HEARTBEAT_ECHO, self._on_echo, HEARTBEAT_QOS,
            callback_group=self._group))
        self._subs.append(self._node.create_subscription(
            String, p.TOPIC_CONNECTION_STATUS, self._on_connections, STATUS_QOS,
            callback_group=self._group))
        self._subs.append(self._node.create_subscription(
            String, p.TOPIC_AGENT_STATE, self._on_agent_state, LATCHED_QOS,
            callback_group=self._group))
        self._timers.append(self._node.create_timer(self._period, self._beat,
                                                    callback_group=self._group))
        # A watchdog per remote, re-armed by every echo, fires just after misses_down periods
        # of silence: a cut is published at that instant, not at the next periodic check.
        for remote in self._remotes.values():
            remote.watchdog = self._node.create_timer(
                remote.beats.timeout_s + WATCHDOG_SLACK_S, self._check,
                callback_group=self._group)
            self._timers.append(remote.watchdog)
        self._readings_max_age = max(3.0, 3.0 / settings.probe_publish_rate_hz)
        self._probe_duration = settings.bandwidth_probe_duration_s
        self._congestion_s = settings.congestion_delay_ms / 1000.0
        self._probe_port = settings.bandwidth_probe_port

    def _decode(self, cls, msg: String, topic: str):
        try:
            return cls.from_json(msg.data, topic)
        except p.ProtocolError as e:
            self._log.warning(f'link monitor: ignoring a bad message: {e}',
                              throttle_duration_sec=10.0)
            return None

    def _on_echo(self, msg: String) -> None:
        now = time.monotonic()
        echo = self._decode(p.Heartbeat, msg, p.TOPIC_HEARTBEAT_ECHO)
        if echo is None or echo.target != self._scale.name:
            return
        remote = self._remotes.get(echo.scale)
        if remote is not None and remote.beats.echo(now, echo.seq) is not None:
            remote.watchdog.reset()
            self._check()

    def _on_connections(self, msg: String) -> None:
        now = time.monotonic()
        report = self._decode(p.ConnectionStatus, msg, p.TOPIC_CONNECTION_STATUS)
        if report is None:
            return
        for name, reading in report.connections.items():
            self._readings[(report.scale, name)] = (reading.bytes_per_s, now)

    def _on_agent_state(self, msg: String) -> None:
        state = self._decode(p.AgentState, msg, p.TOPIC_AGENT_STATE)
        if state is not None:
            self._running[state.scale] = {n: state.scale for n in state.running()}

    def used_kbps(self, remote: str, now: float) -> float:
        """kbit/s of the connections measured crossing the link to ``remote`` now."""
        running: Dict[str, str] = {}
        for nodes in self._running.values():
            running.update(nodes)
        names = crossing_connections(
            ((c.name, c.publisher, c.subscriber) for c in self._deployment.connections),
            running, self._scale.name, remote)
        # Each connection as measured where its subscriber runs: a copy starting or stopping
        # on the other end measures traffic that does not cross the link.
        fresh = {}
        for name in names:
            where = running.get(self._deployment.connection(name).subscriber)
            bps, at = self._readings.get((where, name), (0.0, -math.inf))
            if now - at <= self._readings_max_age:
                fresh[name] = bps
        return used_kbps(fresh, names)

    def _beat(self) -> None:
        self._check()
        now = time.monotonic()
        for name, remote in self._remotes.items():
            self._collect_probe(remote, now)
            used = self.used_kbps(name, now)
            self._judge_congestion(remote, now, used)   # on the beats already sent
            seq = remote.beats.next_beat(now)
            beat = p.Heartbeat(scale=self._scale.name, target=name, seq=seq, sent=now)
            self._beat_pub.publish(String(data=beat.to_json()))
            if remote.bandwidth is not None and not remote.probing \
                    and remote.bandwidth.due(now, remote.beats.up(now), used, remote.congested):
                remote.bandwidth.started(now)
                remote.probing = True
                remote.quiet_since = math.inf      # the probe fills the queue on purpose
                threading.Thread(target=self._run_probe, args=(remote, used), daemon=True,
                                 name=f'anyscale-bw-{name}').start()
            self._publish(remote, now, used)
        # A late beat can be the one that completes misses_down unanswered (see HeartbeatTracker)
        self._check()

    def _judge_congestion(self, remote: _Remote, now: float, used: float) -> None:
        """A link whose queue holds the heartbeats looks full: it is probed at once (see
        BandwidthEstimate), and the decider's bandwidth rule compares what the probe measured
        with what the crossing connections need. A throttle is seen within about a second,
        where a rate past its Δ would take several."""
        up = remote.beats.up(now)
        delay = remote.beats.queueing_delay_s(now, since=remote.quiet_since) if up else None
        if not up or self._congestion_s <= 0:
            congested = False
        elif delay is None:             # not judged (a probe, a return): the verdict stands
            congested = remote.congested
        else:
            congested = delay > self._congestion_s
        if congested != remote.congested:
            if congested:
                self._log.warning(
                    f'link to {remote.scale.name} looks congested: queueing delay '
                    f'{delay * 1000.0:.0f} ms > {self._congestion_s * 1000.0:g} ms with '
                    f'{used:.0f} kbit/s crossing; probing it')
            else:
                self._log.info(f'link to {remote.scale.name} is no longer congested')
        remote.congested = congested
        remote.delay_s = delay

    def _run_probe(self, remote: _Remote, used: float) -> None:
        try:
            bps, error = probe_throughput(remote.scale.host, self._probe_port,
                                          self._probe_duration), ''
        except (OSError, ValueError) as e:
            bps, error = None, str(e) or type(e).__name__
        with self._lock:
            remote.result = (time.monotonic(), bps, error, used)

    def _collect_probe(self, remote: _Remote, now: float) -> None:
        with self._lock:
            result, remote.result = remote.result, None
        if result is None:
            return
        remote.probing = False
        done, bps, error, used = result
        # The probe's own queue drains within the link's latency; one beat period covers it.
        remote.quiet_since = done + self._period
        if bps is None:
            remote.bandwidth.failed(done, error)
            self._log.warning(f'bandwidth probe to {remote.scale.name}: {error}',
                              throttle_duration_sec=60.0)
        else:
            remote.bandwidth.record(done, bps * 8.0 / 1000.0, used)

    def _check(self) -> None:
        now = time.monotonic()
        for remote in self._remotes.values():
            up = remote.beats.up(now)
            if up != remote.was_up:
                remote.was_up = up
                if up:
                    # Beats sent while it was down were lost to the cut, not to a queue; and
                    # what the link carried before the outage may not hold where it came back.
                    remote.quiet_since = max(remote.quiet_since, now)
                    if remote.bandwidth is not None:
                        remote.bandwidth.remeasure()
                self._log.info(f'link to {remote.scale.name} is {"up" if up else "DOWN"}')
                self._publish(remote, now, self.used_kbps(remote.scale.name, now))

    def _publish(self, remote: _Remote, now: float, used: float) -> None:
        beats, estimate = remote.beats, remote.bandwidth
        up = beats.up(now)
        rtt = beats.rtt_s()
        available = estimate.available_kbps if estimate is not None else None
        age = estimate.age_s(now) if estimate is not None else None
        message = p.LinkStatus(master=self._scale.name, remote=remote.scale.name,
                               stamp=time.time(), up=up,
                               rtt_ms=None if rtt is None else rtt * 1000.0,
                               loss=beats.loss(now), bandwidth_available_kbps=available,
                               bandwidth_available_age_s=age, bandwidth_used_kbps=used,
                               queueing_delay_ms=None if remote.delay_s is None
                               else remote.delay_s * 1000.0,
                               congested=remote.congested and up)
        self.last[remote.scale.name] = message
        self._out.send(message)
        reference = available if available is not None else (
            estimate.nominal_kbps if estimate is not None else None)
        if not up:
            level, text = p.ERROR, f'down: no echo for over {beats.timeout_s:g} s'
        elif message.congested:
            delay = message.queueing_delay_ms
            level, text = p.WARN, ('congested: queueing delay '
                                   + ('being probed' if delay is None else f'{delay:.0f} ms')
                                   + f', used {used:.0f} kbit/s')
        elif message.loss > 0.2 or (reference and used > 0.9 * reference):
            level, text = p.WARN, f'up, loss {message.loss:.0%}, used {used:.0f} kbit/s'
        else:
            level, text = p.OK, f'up, rtt {message.rtt_ms or 0.0:.1f} ms'
        values = {'remote': remote.scale.name, 'up': up, 'rtt_ms': message.rtt_ms,
                  'loss': message.loss, 'bandwidth_available_kbps': available,
                  'bandwidth_available_age_s': age, 'bandwidth_used_kbps': used,
                  'queueing_delay_ms': message.queueing_delay_ms,
                  'congested': message.congested}
        if estimate is not None and estimate.last_error:
            values['bandwidth_probe_error'] = estimate.last_error
        self._out.send_diagnostics([status(f'anyscale/link/{remote.link_name}', level, text,
                                           self._scale.host, values)])

    # remote side ----------------------------------------------------------------------------
    def _start_remote(self, settings) -> None:
        self._echo_pub = self._node.create_publisher(String, p.TOPIC_HEARTBEAT_ECHO,
                                                     HEARTBEAT_QOS)
        self._subs.append(self._node.create_subscription(
            String, p.TOPIC_HEARTBEAT, self._on_beat, HEARTBEAT_QOS,
            callback_group=self._group))
        try:
            self._server = ProbeServer(self._scale.host, settings.bandwidth_probe_port,
                                       self._log)
        except OSError as e:
            self._log.error(f'throughput probe server on {self._scale.host}:'
                            f'{settings.bandwidth_probe_port} not started: {e}; the master '
                            f'will use the nominal bandwidth of this link')

    def _on_beat(self, msg: String) -> None:
        beat = self._decode(p.Heartbeat, msg, p.TOPIC_HEARTBEAT)
        if beat is None or beat.target not in ('', self._scale.name):
            return
        echo = p.Heartbeat(scale=self._scale.name, target=beat.scale, seq=beat.seq,
                           sent=beat.sent)
        self._echo_pub.publish(String(data=echo.to_json()))

    def destroy(self) -> None:
        for timer in self._timers:
            self._node.destroy_timer(timer)
        for sub in self._subs:
            self._node.destroy_subscription(sub)
        if self._scale.is_master:
            self._node.destroy_publisher(self._beat_pub)
            self._out.destroy()
        else:
            self._node.destroy_publisher(self._echo_pub)
        if self._server is not None:
            self._server.close()
