"""A killed node's DDS ports are held for a while (agent/ports.py), with real sockets and a
real supervised process."""

import os
import signal
import socket
import time

import pytest

from anyscale_manager.agent import ports
from supervision import drive, py_entry

DOMAIN = 200      # ports 57410..57649: far from any domain a test runs ROS on


def free_port_in(domain):
    for port in ports.participant_range(domain):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind(('0.0.0.0', port))
        except OSError:
            s.close()
            continue
        s.close()
        return port
    raise RuntimeError(f'no free port in domain {domain}')


def bindable(port):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(('0.0.0.0', port))
        return True
    except OSError:
        return False
    finally:
        s.close()


def test_the_participant_range_is_the_rtps_unicast_ports_of_a_domain():
    assert ports.participant_range(0) == range(7410, 7650)
    assert ports.participant_range(62)[0] == 22910 and 22900 not in ports.participant_range(62)
    assert 22901 not in ports.participant_range(62)          # discovery and data multicast
    assert ports.domain_of({'ROS_DOMAIN_ID': '62'}) == 62
    assert ports.domain_of({}) == 0 and ports.domain_of({'ROS_DOMAIN_ID': 'x'}) == 0


def test_the_unicast_ports_of_a_process_are_read_from_proc():
    inside = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    outside = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        inside.bind(('127.0.0.1', free_port_in(DOMAIN)))
        outside.bind(('127.0.0.1', 0))                        # an ephemeral port
        found = ports.unicast_ports([os.getpid()], DOMAIN)
        assert inside.getsockname()[1] in found
        assert outside.getsockname()[1] not in found
        assert inside.getsockname()[1] not in ports.unicast_ports([os.getpid()], DOMAIN + 1)
    finally:
        inside.close()
        outside.close()
    assert ports.unicast_ports([2 ** 22 + 12345], DOMAIN) == frozenset()   # no such pid


def test_a_hold_binds_until_its_time_is_up_and_skips_a_taken_port():
    port, taken = free_port_in(DOMAIN), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(('0.0.0.0', 0))
    hold = ports.PortHold(hold_s=5.0)
    try:
        assert hold.hold([port, taken.getsockname()[1]], now=100.0) == [port]
        assert not bindable(port) and hold.held() == {port}
        assert hold.release(now=104.9) == 0 and not bindable(port)
        assert hold.release(now=105.0) == 1 and bindable(port)
    finally:
        hold.release()
        taken.close()


def test_a_hold_passed_on_by_descriptor_is_adopted_and_anything_else_closed():
    """A restart in place passes its held sockets by descriptor: the new process holds the
    same ports for its own hold_s; a descriptor that is not a UDP socket is closed, not kept."""
    port = free_port_in(DOMAIN)
    old = ports.PortHold(hold_s=5.0)
    assert old.hold([port], now=0.0) == [port]
    fds = [os.dup(s.fileno()) for s in old.sockets()]
    old.release()
    read_end, write_end = os.pipe()
    stream = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    new = ports.PortHold(hold_s=5.0)
    try:
        assert new.adopt(fds + [read_end, stream.detach()], now=100.0) == [port]
        assert not bindable(port) and new.held() == {port}
        with pytest.raises(OSError):
            os.fstat(read_end)                  # closed, not kept
        assert new.release(now=104.0) == 0 and new.release(now=105.0) == 1 and bindable(port)
    finally:
        new.release()
        os.close(write_end)


BINDER = ('import socket, sys, time\n'
          's = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n'
          's.bind(("0.0.0.0", int(sys.argv[1])))\n'
          'while True: time.sleep(1)\n')


def binder(port):
    entry = py_entry('n', BINDER, env={'ROS_DOMAIN_ID': str(DOMAIN)})
    return type(entry)(name=entry.name, argv=entry.argv + (str(port),), env=entry.env,
                       ros_name=entry.ros_name)


def up_when_bound(sup, port):
    """The supervisor's 'visible' for the binder: up once its socket is bound."""
    def visible(entry):
        pid = sup.pids().get('n')
        return bool(pid) and port in ports.unicast_ports([pid], DOMAIN)
    return visible


def test_a_killed_node_is_restarted_at_once_away_from_its_old_ports(make_sup):
    port = free_port_in(DOMAIN)
    sup = make_sup([binder(port)])
    visible = up_when_bound(sup, port)
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running', visible=visible)
    # Found by looking, not by the graph (which still shows a killed copy for seconds).
    assert drive(sup, lambda: sup.dds_ports('n') == {port}, timeout=5.0)
    first = sup.pids()['n']
    os.kill(first, signal.SIGKILL)
    # The step that finds the exit holds the port and starts the node again.
    assert drive(sup, lambda: sup.reports()['n'].restarts == 1, visible=visible)
    assert port in sup.port_hold.held()
    assert any(f'holding its DDS ports {port}' in text for _, text in sup.events)
    # So the new process cannot bind it: it dies, as a DDS participant would move to the next
    # participant id instead.
    assert drive(sup, lambda: sup.reports()['n'].restarts >= 2, visible=visible)
    sup.port_hold.release()
    sup.stop_all(time.monotonic())
    assert drive(sup, sup.all_stopped)


def test_a_node_that_stops_cleanly_leaves_its_ports_free(make_sup):
    port = free_port_in(DOMAIN)
    sup = make_sup([binder(port)])
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running',
                 visible=up_when_bound(sup, port))
    sup.stop_all(time.monotonic())
    assert drive(sup, sup.all_stopped)
    assert sup.port_hold.held() == frozenset() and bindable(port)
