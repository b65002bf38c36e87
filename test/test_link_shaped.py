"""The link monitor on a real shaped link: two network namespaces joined by a token bucket, the
master's LinkMonitor in one and the remote's in the other, each in its own process
(fixtures/link_monitor_host.py). Root only (namespaces, tc)."""

import dataclasses
import os
import socket
import subprocess
import threading
import time
from contextlib import contextmanager

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.agent import warden
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.testbed import harness, netns

NETNS_OK, NETNS_WHY = netns.available()
pytestmark = pytest.mark.skipif(not NETNS_OK, reason=f'no namespaces here: {NETNS_WHY}')
HOST = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'fixtures',
                    'link_monitor_host.py')
SINK = '''
import socket, sys, threading
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("0.0.0.0", int(sys.argv[1]))); s.listen(4)
def drain(c):
    try:
        while c.recv(65536):
            pass
    except OSError:
        pass
while True:
    c, _ = s.accept(); threading.Thread(target=drain, args=(c,), daemon=True).start()
'''
FLOOD = '''
import socket, struct, sys, time
s = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=5.0)
b = b"x" * 8192; t = time.monotonic()
while time.monotonic() - t < float(sys.argv[3]):
    s.send(b)
s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
s.close()
'''


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Watched:
    """The master's LinkStatus lines as (arrival time, status), and waits on them."""

    def __init__(self, master, log):
        self.master, self.log = master, log
        self.seen = []
        self.lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for raw in iter(self.master.stdout.readline, b''):
            with self.lock:
                self.seen.append((time.monotonic(), p.LinkStatus.from_json(raw.decode())))

    def between(self, start, end):
        with self.lock:
            return [s for t, s in self.seen if start <= t <= end]

    def wait(self, condition, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                found = [(t, s) for t, s in self.seen if condition(t, s)]
            if found:
                return found[0]
            assert self.master.poll() is None, \
                f'the master monitor exited:\n{self.log.read_text()[-3000:]}'
            time.sleep(0.02)
        with self.lock:
            last = self.seen[-3:]
        raise AssertionError(f'timed out after {timeout_s} s waiting for {what}; last {last}')


@contextmanager
def monitored_link(testbed_path, python, tmp_path, rate_kbps, *extra):
    """(network, its master's LinkStatus lines, the probe port): a link of ``rate_kbps``, each
    end's LinkMonitor probing once, when the link first comes up (``extra``: the probe's
    duration)."""
    net = netns.Network(rate_kbps=rate_kbps)
    with net:
        robot_ip, laptop_ip = net.addresses['robot'], net.addresses['laptop']
        domain = int(os.environ['ROS_DOMAIN_ID'])
        logs = str(tmp_path / 'ros_log')
        probe_port = free_port()

        def host(scale):
            return [python, HOST, testbed_path, scale, robot_ip, laptop_ip, str(probe_port),
                    *extra]
        net.popen('laptop', host('laptop'), harness.child_env(domain, logs, robot_ip),
                  cpu_quota=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        master_log = tmp_path / 'master.err'
        with open(master_log, 'wb') as err:
            master = net.popen('robot', host('robot'), harness.child_env(domain, logs, laptop_ip),
                               cpu_quota=False, stdout=subprocess.PIPE, stderr=err)
        yield net, Watched(master, master_log), probe_port


@pytest.mark.timeout(120)
def test_link_monitor_sees_a_full_queue_and_never_probes_it(testbed_path, python, tmp_path):
    """A bulk TCP flow fills a 3 Mbit/s link's queue: it is judged congested within a second,
    and not probed while so (a probe would add to the queue; nothing of ours crosses it, so
    nothing delivers below its need either)."""
    with monitored_link(testbed_path, python, tmp_path, 3000.0) as (net, watched, _):
        sink_port = str(free_port())
        net.popen('laptop', [python, '-c', SINK, sink_port], {'PATH': os.environ['PATH']},
                  cpu_quota=False)
        # Up, probed once at its return (the probe fills the queue itself, and is not counted),
        # and calm: the delay is judged and small.
        t_calm, _ = watched.wait(lambda t, s: s.up and s.bandwidth_available_kbps is not None
                                 and s.queueing_delay_ms is not None, 40.0,
                                 'a probed, judged link')
        calm_until = t_calm + 2.0
        watched.wait(lambda t, s: t >= calm_until, 10.0, 'two calm seconds')
        calm = watched.between(t_calm, calm_until)
        assert not any(s.congested for s in calm), calm
        assert max(s.queueing_delay_ms for s in calm) < 20.0
        probed = calm[-1].bandwidth_available_kbps
        print(f'first probe {probed:.0f} kbit/s')
        assert 1000.0 <= probed <= 3600.0, probed     # the probe measured the 3 Mbit/s bucket

        t_flood = time.monotonic()
        flood = net.popen('robot', [python, '-c', FLOOD, net.addresses['laptop'], sink_port,
                                    '5'], {'PATH': os.environ['PATH']}, cpu_quota=False)
        t_seen, status = watched.wait(lambda t, s: t >= t_flood and s.congested, 5.0,
                                      'congestion')
        assert status.up and status.queueing_delay_ms > 50.0
        flood.wait(timeout=15)
        t_end = time.monotonic()
        t_clear, _ = watched.wait(lambda t, s: t >= t_end and not s.congested, 5.0,
                                  'congestion to clear after the flow')
        during = watched.between(t_seen, t_clear)
        assert all(s.bandwidth_available_kbps == probed for s in during), \
            sorted({s.bandwidth_available_kbps for s in during})
        print(f'congestion seen {t_seen - t_flood:.2f} s into the flow, never probed, cleared '
              f'{t_clear - t_end:.2f} s after it')


def probe_running(net, laptop_ip, port):
    """Whether the robot holds an established TCP connection to the laptop's probe port."""
    out = net.run('robot', ['ss', '-Htn', 'state', 'established', 'dst', laptop_ip])
    return any(line.split()[-1].endswith(f':{port}') for line in out.splitlines()
               if line.strip())


def wait_probe(net, watched, laptop_ip, port, timeout_s):
    """Wait for a probe's connection to the laptop; when it was first seen."""
    deadline = time.monotonic() + timeout_s
    while not probe_running(net, laptop_ip, port):
        assert time.monotonic() < deadline, f'no probe seen within {timeout_s} s'
        assert watched.master.poll() is None, watched.log.read_text()[-3000:]
        time.sleep(0.01)
    return time.monotonic()


@pytest.mark.timeout(120)
def test_a_full_probe_is_not_a_cut_and_a_cut_during_one_is_read_at_once(
        testbed_path, python, tmp_path):
    """The probe fills a 3 Mbit/s link on purpose for 2 s: the heartbeats wait behind its data
    or are dropped from the full queue, yet the link is never read down, through the probe's
    end and a second after (it acknowledges the probe's data). A link that comes back is
    probed again at once: cut 1 s into that probe, it is read down as soon as with no probe at
    all (the heartbeat timeout, 3 beats at 10 Hz, and a little), where silence used to be
    allowed the probe's length more (2.44 s measured then)."""
    d = load_deployment(testbed_path)
    timeout_s = d.monitoring.heartbeat_misses_down / d.monitoring.heartbeat_rate_hz
    with monitored_link(testbed_path, python, tmp_path, 3000.0, '2.0') as (net, watched, base):
        mon = dataclasses.replace(d.monitoring, bandwidth_probe_port=base)
        port = warden.warden_port(dataclasses.replace(d, monitoring=mon), 'laptop')
        laptop_ip = net.addresses['laptop']
        # The first probe, when the link first comes up: never a cut, through its end.
        t_probe = wait_probe(net, watched, laptop_ip, port, 40.0)
        t_done, _ = watched.wait(lambda t, s: t >= t_probe
                                 and s.bandwidth_available_kbps is not None, 10.0,
                                 'the first probe measured')
        watched.wait(lambda t, s: t >= t_done + 1.0, 5.0, 'a second after the probe')
        full = watched.between(t_probe, t_done + 1.0)
        assert full and all(s.up for s in full), [s.up for s in full]
        # Cut and restored: probed again at once; cut again 1 s into that probe.
        t_first_cut = time.monotonic()
        net.cut()
        watched.wait(lambda t, s: t >= t_first_cut and not s.up, 10.0, 'the first cut read')
        net.restore()
        t_again = wait_probe(net, watched, laptop_ip, port, 20.0)
        # The fault's schedule, not a wait: the master's reports may come late on a busy machine.
        time.sleep(max(0.0, t_again + 1.0 - time.monotonic()))
        assert probe_running(net, laptop_ip, port), 'the probe ended within its first second'
        t_cut = time.monotonic()
        net.cut()
        assert t_cut - t_again < 1.6, f'the cut came {t_cut - t_again:.2f} s into the probe'
        t_down, _ = watched.wait(lambda t, s: t >= t_cut and not s.up, 10.0, 'the cut read')
        late = t_down - t_cut
        print(f'a 2-s probe: {len(full)} reports, all up; a cut {t_cut - t_again:.2f} s into '
              f'the next read after {late:.2f} s (heartbeat timeout {timeout_s:g} s)')
        assert late <= timeout_s + 0.6, late
