"""discovery.mode server on a link that carries no multicast (a WiFi access point that drops it):
two network namespaces, home (the master) and away, joined by a shaped link with multicast off
on both ends; each scale's warden runs its discovery server, every process of the deployment is
a client of both. The worker moves out, its output reaches a subscriber the test started on
home; the link is cut: the worker is back home within its Δ, and two nodes started cold on away
meanwhile find each other through away's own server; the cut outlasts the DDS leases and, the
link back, the worker moves out again and is heard. The link has no multicast route, and not one
multicast packet crosses it (counted at home's end).
Root only (namespaces, tc)."""

import os
import re
import signal
import sys
import time

import pytest
import yaml

import home_away as ha
from processes import LoggedProcess
from anyscale_manager.testbed import harness, netns

NETNS_OK, NETNS_WHY = netns.available()
pytestmark = pytest.mark.skipif(not NETNS_OK, reason=f'no namespaces here: {NETNS_WHY}')
FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'fixtures')
OBSERVER = os.path.join(FIXTURES, 'ns_observer.py')
COUNT = os.path.join(FIXTURES, 'multicast_count.py')
RATE_HZ = 10.0
TOLERANCE_S = 2.0
HYSTERESIS_S = 5.0
# A cut longer than a DDS participant's lease (20 s): every process has dropped the other
# scale's participants, its server among them, and must find them again after the restore.
STAY_CUT_S = 25.0
SCALES = ('home', 'away')


class Lines:
    """A process's output, read as it grows."""

    def __init__(self, proc):
        self.proc = proc

    def matching(self, pattern, since=0.0):
        out = []
        for line in self.proc.text().splitlines():
            m = re.match(pattern, line)
            if m and float(m.group(1)) >= since:
                out.append(m)
        return out


def wait_for(condition, timeout_s, what, procs):
    deadline = time.monotonic() + timeout_s
    while True:
        found = condition()
        if found:
            return found
        gone = [name for name, p in procs if p.proc.poll() is not None]
        if time.monotonic() > deadline or gone:
            tails = '\n'.join(f'--- {name}:\n{p.text()[-2500:]}' for name, p in procs)
            raise AssertionError(f'not within {timeout_s} s: {what}'
                                 + (f' ({", ".join(gone)} exited)' if gone else '')
                                 + f'\n{tails}')
        time.sleep(0.1)


def deployment(tmp_path, net, topic):
    path = ha.write_deployment(
        tmp_path, f'discovery_{os.getpid()}',
        ha.chain(topic, RATE_HZ, freq_min_hz=RATE_HZ / 2, tolerance_s=TOLERANCE_S),
        link_kbps=20000.0, monitoring={'heartbeat_misses_down': 3},
        decider={'hysteresis_s': HYSTERESIS_S}, port_offset=7)
    data = yaml.safe_load(open(path))
    params = data['/**']['ros__parameters']
    for scale in SCALES:
        params['scales'][scale]['host'] = net.addresses[scale]
    # The default port: the servers listen in the namespaces, and this run's ROS domain keeps
    # it apart from any other run's (discovery.port + 16 x the domain).
    params['discovery'] = {'mode': 'server'}
    with open(path, 'w') as f:
        yaml.safe_dump(data, f)
    return path


def environment(tmp_path):
    """A process of the deployment in a namespace: this run's domain, UDP only, no static
    peers and nothing multicast (the agents and the decider add the servers themselves)."""
    env = harness.child_env(int(os.environ['ROS_DOMAIN_ID']), str(tmp_path / 'ros_log'),
                            peer='')
    env.pop('ROS_STATIC_PEERS', None)
    return env


def servers(path, env):
    """What a process of the deployment in ``env`` (its ROS domain) needs to be a client."""
    from anyscale_manager.agent.discovery import client_setup
    return client_setup(['x', '--ros-args', '--params-file', path], env)[0]


@pytest.mark.timeout(300)
def test_a_deployment_discovers_through_its_servers_with_no_multicast_on_the_link(tmp_path):
    topic = f'/ds_{os.getpid()}'
    procs = []
    with netns.Network(rate_kbps=20000.0, scales=SCALES, multicast=False) as net:
        path = deployment(tmp_path, net, topic)
        env = environment(tmp_path)
        client = dict(env, **servers(path, env))

        def start(name, scale, argv, environ=env):
            proc = LoggedProcess(tmp_path / f'{name}.out', net.command(scale, argv), environ)
            procs.append((name, proc))
            return proc
        try:
            counter = start('multicast_count', 'home', [
                sys.executable, COUNT, net.interfaces[(next(iter(net.wires)), 'home')]])
            wait_for(lambda: 'ready' in counter.text(), 10.0, 'the multicast counter', procs)
            for scale in SCALES:
                start(f'agent_{scale}', scale, [os.path.join(ha.BIN, 'agent'), '--ros-args',
                                                '--params-file', path, '-p', f'scale:={scale}'])
            start('decider', 'home', [os.path.join(ha.BIN, 'decider'), '--ros-args',
                                      '--params-file', path])
            seen = Lines(start('observer', 'home', [sys.executable, OBSERVER, topic + '/w'],
                               client))
            heard = r'heard (\S+) ' + re.escape(topic + '/w')

            def worker_on(scale, since=0.0):
                return seen.matching(rf'state (\S+) {scale} worker running', since)
            wait_for(lambda: worker_on('away') and seen.matching(heard), 90.0,
                     'the worker serving on away, its output heard at home', procs)
            assert 'discovery: a client of the servers' in dict(procs)['agent_home'].text()
            wardens = sorted(tmp_path.glob('log/*/*/warden.log'))
            assert len(wardens) == 2 and all(
                'discovery server started' in w.read_text() for w in wardens), wardens

            # The link cut: the worker home, its output heard there within its Δ.
            net.cut()
            cut = time.monotonic()
            wait_for(lambda: worker_on('home', cut), 30.0, 'the worker serving home', procs)
            back = wait_for(lambda: seen.matching(heard, time.monotonic() - 0.5)
                            and worker_on('home', cut), 30.0, 'its output heard again', procs)
            arrivals = [float(m.group(1)) for m in seen.matching(heard, cut - 5.0)]
            gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
            assert back and max(gaps) <= TOLERANCE_S + 1.0 / (RATE_HZ / 2), max(gaps)

            # Meanwhile on away: two nodes started cold find each other through away's server.
            pair = Lines(start('pair_away', 'away', [sys.executable, OBSERVER, '--pair',
                                                     topic + '/pair'], client))
            wait_for(lambda: pair.matching(r'matched (\S+) \S+ 1'), 15.0,
                     'a talker and a listener started on away during the cut matched', procs)

            # The cut outlasts the leases; restored, the worker moves out again (after T) and
            # its output from away reaches home.
            wait_for(lambda: time.monotonic() - cut > STAY_CUT_S, STAY_CUT_S + 5.0,
                     'the cut outlasting the DDS leases', procs)
            net.restore()
            restored = time.monotonic()
            moved = wait_for(lambda: worker_on('away', restored), 60.0,
                             'the worker serving on away again', procs)
            at = float(moved[0].group(1))
            wait_for(lambda: seen.matching(heard, at + 1.0), 30.0,
                     'its output heard at home from away', procs)
            counter.stop(signal.SIGINT)
            crossed = re.search(r'multicast (\d+) of (\d+)', counter.text())
            assert crossed and crossed.group(1) == '0' and int(crossed.group(2)) > 100, \
                counter.text()
        finally:
            for name, proc in reversed(procs):
                proc.stop(signal.SIGINT, timeout=20.0)
            ha.stop_wardens(tmp_path)
