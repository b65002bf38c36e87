"""The placement filters, each alone: its pass and its fails, with the code and the reason.

The deployment's own filters (model/placement.py: residence, coresidence) on a hand-made
deployment; the filters that read observations (runtime/filters.py) on the test-bed's robot
and laptop, over hand-written observations and the constraint report built from them.
"""

from dataclasses import replace

import pytest

from anyscale_manager.model.loader import load_deployment
from anyscale_manager.model.placement import (PASS, Code, Verdict, allowed, apart,
                                              coresidence, fails, first_failing, passes,
                                              residence, waits)
from anyscale_manager.model.types import Connection, Deployment, Launch, Link, Node, Scale
from anyscale_manager.runtime import filters as f
from anyscale_manager.runtime.constraints import evaluate
from anyscale_manager.runtime.observations import LinkObs, Observations, ScaleObs
from conftest import CONFIG, TESTBED


# --- the deployment's filters -------------------------------------------------------------------

def scale(name, master=False):
    return Scale(name=name, role='master' if master else 'remote', kind='robot',
                 capacity_cpu=100.0, cores=2, clock_ghz=2.0, gain=1.0, host=name)


def node(name, **kw):
    return Node(name=name, launch=Launch(), cpu=10.0, **kw)


@pytest.fixture(scope='module')
def small() -> Deployment:
    """r (master), s, t. src feeds free and nothing feeds it (a data provider); crit is
    critical; res may run only on s; manual is not managed; a and b share a scale, b only on
    s or t."""
    return Deployment(
        name='small', source='<test>',
        scales=(scale('r', master=True), scale('s'), scale('t')),
        links=(Link('r_s', ('r', 's'), 100.0, 'wireless'),
               Link('r_t', ('r', 't'), 100.0, 'wireless')),
        nodes=(node('src'), node('free'), node('crit', critical=True),
               node('res', residence=('s',)), node('manual', managed=False),
               node('a', coresidence=('b',)), node('b', residence=('s', 't'))),
        connections=(Connection(name='src_free', topic='/src', publisher='src',
                                subscriber='free', bandwidth_kbps=1.0),))


def test_a_verdict_says_its_code_its_answer_and_why():
    assert (PASS.code, PASS.ok, PASS.reason, PASS.passed) == (Code.OK, True, '', True)
    no = fails(Code.CPU, 'full')
    assert (no.ok, no.failed, no.passed, no.waiting) == (False, True, False, False)
    wait = waits(Code.CPU_NOT_OBSERVED, 'not yet')
    assert (wait.ok, wait.waiting, wait.failed, wait.passed) == (None, True, False, False)
    assert passes('fits') == Verdict(Code.OK, 'fits', True)


def test_the_first_failing_verdict_stops_the_chain():
    asked = []

    def chain():
        for v in (passes('CPU fits'), PASS, waits(Code.LINK_NOT_OBSERVED, 'wait'),
                  fails(Code.CPU, 'never asked')):
            asked.append(v)
            yield v
    assert first_failing(chain()) == waits(Code.LINK_NOT_OBSERVED, 'wait')
    assert len(asked) == 3
    assert first_failing([passes('CPU fits'), PASS, passes('link fits')]) == \
        passes('CPU fits; link fits')
    assert first_failing([]) == PASS


@pytest.mark.parametrize('name, where', [('free', 's'), ('src', 'r'), ('res', 's'),
                                         ('a', 'r'), ('b', 't')])
def test_residence_passes_where_the_node_may_run_by_itself(small, name, where):
    assert residence(small, name, where) == PASS


@pytest.mark.parametrize('name, where, reason', [
    ('crit', 's', 'is critical (critical: true) and must run on r'),
    ('res', 'r', 'may run only on s (residence)'),
    ('manual', 's', 'is not managed by an agent and stays on r'),
    ('src', 't', 'is a data provider and stays on r'),
])
def test_residence_fails_saying_what_pins_the_node(small, name, where, reason):
    assert residence(small, name, where) == Verdict(Code.RESIDENCE, reason, False)


def test_allowed_is_residence_of_the_whole_coresidence_group(small):
    # a by itself may run on r, but b, which it shares a scale with, may not.
    assert residence(small, 'a', 'r').passed
    assert allowed(small, 'a', 'r') == Verdict(Code.RESIDENCE, 'not allowed there', False)
    assert allowed(small, 'a', 's') == PASS
    for d in (small, load_deployment(TESTBED), load_deployment(f'{CONFIG}/iros2016/'
                                                               'instance_6.yaml')):
        for n in d.node_names:
            for s in d.scale_names:
                group = all(residence(d, m, s).passed for m in d.coresidence_group(n))
                assert allowed(d, n, s).passed == group, (n, s)


def test_coresidence_passes_beside_its_coresidents_or_with_them_unplaced(small):
    assert coresidence(small, 'a', 's', {'a': 's', 'b': 's'}) == PASS
    assert coresidence(small, 'a', 's', {'a': 's'}) == PASS
    assert coresidence(small, 'free', 's', {'free': 's', 'a': 'r'}) == PASS


def test_coresidence_fails_naming_who_is_elsewhere(small):
    assert coresidence(small, 'a', 's', {'a': 's', 'b': 't'}) == \
        Verdict(Code.CORESIDENCE, 'must share a scale with b (on t)', False)
    assert coresidence(small, 'b', 'r', {'a': 's'}) == \
        Verdict(Code.CORESIDENCE, 'must share a scale with a (on s)', False)
    assert apart(small, 'a', 's', {'b': 't'}) == ('b',)
    # Only the pairs a node declares, when asked so (the planners report each pair once).
    assert apart(small, 'b', 's', {'a': 't'}, among=small.node('b').coresidence) == ()


# --- the filters that read observations ------------------------------------------------------

@pytest.fixture(scope='module')
def d():
    return load_deployment(TESTBED)


def snapshot(d, *, now=10.0, link=None, laptop_cpu=100.0, cpu_stamp=None, started=0.0,
             arrived=None, **obs):
    """The test-bed at ``now``: everything on the robot, the laptop's CPU and the wifi link
    reported at ``now`` unless told otherwise (``link=False``: no report at all)."""
    running = {n: 'robot' for n in d.node_names}
    scales = {'robot': ScaleObs(cpu_total=80.0, stamp=now)}
    if laptop_cpu is not None:
        scales['laptop'] = ScaleObs(cpu_total=laptop_cpu,
                                    stamp=now if cpu_stamp is None else cpu_stamp)
    links = {} if link is False else \
        {'laptop': link or LinkObs(up=True, stamp=now, available_kbps=40000.0)}
    o = Observations(now=now, running=running, scales=scales, links=links, **obs)
    report = evaluate(d, d.decider, o, since=started)
    return f.Snapshot(d, d.decider, o, report, started, arrived or {})


def cand(unit=('amcl',), scale='laptop', cpu=50.0, d=None, sent_cpu=0.0):
    running = {n: 'robot' for n in d.node_names} if d is not None else {}
    return f.Candidate(tuple(unit), scale, cpu, running, sent_cpu)


def test_live_agent(d):
    assert f.live_agent(snapshot(d), cand()) == PASS
    lost = snapshot(d, lost_scales=frozenset({'laptop'}), silent_agents={'laptop': 5.0})
    assert f.live_agent(lost, cand()) == Verdict(
        Code.AGENT_SILENT, 'the agent of laptop is lost (silent > 4 s)', False)
    silent = snapshot(d, silent_agents={'laptop': 2.5})
    assert f.live_agent(silent, cand()) == Verdict(
        Code.AGENT_SILENT, 'the agent of laptop is silent', False)


def test_residence_of_a_unit(d):
    assert f.residence(snapshot(d), cand(('amcl', 'ar'))) == PASS
    assert f.residence(snapshot(d), cand(('amcl', 'laser'))) == Verdict(
        Code.RESIDENCE, 'not allowed there', False)


def test_link_up(d):
    assert f.link_up(snapshot(d), cand()) == PASS
    down = snapshot(d, link=LinkObs(up=False, stamp=10.0))
    assert f.link_up(down, cand()) == Verdict(
        Code.LINK_DOWN, 'link wifi to laptop reported down', False)
    silent = snapshot(d, link=LinkObs(up=True, stamp=7.0))
    assert f.link_up(silent, cand()) == Verdict(
        Code.LINK_DOWN, 'link wifi to laptop silent for 3.0 s (max age 2 s)', False)
    unlinked = replace(d, links=())
    assert f.link_up(snapshot(unlinked), cand()) == Verdict(
        Code.NO_LINK, 'no link from robot', False)


def test_link_observed(d):
    assert f.link_observed(snapshot(d), cand()) == PASS
    # Never reported, within observation_max_age_s of the start: up, but not observed.
    early = snapshot(d, now=1.0, link=False)
    assert f.link_up(early, cand()) == PASS
    assert f.link_observed(early, cand()) == Verdict(
        Code.LINK_NOT_OBSERVED, 'link wifi not observed yet', None)


def test_cpu_observed(d):
    assert f.cpu_observed(snapshot(d), cand()) == PASS
    assert f.cpu_observed(snapshot(d, now=1.0, laptop_cpu=None), cand()) == Verdict(
        Code.CPU_NOT_OBSERVED, 'no CPU report from laptop yet', None)
    assert f.cpu_observed(snapshot(d, laptop_cpu=None), cand()) == Verdict(
        Code.CPU_STALE, 'no fresh CPU report from laptop (last never, max age 2 s)', False)
    assert f.cpu_observed(snapshot(d, cpu_stamp=5.0), cand()) == Verdict(
        Code.CPU_STALE, 'no fresh CPU report from laptop (last 5.0 s ago, max age 2 s)', False)
    moved = snapshot(d, cpu_stamp=9.5, arrived={'laptop': (9.5, 'ar')})
    assert f.cpu_observed(moved, cand()) == Verdict(
        Code.CPU_NOT_OBSERVED, 'CPU of laptop not measured since ar started there (0.5 s ago)',
        None)
    assert f.cpu_observed(snapshot(d, arrived={'laptop': (9.5, 'ar')}), cand()) == PASS


def test_cpu_headroom(d):
    # The laptop: capacity 700 x cpu_headroom 0.9 = 630 usable.
    assert f.cpu_headroom(snapshot(d), cand(cpu=50.0)) == passes('CPU 100 + 50 <= 630')
    assert f.cpu_headroom(snapshot(d, laptop_cpu=600.0), cand(cpu=50.0)) == Verdict(
        Code.CPU, 'CPU 600 + 50 > usable 630', False)
    assert f.cpu_headroom(snapshot(d, laptop_cpu=500.0), cand(cpu=50.0, sent_cpu=90.0)) == \
        Verdict(Code.CPU, 'CPU 590 + 50 > usable 630', False)


def test_bandwidth(d):
    # AR on the laptop: camera_ar (6096) and ar_navigation (61) cross the wifi.
    ar = cand(('ar',), d=d)
    assert f.bandwidth(snapshot(d), ar) == passes('link wifi 6157/32000 kbit/s')
    assert f.bandwidth(snapshot(d), cand(('decision',), d=d)) == PASS      # crosses nothing
    slow = snapshot(d, link=LinkObs(up=True, stamp=10.0, available_kbps=5000.0))
    assert f.bandwidth(slow, ar) == Verdict(
        Code.BANDWIDTH, 'link wifi would need 6157 kbit/s > usable 4000', False)
    down = snapshot(d, link=LinkObs(up=False, stamp=10.0))
    assert f.bandwidth(down, ar) == Verdict(Code.LINK_DOWN, 'link wifi down', False)
    loopback = snapshot(d, link=LinkObs(up=True, stamp=10.0, available_kbps=9e6))
    assert f.bandwidth(loopback, ar).reason == (
        'link wifi 6157/43200 kbit/s (measured 9000000 kbit/s, above the nominal: capped at '
        '54000)')


def test_can_host_returns_the_first_that_does_not_pass_or_what_fits(d):
    ar = cand(('ar',), cpu=33.0, d=d)
    assert f.can_host(snapshot(d), ar) == passes(
        'CPU 100 + 33 <= 630; link wifi 6157/32000 kbit/s')
    # A silent agent is said before anything else that fails.
    assert f.can_host(snapshot(d, silent_agents={'laptop': 3.0}, laptop_cpu=None),
                      cand(('laser',), d=d)).code is Code.AGENT_SILENT
    # Waiting for the link is said before a CPU that is not known either.
    early = snapshot(d, now=1.0, link=False, laptop_cpu=None)
    assert f.can_host(early, ar).code is Code.LINK_NOT_OBSERVED
    assert f.can_host(snapshot(d, laptop_cpu=620.0), ar).code is Code.CPU
    assert [x.__name__ for x in f.FILTERS] == [
        'live_agent', 'residence', 'link_up', 'link_observed', 'cpu_observed', 'cpu_headroom',
        'shared_room', 'bandwidth']


def test_reachable(d):
    assert f.reachable(snapshot(d), 'laptop') == PASS
    assert f.reachable(snapshot(d, link=LinkObs(up=False, stamp=10.0)), 'robot') == PASS
    assert f.reachable(snapshot(d, silent_agents={'robot': 3.0}), 'robot') == Verdict(
        Code.AGENT_SILENT, 'the agent of robot is silent', False)
    assert f.reachable(snapshot(d, link=LinkObs(up=False, stamp=10.0)), 'laptop') == Verdict(
        Code.LINK_DOWN, 'link wifi to laptop reported down', False)
    assert f.reachable(snapshot(replace(d, links=())), 'laptop') == Verdict(
        Code.NO_LINK, 'no link from robot to laptop', False)


def test_handover():
    three = load_deployment(f'{CONFIG}/three_scales_testbed.yaml')
    now = 10.0
    links = {'laptop': LinkObs(up=True, stamp=now), 'server': LinkObs(up=True, stamp=now),
             'laptop-server': LinkObs(up=True, stamp=now)}
    o = Observations(now=now, running={}, links=links)
    snap = f.Snapshot(three, three.decider, o, evaluate(three, three.decider, o, since=0.0))
    assert f.handover(snap, 'laptop', 'server') == PASS
    assert f.handover(snap, None, 'server') == PASS
    o = replace(o, links=dict(links, **{'laptop-server': LinkObs(up=False, stamp=now)}))
    snap = replace(snap, obs=o, report=evaluate(three, three.decider, o, since=0.0))
    assert f.handover(snap, 'laptop', 'server') == Verdict(
        Code.HANDOVER, 'link backhaul between laptop and server reported down (the handover '
                       'from laptop needs it)', False)
    assert f.handover(snap, 'robot', 'server') == PASS


def test_hysteresis():
    back = {('amcl', 'laptop'): 10.0, ('amcl', 'server'): 12.0}
    assert f.hysteresis(back, 30.0, ('amcl',), 'laptop', 15.0) == Verdict(
        Code.HYSTERESIS, 'amcl -> laptop: amcl migrated back from laptop 5.0 s ago, within '
                         'T = 30 s', False)
    # Scope 'node': any scale, the latest return named.
    assert f.hysteresis(back, 30.0, ('amcl', 'ar'), None, 15.0) == Verdict(
        Code.HYSTERESIS, 'amcl: amcl migrated back from server 3.0 s ago, within T = 30 s',
        False)
    assert f.hysteresis(back, 30.0, ('amcl',), 'workstation', 15.0) == PASS
    assert f.hysteresis(back, 30.0, ('ar',), 'laptop', 15.0) == PASS
    assert f.hysteresis(back, 30.0, ('amcl',), 'laptop', 40.0) == PASS


def test_shared_room_counts_the_claims_this_deployment_may_not_preempt(d):
    from dataclasses import replace
    from anyscale_manager.protocol import HostShare, ShareClaim
    laptop = replace(d.scale('laptop'), shared=True)
    d = replace(d, scales=tuple(laptop if s.name == 'laptop' else s for s in d.scales),
                priority=1)
    share = HostShare(700.0, 0.0, {'robot_b/amcl': ShareClaim(400.0, 0.0, 1, True),
                                   'robot_c/ar': ShareClaim(150.0, 0.0, 0, True)}, {}, {}, {})
    # Not reported yet: wait for it.
    assert f.shared_room(snapshot(d), cand(d=d)).code is Code.SHARE_NOT_HEARD
    snap = snapshot(d, shares={'laptop': share})
    # 700 x headroom 0.9 = 630 usable, 400 held by an equal priority; robot_c's (priority 0) may
    # be preempted.
    assert f.shared_room(snap, cand(cpu=230.0, d=d)).passed
    v = f.shared_room(snap, cand(cpu=231.0, d=d))
    assert v.code is Code.SHARED and v.reason == (
        'shared laptop: CPU 0 + 231 > 230 left by robot_b/amcl')
    # Measured lower than its nominal CPU, a unit still claims the nominal figure.
    v = f.shared_room(snap, cand(('amcl', 'ar'), cpu=10.0, d=d))
    nominal = d.node('amcl').cpu + d.node('ar').cpu
    assert v.reason.startswith(f'shared laptop: CPU 0 + {nominal:.0f} ')
    # A unit that must leave where it is may not count on a preemption (the lower robots go
    # home first): every claim counts.
    urgent = f.shared_room(snap, f.Candidate(('amcl',), 'laptop', 100.0,
                                             {n: 'robot' for n in d.node_names}, urgent=True))
    assert urgent.reason == 'shared laptop: CPU 0 + 100 > 80 left by robot_b/amcl, robot_c/ar'
    # The host's measured total is not this deployment's: the CPU filter leaves it to claims.
    assert f.cpu_headroom(snapshot(d, laptop_cpu=700.0, shares={'laptop': share}),
                          cand(cpu=100.0, d=d)) == PASS
