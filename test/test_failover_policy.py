"""The policy's answer to a crashed serving copy, on hand-written observations (no ROS): the
test-bed's AMCL keeps standby copies on the robot and the laptop."""

import pytest

from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (FAILOVER, ConnectionObs, CopyObs, LinkObs,
                                                   Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy


@pytest.fixture(scope='module')
def d():
    from anyscale_manager.model.loader import load_deployment
    from conftest import TESTBED
    return load_deployment(TESTBED)


def obs(d, now, running, copies):
    scales = {s: ScaleObs(cpu_total=sum(d.node(n).cpu for n, w in running.items() if w == s),
                          stamp=now) for s in d.scale_names}
    conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=now)
             for c in d.connections if c.monitored}
    return Observations(now=now, running=running, scales=scales,
                        links={'laptop': LinkObs(up=True, stamp=now, available_kbps=40000.0)},
                        connections=conns, copies=copies)


def policy_with_amcl_on(d, scale, now=0.0):
    policy = MigrationPolicy(d)
    layout = dict(master_layout(d), amcl=scale)
    policy.reset(layout, now, layout)
    return policy, layout


def test_a_crashed_serving_copy_fails_over_to_the_standby_copy(d):
    policy, running = policy_with_amcl_on(d, 'laptop')
    running.pop('amcl')
    copies = {'amcl': {'laptop': CopyObs('backoff', crashed_at=10.0,
                                         exit_reason='killed by SIGKILL (Killed)'),
                       'robot': CopyObs('standby')}}
    decisions = policy.step(obs(d, 10.0, running, copies))
    assert [(x.kind, x.node, x.from_scale, x.to_scale) for x in decisions] == [
        (FAILOVER, 'amcl', 'laptop', 'robot')]
    assert 'crashed on laptop (killed by SIGKILL' in decisions[0].reason
    assert policy.layout['amcl'] == 'robot'
    # One failover per crash: the same report again decides nothing more.
    assert not [x for x in policy.step(obs(d, 10.1, running, copies)) if x.node == 'amcl']


def test_without_a_standby_copy_ready_the_node_is_restarted_in_place(d):
    policy, running = policy_with_amcl_on(d, 'laptop')
    running.pop('amcl')
    copies = {'amcl': {'laptop': CopyObs('backoff', crashed_at=10.0, exit_reason='x'),
                       'robot': CopyObs('starting')}}
    assert not [x for x in policy.step(obs(d, 10.0, running, copies)) if x.node == 'amcl']
    assert policy.layout['amcl'] == 'laptop'
    assert any('restarted in place' in n for n in policy.notes)


def test_a_crash_fails_over_to_a_ready_standby_even_within_the_hysteresis(d):
    """T bars voluntary moves, not the rescue of a dead copy: in a crash loop each crash is
    answered by the ready standby on the other scale, and the node is said to crash wherever
    it runs."""
    policy, running = policy_with_amcl_on(d, 'laptop')
    running.pop('amcl')
    crashed = {'amcl': {'laptop': CopyObs('backoff', crashed_at=10.0, exit_reason='x'),
                        'robot': CopyObs('standby')}}
    assert policy.step(obs(d, 10.0, running, crashed))[0].to_scale == 'robot'
    assert not any('wherever' in n for n in policy.notes)
    policy.step(obs(d, 10.5, dict(running, amcl='robot'), crashed))    # it serves there
    # Now the robot's copy crashes too, 5 s later, within T of the laptop's crash: the
    # laptop's copy (restarted as a standby) takes over all the same.
    assert 15.0 - 10.0 < d.decider.hysteresis_s
    again = {'amcl': {'robot': CopyObs('backoff', crashed_at=15.0, exit_reason='y'),
                      'laptop': CopyObs('standby', crashed_at=10.0)}}
    decisions = [x for x in policy.step(obs(d, 15.0, running, again)) if x.node == 'amcl']
    assert [(x.kind, x.from_scale, x.to_scale) for x in decisions] == [
        (FAILOVER, 'robot', 'laptop')]
    assert policy.layout['amcl'] == 'laptop'
    said = [n for n in policy.notes if 'crashes wherever it runs' in n]
    assert said and 'laptop 5.0 s ago' in said[0] and 'robot 0.0 s ago' in said[0], said
    # And back again on the next crash, 5 s later.
    policy.step(obs(d, 15.5, dict(running, amcl='laptop'), again))
    third = {'amcl': {'laptop': CopyObs('backoff', crashed_at=20.0, exit_reason='z'),
                      'robot': CopyObs('standby', crashed_at=15.0)}}
    decisions = [x for x in policy.step(obs(d, 20.0, running, third)) if x.node == 'amcl']
    assert [(x.kind, x.to_scale) for x in decisions] == [(FAILOVER, 'robot')]


def test_a_node_serving_elsewhere_already_is_left_alone(d):
    policy, running = policy_with_amcl_on(d, 'laptop')
    running['amcl'] = 'robot'       # a move in progress: another copy serves
    copies = {'amcl': {'laptop': CopyObs('backoff', crashed_at=10.0, exit_reason='x'),
                       'robot': CopyObs('running', ready=True)}}
    assert not [x for x in policy.step(obs(d, 10.0, running, copies))
                if x.kind == FAILOVER]


def test_the_master_takes_a_crashed_node_back_whatever_its_cpu_reads(d):
    """The robot, run near its quota by the decider and its agent, reads as full: its standby
    copy still takes over at once, as a move back would, rather than leaving the node to a cold
    restart in place (silent meanwhile, and sent home anyway once past Δ)."""
    policy, running = policy_with_amcl_on(d, 'laptop')
    running.pop('amcl')
    copies = {'amcl': {'laptop': CopyObs('starting', crashed_at=10.0, exit_reason='x'),
                       'robot': CopyObs('standby')}}
    seen = obs(d, 10.0, running, copies)
    usable = d.scale('robot').capacity_cpu * d.decider.cpu_headroom
    seen.scales['robot'] = ScaleObs(cpu_total=usable - 1.0, stamp=10.0)
    decisions = [x for x in policy.step(seen) if x.node == 'amcl']
    assert [(x.kind, x.to_scale) for x in decisions] == [(FAILOVER, 'robot')]
