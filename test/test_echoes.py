"""The link monitor's heartbeat socket: what arrived is stamped when it arrived, not when a
late reader got to it (a starved scale must not read a working link as silent)."""

import socket
import time

import pytest

from anyscale_manager.nodes.monitors.echoes import EchoSocket


@pytest.fixture
def echoes():
    sock = EchoSocket(512)
    yield sock
    sock.close()


@pytest.fixture
def sender():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield sock
    sock.close()


def _address(echoes):
    return ('127.0.0.1', echoes._sock.getsockname()[1])


def test_nothing_waiting_reads_nothing(echoes):
    assert echoes.drain() == []


def test_an_echo_read_late_keeps_its_arrival_time(echoes, sender):
    assert echoes.kernel_stamps, 'this platform should stamp datagrams in the kernel'
    before = time.monotonic()
    sender.sendto(b'first', _address(echoes))
    sent = time.monotonic()
    # The reader is late on purpose: this stands for a process that was not scheduled.
    while time.monotonic() - sent < 0.3:
        time.sleep(0.05)
    got = echoes.drain()
    read = time.monotonic()
    assert [data for _, data in got] == [b'first']
    arrival = got[0][0]
    assert before - 0.01 <= arrival <= sent + 0.05
    assert read - arrival >= 0.25


def test_several_arrive_in_order_and_a_drain_stops_at_its_limit(echoes, sender):
    for i in range(5):
        sender.sendto(b'%d' % i, _address(echoes))
    deadline = time.monotonic() + 5.0
    got = []
    while len(got) < 5 and time.monotonic() < deadline:
        got += echoes.drain(limit=2)
        assert len(got) <= 5
    assert [data for _, data in got] == [b'0', b'1', b'2', b'3', b'4']
    stamps = [at for at, _ in got]
    assert stamps == sorted(stamps)


def test_a_payload_longer_than_allowed_is_cut_so_the_parser_refuses_it(echoes, sender):
    sender.sendto(b'x' * 600, _address(echoes))
    deadline = time.monotonic() + 5.0
    got = []
    while not got and time.monotonic() < deadline:
        got = echoes.drain()
    assert len(got[0][1]) == 513


def test_one_drain_keeps_the_kernels_order_when_the_clock_readings_are_far_apart(sender):
    """A reader preempted between its monotonic and wall readings (10 ms at every other
    reading of the wall clock here) must not reorder datagrams that came microseconds apart
    (loopback delivers them within ``sendto``: all five wait for the first drain)."""
    calls = []

    def late_wall():
        calls.append(1)
        if len(calls) % 2 == 0:
            time.sleep(0.01)
        return time.time()
    echoes = EchoSocket(512, wall=late_wall)
    try:
        for i in range(5):
            sender.sendto(b'%d' % i, _address(echoes))
        deadline = time.monotonic() + 5.0
        got = []
        while len(got) < 5 and time.monotonic() < deadline:
            got += echoes.drain()
        stamps = [at for at, _ in got]
        assert len(got) == 5 and stamps == sorted(stamps), stamps
    finally:
        echoes.close()
