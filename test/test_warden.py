"""The warden (agent/warden.py): its judgement of the agent with a hand-written clock, its
echo's wire format, and, with real processes, fencing the nodes of a SIGKILLed agent."""

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from anyscale_manager.agent import procs, warden

SLEEPER = 'import time\nwhile True: time.sleep(1)'


def test_a_dead_agent_is_fenced_after_the_adopt_grace():
    v = warden.Verdict(adopt_grace_s=1.0, restart_grace_s=10.0)
    assert not v.step(0.0, alive=True, restarting=False) and v.state == warden.ALIVE
    assert not v.step(1.0, alive=False, restarting=False) and v.state == warden.GONE
    assert not v.step(1.9, alive=False, restarting=False)
    assert v.step(2.0, alive=False, restarting=False) and v.state == warden.FENCED
    assert not v.step(3.0, alive=False, restarting=False)      # fenced once
    assert not v.step(4.0, alive=True, restarting=False) and v.state == warden.ALIVE


def test_an_announced_restart_gets_the_restart_grace_and_a_successor_stops_the_clock():
    v = warden.Verdict(adopt_grace_s=1.0, restart_grace_s=10.0)
    v.step(0.0, alive=True, restarting=True)
    assert v.state == warden.RESTARTING
    assert not v.step(1.0, alive=False, restarting=True)
    assert not v.step(5.0, alive=False, restarting=True) and v.state == warden.RESTARTING
    assert not v.step(6.0, alive=True, restarting=False) and v.state == warden.ALIVE
    v.step(7.0, alive=False, restarting=False)                   # this one is not announced
    assert v.step(8.0, alive=False, restarting=False) and v.state == warden.FENCED


def test_the_echo_answers_only_its_own_beats():
    reply = warden.answer(warden.beat('d', 'laptop', 7), 'd', 'laptop', warden.GONE, 0.25)
    assert warden.parse_echo(reply, 'd') == ('laptop', 7, warden.GONE, 0.25)
    assert warden.answer(warden.beat('other', 'laptop', 7), 'd', 'laptop', 'alive', 0) is None
    assert warden.answer(warden.beat('d', 'robot', 7), 'd', 'laptop', 'alive', 0) is None
    for junk in (b'', b'{', b'[]', b'\xff', b'{"d": "d", "to": "laptop", "seq": -1}',
                 b'{"d": "d", "to": "laptop", "seq": true}', b'x' * 600):
        assert warden.answer(junk, 'd', 'laptop', 'alive', 0.0) is None
        assert warden.parse_echo(junk, 'd') is None
    assert warden.parse_echo(reply, 'other') is None


def test_with_a_key_beats_and_echoes_are_signed_and_an_echo_answers_one_monitor():
    key, other = bytes(range(32)), bytes(32)
    beat = warden.beat('d', 'laptop', 7, key, monitor='m1')
    reply = warden.answer(beat, 'd', 'laptop', warden.ALIVE, 1.5, key)
    assert warden.parse_echo(reply, 'd', key, 'm1') == ('laptop', 7, warden.ALIVE, 1.5)
    # An echo of another monitor's beat (say, of this process's predecessor) answers nothing.
    assert warden.parse_echo(reply, 'd', key, 'm2') is None
    # Unsigned, or signed with another key: no echo, and no echo taken.
    assert warden.answer(warden.beat('d', 'laptop', 7, monitor='m1'), 'd', 'laptop',
                         warden.ALIVE, 0.0, key) is None
    assert warden.answer(warden.beat('d', 'laptop', 7, other, 'm1'), 'd', 'laptop',
                         warden.ALIVE, 0.0, key) is None
    unsigned = warden.answer(warden.beat('d', 'laptop', 7, monitor='m1'), 'd', 'laptop',
                             warden.ALIVE, 0.0)
    assert warden.parse_echo(unsigned, 'd', key, 'm1') is None
    # Altered on the way (a cut link made to look up by an 'alive' that was 'gone').
    forged = reply.replace(b'"alive"', b'"gone"')
    assert forged != reply and warden.parse_echo(forged, 'd', key, 'm1') is None


def start_warden(tmp_path, port, adopt_grace='0.3'):
    return subprocess.Popen(
        [sys.executable, '-m', 'anyscale_manager.agent.warden', '--state',
         str(tmp_path / 'agent.json'), '--scale', 'laptop', '--deployment', 'd', '--host',
         '127.0.0.1', '--port', str(port), '--adopt-grace', adopt_grace, '--fence-grace', '0.3'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def ask(port, seq, timeout_s=5.0):
    """Beat the warden until it answers; its echo."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(0.2)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            s.sendto(warden.beat('d', 'laptop', seq), ('127.0.0.1', port))
            try:
                return warden.parse_echo(s.recv(1024), 'd')
            except socket.timeout:
                continue
    raise AssertionError(f'no echo from the warden on UDP {port}')


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def wait_for(cond, timeout_s, what):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError(f'timed out after {timeout_s} s waiting for {what}')


def recorded(pid, fence=None, prefix='', wall_clock=False):
    """How a state file records a process: its start in clock ticks since boot, or (an agent
    of an earlier version) on the wall clock only."""
    rec = {f'{prefix}pid': pid}
    if wall_clock:
        rec[f'{prefix}started'] = procs.create_time(pid)
    else:
        rec[f'{prefix}start_ticks'] = procs.start_ticks(pid)
    if fence is not None:
        rec['fence'] = fence
    return rec


@pytest.mark.timeout(60)
@pytest.mark.parametrize('wall_clock', [False, True], ids=['ticks', 'an earlier version'])
def test_the_nodes_of_a_killed_agent_are_stopped_and_the_echo_says_so(tmp_path, wall_clock):
    agent = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    node = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    pinned = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    port = free_udp_port()
    guard = None
    try:
        wait_for(lambda: procs.start_ticks(node.pid) and procs.start_ticks(agent.pid)
                 and procs.start_ticks(pinned.pid), 5.0, 'the processes')
        state = dict(recorded(agent.pid, prefix='agent_', wall_clock=wall_clock),
                     nodes={'n': recorded(node.pid, True, wall_clock=wall_clock),
                            'pinned': recorded(pinned.pid, False, wall_clock=wall_clock)})
        (tmp_path / 'agent.json').write_text(json.dumps(state))
        guard = start_warden(tmp_path, port)
        assert ask(port, 1)[2] == warden.ALIVE
        agent.kill()
        agent.wait()
        killed = time.monotonic()
        wait_for(lambda: node.poll() is not None, 10.0, 'the node stopped by the warden')
        took = time.monotonic() - killed
        assert node.returncode == -signal.SIGINT or node.returncode in (1, -signal.SIGKILL)
        assert took >= 0.3                       # not before the adopt grace
        wait_for(lambda: ask(port, 2)[2] == warden.FENCED, 10.0, "the echo saying 'fenced'")
        assert pinned.poll() is None          # no other copy could meet it: left running
        # A second warden of the same state file leaves at once.
        again = start_warden(tmp_path, free_udp_port())
        assert again.wait(10.0) == 0 and 'another warden' in again.stdout.read()
    finally:
        for proc in (agent, node, pinned, guard):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.timeout(60)
def test_a_successor_within_the_grace_keeps_the_nodes(tmp_path):
    node = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    first = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    port = free_udp_port()
    guard = second = None
    try:
        wait_for(lambda: procs.start_ticks(node.pid) and procs.start_ticks(first.pid), 5.0,
                 'the processes')

        def write(agent_pid, restarting=False):
            state = dict(recorded(agent_pid, prefix='agent_'), restarting=restarting,
                         nodes={'n': recorded(node.pid, True)})
            tmp = tmp_path / 'agent.json.tmp'
            tmp.write_text(json.dumps(state))
            os.replace(tmp, tmp_path / 'agent.json')
        write(first.pid, restarting=True)           # it says it restarts in place
        guard = start_warden(tmp_path, port)
        assert ask(port, 1)[2] == warden.RESTARTING
        first.kill()
        first.wait()
        time.sleep(1.0)                             # longer than the adopt grace (0.3 s)
        assert node.poll() is None and ask(port, 2)[2] == warden.RESTARTING
        second = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
        wait_for(lambda: procs.start_ticks(second.pid), 5.0, 'the successor')
        write(second.pid)
        wait_for(lambda: ask(port, 3)[2] == warden.ALIVE, 5.0, 'the successor seen alive')
        assert node.poll() is None
    finally:
        for proc in (node, first, second, guard):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()


def test_the_warden_answers_heartbeats_at_real_time_priority_or_says_why_not():
    """Run in a child: the scheduling class is the process's own."""
    code = '''
import os
from anyscale_manager.agent.warden import prioritise
said = []
assert prioritise(0, 'laptop', said.append) is False and said == []
got = prioritise(10, 'laptop', said.append)
policy = os.sched_getscheduler(0)
if got:
    assert policy == os.SCHED_RR and os.sched_getparam(0).sched_priority == 10, policy
    assert said == ['heartbeats answered at real-time priority 10 (SCHED_RR)'], said
else:
    assert policy == os.SCHED_OTHER, policy
    assert 'CAP_SYS_NICE' in said[0] and 'warden_priority' in said[0], said
print('rr' if got else 'normal')
'''
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() in ('rr', 'normal')


def test_a_clock_step_hides_no_node_from_the_warden(tmp_path):
    """A node recorded before the wall clock was stepped (a robot's first NTP fix) is still
    found and fenced. Stepping this machine's clock would disturb every other process, so the
    step is stood in for by what it does to a record: its wall-clock start is 2 s off the
    process's start as read after the step. An earlier version's record (wall clock only)
    then names nothing, as that version read it."""
    node = subprocess.Popen([sys.executable, '-c', SLEEPER], start_new_session=True)
    try:
        wait_for(lambda: procs.start_ticks(node.pid), 5.0, 'the node')
        path = tmp_path / 'agent.json'
        stepped = procs.create_time(node.pid) - 2.0
        old = {'pid': node.pid, 'started': stepped, 'fence': True}
        path.write_text(json.dumps({'agent_pid': 0, 'nodes': {'n': old}}))
        assert warden.read_state(str(path)).nodes == ()
        path.write_text(json.dumps({'boot_id': procs.boot_id(), 'agent_pid': 0, 'nodes': {
            'n': dict(recorded(node.pid, True), started=stepped)}}))
        view = warden.read_state(str(path))
        assert view.nodes == ((node.pid, procs.start_ticks(node.pid)),)
        assert warden.fence(view.nodes, 2.0, lambda text: None) == 1
        wait_for(lambda: node.poll() is not None, 5.0, 'the node stopped')
    finally:
        if node.poll() is None:
            node.kill()
        node.wait()


def test_a_state_file_of_another_boot_names_nothing_alive(tmp_path):
    path = tmp_path / 'agent.json'
    me = os.getpid()
    path.write_text(json.dumps(dict(recorded(me, prefix='agent_'), boot_id='an-earlier-boot',
                                    nodes={'n': recorded(me, True)})))
    assert warden.read_state(str(path)) == warden.AgentView()
    path.write_text(json.dumps(dict(recorded(me, prefix='agent_'), boot_id=procs.boot_id(),
                                    nodes={'n': recorded(me, True)})))
    view = warden.read_state(str(path))
    assert view.pid == me and view.nodes == ((me, procs.start_ticks(me)),)
