"""agent.critical_priority: the critical nodes run at real-time priority (agent/priority.py)."""

import dataclasses
import os

import psutil
import pytest

from anyscale_manager.agent import priority
from supervision import FAST, py_entry, wait_for

THREADED = ('import threading, time\n'
            'threading.Thread(target=time.sleep, args=(60,)).start()\n'
            'time.sleep(60)')


def critical(name):
    return dataclasses.replace(py_entry(name, THREADED), critical=True)


def started(sup, name):
    pid = sup.reports()[name].pid
    proc = psutil.Process(pid)
    assert wait_for(lambda: 'python' in ' '.join(proc.cmdline()) and proc.num_threads() >= 2)
    return proc


def policies(proc):
    return {(os.sched_getscheduler(t.id), os.sched_getparam(t.id).sched_priority)
            for t in proc.threads()}


def test_a_critical_node_and_every_thread_it_starts_run_at_real_time_priority(make_sup):
    ok, why = priority.try_realtime(3)
    if not ok:
        pytest.skip(f'this machine refuses real-time priority to its processes: {why}')
    sup = make_sup([critical('odometer'), py_entry('amcl', THREADED)],
                   settings=dataclasses.replace(FAST, critical_priority=3, node_nice=4,
                                                readiness_timeout_s=30.0))
    now = 0.0
    sup.start('odometer', now)
    sup.start('amcl', now)
    assert policies(started(sup, 'odometer')) == {(os.SCHED_RR, 3)}
    heavy = started(sup, 'amcl')
    assert policies(heavy) == {(os.SCHED_OTHER, 0)}
    assert heavy.nice() == os.nice(0) + 4                # node_nice, as before
    said = [(level, text) for level, text in sup.events if 'critical nodes' in text]
    assert said == [('info', 'critical nodes run at real-time priority 3 (SCHED_RR)')]


def test_refused_it_is_said_once_and_the_critical_nodes_run_at_normal_priority(make_sup):
    sup = make_sup([critical('odometer'), critical('odometry')],
                   settings=dataclasses.replace(FAST, critical_priority=3,
                                                readiness_timeout_s=30.0))
    # Stand-in for a machine that refuses the priority (no CAP_SYS_NICE): no chrt to run.
    sup.launch = priority.Launch(3, chrt='/nonexistent/chrt')
    sup.start('odometer', 0.0)
    sup.start('odometry', 0.0)
    for name in ('odometer', 'odometry'):
        assert policies(started(sup, name)) == {(os.SCHED_OTHER, 0)}
        assert sup.reports()[name].state in ('starting', 'running')
    said = [(level, text) for level, text in sup.events if 'critical nodes' in text]
    assert len(said) == 1 and said[0][0] == 'warn'
    assert 'real-time priority 3 refused (/nonexistent/chrt' in said[0][1]
    assert 'agent.critical_priority to 0' in said[0][1]


def test_zero_asks_nothing_of_the_machine():
    launch = priority.Launch(0, chrt='/nonexistent/chrt')
    assert launch.critical_prefix() == ([], '')
    assert launch._prefix is None                       # chrt was never tried


def test_the_first_answer_holds():
    launch = priority.Launch(2)
    prefix, said = launch.critical_prefix()
    again = launch.critical_prefix()
    assert said and again == (prefix, '')
