"""agent.critical_priority: a critical node runs at real-time priority once it is ready
(agent/priority.py)."""

import dataclasses
import os
import time

import psutil
import pytest

from anyscale_manager.agent import priority
from supervision import drive, FAST, py_entry, wait_for

# A node whose third thread starts after the node is raised: it inherits the policy.
THREADED = ('import threading, time\n'
            'threading.Thread(target=time.sleep, args=(60,)).start()\n'
            'time.sleep(4.0)\n'
            'threading.Thread(target=time.sleep, args=(60,)).start()\n'
            'time.sleep(60)')


def critical(name):
    return dataclasses.replace(py_entry(name, THREADED), critical=True)


def threads_up(sup, name, count):
    proc = psutil.Process(sup.reports()[name].pid)
    assert wait_for(lambda: 'python' in ' '.join(proc.cmdline())
                    and proc.num_threads() >= count)
    return proc


def policies(proc):
    return {(os.sched_getscheduler(t.id), os.sched_getparam(t.id).sched_priority)
            for t in proc.threads()}


def said(sup):
    return [(level, text) for level, text in sup.events if 'critical nodes' in text]


def can_raise():
    """Why this process may not raise a thread to real-time round robin (None: it may). A
    thread of its own is raised and ends."""
    import threading
    why = [None]

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
        except OSError as e:
            why[0] = e.strerror
    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return why[0]


def test_a_critical_node_runs_at_normal_priority_until_settled_then_every_thread_real_time(
        make_sup):
    refused = can_raise()
    if refused:
        pytest.skip(f'this machine refuses real-time priority to its processes: {refused}')
    sup = make_sup([critical('odometer'), py_entry('amcl', THREADED)],
                   settings=dataclasses.replace(FAST, critical_priority=3, node_nice=4,
                                                readiness_timeout_s=30.0))
    sup.start('odometer', time.monotonic())
    sup.start('amcl', time.monotonic())
    odometer = threads_up(sup, 'odometer', 2)
    sup.step(time.monotonic())                         # not seen in the graph yet
    assert policies(odometer) == {(os.SCHED_OTHER, 0)}
    assert drive(sup, lambda: sup.reports()['odometer'].ready, visible=lambda e: True)
    ready = time.monotonic()
    sup.step(ready, lambda e: True)                    # ready, not settled yet
    assert policies(odometer) == {(os.SCHED_OTHER, 0)}
    due = sup.next_due(ready)
    assert due is not None and due <= ready + priority.SETTLE_S
    assert drive(sup, lambda: policies(odometer) == {(os.SCHED_RR, 3)},
                 timeout=priority.SETTLE_S + 5.0, visible=lambda e: True)
    assert time.monotonic() - ready >= priority.SETTLE_S - 0.3
    threads_up(sup, 'odometer', 3)                     # started after the raise
    assert policies(odometer) == {(os.SCHED_RR, 3)}
    heavy = threads_up(sup, 'amcl', 3)
    assert policies(heavy) == {(os.SCHED_OTHER, 0)}    # not critical: node_nice, as before
    assert heavy.nice() == os.nice(0) + 4
    assert said(sup) == [('info', 'critical nodes run at real-time priority 3 (SCHED_RR) '
                                  'once ready: odometer is the first')]


def test_refused_it_is_said_once_and_the_critical_nodes_keep_serving(make_sup, monkeypatch):
    sup = make_sup([critical('odometer'), critical('odometry')],
                   settings=dataclasses.replace(FAST, critical_priority=3,
                                                readiness_timeout_s=30.0))
    tried = []

    def refuse(tid, policy, param):                    # stand-in: no CAP_SYS_NICE here
        tried.append(tid)
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(priority.os, 'sched_setscheduler', refuse)
    for name in ('odometer', 'odometry'):
        sup.start(name, time.monotonic())
        threads_up(sup, name, 2)
    assert drive(sup, lambda: all(r.ready for r in sup.reports().values()),
                 visible=lambda e: True)
    assert drive(sup, lambda: len(tried) == 1, timeout=priority.SETTLE_S + 5.0,
                 visible=lambda e: True)
    drive(sup, lambda: False, timeout=priority.SETTLE_S + 0.5, visible=lambda e: True)
    for name in ('odometer', 'odometry'):
        assert sup.reports()[name].state == 'running'
    assert len(tried) == 1                             # refused once, not tried again
    [(level, text)] = said(sup)
    assert level == 'warn' and 'real-time priority 3 refused for odometer' in text
    assert 'Operation not permitted' in text and 'agent.critical_priority to 0' in text


def test_zero_raises_nothing(monkeypatch):
    monkeypatch.setattr(priority.os, 'sched_setscheduler',
                        lambda *a: pytest.fail('asked the kernel with critical_priority 0'))
    assert priority.Realtime(0).raise_node('odometer', os.getpid()) == ''


def test_a_process_gone_is_nothing_to_raise():
    assert priority.raise_threads(2 ** 22 + 12345, 3) is None
