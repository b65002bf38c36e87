"""The examples under examples/, run as the agent would run them, over DDS."""

import os
import subprocess
import sys

import pytest
from std_msgs.msg import Int64

from conftest import REPO
from test_workload import (ACTIVATE, CONFIGURE, DEACTIVATE, LifecycleProbe, _stop,
                           scale_remaps)

TALKER = os.path.join(REPO, 'examples', 'minimal_lifecycle_talker.py')


def _start_talker(python, env, *ros_args):
    return subprocess.Popen([python, TALKER, *scale_remaps('robot'), '-r', 'counter:=/ex_counter',
                             '-r', 'reset:=/ex_reset', *ros_args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def test_minimal_lifecycle_talker_is_silent_inactive_and_counts_when_active(python, ros_env):
    proc = _start_talker(python, ros_env, '-p', 'rate_hz:=20.0')
    probe = LifecycleProbe([])
    counts = []
    probe.node.create_subscription(Int64, '/ex_counter', lambda m: counts.append(m.data), 10)
    robot = '/minimal_lifecycle_talker/robot'
    graph = probe.node
    try:
        assert probe.state(robot) == 'unconfigured'
        assert probe.change(robot, CONFIGURE)
        assert probe.state(robot) == 'inactive'
        probe.spin_until(lambda: graph.count_publishers('/ex_counter') == 1, 10.0,
                         'the configured talker discovered')
        probe.spin_for(1.0)
        assert not counts, 'the inactive talker published'
        assert graph.count_subscribers('/ex_reset') == 0

        assert probe.change(robot, ACTIVATE)
        probe.spin_until(
            lambda: len(counts) >= 5 and graph.count_subscribers('/ex_reset') == 1, 15.0,
            'five counts and the reset subscription of the activated talker')
        assert counts[:5] == list(range(5))

        assert probe.change(robot, DEACTIVATE)
        probe.spin_until(lambda: graph.count_subscribers('/ex_reset') == 0, 10.0,
                         'the deactivated talker dropping its subscription')
        probe.spin_for(0.3)
        seen = len(counts)
        probe.spin_for(1.0)
        assert len(counts) == seen, 'the deactivated talker kept publishing'
    finally:
        probe.close()
        code = _stop(proc)
        log = proc.stdout.read()
        print(log)      # shown when the test fails
    assert code == 0, log
    assert 'activated: publishing the counter' in log, log


def test_minimal_lifecycle_talker_refuses_a_bad_rate_and_says_why(python, ros_env):
    proc = _start_talker(python, ros_env, '-p', 'rate_hz:=0.0')
    probe = LifecycleProbe([])
    robot = '/minimal_lifecycle_talker/robot'
    try:
        assert not probe.change(robot, CONFIGURE)
        assert probe.state(robot) == 'unconfigured'
    finally:
        probe.close()
        code = _stop(proc)
        log = proc.stdout.read()
        print(log)      # shown when the test fails
    assert code == 0, log
    assert 'configure refused: rate_hz must be > 0, got 0.0' in log, log


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v']))
