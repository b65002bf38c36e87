"""The heartbeat socket of a link monitor: datagrams stamped with the kernel's arrival time.

A link is judged down when no echo has arrived for a few heartbeat periods. On a starved scale
(a CPU quota filled, a discovery storm) the process that reads the echoes can run late by more
than that, and a thread that stamps each echo when it gets to read it would call a working link
down. The kernel stamps every datagram as it arrives (SO_TIMESTAMPNS), so the judge reads
whatever is waiting just before it judges and knows when each echo really came.
"""

import math
import socket
import struct
import time
from typing import Callable, List, Optional, Tuple

from .clocks import clock_offset_s

# Linux's SO_TIMESTAMPNS (asm-generic, as on x86_64 and aarch64); the control message that
# carries the stamp has the same number. Python's socket module does not name it.
SO_TIMESTAMPNS = 35
SCM_TIMESTAMPNS = SO_TIMESTAMPNS
_TIMESPEC = struct.Struct('@ll')
# At most this many datagrams are read per drain, so that a flood cannot hold the executor.
DRAIN_LIMIT = 256


class EchoSocket:
    """A non-blocking UDP socket bound to an ephemeral port. ``drain()`` returns what has
    arrived, each with its arrival time on the monotonic clock: the kernel's stamp where the
    platform gives one, else the time it was read (``kernel_stamps`` says which)."""

    def __init__(self, max_datagram: int,
                 monotonic: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time):
        self._max = max_datagram
        self._monotonic = monotonic
        self._wall = wall
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(('', 0))
        self._sock.setblocking(False)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self.kernel_stamps = True
        except OSError:
            self.kernel_stamps = False
        self._ancillary = socket.CMSG_SPACE(_TIMESPEC.size)

    def sendto(self, data: bytes, address: Tuple[str, int]) -> None:
        self._sock.sendto(data, address)

    def drain(self, limit: int = DRAIN_LIMIT) -> List[Tuple[float, bytes]]:
        """Every datagram waiting (up to ``limit``), oldest first, as (arrival, payload). The
        kernel's wall-clock stamps are put on the monotonic clock with one offset per drain:
        one read per datagram would shift each by the time between its two clock readings, and
        two datagrams microseconds apart could come out in the wrong order."""
        got: List[Tuple[float, bytes]] = []
        offset: Optional[float] = None
        while len(got) < limit:
            try:
                data, ancillary, _flags, _peer = self._sock.recvmsg(self._max + 1,
                                                                    self._ancillary)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break       # e.g. an ICMP error queued by a send to an unreachable peer
            if offset is None:
                offset = clock_offset_s(3, self._monotonic, self._wall)
            got.append((self._arrival(ancillary, offset), data))
        return got

    def _arrival(self, ancillary, offset: float) -> float:
        now = self._monotonic()
        stamp = _kernel_stamp(ancillary)
        if stamp is None or not math.isfinite(stamp - offset):
            return now
        # The kernel stamps on the wall clock; never later than now (a clock stepped back).
        return min(stamp - offset, now)

    def close(self) -> None:
        self._sock.close()


def _kernel_stamp(ancillary) -> Optional[float]:
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SCM_TIMESTAMPNS \
                and len(data) >= _TIMESPEC.size:
            seconds, nanoseconds = _TIMESPEC.unpack_from(data)
            return seconds + nanoseconds / 1e9
    return None
