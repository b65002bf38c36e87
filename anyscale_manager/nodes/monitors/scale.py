"""ScaleMonitor: the CPU of a scale (its cgroup under a quota, else the machine) and of
the nodes serving on it."""

import os
import time
from typing import Callable, Dict, Mapping, Optional, Tuple

import psutil
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from ... import protocol as p
from ...agent import procs
from ...model.types import Deployment
from ...runtime import cpu as cpu_math
from .common import Publishers, period_of, scale_of, status


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
        self._scale = scale_of(deployment, scale)
        self._pids = pids
        period = period_of(deployment.monitoring.scale_rate_hz, 'scale_rate_hz')
        self._system = _SystemCpu(os.getpid())
        self._total = cpu_math.CpuCounter()
        self._procs = cpu_math.ProcessGroupCpu()
        self._out = Publishers(node, p.TOPIC_SCALE_STATUS)
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
