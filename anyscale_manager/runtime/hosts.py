"""Scales that share one machine: single-machine mode, told from the agents' reports.

Pure (no ROS, time passed in). Every agent reports the identity of the machine it runs on
(``AgentState.host_id``, with ``host``, its host name, for people). Scales whose agents report
the same identity share one machine: that is single-machine mode, how every user starts (two
agents on a laptop). Nothing needs declaring: the agents tell.

The identity is the kernel's boot id (``/proc/sys/kernel/random/boot_id``): a random number
drawn at each boot and shared by every process of that kernel, containers included, and not by
a virtual machine (a kernel of its own). That is exactly the set of processes that share CPUs
and a loopback interface. Without it, ``/etc/machine-id``; without either, the host name.

What the mode changes (docs/monitoring.md, docs/decider.md): a scale that no cgroup quota
confines measures its CPU as its agent's own process tree, not the machine's (``cpu.py``); and a
link between two such scales is loopback, whose measured bandwidth the decider caps at the
link's nominal (``constraints.py``: that cap holds for every link).
"""

from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

MAX_HOST_TEXT = 256


def identity_from(boot_id: str = '', machine_id: str = '', host_name: str = '') -> str:
    """The identity an agent reports: ``boot:<boot id>``, else ``machine:<machine id>``, else
    ``name:<host name>``; '' when none is known."""
    for kind, value in (('boot', boot_id), ('machine', machine_id), ('name', host_name)):
        value = value.strip()
        if value:
            return f'{kind}:{value}'[:MAX_HOST_TEXT]
    return ''


def shared_groups(hosts: Mapping[str, str], order: Sequence[str] = ()
                  ) -> Tuple[Tuple[str, ...], ...]:
    """Groups of two or more scales that report one machine (``hosts``: scale -> host id;
    an empty id says nothing). Scales in ``order`` (the deployment's), then by name."""
    rank = {name: i for i, name in enumerate(order)}
    by_host: Dict[str, List[str]] = {}
    for scale, host_id in hosts.items():
        if host_id:
            by_host.setdefault(host_id, []).append(scale)
    groups = [tuple(sorted(scales, key=lambda s: (rank.get(s, len(rank)), s)))
              for scales in by_host.values() if len(scales) > 1]
    groups.sort(key=lambda g: (rank.get(g[0], len(rank)), g[0]))
    return tuple(groups)


def names_of(scales: Iterable[str], names: Mapping[str, str]) -> str:
    """The host names the scales report, each once: 'laptop' or 'a / b' (containers)."""
    seen: List[str] = []
    for s in scales:
        name = names.get(s, '')
        if name and name not in seen:
            seen.append(name)
    return ' / '.join(seen) or 'unnamed'


def describe(group: Sequence[str], names: Mapping[str, str]) -> str:
    """'robot, laptop on host vm': one group of scales that share a machine."""
    return f'{", ".join(group)} on host {names_of(group, names)}'


MEANING = ("each scale that no cgroup quota confines measures its CPU as its own agent's "
           "process tree (the agent, its monitors and the nodes it runs), not the machine's, "
           "so a load one scale causes is not taken for another's; a link between them "
           'stays on this machine (loopback measures memory copies): a measured bandwidth '
           'above its nominal is capped at the nominal')


class HostBook:
    """The machine each other scale's agent last reported, and when (an agent's view)."""

    def __init__(self):
        self._heard: Dict[str, Tuple[str, str, float]] = {}   # scale -> (id, name, when)

    def heard(self, scale: str, host_id: Optional[str], host_name: Optional[str],
              now: float) -> None:
        self._heard[scale] = (host_id or '', host_name or '', now)

    def sharing(self, scale: str, host_id: str, now: float, max_age_s: float
                ) -> Tuple[str, ...]:
        """The other scales whose agents, heard within ``max_age_s``, report ``host_id``."""
        if not host_id:
            return ()
        return tuple(sorted(s for s, (other, _, when) in self._heard.items()
                            if s != scale and other == host_id and now - when <= max_age_s))


class SingleMachineWatch:
    """The decider's view: which scales share a machine, said when that changes (not every
    turn), and a one-line summary for its diagnostics."""

    def __init__(self, order: Sequence[str] = ()):
        self.order = tuple(order)
        self.groups: Tuple[Tuple[str, ...], ...] = ()
        self.names: Dict[str, str] = {}

    def update(self, hosts: Mapping[str, Tuple[str, str]]) -> Optional[str]:
        """``hosts``: scale -> (host id, host name) as its agent last reported. The text to
        log and publish when the groups changed, else None."""
        groups = shared_groups({s: h[0] for s, h in hosts.items()}, self.order)
        names = {s: h[1] for s, h in hosts.items()}
        if groups == self.groups:
            self.names = names
            return None
        before, self.groups, self.names = self.groups, groups, names
        if groups:
            where = '; '.join(describe(g, names) for g in groups)
            return f'single-machine mode: scales {where} share one machine: {MEANING}'
        return ('single-machine mode ended: scales ' + '; '.join(', '.join(g) for g in before)
                + " no longer report one machine; each scale's CPU is its machine's (or its "
                "cgroup's) again")

    def summary(self) -> str:
        """'robot, laptop on host vm' (several groups joined by '; '), '' when none."""
        return '; '.join(describe(g, self.names) for g in self.groups)


__all__ = ['HostBook', 'MEANING', 'SingleMachineWatch', 'describe', 'identity_from',
           'names_of', 'shared_groups']
