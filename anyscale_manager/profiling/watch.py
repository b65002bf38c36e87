"""The rclpy and psutil side of ``profile``: watch the graph, measure topics and processes.

Glue only: snapshots of the graph go into ``graph.GraphSeen``, every arrival into a
``stats.TopicMeter``, process CPU into a ``stats.CpuMeter``; nodes are matched to processes by
``processes.match_node``. The profiler is one node, ``anyscale_profile_<pid>``, with a raw
subscription per topic that has a connection (no deserialisation, as the agents' probes do).
"""

import math
import os
import socket
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import psutil
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..nodes.shutdown import shut_rclpy_down
from .graph import Endpoint, GraphSeen, PUB, SUB, TopicPlan, full_name, skipped_topic
from .processes import ProcessInfo, ProcessMatch, match_node, shared_processes
from .skeleton import HostInfo, NodeReport, Profile, TopicReport
from .stats import CpuMeter, CpuSummary, TopicMeter
from .suggest import LIFECYCLE_EVENT_TYPE

GRAPH_PERIOD_S = 0.5        # graph snapshots: new nodes and topics are picked up this fast
PROCESS_PERIOD_S = 1.0      # process table scans while some node has no process yet
TICK_S = 1.0                # rate and CPU readings, and the progress line


@dataclass
class WatchResult:
    graph: GraphSeen
    meters: Dict[str, TopicMeter]
    plans: Dict[str, TopicPlan]
    problems: Dict[str, str]                 # topic -> why it has no subscription
    matches: Dict[str, ProcessMatch]
    no_match: Dict[str, str]                 # node -> why no process was found
    cpu: CpuMeter
    cmdlines: Dict[int, Tuple[str, ...]]
    started: str
    duration_s: float
    last_snapshot_s: float
    interrupted: bool = False
    host: HostInfo = field(default_factory=lambda: host_info())

    def profile(self, name: str, domain_id: str) -> Profile:
        """The pure description of what was seen, for ``skeleton.render``."""
        shared = shared_processes(self.matches)
        nodes = []
        for node in self.graph.kept_nodes():
            match = self.matches.get(node)
            cpu = _node_cpu(self.cpu, match, shared) if match else None
            seen = self.graph.seen(node)
            gone = self.last_snapshot_s - seen.last_s if seen else 0.0
            others = sorted({o for pid in (match.pids if match else ()) for o in
                             shared.get(pid, ()) if o != node})
            nodes.append(NodeReport(
                name=node, cpu=cpu, process=match,
                cmdline=self.cmdlines.get(match.pids[0], ()) if match else (),
                no_cpu_reason=self.no_match.get(node, '') if not match else
                ('' if cpu else 'its process gave no reading'),
                shares_with=tuple(others), copies=seen.copies if seen else 1,
                gone_s=gone if gone > GRAPH_PERIOD_S * 2 else 0.0,
                lifecycle=self.graph.publishes_type(node, LIFECYCLE_EVENT_TYPE)))
        topics = {}
        for topic, plan in self.plans.items():
            meter = self.meters.get(topic)
            topics[topic] = TopicReport(topic=topic, msg_type=plan.msg_type,
                                        rate=meter.summary() if meter else None,
                                        problem=self.problems.get(topic, ''), types=plan.types)
        return Profile(name=name, host=self.host, domain_id=domain_id,
                       duration_s=round(self.duration_s, 1), started=self.started,
                       nodes=tuple(nodes), edges=tuple(self.graph.edges()), topics=topics,
                       interrupted=self.interrupted)


def _node_cpu(meter: CpuMeter, match: ProcessMatch, shared: Dict[int, Tuple[str, ...]]
              ) -> Optional[CpuSummary]:
    parts = [(meter.summary(pid), len(shared.get(pid, ())) or 1) for pid in match.pids]
    parts = [(s.share(k), k) for s, k in parts if s is not None]
    if not parts:
        return None
    length = min(len(s.readings) for s, _ in parts)
    return CpuSummary(tuple(sum(s.readings[i] for s, _ in parts) for i in range(length)))


def host_info() -> HostInfo:
    freq = None
    try:
        f = psutil.cpu_freq()
        freq = (f.max or f.current) / 1000.0 if f and (f.max or f.current) else None
    except (OSError, RuntimeError, AttributeError, NotImplementedError):
        pass
    return HostInfo(hostname=socket.gethostname(), cores=psutil.cpu_count() or 1,
                    clock_ghz=freq)


def _endpoint(info, topic: str, kind: str) -> Endpoint:
    qos = info.qos_profile
    return Endpoint(node=full_name(info.node_name, info.node_namespace), topic=topic,
                    msg_type=info.topic_type, kind=kind, gid=bytes(info.endpoint_gid),
                    reliable=qos.reliability == ReliabilityPolicy.RELIABLE,
                    transient_local=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL)


def snapshot(node) -> Tuple[List[str], List[Endpoint]]:
    """Every node's full name and every endpoint of every topic the profile keeps."""
    names = [full_name(n, ns) for n, ns in node.get_node_names_and_namespaces()]
    endpoints = []
    for topic, _types in node.get_topic_names_and_types():
        if topic == '/rosout':
            # Every node writes it: its GUIDs find the process of a node with no other topic.
            endpoints += [_endpoint(i, topic, PUB)
                          for i in node.get_publishers_info_by_topic(topic)]
            continue
        if skipped_topic(topic):
            continue
        endpoints += [_endpoint(i, topic, PUB) for i in node.get_publishers_info_by_topic(topic)]
        endpoints += [_endpoint(i, topic, SUB)
                      for i in node.get_subscriptions_info_by_topic(topic)]
    return names, endpoints


def process_table(exclude: int) -> Dict[int, ProcessInfo]:
    out = {}
    for proc in psutil.process_iter(['pid', 'ppid', 'cmdline']):
        info = proc.info
        if info['pid'] == exclude or not info.get('cmdline'):
            continue
        out[info['pid']] = ProcessInfo(info['pid'], info['ppid'] or 0, tuple(info['cmdline']))
    return out


def _absolute(pid: int, cmdline: Tuple[str, ...]) -> Tuple[str, ...]:
    """The command line with a relative program path (``.venv/bin/python``) made absolute
    from the process's folder, so that it still works as a launch command elsewhere."""
    if not cmdline or os.path.isabs(cmdline[0]) or os.sep not in cmdline[0]:
        return cmdline
    try:
        return (os.path.join(psutil.Process(pid).cwd(), cmdline[0]),) + cmdline[1:]
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return cmdline


def uses_fastdds(pid: int) -> Optional[bool]:
    """Whether the process maps a Fast DDS library (None: its maps cannot be read)."""
    try:
        with open(f'/proc/{pid}/maps', encoding='utf-8', errors='replace') as f:
            return any('libfastrtps' in line or 'libfastdds' in line for line in f)
    except OSError:
        return None


def _cpu_sample(procs: Dict[int, psutil.Process], pids) -> Dict[int, Dict[int, float]]:
    """Top pid -> {pid of it and of each descendant: cumulative user + system CPU seconds}."""
    out = {}
    for pid in pids:
        proc = procs.get(pid)
        try:
            if proc is None:
                proc = procs[pid] = psutil.Process(pid)
            family = [proc] + proc.children(recursive=True)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        per_pid = {}
        for p in family:
            try:
                t = p.cpu_times()
                per_pid[p.pid] = t.user + t.system
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                pass
        out[pid] = per_pid
    return out


def _own_host(node, timeout_s: float = 2.0) -> Optional[bytes]:
    """The host id in the profiler's own GUID (its /rosout writer), known locally at once."""
    own = full_name(node.get_name(), node.get_namespace())
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for info in node.get_publishers_info_by_topic('/rosout'):
            if full_name(info.node_name, info.node_namespace) == own:
                gid = bytes(info.endpoint_gid)
                return gid[2:4] if len(gid) >= 12 else None
        time.sleep(0.05)
    return None


class _Watcher:
    """The profiler's node and everything it accumulates; ``step`` does what is due."""

    def __init__(self, node, clock: Callable[[], float]):
        from ..nodes.monitors.common import import_message_class
        self._import = import_message_class
        self.node = node
        self.clock = clock
        self.graph = GraphSeen()
        self.meters: Dict[str, TopicMeter] = {}
        self.plans: Dict[str, TopicPlan] = {}
        self.problems: Dict[str, str] = {}
        self.matches: Dict[str, ProcessMatch] = {}
        self.no_match: Dict[str, str] = {}
        self.cmdlines: Dict[int, Tuple[str, ...]] = {}
        self.cpu = CpuMeter()
        self._procs: Dict[int, psutil.Process] = {}
        self._tried: set = set()      # nodes matched against a process table at least once
        self.own_host = _own_host(node)
        self.last_snapshot = -math.inf

    def look(self, now: float) -> None:
        """A graph snapshot; new topics get their subscription, new nodes a process."""
        self.graph.add(now, *snapshot(self.node))
        self.last_snapshot = now
        for topic, plan in self.graph.topic_plans().items():
            if topic not in self.plans:
                self.plans[topic] = plan
                self._subscribe(plan)

    def new_nodes(self) -> bool:
        return any(n not in self._tried for n in self.graph.kept_nodes())

    def find_processes(self) -> None:
        unmatched = [n for n in self.graph.kept_nodes() if n not in self.matches]
        if not unmatched:
            return
        table = process_table(exclude=os.getpid())
        for name in unmatched:
            self._tried.add(name)
            match, why = match_node(name, self.graph.gids(name), table, self.own_host,
                                    uses_fastdds)
            if match is None:
                self.no_match[name] = why
                continue
            self.matches[name] = match
            for pid in match.pids:
                self.cmdlines[pid] = _absolute(pid, table[pid].cmdline)

    def read(self, now: float) -> None:
        """One rate reading of every topic and one CPU reading of every process found."""
        for meter in self.meters.values():
            meter.sample(now)
        pids = sorted({pid for m in self.matches.values() for pid in m.pids})
        self.cpu.update(now, _cpu_sample(self._procs, pids))

    def _subscribe(self, plan: TopicPlan) -> None:
        try:
            cls = self._import(plan.msg_type)
        except ValueError as e:
            self.problems[plan.topic] = f'{e}: install its package where the profile runs'
            return
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10,
            reliability=ReliabilityPolicy.RELIABLE if plan.reliable
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if plan.transient_local
            else DurabilityPolicy.VOLATILE)
        meter = self.meters[plan.topic] = TopicMeter()
        clock = self.clock
        self.node.create_subscription(cls, plan.topic,
                                      lambda raw: meter.add(clock(), len(raw)), qos, raw=True)


def watch(duration_s: float, progress: Callable[[str], None] = lambda line: None,
          clock: Callable[[], float] = time.monotonic) -> WatchResult:
    """Watch the graph of this shell's ROS domain for ``duration_s`` seconds."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(f'anyscale_profile_{os.getpid()}', context=ctx,
                             start_parameter_services=False)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    started = time.strftime('%Y-%m-%d %H:%M:%S')
    interrupted = False
    w = None
    t0 = clock()
    end = t0 + duration_s
    last_read = t0
    try:
        w = _Watcher(node, clock)
        next_look = next_find = t0
        next_read = t0 + TICK_S
        while True:
            now = clock()
            if now >= end:
                break
            if now >= next_look:
                w.look(now)
                next_look = now + GRAPH_PERIOD_S
                if w.new_nodes():
                    next_find = now
            if now >= next_find:
                w.find_processes()
                next_find = now + PROCESS_PERIOD_S
            if now >= next_read:
                w.read(now)
                last_read = now
                progress(_progress_line(now - t0, duration_s, w.graph, w.meters))
                next_read += TICK_S
            executor.spin_once(timeout_sec=max(0.0, min(0.05, next_read - now,
                                                        next_look - now, end - now)))
        if clock() - last_read > TICK_S / 2:
            w.read(clock())     # the last stretch counts too
    except (KeyboardInterrupt, ExternalShutdownException):
        interrupted = True
    finally:
        executor.shutdown()
        node.destroy_node()
        shut_rclpy_down(context=ctx)
    if w is None:
        raise KeyboardInterrupt
    return WatchResult(graph=w.graph, meters=w.meters, plans=w.plans, problems=w.problems,
                       matches=w.matches, no_match=w.no_match, cpu=w.cpu, cmdlines=w.cmdlines,
                       started=started, duration_s=min(clock(), end) - t0,
                       last_snapshot_s=w.last_snapshot, interrupted=interrupted)


def _progress_line(elapsed_s: float, duration_s: float, graph: GraphSeen,
                   meters: Dict[str, TopicMeter]) -> str:
    return (f'profile: {elapsed_s:4.0f}/{duration_s:g} s: {len(graph.kept_nodes())} nodes, '
            f'{len(graph.edges())} connections on {len(meters)} topics, '
            f'{sum(m.messages for m in meters.values())} messages')
