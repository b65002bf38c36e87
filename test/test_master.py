"""`master`: the master scale's agent and the decider as one process, over real DDS, beside the
away scale's agent as its own process (two scales of this machine, test/home_away.py)."""

import os
import signal
from contextlib import contextmanager

import psutil
import pytest

import home_away as ha
from home_away import runs
from processes import LoggedProcess
from spinning import spin_until


@pytest.fixture
def listener():
    with ha.listening('master_listener') as heard:
        yield heard


def start_master(procs, tmp_path, env, path, scale='home'):
    proc = LoggedProcess(tmp_path / f'master_{scale}.out',
                         [os.path.join(ha.BIN, 'master'), '--ros-args', '--params-file', path,
                          '-p', f'scale:={scale}'], env)
    procs.append(('master', proc))
    return proc


@contextmanager
def master_beside_away(tmp_path, env, ex, name, codes):
    """(master, procs, wait): a `master` on home and an agent on away running
    worker_and_pinned; ``wait(cond, timeout, what)`` spins ``ex`` until ``cond`` (the master's
    end ends it). Both are stopped (SIGINT) at the end, their exit codes put in ``codes``."""
    path = ha.write_deployment(tmp_path, f'{name}_{os.getpid()}',
                               ha.worker_and_pinned(f'/{name}_{os.getpid()}'))
    procs = []
    try:
        master = start_master(procs, tmp_path, env, path)
        ha.start(procs, tmp_path, env, path, 'agent_away', '-p', 'scale:=away')

        def wait(cond, timeout, what):
            spin_until(ex, cond, timeout, what, procs, watch=('master',))
        yield master, procs, wait
    finally:
        codes.update({n: pr.stop() for n, pr in reversed(procs)})


def test_one_process_places_moves_and_stops_the_nodes_as_agent_and_decider_do(
        tmp_path, ros_env, listener):
    ex, seen = listener
    codes = {}
    with master_beside_away(tmp_path, ros_env, ex, 'master', codes) as (master, procs, wait):
        wait(lambda: seen['layouts'], 40.0, 'the first layout')
        # The layouts come from this one process: its decider's pid is the master's.
        assert seen['layouts'][-1].decider.pid == master.proc.pid
        assert seen['layouts'][-1].assignments['pinned'] == 'home'
        wait(lambda: runs(seen, 'away', 'worker') and not runs(seen, 'home', 'worker'), 60.0,
             'the worker moved out to away')
        wait(lambda: runs(seen, 'home', 'pinned'), 20.0, 'pinned running home')
        pinned = seen['states']['home'].nodes['pinned'].pid
        assert psutil.pid_exists(pinned)
        last = seen['layouts'][-1].generation

        # A stop: the decider goes first, so nothing answers the home nodes' stop with a new
        # layout; the agent stops its nodes and the process exits 0.
        assert master.stop(signal.SIGINT) == 0, master.text()[-3000:]
        spin_until(ex, lambda: not psutil.pid_exists(pinned), 10.0, 'pinned stopped')
        assert seen['layouts'][-1].generation == last
        spin_until(ex, lambda: runs(seen, 'away', 'worker'), 5.0,
                   'the worker still running on away', procs, watch=('agent_away',))
    assert codes['agent_away'] == 0


def test_a_scale_that_is_not_the_master_is_refused_and_starts_nothing(tmp_path, ros_env):
    path = ha.write_deployment(tmp_path, f'master_away_{os.getpid()}',
                               ha.worker_and_pinned(f'/master_away_{os.getpid()}'))
    proc = start_master([], tmp_path, ros_env, path, scale='away')
    assert proc.proc.wait(30.0) == 2
    text = proc.text()
    assert "scale 'away' is not the master of deployment" in text and "('home')" in text, text
    assert not (tmp_path / 'log').exists() or not os.listdir(tmp_path / 'log')


def test_sighup_restarts_the_process_in_place_with_its_decider_and_its_nodes_run_on(
        tmp_path, ros_env, listener):
    ex, seen = listener
    codes = {}
    with master_beside_away(tmp_path, ros_env, ex, 'master_hup', codes) as (master, _, wait):
        wait(lambda: seen['layouts'] and runs(seen, 'home', 'pinned')
             and runs(seen, 'away', 'worker'), 60.0, 'pinned home and the worker away')
        pinned = seen['states']['home'].nodes['pinned'].pid
        first = seen['layouts'][-1].decider.id
        master.proc.send_signal(signal.SIGHUP)
        # The same process (exec), a new decider in it, the same nodes adopted.
        wait(lambda: seen['layouts'][-1].decider.id != first, 40.0,
             "a layout of the restarted process's decider")
        assert seen['layouts'][-1].decider.pid == master.proc.pid
        assert seen['layouts'][-1].assignments == {'pinned': 'home', 'worker': 'away'}
        wait(lambda: runs(seen, 'home', 'pinned')
             and seen['states']['home'].nodes['pinned'].pid == pinned, 30.0,
             'the same pinned reported by the restarted agent')
        assert seen['states']['home'].nodes['pinned'].restarts == 0
    assert codes['master'] == 0 and codes['agent_away'] == 0
