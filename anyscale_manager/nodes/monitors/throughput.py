"""The link throughput probe: a bulk TCP burst (probe_throughput) and its receiver
(ProbeServer)."""

import json
import select
import socket
import struct
import threading
import time
from typing import Callable, List, Optional, Tuple

from ...runtime.bandwidth import steady_throughput_bps

# 8 bytes, the requested duration in ms (uint32), the length (uint16) of a JSON object naming
# the deployment and scale the sender means to measure, then that object: a probe server of
# another deployment or scale (a port shared by mistake) refuses rather than be measured.
PROBE_MAGIC = b'ASBWPRB2'
MAX_IDENTITY = 1024
REQUEST_S = 2.0                      # the whole request must arrive within this
PROBE_MAX_DURATION_S = 2.0           # the server never receives longer than this
PROBE_CHUNK = 64 * 1024
PROBE_RECV_BYTES = 1 << 20
ACK_READ_S = 0.02                    # how often the sender reads when the link last acked
# struct tcp_info (linux/tcp.h): 8 one-byte fields, then 32-bit fields; tcpi_last_ack_recv (ms
# since the last ACK arrived) is the 13th of those.
_TCP_INFO_LAST_ACK_RECV = 8 + 12 * 4


def last_ack_age_s(sock: socket.socket) -> Optional[float]:
    """Seconds since the kernel last received an ACK on a TCP socket (Linux TCP_INFO), or
    None where that cannot be read."""
    try:
        info = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 104)
        return struct.unpack_from('I', info, _TCP_INFO_LAST_ACK_RECV)[0] / 1000.0
    except (OSError, AttributeError, struct.error):
        return None


def probe_throughput(host: str, port: int, duration_s: float, timeout_s: float = 3.0,
                     deployment: str = '', scale: str = '',
                     acked: Optional[Callable[[float], None]] = None) -> float:
    """Send a bulk TCP burst to a probe server for ``duration_s``; its measured bytes/s.

    The receiver times the transfer and answers with one JSON line; the sender keeps the pipe
    full until that answer arrives, so the measurement is bounded by the receiver's clock and
    not by how much the local socket buffers swallowed. Raises OSError, or ValueError also
    when the server there is not ``scale`` of ``deployment``. ``acked`` is called, every
    ACK_READ_S while the burst runs, with when (time.monotonic) the link last acknowledged its
    data: the burst's own proof that the link carries, while the heartbeats wait behind it.
    """
    duration_ms = int(min(max(duration_s, 0.05), PROBE_MAX_DURATION_S) * 1000)
    deadline = time.monotonic() + duration_ms / 1000.0 + timeout_s
    chunk = bytes(PROBE_CHUNK)
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        identity = json.dumps({'d': deployment, 'to': scale}).encode('utf-8')
        if len(identity) > MAX_IDENTITY:
            raise ValueError(f'throughput probe to {host}:{port}: deployment and scale names '
                             f'too long ({len(identity)} bytes > {MAX_IDENTITY})')
        sock.sendall(PROBE_MAGIC + struct.pack('!IH', duration_ms, len(identity)) + identity)
        sock.setblocking(False)
        reply = b''
        read_ack = -float('inf')
        while time.monotonic() < deadline:
            now = time.monotonic()
            if acked is not None and now - read_ack >= ACK_READ_S:
                read_ack = now
                age = last_ack_age_s(sock)
                if age is not None:
                    acked(now - age)
            readable, writable, _ = select.select([sock], [sock], [], ACK_READ_S)
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
        what = 'no answer (a server of an older version, or not a probe server?)' if not reply \
            else f'bad answer {reply[:60]!r}'
        raise ValueError(f'throughput probe to {host}:{port}: {what}') from None
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


def _read_exactly(conn: socket.socket, size: int, deadline: float):
    """``size`` bytes from ``conn``, or None when it closes first; socket.timeout (an OSError)
    past ``deadline``: a slow sender holds the one server no longer than that."""
    data = b''
    while len(data) < size:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout('the request took too long to arrive')
        conn.settimeout(min(2.0, left))
        chunk = conn.recv(size - len(data))
        if not chunk:
            return None
        data += chunk
    return data


def _answer(conn: socket.socket, answer: dict) -> None:
    """Send the one-line answer, then drain what the sender still had in flight until it
    closes, so the answer is not discarded by a reset."""
    conn.sendall(json.dumps(answer).encode('ascii') + b'\n')
    conn.shutdown(socket.SHUT_WR)
    end = time.monotonic() + 2.0
    try:
        while time.monotonic() < end and conn.recv(PROBE_CHUNK):
            pass
    except OSError:
        pass


class ProbeServer:
    """The remote end of the throughput probe: receives one bounded burst at a time."""

    def __init__(self, host: str, port: int, logger=None, deployment: str = '',
                 scale: str = ''):
        self._logger = logger
        self._identity = {'d': deployment, 'to': scale}
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
        deadline = time.monotonic() + REQUEST_S
        header = _read_exactly(conn, 14, deadline)
        if header is None or header[:8] != PROBE_MAGIC:
            return         # not ours: drop the connection without an answer
        duration_ms, size = struct.unpack('!IH', header[8:])
        asked = None
        if size <= MAX_IDENTITY:
            raw = _read_exactly(conn, size, deadline)
            try:
                asked = json.loads(raw.decode('utf-8')) if raw is not None else None
            except (ValueError, UnicodeDecodeError):
                pass
        conn.settimeout(2.0)
        if not isinstance(asked, dict):
            _answer(conn, {'bytes': 0, 'bytes_per_s': 0.0,
                           'error': 'a request without a readable deployment and scale'})
            return
        if asked != self._identity:
            mine, theirs = self._identity, asked
            which = 'two deployments share' if theirs.get('d') != mine['d'] else \
                'two scales of this deployment share'
            error = (f"this port is scale {mine['to']!r} of deployment {mine['d']!r}, not "
                     f"scale {str(theirs.get('to'))[:60]!r} of deployment "
                     f"{str(theirs.get('d'))[:60]!r}: {which} a port (set the scales' port, "
                     'or monitoring.bandwidth_probe_port, apart)')
            _answer(conn, {'bytes': 0, 'bytes_per_s': 0.0, 'error': error})
            return
        duration = min(max(duration_ms / 1000.0, 0.05), PROBE_MAX_DURATION_S)
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
        _answer(conn, answer)

    def close(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(timeout=2.0)
