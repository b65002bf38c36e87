"""A connection starved by its own publisher moves nothing (runtime/upstream.py), on
hand-written observations of the ICAR test-bed (no ROS): AMCL serves on the laptop and the
laser, pinned to the robot, feeds it."""

import pytest

from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (MIGRATE_BACK, ConnectionObs, CopyObs,
                                                   LinkObs, Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy


@pytest.fixture(scope='module')
def d():
    from anyscale_manager.model.loader import load_deployment
    from conftest import TESTBED
    return load_deployment(TESTBED)


def observe(d, now, running, laser, starved=('laser_amcl',)):
    """``laser``: the laser's copy on the robot; ``starved``: connections below freq_min
    for 5 s (past every Δ of the test-bed's)."""
    scales = {s: ScaleObs(cpu_total=10.0, stamp=now) for s in d.scale_names}
    conns = {}
    for c in d.connections:
        if not c.monitored:
            continue
        if c.name in starved:
            conns[c.name] = ConnectionObs(rate_hz=0.0, stamp=now, below_for_s=5.0, below=True)
        else:
            conns[c.name] = ConnectionObs(rate_hz=c.freq_opt_hz, stamp=now)
    copies = {n: {s: CopyObs('running', ready=True)} for n, s in running.items()}
    copies['laser'] = {'robot': laser}
    # The agents report a copy starting or running as live; one in its backoff as not.
    live = {n: s for n, s in running.items()
            if n != 'laser' or laser.state in ('running', 'starting')}
    return Observations(now=now, running=live, scales=scales,
                        links={'laptop': LinkObs(up=True, stamp=now, available_kbps=40000.0)},
                        connections=conns, copies=copies)


def amcl_out(d):
    policy = MigrationPolicy(d)
    layout = dict(master_layout(d), amcl='laptop')
    policy.reset(layout, 0.0, layout)
    return policy, layout


def backs(decisions):
    return [x for x in decisions if x.kind == MIGRATE_BACK]


def test_a_dead_publisher_explains_its_connection_and_nothing_moves(d):
    policy, running = amcl_out(d)
    # Killed, restarted by its agent and not up yet: its connections are judged (it is
    # reported live) and starve.
    restarting = CopyObs('starting', crashed_at=29.0, exit_reason='killed by SIGKILL')
    starved = ('laser_amcl', 'laser_navigation')
    assert not backs(policy.step(observe(d, 30.0, running, restarting, starved)))
    assert policy.layout['amcl'] == 'laptop'
    said = [n for n in policy.notes if n.startswith('laser_amcl below freq_min, explained')]
    assert said and 'its publisher laser is not serving (starting)' in said[0], policy.notes


def test_a_publisher_just_back_is_given_its_grace(d):
    policy, running = amcl_out(d)
    policy.step(observe(d, 30.0, running, CopyObs('backoff', crashed_at=29.0),
                        ('laser_amcl', 'laser_navigation')))
    back = CopyObs('running', ready=True)
    assert not backs(policy.step(observe(d, 31.0, running, back)))
    assert any('came back within grace_s' in n for n in policy.notes), policy.notes
    # Still starved once its grace is over: the link or the laptop is to blame now.
    later = 31.0 + d.decider.grace_s
    assert [x.node for x in backs(policy.step(observe(d, later, running, back)))] == ['amcl']


def test_a_publisher_below_its_rate_where_no_link_is_crossed_explains_it(d):
    policy, running = amcl_out(d)
    slow = ('laser_amcl', 'laser_navigation')
    assert not backs(policy.step(observe(d, 30.0, running, CopyObs('running', ready=True),
                                         slow)))
    assert any('below freq_min on laser_navigation too' in n for n in policy.notes)


def test_a_healthy_publisher_leaves_the_rule_as_it_was(d):
    """The control: the same starvation with the laser serving and its other connection fine
    brings AMCL home (Algorithm 1)."""
    policy, running = amcl_out(d)
    decisions = backs(policy.step(observe(d, 30.0, running, CopyObs('running', ready=True))))
    assert [x.node for x in decisions] == ['amcl']
