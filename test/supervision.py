"""Supervising real processes in tests: quick settings, a node that sleeps, and a factory of
supervisors whose processes never outlive the test (the ``make_sup`` fixture, conftest.py)."""

import os
import sys
import time

import psutil

from anyscale_manager.agent.catalogue import base_environment, ENV_NODE, Entry
from anyscale_manager.agent.supervisor import Supervisor
from anyscale_manager.model import types as t

FAST = t.AgentSettings(sigint_grace_s=0.3, sigterm_grace_s=0.3, readiness_timeout_s=0.5,
                       restart_backoff_s=0.2, restart_backoff_max_s=1.0)
SLEEPER = 'import time\nwhile True: time.sleep(1)'


def wait_for(cond, timeout=10.0, step=None, period=0.02):
    """Poll ``cond`` (after ``step``) until true or the deadline; return its last value."""
    end = time.monotonic() + timeout
    while True:
        if step is not None:
            step()
        value = cond()
        if value or time.monotonic() > end:
            return value
        time.sleep(period)


def drive(sup, cond, timeout=10.0, visible=lambda e: False):
    """Step ``sup`` until ``cond()`` or the deadline; return its last value."""
    return wait_for(cond, timeout, step=lambda: sup.step(time.monotonic(), visible))


def gone(pid):
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def py_entry(name, code, env=None):
    base = base_environment(os.environ)
    base.update(env or {})
    base[ENV_NODE] = name
    return Entry(name=name, argv=(sys.executable, '-c', code), env=base, ros_name=name)


class Supervisors:
    """Makes supervisors under ``tmp_path`` and kills what they started, at the end."""

    def __init__(self, tmp_path):
        self.tmp_path = tmp_path
        self.made = []

    def make(self, entries, settings=FAST, state=True, log_dir=None, state_path=None):
        """A supervisor of ``entries``; its state file is ``state_path`` (default
        <tmp>/state.json), none without ``state``; its logs go to ``log_dir``."""
        path = str(state_path or self.tmp_path / 'state.json') if state else ''
        sup = Supervisor({e.name: e for e in entries}, settings,
                         str(log_dir or self.tmp_path / 'log'), state_path=path,
                         identity={'deployment': 'd', 'scale': 's'})
        self.made.append(sup)
        return sup

    def kill_all(self):
        for sup in self.made:
            sup.kill_all(time.monotonic())
            drive(sup, sup.all_stopped)
