"""ScaleMonitor: the CPU of a scale (its cgroup under a quota; else, when another scale's agent
runs on this machine, its agent's process tree; else the machine) and of the nodes serving on
it."""

import os
import time
from typing import Callable, Dict, Iterable, Mapping, Optional, Sequence, Set, Tuple

import psutil
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from ... import protocol as p
from ...agent import procs
from ...model.types import Deployment
from ...protocol_auth import Sealer
from ...runtime import cpu as cpu_math
from ..steady_loop import destroy_steady, steady_timer
from .common import Publishers, period_of, scale_of, status

FULL_WALK_EVERY = 8     # samples between two walks of every thread's children (8 s at 1 Hz)


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
        self.quota_confined = self.cgroup_usage_path is not None
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


def cores_note(scale, measured_cores: float, quota_confined: bool) -> str:
    """What the scale monitor says at its start of the CPUs it measures against the ``cores``
    the deployment declares: readings are spread over the CPUs measured, and the decider judges
    them against ``capacity_cpu`` whatever ``cores`` says."""
    name, declared, capacity = scale.name, scale.cores, scale.capacity_cpu
    offered = 'its CPU quota allows' if quota_confined else 'this machine has'
    cpus = f'{measured_cores:g} CPU{"" if measured_cores == 1 else "s"}'
    head = (f'scale monitor for {name}: {offered} {cpus}; a reading of '
            f'{capacity:g} (capacity_cpu) means all of them busy, one busy CPU reads '
            f'{capacity / measured_cores:.3g}, and the decider judges readings against '
            f'capacity_cpu {capacity:g}')
    if float(declared) == measured_cores:
        return head
    return (f'{head}. The deployment declares scales.{name}.cores: {declared}, not '
            f'{measured_cores:g}: if this scale should have {declared} '
            f'core{"" if declared == 1 else "s"}, give its agent a CPU quota of {declared} '
            f'(systemd CPUQuota={declared * 100}%, or cgroup cpu.max); if it has the {cpus}, '
            f'set scales.{name}.cores to match and capacity_cpu to what they are worth in '
            'reference-core percent')


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ''


class ScaleMonitor:
    """Publishes protocol.ScaleStatus on TOPIC_SCALE_STATUS and a scale DiagnosticStatus.

    ``pids``: the serving nodes' pids (their CPU by node). ``own_pids``: every process the
    agent supervises (standby copies, adopted nodes); ``shared_with``: the other scales whose
    agents run on this machine. While ``shared_with`` names one and no cgroup quota confines
    this scale, its CPU is the process tree of this agent and of ``own_pids``
    (``runtime.cpu.cpu_source``): the machine's busy time would be every scale's.
    """

    def __init__(self, node, deployment: Deployment, scale: str,
                 pids: Callable[[], Mapping[str, int]],
                 own_pids: Optional[Callable[[], Iterable[int]]] = None,
                 shared_with: Optional[Callable[[], Sequence[str]]] = None,
                 sealer: Optional[Sealer] = None):
        self._node = node
        self._scale = scale_of(deployment, scale)
        self._pids = pids
        self._own_pids = own_pids or (lambda: ())
        self._shared_with = shared_with or (lambda: ())
        period = period_of(deployment.monitoring.scale_rate_hz, 'scale_rate_hz')
        self._period = period
        self._sampled_at = -float('inf')
        self._system = _SystemCpu(os.getpid())
        self._total = cpu_math.CpuCounter()
        self._procs = cpu_math.ProcessGroupCpu()
        self._own = cpu_math.ProcessGroupCpu()
        self._walks, self._walked_roots, self._members = 0, set(), set()
        self.source = cpu_math.CGROUP if self._system.quota_confined else cpu_math.MACHINE
        self.sharing: Tuple[str, ...] = ()
        self._out = Publishers(node, p.TOPIC_SCALE_STATUS, sealer)
        self._group = MutuallyExclusiveCallbackGroup()
        self.last: Optional[p.ScaleStatus] = None
        self._sample()     # prime every counter now, so the first tick already has a reading
        self._timer = steady_timer(node, period, self._tick, callback_group=self._group)
        # What this process can use against what the file declares: a machine (or quota) of 2
        # CPUs running a scale declared with 1 core is not an error, but the readings then mean
        # something else than the file suggests, and the log says what to change.
        text = cores_note(self._scale, self._system.cores, self._system.quota_confined)
        if float(self._scale.cores) == self._system.cores:
            node.get_logger().info(f'{text} (measured from {self._system.source})')
        else:
            node.get_logger().warning(f'{text} (measured from {self._system.source})')

    def _choose_source(self) -> None:
        """Single-machine mode or not, from the other agents' reports; said when it changes."""
        try:
            sharing = tuple(self._shared_with())
        except Exception as e:  # the agent's callback; never let it kill the monitor
            self._node.get_logger().warning(f'scale monitor: shared_with() failed: {e}',
                                            throttle_duration_sec=10.0)
            sharing = self.sharing
        source = cpu_math.cpu_source(self._system.quota_confined, bool(sharing))
        if (source, sharing) == (self.source, self.sharing):
            return
        name = self._scale.name
        others = ', '.join(sharing)
        if source == cpu_math.PROCESSES:
            text = (f'scale {name} shares this machine with {others}: single-machine mode, '
                    f"the CPU of {name} is its agent's own processes (pid {os.getpid()}, its "
                    "monitors and the nodes it supervises), not the machine's")
        elif sharing:
            text = (f'scale {name} shares this machine with {others}; a CPU quota confines '
                    f'it, so its CPU is its cgroup usage ({self._system.source})')
        else:
            where = 'its cgroup usage' if source == cpu_math.CGROUP else 'the whole machine'
            text = (f'scale {name} no longer shares this machine with another scale: its CPU '
                    f'is {where} again ({self._system.source})')
        self._node.get_logger().info(text)
        self.source, self.sharing = source, sharing

    def _sample(self) -> Tuple[Optional[float], Dict[str, float]]:
        now = self._sampled_at = time.monotonic()
        self._choose_source()
        own = self.source == cpu_math.PROCESSES
        if own:
            self._total = cpu_math.CpuCounter()     # primed afresh when the mode ends
        busy = None if own else self._system.busy_seconds()
        total = None if busy is None else self._total.update(now, busy)
        try:
            pids = dict(self._pids())
        except Exception as e:  # the agent's callback; never let it kill the monitor
            self._node.get_logger().warning(f'scale monitor: pids() failed: {e}',
                                            throttle_duration_sec=10.0)
            pids = {}
        # One pass over the trees of the nodes (and, in single-machine mode, of this agent)
        # for every figure: walking each node's tree with psutil rescans /proc once per node,
        # which was half the agent's CPU; reading every process of the machine costs a few
        # milliseconds a sample where the trees take a fraction of one.
        leaders = {name: pid for name, pid in pids.items() if isinstance(pid, int) and pid > 0}
        roots: Set[int] = set()
        if own:
            try:
                roots = {os.getpid(), *(pid for pid in self._own_pids()
                                        if isinstance(pid, int) and pid > 0)}
            except Exception as e:  # the agent's callback; never let it kill the monitor
                self._node.get_logger().warning(f'scale monitor: own_pids() failed: {e}',
                                                throttle_duration_sec=10.0)
                roots = {os.getpid()}
        table = self._walk(roots | set(leaders.values())) if leaders or own else {}
        samples = procs.tree_cpu_seconds(table, leaders) if leaders else {}
        if own:
            # The first sample after a switch only primes the counter: no reading then.
            total = self._own.update(now, {'scale': cpu_math.own_cpu_seconds(table, roots)}
                                     ).get('scale')
        else:
            self._own = cpu_math.ProcessGroupCpu()
        return total, self._procs.update(now, samples)

    def _walk(self, roots: Set[int]) -> Dict[int, Tuple[int, float]]:
        """The trees of ``roots``: every thread's children every FULL_WALK_EVERY samples, or
        when the roots change; else the main threads' children and the processes of the last
        full walk (procs.tree_table), a fifth of the reads for nodes of 15 threads."""
        self._walks += 1
        full = roots != self._walked_roots or self._walks >= FULL_WALK_EVERY
        table = procs.tree_table(roots, self._members, all_threads=full)
        if full:
            self._walks, self._walked_roots = 0, roots
        self._members = set(table)
        return table

    def _ref(self, core_seconds_per_s: float) -> float:
        return cpu_math.reference_percent(core_seconds_per_s, self._scale.capacity_cpu,
                                          self._system.cores)

    def _tick(self) -> None:
        if time.monotonic() - self._sampled_at < 0.5 * self._period:
            # A timer that fired late fires its next call early, and over a few milliseconds
            # one of the kernel's 10 ms CPU ticks reads as a whole core: a scale of three light
            # processes, read in steps of 4 of its 200 at 4 Hz, once read 86 (an interval of
            # about 50 ms). The next tick measures the longer interval.
            return
        total, by_node = self._sample()
        if total is None:
            return
        capacity = self._scale.capacity_cpu
        cpu_total = min(self._ref(total), capacity)
        message = p.ScaleStatus(
            scale=self._scale.name, stamp=time.time(), cpu_total=cpu_total,
            capacity_cpu=capacity,
            cpu_by_node={name: self._ref(v) for name, v in sorted(by_node.items())},
            mem_percent=procs.memory_percent(),
            load_1m=float(os.getloadavg()[0]), cpu_source=self.source,
            cores=self._system.cores)
        self.last = message
        self._out.send(message)
        level = p.WARN if cpu_total >= 0.9 * capacity else p.OK
        text = (f'CPU {cpu_total:.0f} of {capacity:.0f}' +
                (' (near capacity)' if level == p.WARN else ''))
        values = {'cpu_total': cpu_total, 'capacity_cpu': capacity,
                  'mem_percent': message.mem_percent, 'load_1m': message.load_1m,
                  'cpu_source': self.source, 'shares_machine_with': ', '.join(self.sharing)}
        values.update({f'cpu.{k}': v for k, v in message.cpu_by_node.items()})
        name = f'anyscale/scale/{self._scale.name}'
        if self._out.diagnostics_due(name, level):
            self._out.send_diagnostics([status(name, level, text, self._scale.host, values)])

    def destroy(self) -> None:
        destroy_steady(self._node, self._timer)
        self._out.destroy()
