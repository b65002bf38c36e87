"""Pure CPU arithmetic of the scale monitor: deltas of cumulative CPU time, normalised.

The unit of the whole project is the percent of one reference core (a robot core = 100). A scale
declares its ``capacity_cpu`` in that unit; the monitor measures CPU seconds per second on the
CPUs the scale can actually use (``effective_cores``: the logical CPUs it may run on, fewer if a
cgroup quota caps it) and spreads the capacity evenly over them, so a fully busy scale reads its
capacity. When the effective CPUs equal the declared ``cores`` this is exactly ``capacity_cpu /
cores`` per core.

psutil's ``cpu_percent(interval=None)`` answers 0.0 on its first call and
``Process.cpu_percent`` exceeds 100 on several cores; both are avoided by working from cumulative
CPU seconds: the first sample of anything only primes it (no reading), later samples give the
CPU seconds spent per wall second, which may be above 1 on several cores.
"""

import math
from typing import Dict, Iterable, List, Mapping, Optional, Tuple

# Where a scale's CPU comes from (ScaleStatus.cpu_source).
CGROUP = 'cgroup'           # its cgroup's usage, when a CPU quota confines the scale
MACHINE = 'machine'         # the whole machine's busy time: the scale is alone on it
PROCESSES = 'processes'     # its agent's process tree: the machine is shared (single-machine)


def reference_percent(core_seconds_per_s: float, capacity_cpu: float,
                      effective_cores: float) -> float:
    """CPU seconds per second on the scale's own CPUs -> percent of one reference core."""
    if effective_cores <= 0 or not math.isfinite(effective_cores):
        raise ValueError(f'effective_cores must be positive, got {effective_cores!r}')
    return max(0.0, core_seconds_per_s) * capacity_cpu / effective_cores


def effective_cores(logical_cpus: int, quota_cores: Optional[float] = None) -> float:
    """The CPUs a scale can use: its logical CPUs, or fewer when a quota caps them."""
    if logical_cpus < 1:
        raise ValueError(f'logical_cpus must be >= 1, got {logical_cpus!r}')
    if quota_cores is not None and 0 < quota_cores < logical_cpus:
        return float(quota_cores)
    return float(logical_cpus)


def parse_proc_cgroup(text: str) -> Dict[str, str]:
    """/proc/<pid>/cgroup -> controller -> path ('' for the unified v2 hierarchy)."""
    out: Dict[str, str] = {}
    for line in text.splitlines():
        parts = line.split(':', 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == '':
            out.setdefault('', path)
        for c in controllers.split(','):
            if c:
                out[c] = path
    return out


def quota_cores_v1(quota_us_text: str, period_us_text: str) -> Optional[float]:
    """cpu.cfs_quota_us / cpu.cfs_period_us -> cores, None when unlimited (-1)."""
    try:
        quota, period = int(quota_us_text.strip()), int(period_us_text.strip())
    except ValueError:
        return None
    if quota <= 0 or period <= 0:
        return None
    return quota / period


def quota_cores_v2(cpu_max_text: str) -> Optional[float]:
    """cgroup v2 cpu.max ('max 100000' or '50000 100000') -> cores, None when unlimited."""
    parts = cpu_max_text.split()
    if len(parts) != 2 or parts[0] == 'max':
        return None
    try:
        quota, period = int(parts[0]), int(parts[1])
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def cpu_source(quota_confined: bool, shares_machine: bool) -> str:
    """The rule: a cgroup quota confines the scale -> its cgroup (the test-bed's scales, even on
    one machine); else, another scale's agent on this machine -> the agent's process tree
    (single-machine mode: the machine's busy time is every scale's); else the machine."""
    if quota_confined:
        return CGROUP
    return PROCESSES if shares_machine else MACHINE


def own_cpu_seconds(table: Mapping[int, Tuple[int, float]], roots: Iterable[int]
                    ) -> Dict[int, float]:
    """pid -> cumulative CPU seconds of every process in the trees of ``roots`` (the agent, and
    the nodes it supervises: an adopted node is no child of the agent), each pid once.

    ``table``: pid -> (parent pid, cumulative CPU seconds) of every live process. A root that is
    gone is left out; processes outside the trees (another scale's, a user's) never count.
    """
    children: Dict[int, List[int]] = {}
    for child, (parent, _) in table.items():
        children.setdefault(parent, []).append(child)
    out: Dict[int, float] = {}
    todo = [pid for pid in roots if pid in table]
    while todo:
        pid = todo.pop()
        if pid not in out:
            out[pid] = table[pid][1]
            todo.extend(children.get(pid, ()))
    return out


class CpuCounter:
    """CPU seconds per wall second from samples of one cumulative CPU-seconds counter."""

    def __init__(self):
        self._last: Optional[Tuple[float, float]] = None

    def update(self, now: float, cpu_seconds: float) -> Optional[float]:
        """Return the rate since the previous sample; None for the first (priming) sample."""
        last, self._last = self._last, (now, cpu_seconds)
        if last is None or now <= last[0]:
            return None
        # A counter that went backwards was reset (a cgroup recreated): prime again.
        if cpu_seconds < last[1]:
            return None
        return (cpu_seconds - last[1]) / (now - last[0])


class ProcessGroupCpu:
    """Per managed node: CPU seconds per second of its process and all its descendants.

    Samples map node -> pid -> cumulative CPU seconds of that pid. Each pid is tracked on its
    own: a pid seen for the first time only primes (its earlier CPU time was spent at an
    unknown moment), a pid that vanished simply stops counting, a reused pid whose counter went
    backwards is primed again. A node's first sample yields no reading, nor does a node with no
    live process (its pid is gone).
    """

    def __init__(self):
        self._pids: Dict[Tuple[str, int], float] = {}
        self._last_now: Optional[float] = None
        self._seen_nodes: Dict[str, bool] = {}

    def update(self, now: float,
               samples: Mapping[str, Mapping[int, float]]) -> Dict[str, float]:
        last_now, self._last_now = self._last_now, now
        dt = None if last_now is None or now <= last_now else now - last_now
        pids: Dict[Tuple[str, int], float] = {}
        out: Dict[str, float] = {}
        for node, per_pid in samples.items():
            spent = 0.0
            for pid, cpu_s in per_pid.items():
                key = (node, pid)
                pids[key] = cpu_s
                before = self._pids.get(key)
                if before is not None and cpu_s >= before:
                    spent += cpu_s - before
            if dt is not None and self._seen_nodes.get(node) and per_pid:
                out[node] = spent / dt
        self._pids = pids
        self._seen_nodes = {node: bool(pids_of) for node, pids_of in samples.items()}
        return out
