"""The agent's pure core with real processes: catalogue, supervisor, adoption, move orders."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import psutil
import pytest

from anyscale_manager import protocol
from anyscale_manager.agent import procs
from anyscale_manager.agent.catalogue import (build_catalogue, ENV_INSTANCE, ENV_NODE, ENV_SCALE,
                                              Entry, format_parameter)
from anyscale_manager.agent.exits import ExitWatcher
from anyscale_manager.agent.reconcile import HEAR_PATIENCE_S, Reconciler
from anyscale_manager.model import types as t
from anyscale_manager.model.loader import load_mapping
from supervision import drive, FAST, gone, py_entry, SLEEPER, wait_for

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURES = os.path.join(HERE, 'fixtures')


# --- catalogue ----------------------------------------------------------------------------

def deployment_dict(nodes, names=None):
    return {'/**': {'ros__parameters': {
        'deployment': {'name': 'unit'},
        'scales': {'names': ['a', 'b'],
                   'a': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                   'b': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100.0}},
        'nodes': dict({'names': names or list(nodes)}, **nodes),
    }}}


def test_catalogue_builds_argv_env_and_filters_by_scale():
    d = load_mapping(deployment_dict({
        'cmd': {'launch': {'command': ['sleep', '5'], 'arguments': ['--x'],
                           'env': {'FOO': 'bar'},
                           'parameters': {'rate': 2.5, 'label': '5', 'on': True,
                                          'list': [1, 2]}}, 'cpu': 1.0},
        'pkg': {'launch': {'package': 'anyscale_manager', 'executable': 'workload',
                           'ros_name': '/ns/worker'}, 'cpu': 1.0},
        'only_b': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'residence': ['b']},
        'manual': {'cpu': 1.0, 'managed': False, 'residence': ['a']},
        'missing': {'launch': {'package': 'no_such_pkg', 'executable': 'nope'}, 'cpu': 1.0},
    }))
    environ = {'PATH': os.environ['PATH'], 'HOME': '/home/x', 'ROS_DOMAIN_ID': '7',
               'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp', 'SECRET_TOKEN': 'leak',
               'BASH_ENV': '/etc/rc'}
    cat = build_catalogue(d, 'a', environ)
    assert list(cat) == ['cmd', 'pkg', 'missing']
    assert set(build_catalogue(d, 'b', environ)) == {'cmd', 'pkg', 'only_b', 'missing'}
    cmd = cat['cmd']
    assert os.path.isabs(cmd.argv[0]) and cmd.argv[1:3] == ('5', '--x')
    tail = cmd.argv[cmd.argv.index('--ros-args'):]
    assert tail[:3] == ('--ros-args', '-r', '__node:=cmd')
    assert "label:='5'" in tail and 'rate:=2.5' in tail and 'on:=true' in tail
    assert 'list:=[1, 2]' in tail
    assert cmd.env['FOO'] == 'bar' and cmd.env['ROS_DOMAIN_ID'] == '7'
    assert cmd.env[ENV_NODE] == 'cmd' and cmd.env[ENV_SCALE] == 'a'
    assert 'SECRET_TOKEN' not in cmd.env and 'BASH_ENV' not in cmd.env
    # Not in an ament index here: found next to the interpreter (the editable install).
    pkg = cat['pkg']
    assert pkg.startable, pkg.problem
    assert os.path.basename(pkg.argv[0]) == 'workload'
    assert '__node:=worker' in pkg.argv and '__ns:=/ns' in pkg.argv
    assert pkg.ros_name == '/ns/worker'
    assert not cat['missing'].startable and 'no_such_pkg' in cat['missing'].problem
    with pytest.raises(ValueError, match='unknown scale'):
        build_catalogue(d, 'zz', environ)


def test_nodes_leave_shared_memory_out_unless_the_environment_or_the_node_says():
    def transports(environ, node_env=None, setting=None):
        raw = deployment_dict({'n': {'launch': {'command': ['sleep', '5'],
                                                'env': node_env or {}}, 'cpu': 1.0}})
        if setting is not None:
            raw['/**']['ros__parameters']['agent'] = {'node_dds_transports': setting}
        env = build_catalogue(load_mapping(raw), 'a', dict(environ, PATH='/usr/bin'))['n'].env
        return env.get('FASTDDS_BUILTIN_TRANSPORTS')
    assert transports({}) == 'UDPv4'
    assert transports({'FASTDDS_BUILTIN_TRANSPORTS': 'SHM'}) == 'SHM'
    assert transports({}, node_env={'FASTDDS_BUILTIN_TRANSPORTS': 'LARGE_DATA'}) == 'LARGE_DATA'
    assert transports({}, setting='') is None
    assert transports({}, setting='DEFAULT') == 'DEFAULT'
    with pytest.raises(ValueError, match='node_dds_transports.*UDPv4'):
        transports({}, setting='udp')


def test_catalogue_prefers_the_ament_index(tmp_path):
    exe = tmp_path / 'lib' / 'demo' / 'run'
    exe.parent.mkdir(parents=True)
    exe.write_text('#!/bin/sh\n')
    exe.chmod(0o755)
    d = load_mapping(deployment_dict({
        'n': {'launch': {'package': 'demo', 'executable': 'run'}, 'cpu': 1.0}}))
    cat = build_catalogue(d, 'a', {'PATH': '/usr/bin'}, ament_prefix=lambda p: str(tmp_path))
    assert cat['n'].argv[0] == str(exe)


@pytest.mark.parametrize('value,text', [
    (True, 'true'), (3, '3'), (2.5, '2.5'), ('x y', "'x y'"), ("it's", "'it''s'"),
    ('true', "'true'"), ([1.0, 2.0], '[1.0, 2.0]'), (['a', 'b'], "['a', 'b']")])
def test_parameter_values_keep_their_type(value, text):
    assert format_parameter(value) == text


@pytest.mark.parametrize('code,words', [
    (0, 'exited with status 0'), (3, 'exited with status 3'),
    (-signal.SIGKILL, 'killed by SIGKILL (Killed)'), (-signal.SIGSEGV, 'SIGSEGV')])
def test_exit_descriptions(code, words):
    assert words in procs.describe_exit(code)


# --- supervisor ---------------------------------------------------------------------------

def test_start_ready_and_stop(make_sup):
    # A generous SIGINT grace: a loaded machine may still be starting the interpreter.
    sup = make_sup([py_entry('n', SLEEPER)], settings=t.AgentSettings(
        sigint_grace_s=10.0, sigterm_grace_s=1.0, readiness_timeout_s=5.0))
    now = time.monotonic()
    sup.start('n', now)
    r = sup.reports()['n']
    assert r.state == 'starting' and r.pid > 0 and not r.ready
    pid = r.pid
    assert os.getpgid(pid) == pid and os.getsid(pid) == pid   # its own session and group
    # Just started: its exec may still be setting up the environment the kernel shows.
    assert procs.environ_value(pid, ENV_INSTANCE, exec_wait_s=5.0)
    assert drive(sup, lambda: sup.reports()['n'].ready, visible=lambda e: e.name == 'n')
    assert sup.reports()['n'].state == 'running'
    assert sup.pids() == {'n': pid}
    state = json.load(open(sup.state_path))
    assert state['nodes']['n']['pid'] == pid
    sup.stop('n', time.monotonic())
    assert sup.reports()['n'].state == 'stopping'
    assert drive(sup, lambda: sup.reports()['n'].state == 'stopped', timeout=15.0)
    r = sup.reports()['n']
    # SIGINT alone ended it (during interpreter start-up Python exits with status 1 instead).
    assert r.pid == 0 and r.exit_reason.startswith('stopped (')
    assert 'after SIG' not in r.exit_reason
    assert gone(pid)
    assert json.load(open(sup.state_path))['nodes'] == {}
    log = open(sup.log_path('n')).read()
    assert 'starting' in log


def test_a_broken_dds_port_file_is_cleared_before_a_start(make_sup, tmp_path):
    shm_dir = tmp_path / 'shm'
    shm_dir.mkdir()
    broken = shm_dir / 'fastrtps_port7413'
    broken.write_bytes(b'')
    old = time.time() - 60
    os.utime(broken, (old, old))
    sup = make_sup([py_entry('n', SLEEPER)])
    sup.shm_dir = str(shm_dir)
    sup.start('n', time.monotonic())
    assert not broken.exists()
    assert any(level == 'warn' and 'fastrtps_port7413' in text for level, text in sup.events)
    assert sup.reports()['n'].state == 'starting'


def test_node_nice_runs_the_node_below_the_agent(make_sup):
    """agent.node_nice: the node (and every thread it starts) runs at that niceness, same pid,
    so a CPU-bound node cannot starve the agent's monitors."""
    import dataclasses
    sup = make_sup([py_entry('n', 'import threading, time\n'
                                  'threading.Thread(target=time.sleep, args=(60,)).start()\n'
                                  'time.sleep(60)')],
                   settings=dataclasses.replace(FAST, node_nice=7, readiness_timeout_s=30.0))
    sup.start('n', time.monotonic())
    pid = sup.reports()['n'].pid
    proc = psutil.Process(pid)
    assert wait_for(lambda: 'python' in ' '.join(proc.cmdline()) and proc.num_threads() >= 2)
    assert proc.nice() == os.nice(0) + 7
    for thread in proc.threads():
        assert psutil.Process(thread.id).nice() == os.nice(0) + 7
    assert procs.environ_value(pid, ENV_INSTANCE)       # the same process the agent tracks


def test_readiness_times_out_without_the_graph(make_sup):
    sup = make_sup([py_entry('n', SLEEPER)])
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running', timeout=5.0)
    r = sup.reports()['n']
    assert not r.ready and 'not visible in the ROS graph' in r.exit_reason


def test_ignoring_sigint_and_sigterm_ends_in_sigkill(make_sup):
    stubborn = os.path.join(FIXTURES, 'agent_stubborn.py')
    e = py_entry('stubborn', '')
    e = Entry(name='stubborn', argv=(sys.executable, stubborn), env=e.env, ros_name='stubborn')
    sup = make_sup([e])
    sup.start('stubborn', time.monotonic())
    log = sup.log_path('stubborn')
    assert wait_for(lambda: os.path.exists(log) and 'ignoring' in open(log).read(), 10.0)
    pid = sup.pids()['stubborn']
    t0 = time.monotonic()
    sup.stop('stubborn', t0)
    assert drive(sup, lambda: sup.reports()['stubborn'].state == 'stopped', timeout=10.0)
    elapsed = time.monotonic() - t0
    assert elapsed >= FAST.sigint_grace_s + FAST.sigterm_grace_s
    assert 'SIGKILL' in sup.reports()['stubborn'].exit_reason
    texts = ' '.join(text for _, text in sup.events)
    assert 'sending SIGTERM' in texts and 'sending SIGKILL' in texts
    assert gone(pid) and not procs.session_members(pid)


def read_pids(path):
    assert wait_for(lambda: os.path.exists(path), 10.0), 'forker never wrote its pids'
    return [int(x) for x in open(path).read().split()]


@pytest.mark.parametrize('how', ['stop', 'crash'])
def test_grandchildren_do_not_survive(make_sup, tmp_path, how):
    pids_file = str(tmp_path / 'pids')
    base = py_entry('forker', '')
    e = Entry(name='forker', argv=(sys.executable, os.path.join(FIXTURES, 'agent_forker.py'),
                                   pids_file), env=base.env, ros_name='forker')
    sup = make_sup([e])
    sup.start('forker', time.monotonic())
    parent, grandchild = read_pids(pids_file)
    assert psutil.Process(grandchild).ppid() == parent
    if how == 'stop':
        sup.stop('forker', time.monotonic())
        assert drive(sup, lambda: sup.reports()['forker'].state == 'stopped')
    else:
        os.kill(parent, signal.SIGKILL)
        assert drive(sup, lambda: sup.reports()['forker'].state in ('backoff', 'starting')
                     and sup.reports()['forker'].pid != parent)
        assert 'SIGKILL' in sup.reports()['forker'].exit_reason or \
            sup.reports()['forker'].restarts == 1
    assert wait_for(lambda: gone(grandchild), 5.0)
    assert gone(parent)


def test_crash_is_reported_and_restarted_at_once_the_first_time(make_sup):
    sup = make_sup([py_entry('n', SLEEPER)])
    sup.start('n', time.monotonic())
    first = sup.pids()['n']
    os.kill(first, signal.SIGKILL)
    # The step that finds the exit starts the node again: no backoff state in between.
    assert drive(sup, lambda: sup.reports()['n'].restarts == 1)
    r = sup.reports()['n']
    assert r.state == 'starting' and r.pid not in (0, first)
    assert r.exit_reason.startswith('killed by SIGKILL (Killed)')     # until it is up
    assert any('crashed' in text for _, text in sup.events)
    assert drive(sup, lambda: sup.reports()['n'].state == 'running', visible=lambda e: True)
    assert sup.reports()['n'].exit_reason == ''


def test_backoff_doubles_up_to_the_maximum(make_sup):
    settings = t.AgentSettings(sigint_grace_s=0.2, sigterm_grace_s=0.2, readiness_timeout_s=5.0,
                               restart_backoff_s=0.1, restart_backoff_max_s=0.4)
    sup = make_sup([py_entry('n', 'raise SystemExit(3)')], settings=settings)
    sup.start('n', time.monotonic())
    starts = []

    def step():
        sup.step(time.monotonic())
        r = sup.reports()['n']
        if r.state == 'starting' and (not starts or starts[-1][1] != r.restarts):
            starts.append((time.monotonic(), r.restarts))

    assert wait_for(lambda: len(starts) >= 5, 15.0, step=step)
    gaps = [b[0] - a[0] for a, b in zip(starts, starts[1:])]
    # No backoff for the first crash, then 0.1, 0.2, 0.4 s, plus the time the process takes to
    # exit: a crash loop is held back.
    assert gaps[1] >= 0.1 and gaps[2] >= 0.2 and gaps[3] >= 0.4
    assert sup.reports()['n'].exit_reason == 'exited with status 3' or \
        sup.reports()['n'].state == 'starting'


def test_a_long_healthy_run_makes_the_next_crash_a_first_one(make_sup):
    sup = make_sup([py_entry('n', SLEEPER)])      # restart_backoff_max_s 1.0: a healthy run
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running')
    for expected_delay in (0.0, 0.2):
        pid = sup.pids()['n']
        os.kill(pid, signal.SIGKILL)
        assert drive(sup, lambda: any('crashed' in text for _, text in sup.events))
        assert any(f'restarting in {expected_delay:g} s' in text for _, text in sup.events)
        sup.events.clear()
        assert drive(sup, lambda: sup.pids().get('n', pid) != pid, timeout=5.0)
    assert drive(sup, lambda: sup.reports()['n'].state == 'running')
    healthy_since = time.monotonic()      # running as long as restart_backoff_max_s, and more
    assert drive(sup, lambda: time.monotonic() - healthy_since > 1.2, timeout=5.0)
    os.kill(sup.pids()['n'], signal.SIGKILL)
    assert drive(sup, lambda: any('crashed' in text for _, text in sup.events))
    assert any('restarting in 0 s' in text for _, text in sup.events)
    sup.events.clear()
    # The same with no step during the healthy run (an idle agent steps once a second at most):
    # the crash is judged by how long the node ran, not by a step taken meanwhile.
    assert drive(sup, lambda: sup.reports()['n'].state == 'running')
    pid = sup.pids()['n']
    os.kill(pid, signal.SIGKILL)          # a second crash at once: the next waits 0.2 s
    assert drive(sup, lambda: sup.reports()['n'].state == 'running'
                 and sup.pids()['n'] != pid, timeout=5.0)
    assert any('restarting in 0.2 s' in text for _, text in sup.events)
    sup.events.clear()
    time.sleep(1.2)
    os.kill(sup.pids()['n'], signal.SIGKILL)
    assert drive(sup, lambda: any('crashed' in text for _, text in sup.events))
    assert any('restarting in 0 s' in text for _, text in sup.events), sup.events


def test_an_exit_wakes_the_watcher_without_polling():
    woken = threading.Event()
    watcher = ExitWatcher(woken.set)
    proc = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(0.3)'])
    try:
        assert watcher.watch(proc.pid)
        assert not woken.is_set()
        assert woken.wait(10.0)
        assert proc.wait(5.0) == 0          # watching reaps nothing: the supervisor does
    finally:
        proc.kill()
        proc.wait()
    assert not watcher.watch(proc.pid)      # gone: nothing to watch


def test_unstartable_entry_fails_without_spawning(make_sup):
    sup = make_sup([Entry(name='n', argv=(), problem='executable not found')])
    sup.start('n', time.monotonic())
    r = sup.reports()['n']
    assert r.state == 'failed' and r.exit_reason == 'executable not found' and r.pid == 0
    with pytest.raises(KeyError, match='not in the catalogue'):
        sup.start('intruder', time.monotonic())


def test_adoption_after_a_restart(make_sup):
    e = py_entry('n', SLEEPER)
    first = make_sup([e])
    first.start('n', time.monotonic())
    pid = first.pids()['n']
    # The first supervisor disappears without stopping anything (the agent was killed).
    second = make_sup([e])
    notes = second.adopt(time.monotonic())
    assert notes == [f'n: adopted pid {pid}']
    assert second.pids() == {'n': pid} and second.wanted() == ('n',)
    assert second.reports()['n'].state == 'starting'
    assert drive(second, lambda: second.reports()['n'].ready, visible=lambda e: True)
    # The adopted process dies: reported and restarted. Both supervisors are this process, so
    # it is still our child (as after an agent's restart in place): reaped, with its status.
    os.kill(pid, signal.SIGKILL)
    assert drive(second, lambda: second.reports()['n'].state in ('backoff', 'starting')
                 and second.reports()['n'].pid != pid)
    assert 'killed by SIGKILL' in second.reports()['n'].exit_reason or \
        second.reports()['n'].restarts == 1
    assert not psutil.pid_exists(pid)                   # no zombie left


def test_adoption_holds_across_a_clock_step_and_reads_an_earlier_versions_file(make_sup):
    """The wall clock stepped (a robot's first NTP fix) while the agent was down: its nodes
    are still adopted, not left running unsupervised. Stepping this machine's clock would
    disturb every other process, so the step is stood in for by what it does to a record:
    its wall-clock start is 2 s off the process's start as read after the step."""
    e = py_entry('n', SLEEPER)
    first = make_sup([e])
    first.start('n', time.monotonic())
    pid = first.pids()['n']
    with open(first.state_path) as f:
        saved = json.load(f)
    assert saved['boot_id'] == procs.boot_id()
    assert saved['nodes']['n']['start_ticks'] == procs.start_ticks(pid)
    assert abs(saved['nodes']['n']['started'] - procs.create_time(pid)) < 0.05
    saved['nodes']['n']['started'] -= 2.0
    with open(first.state_path, 'w') as f:
        json.dump(saved, f)
    second = make_sup([e])
    assert second.adopt(time.monotonic()) == [f'n: adopted pid {pid}']
    # A file of an earlier version (wall-clock starts only) is read as that version did:
    # adopted when its start matches, gone after the step.
    del saved['nodes']['n']['start_ticks']
    saved['nodes']['n']['started'] = procs.create_time(pid)
    with open(first.state_path, 'w') as f:
        json.dump(saved, f)
    third = make_sup([e])
    assert third.adopt(time.monotonic()) == [f'n: adopted pid {pid}']
    saved['nodes']['n']['started'] -= 2.0
    with open(first.state_path, 'w') as f:
        json.dump(saved, f)
    assert make_sup([e]).adopt(time.monotonic()) == [f'n: recorded pid {pid} is gone']
    saved['boot_id'] = 'an-earlier-boot'
    with open(first.state_path, 'w') as f:
        json.dump(saved, f)
    assert 'before this machine last booted' in make_sup([e]).adopt(time.monotonic())[0]
    third.stop('n', time.monotonic())
    assert drive(third, third.all_stopped, timeout=5.0)


def test_adoption_refuses_a_reused_pid(make_sup, tmp_path):
    e = py_entry('n', SLEEPER)
    sup = make_sup([e])
    # A record naming a live process that is not ours: this test's own pid.
    me = psutil.Process()
    records = {
        'n': {'pid': me.pid, 'start_ticks': procs.start_ticks(me.pid), 'instance': 'x' * 32,
              'argv': list(e.argv), 'restarts': 0},
    }
    with open(sup.state_path, 'w') as f:
        json.dump({'version': 1, 'deployment': 'd', 'scale': 's', 'nodes': records}, f)
    notes = sup.adopt(time.monotonic())
    assert 'token differs' in notes[0] and sup.pids() == {}
    records['n']['start_ticks'] -= 1                       # right pid, another start
    with open(sup.state_path, 'w') as f:
        json.dump({'version': 1, 'deployment': 'd', 'scale': 's', 'nodes': records}, f)
    assert 'gone' in sup.adopt(time.monotonic())[0] and sup.pids() == {}
    with open(sup.state_path, 'w') as f:
        f.write('{not json')
    assert 'unreadable' in sup.adopt(time.monotonic())[0]


def test_adopted_process_no_longer_in_the_catalogue_is_stopped(make_sup):
    e = py_entry('old', SLEEPER)
    first = make_sup([e])
    first.start('old', time.monotonic())
    pid = first.pids()['old']
    second = make_sup([py_entry('new', SLEEPER)])
    notes = second.adopt(time.monotonic())
    assert 'not in the catalogue' in notes[0]
    assert drive(second, second.all_stopped, timeout=5.0)
    assert gone(pid)
    with pytest.raises(KeyError):
        second.start('old', time.monotonic())


# --- move orders (pure, fake clock) -------------------------------------------------------

def move_deployment():
    return load_mapping(deployment_dict({
        'sbs': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0},
        'sbs2': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0,
                 'move_order': 'stop_before_start'},
        'pinned': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'residence': ['a']},
        'manual': {'cpu': 1.0, 'managed': False, 'residence': ['a']},
    }))


def layout(gen, assignments, name='unit'):
    return protocol.Layout(generation=gen, deployment=name, assignments=assignments,
                           reason='test', stamp=0.0)


def agent_state(scale, gen, nodes):
    return protocol.AgentState(scale=scale, generation=gen, stamp=0.0, nodes={
        n: protocol.NodeReport(state=s, pid=1, since=0.0, restarts=0, ready=r, exit_reason='')
        for n, (s, r) in nodes.items()})


def reconciler(scale):
    d = move_deployment()
    return Reconciler(d, scale, ('sbs', 'sbs2', 'pinned') if scale == 'a' else ('sbs', 'sbs2'),
                      readiness_timeout_s=10.0, agent_timeout_s=3.0)


def test_nothing_runs_before_a_layout_and_adopted_nodes_stay():
    r = reconciler('a')
    assert r.desired(0.0, ()) == set()
    assert r.desired(0.0, ('sbs',)) == {'sbs'}


def test_bad_layouts_change_nothing():
    r = reconciler('a')
    assert r.apply_layout(layout(5, {'sbs': 'a', 'sbs2': 'a', 'pinned': 'a'}), 0.0).applied
    before = dict(r.assignments)
    v = r.apply_layout(layout(4, {'sbs': 'b'}), 1.0)
    assert not v.applied and 'not newer' in v.warnings[0]
    assert not r.apply_layout(layout(5, {'sbs': 'b'}), 1.0).applied
    v = r.apply_layout(layout(9, {'sbs': 'b'}, name='other'), 1.0)
    assert not v.applied and 'other' in v.warnings[0]
    assert r.assignments == before and r.generation == 5
    v = r.apply_layout(layout(6, {'ghost': 'a', 'sbs': 'mars', 'pinned': 'b', 'manual': 'a',
                                  'sbs2': 'a'}), 2.0)
    assert v.applied and r.generation == 6
    text = ' '.join(v.warnings)
    assert "'ghost': unknown node" in text and "unknown scale 'mars'" in text
    assert "may not run on 'b'" in text and 'not a managed node' in text
    assert r.assignments == before


def test_start_before_stop_keeps_the_old_copy_until_the_new_one_is_ready():
    r = reconciler('a')
    r.apply_layout(layout(1, {'sbs': 'a', 'sbs2': 'a', 'pinned': 'a'}), 0.0)
    assert r.desired(0.0, ()) == {'sbs', 'sbs2', 'pinned'}
    r.apply_layout(layout(2, {'sbs': 'b', 'sbs2': 'a', 'pinned': 'a'}), 10.0)
    assert 'sbs' in r.desired(10.0, ('sbs', 'sbs2', 'pinned'))
    r.peer_state(agent_state('b', 2, {'sbs': ('starting', False)}), 11.0)
    assert 'sbs' in r.desired(11.0, ('sbs', 'sbs2', 'pinned'))
    assert 'running and ready on b' in r.waiting['sbs']
    # A report from before the move does not count.
    r.peer_state(agent_state('b', 1, {'sbs': ('running', True)}), 12.0)
    assert 'sbs' in r.desired(12.0, ('sbs', 'sbs2', 'pinned'))
    r.peer_state(agent_state('b', 2, {'sbs': ('running', True)}), 12.5)
    assert 'sbs' not in r.desired(12.5, ('sbs', 'sbs2', 'pinned'))
    assert r.copies_elsewhere('sbs', 12.5) == 1 and r.copies_elsewhere('sbs', 20.0) == 0
    # Let go for good: a later blink of the new copy does not bring the old one back.
    r.peer_state(agent_state('b', 2, {'sbs': ('backoff', False)}), 12.6)
    assert 'sbs' not in r.desired(12.7, ('sbs', 'sbs2', 'pinned'))
    # A new layout placing it here again does.
    r.apply_layout(layout(3, {'sbs': 'a'}), 13.0)
    assert 'sbs' in r.desired(13.0, ('sbs', 'sbs2', 'pinned'))


def test_a_remote_copy_moved_home_to_a_standby_copy_is_let_go_at_once():
    d = load_mapping(deployment_dict({
        'lc': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'lifecycle': True,
               'standby': True},
        'plain': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0},
    }))
    remote = Reconciler(d, 'b', ('lc', 'plain'), readiness_timeout_s=10.0, agent_timeout_s=3.0)
    remote.apply_layout(layout(1, {'lc': 'b', 'plain': 'b'}), 0.0)
    assert remote.desired(0.0, ('lc', 'plain')) == {'lc', 'plain'}
    remote.apply_layout(layout(2, {'lc': 'a', 'plain': 'a'}), 10.0)
    # The master's standby copy serves within milliseconds: nothing heard from it is awaited.
    # A plain node starts cold there: kept here until it runs and is ready.
    assert remote.desired(10.0, ('lc', 'plain')) == {'plain'}
    assert 'running and ready on a' in remote.waiting['plain']
    # Moving the other way (a remote copy taking over from the master's), the master keeps its
    # copy until the remote one serves.
    master = Reconciler(d, 'a', ('lc', 'plain'), readiness_timeout_s=10.0, agent_timeout_s=3.0)
    master.apply_layout(layout(1, {'lc': 'a'}), 0.0)
    master.apply_layout(layout(2, {'lc': 'b'}), 10.0)
    assert master.desired(10.0, ('lc',)) == {'lc'}
    assert 'running and ready on b' in master.waiting['lc']


def test_start_before_stop_keeps_the_old_copy_until_this_scale_hears_the_new_one():
    r = reconciler('a')
    r.apply_layout(layout(1, {'sbs': 'a'}), 0.0)
    heard = {'sbs': False}
    asked = []

    def heard_here(node, since):
        asked.append((node, since))
        return heard[node]

    def moved_and_ready(gen, t):
        """Back here at t, away at t + 1 (layout generation gen), ready there at t + 1.5."""
        r.apply_layout(layout(gen - 1, {'sbs': 'a'}), t)
        r.apply_layout(layout(gen, {'sbs': 'b'}), t + 1.0)
        r.peer_state(agent_state('b', gen, {'sbs': ('running', True)}), t + 1.5)
    moved_and_ready(3, 4.0)
    # Ready on b, but this scale has not heard the new copy yet: kept.
    assert r.desired(5.5, ('sbs',), heard_here) == {'sbs'}
    assert 'heard here from b (ready there)' in r.waiting['sbs'] and asked == [('sbs', 5.0)]
    heard['sbs'] = None                       # nothing here can tell: readiness alone decides
    assert r.desired(6.0, ('sbs',), heard_here) == set()
    # Heard: let go at once.
    moved_and_ready(5, 7.0)
    heard['sbs'] = False
    assert r.desired(8.5, ('sbs',), heard_here) == {'sbs'}
    heard['sbs'] = True
    assert r.desired(8.6, ('sbs',), heard_here) == set()
    # Never heard: kept at most HEAR_PATIENCE_S past the ready report.
    moved_and_ready(7, 9.0)
    heard['sbs'] = False
    assert r.desired(10.5, ('sbs',), heard_here) == {'sbs'}
    r.peer_state(agent_state('b', 7, {'sbs': ('running', True)}), 15.0)
    assert r.desired(10.5 + HEAR_PATIENCE_S - 0.1, ('sbs',), heard_here) == {'sbs'}
    assert r.desired(10.5 + HEAR_PATIENCE_S, ('sbs',), heard_here) == set()
    # Not asked before the new copy is ready there.
    r.apply_layout(layout(8, {'sbs': 'a'}), 21.0)
    r.apply_layout(layout(9, {'sbs': 'b'}), 22.0)
    asked.clear()
    assert r.desired(22.5, ('sbs',), heard_here) == {'sbs'} and asked == []


def test_start_before_stop_gives_up_waiting_after_the_readiness_timeout():
    r = reconciler('a')
    r.apply_layout(layout(1, {'sbs': 'a'}), 0.0)
    r.apply_layout(layout(2, {'sbs': 'b'}), 5.0)
    assert r.desired(14.9, ('sbs',)) == {'sbs'}
    assert r.desired(15.0, ('sbs',)) == set()


def test_stop_before_start_waits_for_the_other_copy_to_stop():
    gain = reconciler('b')
    gain.apply_layout(layout(1, {'sbs2': 'a'}), 0.0)
    gain.peer_state(agent_state('a', 1, {'sbs2': ('running', True)}), 0.5)
    assert gain.desired(1.0, ()) == set()
    gain.apply_layout(layout(2, {'sbs2': 'b'}), 1.0)
    assert gain.desired(1.0, ()) == set()
    assert 'waiting for a to stop it' in gain.waiting['sbs2']
    gain.peer_state(agent_state('a', 2, {'sbs2': ('stopping', False)}), 1.5)
    assert gain.desired(1.6, ()) == set()
    gain.peer_state(agent_state('a', 2, {'sbs2': ('stopped', False)}), 2.0)
    assert gain.desired(2.0, ()) == {'sbs2'}
    # The losing side stops at once.
    lose = reconciler('a')
    lose.apply_layout(layout(1, {'sbs2': 'a'}), 0.0)
    lose.apply_layout(layout(2, {'sbs2': 'b'}), 1.0)
    assert lose.desired(1.0, ('sbs2',)) == set()


def test_stop_before_start_waits_for_a_lagging_agent_but_not_a_silent_one():
    gain = reconciler('b')
    gain.peer_state(agent_state('a', 1, {'sbs2': ('stopped', False)}), 0.0)
    gain.apply_layout(layout(2, {'sbs2': 'b'}), 0.5)
    assert gain.desired(1.0, ()) == set()
    assert 'apply generation 2' in gain.waiting['sbs2']
    gain.peer_state(agent_state('a', 1, {'sbs2': ('running', True)}), 1.0)
    assert gain.desired(3.9, ()) == set()
    gain.heard_master(4.0)                       # the decider is heard: the link is up
    assert gain.desired(4.1, ()) == {'sbs2'}     # silent for more than agent_timeout_s


def test_unknown_peers_are_ignored():
    r = reconciler('a')
    assert 'unknown scale' in r.peer_state(agent_state('mars', 1, {}), 0.0)
    assert r.peer_state(agent_state('a', 1, {'sbs': ('running', True)}), 0.0) is None
    assert r.copies_elsewhere('sbs', 0.0) == 0


def test_a_live_copy_can_be_restarted_at_once(make_sup):
    sup = make_sup([py_entry('n', SLEEPER)])
    sup.start('n', time.monotonic())
    pid = sup.pids()['n']
    assert drive(sup, lambda: sup.reports()['n'].ready, visible=lambda e: True)
    restarts = sup.reports()['n'].restarts
    assert sup.restart('n', time.monotonic(), 'its lifecycle did not reach active')
    assert gone(pid) and not procs.session_members(pid)
    r = sup.reports()['n']
    assert r.state == 'backoff' and 'did not reach active' in r.exit_reason
    # Respawned at the next step, without backoff.
    sup.step(time.monotonic(), visible=lambda e: True)
    assert sup.pids()['n'] != pid and sup.reports()['n'].restarts == restarts + 1
    assert not sup.restart('ghost', time.monotonic(), 'x')
    sup.stop_all(time.monotonic())
    assert drive(sup, sup.all_stopped)


def test_process_table_and_trees_in_one_pass():
    table = procs.process_table()
    me = os.getpid()
    assert table[me][0] == os.getppid() and table[me][1] > 0.0
    synthetic = {10: (1, 1.0), 11: (10, 2.0), 12: (11, 0.5), 20: (1, 4.0), 21: (20, 1.0)}
    trees = procs.tree_cpu_seconds(synthetic, {'a': 10, 'b': 20, 'leaf': 12, 'gone': 99})
    assert trees == {'a': {10: 1.0, 11: 2.0, 12: 0.5}, 'b': {20: 4.0, 21: 1.0},
                     'leaf': {12: 0.5}, 'gone': {}}


def test_the_memory_in_use_reads_as_psutil_has_it():
    assert abs(procs.memory_percent() - psutil.virtual_memory().percent) < 1.0


def test_the_table_of_a_few_trees_reads_only_them():
    """tree_table: the processes of the given trees (a child started by another thread and a
    grandchild included) as process_table has them, and nothing else of the machine; reading
    the main threads only, what an earlier full pass found."""
    me = os.getpid()
    started = []
    thread = threading.Thread(target=lambda: started.append(subprocess.Popen(
        ['sh', '-c', 'sleep 30 & wait'], start_new_session=True)))
    thread.start()
    thread.join()
    child = started[0]
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not psutil.Process(child.pid).children():
            time.sleep(0.02)
        grandchild = psutil.Process(child.pid).children()[0].pid
        table = procs.tree_table([me, 999999999])
        assert {me, child.pid, grandchild} <= set(table) and os.getppid() not in table
        full = procs.process_table()
        assert all(table[pid][0] == full[pid][0] for pid in (child.pid, grandchild))
        assert table[grandchild][0] == child.pid and table[child.pid][0] == me
        assert procs.tree_table([child.pid]).keys() == {child.pid, grandchild}
        # Main threads only (the thread that started the child has ended, so the main
        # thread lists it now), and what a full pass found.
        assert {child.pid, grandchild} <= set(procs.tree_table([me], all_threads=False))
        partial = procs.tree_table([me], known=set(table), all_threads=False)
        assert {me, child.pid, grandchild} <= set(partial)
        assert partial[grandchild][0] == child.pid
    finally:
        procs.signal_session(child.pid, signal.SIGKILL)
        child.wait(5.0)


def test_a_remote_scale_cut_off_from_the_master_stops_its_migratable_nodes():
    r = reconciler('b')                       # 'a' is the master
    r.heard_master(0.0)                       # the agent's start counts as word from it
    r.apply_layout(layout(1, {'sbs': 'b', 'sbs2': 'b', 'pinned': 'a'}), 0.0)
    assert r.desired(1.0, ()) == {'sbs', 'sbs2'}
    r.peer_state(agent_state('a', 1, {'pinned': ('running', True)}), 2.0)
    assert r.desired(5.0, ('sbs', 'sbs2')) == {'sbs', 'sbs2'}      # 3 s: within the timeout
    # Neither the master's agent nor the decider heard for agent_timeout_s (3 s): stopped.
    assert r.desired(5.1, ('sbs', 'sbs2')) == set()
    assert 'cut off from a' in r.waiting['sbs']
    # Word from the master again is not enough: the layout held is the one the decider has
    # overridden; they stay stopped until a newer one arrives.
    r.peer_state(agent_state('a', 1, {'pinned': ('running', True)}), 9.0)
    assert not r.cut_off(9.0)
    assert r.desired(9.0, ()) == set()
    r.apply_layout(layout(2, {'sbs': 'b', 'sbs2': 'a', 'pinned': 'a'}), 9.5)
    assert r.desired(9.5, ()) == {'sbs'}
    # The decider's output keeps the contact alive without the master's agent.
    r.heard_master(12.0)
    assert r.desired(15.0, ('sbs',)) == {'sbs'}
    assert r.desired(15.1, ('sbs',)) == set()


def test_the_master_itself_is_never_cut_off():
    r = reconciler('a')
    r.heard_master(0.0)
    r.apply_layout(layout(1, {'sbs': 'a', 'sbs2': 'a', 'pinned': 'a'}), 0.0)
    assert not r.cut_off(100.0)
    assert r.desired(100.0, ('sbs', 'sbs2', 'pinned')) == {'sbs', 'sbs2', 'pinned'}


def test_a_copy_cut_off_from_the_master_stands_down_when_a_peer_serves_it_under_a_newer_layout():
    """Three scales: the server (c) is cut off from the master (a) but still hears the laptop
    (b). The decider moved 'sbs' from c to b; b reports it serving under the newer layout. c
    stands its copy down about a second after the master fell silent, not agent_timeout_s
    later: b's subscribers never hear two copies for long."""
    d = load_mapping({'/**': {'ros__parameters': {
        'deployment': {'name': 'unit'},
        'scales': {'names': ['a', 'b', 'c'],
                   'a': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                   'b': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 300.0},
                   'c': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 600.0}},
        'links': {'names': ['ab', 'ac', 'bc'],
                  'ab': {'ends': ['a', 'b'], 'bandwidth_kbps': 1000.0},
                  'ac': {'ends': ['a', 'c'], 'bandwidth_kbps': 1000.0},
                  'bc': {'ends': ['b', 'c'], 'bandwidth_kbps': 1000.0}},
        'nodes': {'names': ['sbs'],
                  'sbs': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0}},
    }}})
    r = Reconciler(d, 'c', ('sbs',), readiness_timeout_s=10.0, agent_timeout_s=4.0)
    r.heard_master(0.0)
    r.apply_layout(layout(3, {'sbs': 'c'}), 0.0)
    assert r.desired(0.5, ('sbs',)) == {'sbs'}

    def laptop(gen, at, decider=None, term=None):
        state = agent_state('b', gen, {'sbs': ('running', True)})
        state.decider, state.term = decider, term
        r.peer_state(state, at)
    # Heard from the master 0.5 s ago: the layout is on its way; the handover decides.
    r.heard_master(0.5)
    laptop(4, 1.0)
    assert r.desired(1.0, ('sbs',)) == {'sbs'}
    # A second of silence from the master: stand down.
    laptop(4, 1.4)
    assert r.desired(1.5, ('sbs',)) == set()
    assert 'stood down: b serves it under layout generation 4' in r.waiting['sbs']
    # Stood down (no longer serving here), it stays down while b serves it: not started or
    # activated again at the next step, and said in the same words (the agent logs it once).
    said = r.waiting['sbs'].split(' (')[0]
    for k in range(1, 20):
        laptop(4, 1.5 + 0.1 * k)
        assert r.desired(1.5 + 0.1 * k, ()) == set()
        assert r.waiting['sbs'].split(' (')[0] == said
    # A peer under the same generation, or following another decider, is not a reason.
    r2 = Reconciler(d, 'c', ('sbs',), readiness_timeout_s=10.0, agent_timeout_s=4.0)
    r2.heard_master(0.0)
    r2.apply_layout(layout(3, {'sbs': 'c'}), 0.0)
    for gen, decider in ((3, None), (9, 'another')):
        state = agent_state('b', gen, {'sbs': ('running', True)})
        state.decider = decider
        r2.peer_state(state, 1.4)
        assert r2.desired(1.5, ('sbs',)) == {'sbs'}


# --- timers ---------------------------------------------------------------------------------
def test_a_cadence_runs_each_job_at_its_period_from_one_tick():
    from anyscale_manager.nodes.monitors.common import Cadence
    runs = []
    c = Cadence(0.05, start=10.0)
    c.every(0.05, lambda: runs.append('drain'))
    c.every(0.2, lambda: runs.append('publish'))
    c.every(1.0, lambda: runs.append('resolve'))
    # A timer's ticks, a little early or late: each job keeps its own period.
    for i in range(1, 41):
        c.run(10.0 + 0.05 * i + (0.004 if i % 2 else -0.004))
    assert runs.count('drain') == 40 and runs.count('publish') == 10
    assert runs.count('resolve') == 2
    assert runs[:5] == ['drain'] * 4 + ['publish']      # due together: in the order added
    # Periods missed while the executor was busy are skipped, not caught up.
    runs.clear()
    c.run(20.0)
    c.run(20.05)
    assert runs == ['drain', 'publish', 'resolve', 'drain']
    with pytest.raises(ValueError, match='faster than the tick'):
        c.every(0.01, lambda: None)


class _TimerCountingNode:
    """Enough of an rclpy node for the monitors to be built on: it counts their timers."""

    def __init__(self, name='anyscale_agent_a', *args, **kwargs):
        self.name = name
        self.timers = []
        self.context = None

    def create_timer(self, period_s, callback, callback_group=None):
        self.timers.append((period_s, callback))
        return object()

    def create_publisher(self, *args, **kwargs):
        return object()

    def create_subscription(self, *args, **kwargs):
        return object()

    def get_logger(self):
        import logging
        return logging.getLogger('timer-count')

    def get_name(self):
        return self.name

    def get_namespace(self):
        return '/'

    def resolve_topic_name(self, topic):
        return topic

    def destroy_timer(self, timer):
        pass

    destroy_subscription = destroy_publisher = destroy_timer

    def destroy_node(self):
        pass


def many_connections_deployment(count=40):
    nodes = {f'n{i}': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0} for i in range(count)}
    connections = {f'c{i}': {'topic': f'/t{i}', 'publisher': f'n{i}',
                             'subscriber': f'n{(i + 1) % count}',
                             'msg_type': 'std_msgs/msg/String', 'freq_min_hz': 5.0,
                             'tolerance_s': 2.0}
                   for i in range(count)}
    data = deployment_dict(nodes)
    params = data['/**']['ros__parameters']
    params['scales'] = {'names': ['a', 'b', 'c'],
                        'a': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                        'b': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100.0},
                        'c': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 100.0}}
    params['connections'] = dict({'names': list(connections)}, **connections)
    return load_mapping(data)


def test_the_monitors_use_one_timer_each_however_many_connections_and_links(monkeypatch):
    """rclpy's events executor warns from 8 timers on one clock, and every monitor shares the
    agent node's: the agent keeps 3 (its loop, its heartbeat, the one-shot exit wake)."""
    from anyscale_manager.nodes import monitors
    from anyscale_manager.nodes.monitors import probes
    monkeypatch.setattr(probes, 'Node', _TimerCountingNode)
    d = many_connections_deployment()
    node = _TimerCountingNode()
    built = [monitors.ScaleMonitor(node, d, 'a', pids=dict)]
    try:
        built.append(monitors.LinkMonitor(node, d, 'a'))      # it watches two links
        built.append(monitors.ProbeManager(node, d, 'a', handovers=True))
        built[-1].set_connections(c.name for c in d.connections)
        assert len(built[-1].connections) == 40
        assert len(node.timers) == 3
    finally:
        for monitor in built:
            monitor.destroy()


def test_the_scale_monitor_says_what_cores_the_file_declares_against_what_it_measures():
    from types import SimpleNamespace
    from anyscale_manager.nodes.monitors.scale import cores_note
    robot = SimpleNamespace(name='robot', cores=1, capacity_cpu=100.0)
    text = cores_note(robot, 2.0, quota_confined=False)
    assert 'this machine has 2 CPUs' in text and 'one busy CPU reads 50' in text
    assert 'the decider judges readings against capacity_cpu 100' in text
    assert 'declares scales.robot.cores: 1, not 2' in text
    assert 'CPU quota of 1 (systemd CPUQuota=100%' in text and 'set scales.robot.cores' in text
    quota = cores_note(SimpleNamespace(name='robot', cores=2, capacity_cpu=200.0), 1.5, True)
    assert quota.startswith('scale monitor for robot: its CPU quota allows 1.5 CPUs')
    same = cores_note(SimpleNamespace(name='robot', cores=2, capacity_cpu=200.0), 2.0, False)
    assert 'declares' not in same and same.endswith('against capacity_cpu 200')
