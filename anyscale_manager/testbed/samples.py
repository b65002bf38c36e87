"""The chaos soak's samples of the system's processes, taken while the faults run.

The CPU and memory of the decider and the agents (every ``SAMPLE_RESOURCES_S``), and the live
processes of each managed node on each scale (every ``SAMPLE_PROCESSES_S``), found by the
markers every agent puts in its nodes' environment, whoever supervises them now. More than one
live process of a node on one scale for ``DUPLICATE_PROCESS_S`` is a duplicate: a second copy,
not a restart. The census is ``count``, pure, fed by ``node_processes``.
"""

from typing import Callable, Dict, List, Mapping, Optional, Tuple

import psutil

from ..agent.catalogue import ENV_NODE, ENV_SCALE
from . import chaos

SAMPLE_RESOURCES_S = 5.0
SAMPLE_PROCESSES_S = 1.0
# Two process samples of one node on one scale this far apart: a second copy, not a restart.
DUPLICATE_PROCESS_S = 3.0


def node_processes() -> Optional[Dict[Tuple[str, str], int]]:
    """Live processes per (node, scale) among this process's descendants; None when they
    cannot be listed."""
    counts: Dict[Tuple[str, str], int] = {}
    try:
        children = psutil.Process().children(recursive=True)
    except psutil.Error:
        return None
    for child in children:
        try:
            if child.status() == psutil.STATUS_ZOMBIE:
                continue
            env = child.environ()
        except psutil.Error:
            continue
        node, scale = env.get(ENV_NODE), env.get(ENV_SCALE)
        if node and scale:
            counts[(node, scale)] = counts.get((node, scale), 0) + 1
    return counts


class Samples:
    """What the soak sampled: ``resources`` (chaos.Resources), ``processes`` ((t, live
    processes per node) each census) and ``duplicates`` (one entry per node, scale and start
    of a duplicate), each duplicate also said through ``log``."""

    def __init__(self, log: Callable[[str], None] = print):
        self.log = log
        self.resources = chaos.Resources()
        self.processes: List[Tuple[float, Dict[str, int]]] = []
        self.duplicates: List[Dict[str, object]] = []
        self._dup_since: Dict[Tuple[str, str], float] = {}

    def add_resources(self, now: float, pids: Mapping[str, int]) -> None:
        """CPU seconds and RSS of each named process (``pids``: name -> pid) at ``now``."""
        for name, pid in pids.items():
            try:
                ps = psutil.Process(pid)
                t = ps.cpu_times()
                self.resources.add(now, name, ps.pid, t.user + t.system, ps.memory_info().rss)
            except psutil.Error:
                continue

    def add_processes(self, now: float) -> None:
        """A census of the nodes' live processes at ``now``."""
        counts = node_processes()
        if counts is not None:
            self.count(now, counts)

    def count(self, now: float, counts: Mapping[Tuple[str, str], int]) -> None:
        """Take one census (live processes per (node, scale)) at ``now``."""
        per_node: Dict[str, int] = {}
        for (node, _), n in counts.items():
            per_node[node] = per_node.get(node, 0) + n
        self.processes.append((now, per_node))
        for key in list(self._dup_since):
            if counts.get(key, 0) <= 1:
                del self._dup_since[key]
        for key, n in counts.items():
            if n > 1:
                since = self._dup_since.setdefault(key, now)
                if now - since >= DUPLICATE_PROCESS_S and not any(
                        x['node'] == key[0] and x['scale'] == key[1] and x['since'] == since
                        for x in self.duplicates):
                    self.duplicates.append({'node': key[0], 'scale': key[1],
                                            'since': since, 'count': n})
                    self.log(f'!! {n} live processes of {key[0]} on the {key[1]} for '
                             f'{now - since:.1f} s')


__all__ = ['DUPLICATE_PROCESS_S', 'SAMPLE_PROCESSES_S', 'SAMPLE_RESOURCES_S', 'Samples',
           'node_processes']
