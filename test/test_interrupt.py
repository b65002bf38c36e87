"""Ctrl-C stops the package's programs even when they inherit SIGINT ignored (started with `&`
from a script): a workload node, the live status view and the profiler (whose rclpy context
is its own: rclpy's handler ends only the default one), real processes."""

import os
import signal
import subprocess
import sys

from anyscale_manager.interrupt import restore_ctrl_c
from supervision import wait_for

BIN = os.path.dirname(sys.executable)


def ignoring_sigint():
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start(argv, tmp_path, name):
    log = open(tmp_path / f'{name}.out', 'w')
    return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            preexec_fn=ignoring_sigint), tmp_path / f'{name}.out'


def stopped_by_sigint(proc, log, ready, tmp_path):
    try:
        assert wait_for(lambda: ready in log.read_text() or proc.poll() is not None, 60.0,
                        period=0.05), f'{ready!r} not logged in 60 s'
        assert proc.poll() is None, log.read_text()
        proc.send_signal(signal.SIGINT)
        proc.wait(15.0)
        return proc.returncode
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_node_started_with_sigint_ignored_stops_on_ctrl_c(tmp_path):
    proc, log = start([os.path.join(BIN, 'workload'), '--name', f'ctrl_c_{os.getpid()}',
                       '--pub', f'/ctrl_c_{os.getpid()}', '--rate-hz', '5'], tmp_path, 'node')
    assert stopped_by_sigint(proc, log, 'first output published', tmp_path) == 0, \
        log.read_text()


def test_the_status_view_started_with_sigint_ignored_stops_on_ctrl_c(tmp_path):
    deployment = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                              'config', 'icar2015_testbed.yaml')
    proc, log = start([sys.executable, '-u', '-m', 'anyscale_manager.cli', 'status',
                       '--params-file', deployment, '--interval', '0.3'], tmp_path, 'status')
    assert stopped_by_sigint(proc, log, 'deployment ', tmp_path) == 0, log.read_text()


def test_the_profiler_started_with_sigint_ignored_stops_on_ctrl_c(tmp_path):
    proc, log = start([sys.executable, '-u', '-m', 'anyscale_manager.cli', 'profile',
                       '--duration', '60', '--output', str(tmp_path / 'p.yaml')], tmp_path,
                      'profile')
    stopped_by_sigint(proc, log, '/60 s', tmp_path)
    assert '(Ctrl-C)' in log.read_text(), log.read_text()


def test_restore_ctrl_c_only_replaces_an_ignored_sigint():
    before = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        restore_ctrl_c()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        mine = lambda *_: None    # noqa: E731 - a handler of the program's own stays
        signal.signal(signal.SIGINT, mine)
        restore_ctrl_c()
        assert signal.getsignal(signal.SIGINT) is mine
    finally:
        signal.signal(signal.SIGINT, before)
