"""A killed node's DDS ports, held for a few seconds so that its replacement takes others.

Fast DDS (the default ROS 2 Jazzy middleware) gives a participant the lowest free participant
id of its domain and derives its unicast UDP ports from it: ``7410 + 250 * domain + 2 * id``
for discovery and one more for data. A node that is killed (SIGKILL, a crash, the OOM killer)
cannot say goodbye, and a process started at once takes the same id and the same ports; the
participants that knew the dead one then leave the newcomer's readers unmatched for about 3 s
(measured on Fast DDS 2.14, one publisher at 20 Hz on loopback: a subscriber started 0.1 s
after the previous one's SIGKILL heard its first message 2.65-3.6 s after it was up, in 5 of 5
starts; 0.06-0.4 s when the dead one's ports were held meanwhile, or when it started 4 s later;
after a SIGINT, 0.06-0.09 s). A node restarted in place would stay silent that long.

So the supervisor notes the unicast ports of each node's processes once the node is up (read
from /proc: the sockets of the session's processes, kept when they lie in the participant
range of the node's ``ROS_DOMAIN_ID``; multicast and ephemeral ports are never touched), and
when the node dies without a clean exit it binds them for ``HOLD_S``: the restarted node's
participant takes the next free id. A port that cannot be bound (someone took it) is skipped.
Pure socket and /proc code, no ROS.
"""

import os
import socket
from typing import Dict, FrozenSet, Iterable, List, Optional, Tuple

# Longer than the ~3 s during which a newcomer on a dead participant's ports goes unmatched.
HOLD_S = 5.0
PORT_BASE, DOMAIN_GAIN, UNICAST_OFFSET = 7400, 250, 10      # the RTPS well-known ports


def participant_range(domain: int) -> range:
    """The unicast (discovery and data) ports of every participant id of ``domain``."""
    start = PORT_BASE + DOMAIN_GAIN * domain
    return range(start + UNICAST_OFFSET, start + DOMAIN_GAIN)


def _socket_inodes(pid: int) -> List[int]:
    inodes = []
    try:
        names = os.listdir(f'/proc/{pid}/fd')
    except OSError:
        return inodes
    for name in names:
        try:
            target = os.readlink(f'/proc/{pid}/fd/{name}')
        except OSError:
            continue
        if target.startswith('socket:['):
            inodes.append(int(target[8:-1]))
    return inodes


def _udp_table(pid: int) -> Dict[int, int]:
    """inode -> local port of the IPv4 UDP sockets in ``pid``'s network namespace."""
    table = {}
    try:
        with open(f'/proc/{pid}/net/udp') as f:
            lines = f.read().splitlines()[1:]
    except OSError:
        return table
    for line in lines:
        fields = line.split()
        if len(fields) < 10:
            continue
        try:
            table[int(fields[9])] = int(fields[1].rsplit(':', 1)[1], 16)
        except ValueError:
            continue
    return table


def unicast_ports(pids: Iterable[int], domain: int) -> FrozenSet[int]:
    """The participant-range UDP ports bound by the sockets of ``pids``."""
    wanted = participant_range(domain)
    found = set()
    for pid in pids:
        inodes = _socket_inodes(pid)
        if not inodes:
            continue
        table = _udp_table(pid)
        found.update(table[i] for i in inodes if i in table and table[i] in wanted)
    return frozenset(found)


def domain_of(environ: Dict[str, str]) -> int:
    """``ROS_DOMAIN_ID`` as a participant's ports use it (0 when unset or not a number)."""
    try:
        return int(environ.get('ROS_DOMAIN_ID', '') or 0)
    except ValueError:
        return 0


class PortHold:
    """Binds ports for a while so that no new participant takes them (see the module doc)."""

    def __init__(self, hold_s: float = HOLD_S):
        self.hold_s = hold_s
        self._held: List[Tuple[float, socket.socket]] = []

    def hold(self, ports: Iterable[int], now: float) -> List[int]:
        """Bind each port until ``now + hold_s``; returns the ports now held."""
        held = []
        for port in sorted(ports):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                s.bind(('0.0.0.0', port))
            except OSError:
                s.close()
                continue
            self._held.append((now + self.hold_s, s))
            held.append(port)
        return held

    def release(self, now: Optional[float] = None) -> int:
        """Close the sockets whose time is up (all of them without ``now``); how many."""
        keep, closed = [], 0
        for until, s in self._held:
            if now is not None and now < until:
                keep.append((until, s))
            else:
                s.close()
                closed += 1
        self._held = keep
        return closed

    def sockets(self) -> List[socket.socket]:
        """The sockets that hold the ports (to be passed on across an exec)."""
        return [s for _, s in self._held]

    def adopt(self, fds: Iterable[int], now: float) -> List[int]:
        """Hold until ``now + hold_s`` the bound sockets of ``fds`` (inherited from the process
        this one replaced); returns their ports. A descriptor that is not a bound UDP socket is
        closed and skipped."""
        ports = []
        for fd in fds:
            try:
                s = socket.socket(fileno=fd)
                port = s.getsockname()[1]
            except OSError:
                try:
                    os.close(fd)
                except OSError:
                    pass
                continue
            if s.type != socket.SOCK_DGRAM or not port:
                s.close()
                continue
            self._held.append((now + self.hold_s, s))
            ports.append(port)
        return ports

    def held(self) -> FrozenSet[int]:
        return frozenset(s.getsockname()[1] for _, s in self._held)

    def next_release(self) -> Optional[float]:
        """When the first held port is due to be released (None: none held)."""
        return min((until for until, _ in self._held), default=None)
