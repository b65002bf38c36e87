"""Which process on this host runs a ROS node. Pure: the process table and the graph in.

Two pieces of evidence, in this order:

1. **The DDS endpoint GUID** (Fast DDS, the Jazzy default): the GUID prefix of every endpoint a
   node owns holds the eProsima vendor id (bytes 0-1), a host id (2-3) and the low 16 bits of
   the process id (4-5). A node's process is the local process whose pid has those low bits. It
   is taken when exactly one local process qualifies and either the host id is this host's (the
   profiler's own endpoints carry it) or that process maps a Fast DDS library or names the node
   on its command line. When several qualify (pids more than 65536 apart), the same two tests
   pick one or none.
2. **The command line's ``__node:=NAME`` remap** (``--ros-args -r __node:=NAME``, as launch files
   and ``ros2 run ... --ros-args -r __node:=`` write it), with ``__ns:=`` when given: every
   process whose command line renames a node to this name and namespace, less those whose
   parent is among them (``ros2 run`` and its child carry the same arguments).

Neither works for a node of another host (no CPU is reported for it) or another DDS vendor than
Fast DDS (the remap still works). A node renamed in its code, with no remap on its command line,
running under another DDS, is not found: the file says so.
"""

import re
from dataclasses import dataclass
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Set, Tuple

from .graph import base_name, namespace_of

FASTDDS_VENDOR = b'\x01\x0f'
REMAP_RE = re.compile(r'^(?:[A-Za-z0-9_/~]+:)?__(node|name|ns):=(.+)$')
GUID = 'its DDS endpoint GUID'
REMAP = 'the __node:= remap on its command line'


@dataclass(frozen=True)
class ProcessInfo:
    pid: int
    ppid: int
    cmdline: Tuple[str, ...]


@dataclass(frozen=True)
class ProcessMatch:
    """The process(es) of one node and how they were found."""

    pids: Tuple[int, ...]
    how: str


def guid_pid16(gid: bytes) -> Optional[int]:
    """The low 16 bits of the process id in a Fast DDS GUID; None for another vendor."""
    if len(gid) < 12 or gid[:2] != FASTDDS_VENDOR:
        return None
    return gid[4] | gid[5] << 8


def guid_host(gid: bytes) -> Optional[bytes]:
    """The host id in a Fast DDS GUID; None for another vendor."""
    if len(gid) < 12 or gid[:2] != FASTDDS_VENDOR:
        return None
    return bytes(gid[2:4])


def remapped(cmdline: Sequence[str]) -> Tuple[Optional[str], Optional[str]]:
    """(node name, namespace) a command line's ``__node:=`` / ``__ns:=`` remaps set, or None."""
    node = ns = None
    for arg in cmdline:
        m = REMAP_RE.match(arg)
        if not m:
            continue
        if m.group(1) == 'ns':
            ns = m.group(2)
        else:
            node = m.group(2)
    if ns is not None and not ns.startswith('/'):
        ns = '/' + ns
    return node, ns


def names_node(info: ProcessInfo, node: str) -> bool:
    """Whether a command line names the node: a remap to it, or its base name as an argument."""
    name, _ = remapped(info.cmdline)
    return name == base_name(node) or base_name(node) in info.cmdline[1:]


def _by_remap(node: str, processes: Mapping[int, ProcessInfo]) -> List[int]:
    want_name, want_ns = base_name(node), namespace_of(node).rstrip('/')
    exact, no_ns = set(), set()
    for pid, info in processes.items():
        name, ns = remapped(info.cmdline)
        if name == want_name and ns is None:
            no_ns.add(pid)      # its namespace is set elsewhere (its code): maybe this one
        elif name == want_name and ns.rstrip('/') == want_ns:
            exact.add(pid)
    found = exact or no_ns
    # The top of each chain only: its CPU counts its descendants.
    return sorted(pid for pid in found if processes[pid].ppid not in found)


def _by_guid(node: str, pid16: int, local: bool, processes: Mapping[int, ProcessInfo],
             uses_fastdds: Callable[[int], Optional[bool]]) -> Optional[int]:
    candidates = [pid for pid in processes if pid & 0xffff == pid16]
    if len(candidates) > 1:
        candidates = [pid for pid in candidates if uses_fastdds(pid)] or \
            [pid for pid in candidates if names_node(processes[pid], node)]
    if len(candidates) != 1:
        return None
    pid = candidates[0]
    if local or uses_fastdds(pid) or names_node(processes[pid], node):
        return pid
    return None


def match_node(node: str, gids: Iterable[bytes], processes: Mapping[int, ProcessInfo],
               own_host: Optional[bytes],
               uses_fastdds: Callable[[int], Optional[bool]] = lambda pid: None,
               ) -> Tuple[Optional[ProcessMatch], str]:
    """The node's process(es) on this host, or None with the reason.

    ``processes``: the local process table (the profiler's own process left out);
    ``own_host``: the host id of the profiler's own GUIDs; ``uses_fastdds(pid)``: whether the
    process maps a Fast DDS library (None: cannot tell)."""
    pids: Set[int] = set()
    vendors = set()
    for gid in gids:
        pid16 = guid_pid16(gid)
        if pid16 is None:
            vendors.add(bytes(gid[:2]).hex())
            continue
        pid = _by_guid(node, pid16, guid_host(gid) == own_host, processes, uses_fastdds)
        if pid is not None:
            pids.add(pid)
    if pids:
        return ProcessMatch(tuple(sorted(pids)), GUID), ''
    remap = _by_remap(node, processes)
    if remap:
        return ProcessMatch(tuple(remap), REMAP), ''
    if vendors:
        return None, (f'its GUIDs are not Fast DDS ones (vendor {", ".join(sorted(vendors))}) '
                      f'and no command line here has __node:={base_name(node)}')
    return None, ('no process on this host has its DDS GUID or __node:='
                  f'{base_name(node)} on its command line: another host?')


def shared_processes(matches: Mapping[str, ProcessMatch]) -> Dict[int, Tuple[str, ...]]:
    """pid -> the nodes found in it, for every pid that hosts more than one node."""
    by_pid: Dict[int, List[str]] = {}
    for node, match in matches.items():
        for pid in match.pids:
            by_pid.setdefault(pid, []).append(node)
    return {pid: tuple(sorted(nodes)) for pid, nodes in by_pid.items() if len(nodes) > 1}
