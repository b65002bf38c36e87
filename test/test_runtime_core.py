"""Constraint evaluation, the Δ timer, the cost function, plan against reality, first layout."""

import types
from dataclasses import replace

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime import layout as layout_mod
from anyscale_manager.runtime.constraints import (BANDWIDTH, CPU, FREQUENCY, LINK_DOWN, STALE,
                                                  evaluate, required_kbps)
from anyscale_manager.runtime.delta import DeltaTracker
from anyscale_manager.runtime.cost import CostIntegrator, perf_map
from anyscale_manager.runtime.intake import ObservationBook
from anyscale_manager.runtime.layout import (LayoutError, adopt, check_layout, initial_layout,
                                             master_layout)
from anyscale_manager.runtime.observations import (ConnectionObs, LinkObs, Observations,
                                                   ScaleObs)
from anyscale_manager.runtime.plan_check import check_plan, expectations


@pytest.fixture(scope='module')
def d():
    from conftest import TESTBED
    return load_deployment(TESTBED)


def fresh_obs(d, now=10.0, running=None, link=None, conns=None, scales=None, lost=frozenset()):
    running = master_layout(d) if running is None else running
    if link is None:
        link = LinkObs(up=True, stamp=now)
    if conns is None:
        conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=now)
                 for c in d.connections if c.monitored}
    if scales is None:
        scales = {s: ScaleObs(cpu_total=sum(d.node(n).cpu for n, w in running.items()
                                            if w == s), stamp=now) for s in d.scale_names}
    links = {} if link is False else {'laptop': link}
    return Observations(now=now, running=running, scales=scales, links=links,
                        connections=conns, lost_scales=lost)


# --- constraints ---------------------------------------------------------------------------------

def test_all_on_master_holds(d):
    report = evaluate(d, d.decider, fresh_obs(d))
    assert report.ok and report.bandwidth_ok and report.frequency_ok and report.cpu_ok
    assert report.links['wifi'].required_kbps == 0


def test_required_against_available_bandwidth_per_link(d):
    running = dict(master_layout(d), amcl='laptop', ar='laptop')
    # laser -> amcl, amcl -> ekf, camera -> ar, ar -> navigation cross the link
    assert required_kbps(d, running) == {'wifi': pytest.approx(224 + 15 + 6096 + 61)}
    report = evaluate(d, d.decider, fresh_obs(d, running=running,
                                              link=LinkObs(up=True, stamp=10.0,
                                                           available_kbps=5000.0)))
    load = report.links['wifi']
    assert load.available_kbps == 5000.0
    assert load.usable_kbps == pytest.approx(5000.0 * d.decider.bandwidth_margin)
    assert load.required_kbps == pytest.approx(6396)
    assert not load.ok and not report.bandwidth_ok
    (v,) = report.of_kind(BANDWIDTH)
    assert v.subject == 'wifi' and set(v.nodes) == {'amcl', 'ar'} and 'kbit/s' in v.reason
    # not measured: the nominal bandwidth
    report = evaluate(d, d.decider, fresh_obs(d, running=running))
    assert report.links['wifi'].available_kbps == 54000.0 and report.bandwidth_ok


@pytest.mark.parametrize('link, word', [(LinkObs(up=False, stamp=10.0), 'reported down'),
                                        (LinkObs(up=True, stamp=7.5), 'silent for 2.5 s'),
                                        (False, 'never reported')])
def test_down_silent_or_missing_link_is_down(d, link, word):
    running = dict(master_layout(d), amcl='laptop')
    report = evaluate(d, d.decider, fresh_obs(d, running=running, link=link))
    (v,) = report.of_kind(LINK_DOWN)
    assert v.nodes == ('amcl',)
    assert word in v.reason
    assert not report.links['wifi'].up and not report.bandwidth_ok


def test_missing_link_within_max_age_of_start_is_not_yet_down(d):
    running = dict(master_layout(d), amcl='laptop')
    obs = fresh_obs(d, running=running, link=False)
    assert evaluate(d, d.decider, obs, since=9.0).bandwidth_ok
    assert not evaluate(d, d.decider, obs, since=5.0).bandwidth_ok


def test_down_link_with_nothing_beyond_is_no_violation(d):
    report = evaluate(d, d.decider, fresh_obs(d, link=LinkObs(up=False, stamp=10.0)))
    assert report.ok and not report.links['wifi'].up


def test_frequency_violation_needs_more_than_delta(d):
    running = dict(master_layout(d), amcl='laptop')
    conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=10.0) for c in d.connections}
    conns['laser_amcl'] = ConnectionObs(rate_hz=1.0, stamp=10.0, below_for_s=1.9, below=True)
    report = evaluate(d, d.decider, fresh_obs(d, running=running, conns=conns))
    assert report.frequency_ok
    assert report.connections['laser_amcl'].below_for_s == pytest.approx(1.9)
    conns['laser_amcl'] = ConnectionObs(rate_hz=1.0, stamp=10.0, below_for_s=2.1, below=True)
    report = evaluate(d, d.decider, fresh_obs(d, running=running, conns=conns))
    (v,) = report.of_kind(FREQUENCY)
    assert v.subject == 'laser_amcl' and v.nodes == ('amcl',)
    # not judged during the node's grace period
    report = evaluate(d, d.decider, fresh_obs(d, running=running, conns=conns),
                      grace_until={'amcl': 11.0})
    assert report.frequency_ok and not report.connections['laser_amcl'].judged


def test_stale_reading_counts_as_zero_and_is_reported(d):
    conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=10.0) for c in d.connections}
    conns['amcl_ekf'] = ConnectionObs(rate_hz=5.0, stamp=6.5)       # 3.5 s old, max age 2
    report = evaluate(d, d.decider, fresh_obs(d, conns=conns))
    check = report.connections['amcl_ekf']
    assert check.rate_hz is None
    assert check.below_for_s == pytest.approx(10.0 - (6.5 + 2.0))
    assert [v.subject for v in report.of_kind(STALE)] == ['amcl_ekf']
    conns['amcl_ekf'] = ConnectionObs(rate_hz=5.0, stamp=5.0)       # missing for 3 s > Δ 2
    report = evaluate(d, d.decider, fresh_obs(d, conns=conns))
    assert [v.subject for v in report.of_kind(FREQUENCY)] == ['amcl_ekf']
    assert report.of_kind(FREQUENCY)[0].nodes == ()                  # both ends on the master


def test_cpu_over_headroom(d):
    running = dict(master_layout(d), amcl='laptop')
    scales = {'robot': ScaleObs(cpu_total=100.0, stamp=10.0),
              'laptop': ScaleObs(cpu_total=640.0, stamp=10.0)}
    report = evaluate(d, d.decider, fresh_obs(d, running=running, scales=scales))
    (v,) = report.of_kind(CPU)
    assert v.subject == 'laptop' and v.nodes == ('amcl',)
    assert report.scales['laptop'].usable_cpu == pytest.approx(630.0)
    # a stale report falls back to the nominal CPU of what runs there, and says so
    scales['laptop'] = ScaleObs(cpu_total=640.0, stamp=1.0)
    report = evaluate(d, d.decider, fresh_obs(d, running=running, scales=scales))
    assert report.cpu_ok and report.scales['laptop'].cpu_used == 50.0
    assert [v.subject for v in report.of_kind(STALE)] == ['laptop']


def test_delta_tracker_from_observation_times(d):
    settings = d.decider
    tracker = DeltaTracker(d)
    base = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=0.0) for c in d.connections}

    def at(now, **readings):
        conns = dict(base)
        for k, v in readings.items():
            conns[k] = v
        for k in conns:
            if k not in readings:
                conns[k] = replace(conns[k], stamp=now)
        return tracker.update(Observations(now=now, running={}, connections=conns), settings)

    assert at(0.0)['laser_amcl'] == 0.0
    # below, with the probe saying it has been below for 0.4 s already: the earlier start wins
    below = at(1.0, laser_amcl=ConnectionObs(rate_hz=1.0, stamp=1.0, below_for_s=0.4, below=True))
    assert below['laser_amcl'] == pytest.approx(0.4)
    below = at(2.0, laser_amcl=ConnectionObs(rate_hz=1.0, stamp=2.0, below_for_s=0.1, below=True))
    assert below['laser_amcl'] == pytest.approx(1.4)
    # the reading stops arriving: the timer keeps running
    below = at(5.0, laser_amcl=ConnectionObs(rate_hz=1.0, stamp=2.0, below_for_s=0.1, below=True))
    assert below['laser_amcl'] == pytest.approx(4.4)
    # recovered
    assert at(6.0)['laser_amcl'] == 0.0
    # an OK reading going stale: 0 Hz from the moment it became missing
    stale = ConnectionObs(rate_hz=10.0, stamp=6.0)
    assert at(7.0, laser_amcl=stale)['laser_amcl'] == 0.0
    assert at(9.5, laser_amcl=stale)['laser_amcl'] == pytest.approx(9.5 - 8.0)


def test_delta_tracker_never_reported(d):
    tracker = DeltaTracker(d)
    assert tracker.update(Observations(now=100.0, running={}), d.decider)['camera_ar'] == 0.0
    below = tracker.update(Observations(now=103.0, running={}), d.decider)
    assert below['camera_ar'] == pytest.approx(103.0 - 100.0 - d.decider.observation_max_age_s)


# --- cost ---------------------------------------------------------------------------------------

def test_perf_map_is_eq_1(d):
    running = master_layout(d)
    nominal = sum(n.cpu for n in d.nodes if n.managed)
    assert perf_map(d, running) == pytest.approx(nominal * 1.0)
    running['amcl'] = 'laptop'
    assert perf_map(d, running) == pytest.approx(nominal - 50 + 50 * 3.5)
    assert perf_map(d, running, {'amcl': 20.0}) == pytest.approx(nominal - 50 + 20 * 3.5)
    assert perf_map(d, {'ghost': 'robot', 'amcl': 'moon'}) == 0.0


def test_cost_integrator_is_eq_2(d):
    cost = CostIntegrator(d)
    home = master_layout(d)
    out = dict(home, amcl='laptop')
    p0, i0 = cost.update(0.0, home)
    assert i0 == 0.0
    _, i1 = cost.update(10.0, out)             # home held for 10 s
    assert i1 == pytest.approx(10 * p0)
    p2, i2 = cost.update(15.0, out)            # out held for 5 s
    assert i2 == pytest.approx(10 * p0 + 5 * p2)
    assert cost.elapsed_s == 15.0
    assert cost.update(14.0, home)[1] == pytest.approx(i2)   # time does not run backwards
    assert cost.mean == pytest.approx(i2 / 15.0)


# --- plan against reality ----------------------------------------------------------------------

def test_plan_check_eq_10(d):
    placements = {'amcl': types.SimpleNamespace(scale='laptop', cpu=50.0, performance=80.0)}
    exp = expectations(d, placements)
    assert exp['amcl'].expected_hz == 5.0 and exp['amcl'].expected_performance == 80.0
    conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=10.0) for c in d.connections}
    conns['amcl_ekf'] = ConnectionObs(rate_hz=4.0, stamp=10.0)
    obs = fresh_obs(d, running=dict(master_layout(d), amcl='laptop'), conns=conns)
    report = check_plan(d, exp, obs)
    a = report.nodes['amcl']
    assert a.measured_performance == pytest.approx(80.0 * 4.0 / 5.0)
    assert a.deviation == pytest.approx(-0.2)
    assert report.overall_deviation == pytest.approx(-0.2)    # only amcl has a performance
    assert not report.overloaded and not report.warnings


def test_plan_check_flags_an_overloaded_scale(d):
    scales = {'robot': ScaleObs(cpu_total=195.0, stamp=10.0),
              'laptop': ScaleObs(cpu_total=10.0, stamp=10.0)}
    conns = {c.name: ConnectionObs(rate_hz=c.freq_min_hz, stamp=10.0) for c in d.connections}
    report = check_plan(d, expectations(d), fresh_obs(d, scales=scales, conns=conns))
    assert set(report.overloaded) == {'robot'}
    assert 'plan does not hold' in report.warnings[0] and 'amcl' in report.warnings[0]
    assert report.overall_deviation < 0


# --- first layout -------------------------------------------------------------------------------

def test_master_layout_pins_everything_home(d):
    lay = initial_layout(d)
    assert set(lay) == {n.name for n in d.nodes if n.managed}
    assert set(lay.values()) == {'robot'}


def test_explicit_layout_and_its_errors(d):
    settings = replace(d.decider, initial_layout='explicit', layout={'amcl': 'laptop'})
    assert initial_layout(d, settings)['amcl'] == 'laptop'
    bad = replace(settings, layout={'laser': 'laptop'})
    with pytest.raises(LayoutError, match='laser may not run on laptop'):
        initial_layout(d, bad)
    with pytest.raises(LayoutError, match='not a managed node'):
        initial_layout(d, replace(settings, layout={'ghost': 'laptop'}))


def test_planner_layout_errors_are_clear(d, monkeypatch):
    settings = replace(d.decider, initial_layout='problem1')
    planning = __import__('anyscale_manager.planning', fromlist=['x'])
    # A stand-in planner (named as such): the planner itself is tested in its own suite.
    infeasible = types.SimpleNamespace(feasible=False, layout={}, violations=['no room'])
    monkeypatch.setattr(planning, 'solve', lambda dep, problem: infeasible, raising=False)
    with pytest.raises(LayoutError, match='no feasible plan.*no room'):
        initial_layout(d, settings)
    placement = types.SimpleNamespace(scale='laptop', cpu=50.0, performance=1.0,
                                      parameter_value=None)
    ok = types.SimpleNamespace(feasible=True, layout={'amcl': placement}, violations=[])
    monkeypatch.setattr(planning, 'solve', lambda dep, problem: ok, raising=False)
    lay, placements = layout_mod.initial_plan(d, settings)
    assert lay['amcl'] == 'laptop' and placements['amcl'] is placement
    monkeypatch.delattr(planning, 'solve')
    with pytest.raises(LayoutError, match='planner is not available'):
        initial_layout(d, settings)


def test_adopt_keeps_what_runs_where_allowed(d):
    planned = master_layout(d)
    lay, notes = adopt(d, planned, {'amcl': 'laptop', 'laser': 'laptop', 'ekf': 'robot'})
    assert lay['amcl'] == 'laptop' and lay['laser'] == 'robot'
    assert any('adopted amcl' in n for n in notes)
    assert any('laser runs on laptop' in n for n in notes)
    assert not check_layout(d, lay)


# --- intake -------------------------------------------------------------------------------------

def agent(scale, gen=0, **nodes):
    return p.AgentState(scale=scale, generation=gen, stamp=0.0, nodes={
        n: p.NodeReport(state=s, pid=1, since=0.0, restarts=0, ready=s == 'running',
                        exit_reason='') for n, s in nodes.items()})


def test_book_running_lost_and_refusals(d):
    book = ObservationBook(d, d.decider, started=0.0)
    book.agent_state(agent('robot', 3, laser='running', amcl='running', ghost='running'), 1.0)
    book.agent_state(agent('laptop', 5, amcl='starting', ar='running'), 1.0)
    assert book.running(2.0) == {'laser': 'robot', 'amcl': 'robot', 'ar': 'laptop'}
    assert book.max_generation == 5 and book.all_agents_heard()
    timeout = d.decider.agent_timeout_s
    book.agent_state(agent('robot', 3, laser='running'), 1.0 + timeout)
    assert book.lost_scales(2.0 + timeout) == {'laptop'}
    assert 'ar' not in book.running(2.0 + timeout)
    with pytest.raises(ValueError, match='unknown scale'):
        book.agent_state(agent('moon'), 1.0)
    with pytest.raises(ValueError, match="scale 'laptop' does not watch a link to 'robot'"):
        book.link_status(p.LinkStatus(master='laptop', remote='robot', stamp=0.0, up=True,
                                      rtt_ms=None, loss=0.0, bandwidth_available_kbps=None,
                                      bandwidth_available_age_s=None,
                                      bandwidth_used_kbps=0.0), 1.0)
    assert any('ghost' in k for k in book.ignored)


def test_book_says_which_link_reports_call_for_a_decision_now(d):
    book = ObservationBook(d, d.decider, started=0.0)

    def report(up=True, kbps=None, agent='alive'):
        return book.link_status(p.LinkStatus(
            master='robot', remote='laptop', stamp=0.0, up=up, rtt_ms=1.0, loss=0.0,
            bandwidth_available_kbps=kbps, bandwidth_available_age_s=None,
            bandwidth_used_kbps=0.0, peer_agent=agent), 1.0)
    assert not report(up=False)               # first heard down: nothing was beyond it yet
    assert not report()
    assert report(up=False)                   # up -> down
    assert not report(up=False) and not report()
    assert not report(kbps=52000.0)           # within 5 % of the nominal 54000
    assert report(kbps=40000.0)               # shrank
    assert not report(kbps=39000.0) and not report()   # 2.5 % less; no figure: kept
    assert report(agent='fenced')             # its warden stopped the dead agent's nodes
    assert not report(agent='fenced')


def test_book_prefers_the_subscribers_probe(d):
    book = ObservationBook(d, d.decider, started=0.0)
    reading = p.ConnectionReading(rate_hz=0.0, bytes_per_s=0.0, below_for_s=1.0, level=1)
    good = p.ConnectionReading(rate_hz=10.0, bytes_per_s=100.0, below_for_s=0.0, level=0)
    book.connection_status(p.ConnectionStatus(scale='laptop', stamp=0.0,
                                              connections={'laser_amcl': good}), 1.0)
    book.connection_status(p.ConnectionStatus(scale='robot', stamp=0.0,
                                              connections={'laser_amcl': reading,
                                                           'nope': reading}), 2.0)
    assert book.connections({'amcl': 'laptop'})['laser_amcl'].rate_hz == 10.0
    assert book.connections({'amcl': 'robot'})['laser_amcl'].rate_hz == 0.0
    obs = book.snapshot(2.5, {'amcl': 'laptop'})
    assert obs.now == 2.5 and obs.connections['laser_amcl'].stamp == 2.0   # receive time


def test_book_ranks_nodes_on_their_mean_cpu_not_one_sample(d):
    """AMCL works in bursts: one 0.5 s reading may catch a quarter of its usage and rank it
    below AR. The book averages each node over the fresh readings; the total stays the latest."""
    from anyscale_manager.runtime.constraints import node_cpu
    book = ObservationBook(d, d.decider, started=0.0)
    running = {n: 'robot' for n in master_layout(d)}
    samples = [(0.5, 80.0, 20.0), (1.0, 70.0, 22.0), (1.5, 75.0, 18.0), (2.0, 25.0, 32.0)]
    for t, amcl, ar in samples:
        book.scale_status(p.ScaleStatus(scale='robot', stamp=t, cpu_total=150.0 + t,
                                        capacity_cpu=200.0, cpu_by_node={'amcl': amcl, 'ar': ar},
                                        mem_percent=0.0, load_1m=0.0), t)
    obs = book.snapshot(2.0, running)
    assert obs.scales['robot'].cpu_total == 152.0                    # the latest
    assert obs.scales['robot'].cpu_by_node['amcl'] == pytest.approx(62.5)
    assert obs.scales['robot'].cpu_by_node['ar'] == pytest.approx(23.0)
    obs = replace(obs, running=running)
    assert node_cpu(d, d.decider, obs, 'amcl') > node_cpu(d, d.decider, obs, 'ar')
    # Readings older than observation_max_age_s drop out of the mean.
    late = 2.0 + d.decider.observation_max_age_s + 0.1
    book.scale_status(p.ScaleStatus(scale='robot', stamp=late, cpu_total=150.0,
                                    capacity_cpu=200.0, cpu_by_node={'amcl': 40.0},
                                    mem_percent=0.0, load_1m=0.0), late)
    assert book.scales['robot'].cpu_by_node == {'amcl': 40.0}


def test_status_render_without_ros(d):
    from anyscale_manager.nodes.status import StatusBook, render
    book = StatusBook(d)
    book.take(p.TOPIC_LAYOUT, p.Layout(generation=4, deployment=d.name,
                                       assignments=dict(master_layout(d), amcl='laptop'),
                                       reason='x', stamp=0.0).to_json(), 10.0)
    book.take(p.TOPIC_AGENT_STATE, agent('robot', 4, laser='running', amcl='running').to_json(),
              10.0)
    reading = p.ConnectionReading(rate_hz=0.5, bytes_per_s=0.0, below_for_s=0.6, level=1)
    book.take(p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus(
        scale='robot', stamp=0.0, connections={'camera_ar': reading}).to_json(), 10.0)
    book.take(p.TOPIC_LINK_STATUS, 'garbage', 10.0)
    text = render(book, 11.0)
    assert 'layout generation 4' in text
    assert 'camera_ar' in text and '0.6 / 1' in text and 'below, within Δ' in text
    assert 'amcl' in text and '(moving)' in text          # wanted on laptop, runs on robot
    assert '1 malformed message(s) ignored' in text
    assert 'not heard' in text                            # the laptop's agent
    assert 'STALE' in render(book, 20.0)
    # An inactive standby copy is listed apart, never as where the node runs.
    standby = p.NodeReport(state='standby', pid=2, since=0.0, restarts=0, ready=False,
                           exit_reason='', lifecycle='inactive')
    book.take(p.TOPIC_AGENT_STATE, p.AgentState(scale='laptop', generation=4, stamp=0.0,
                                                nodes={'amcl': standby}).to_json(), 11.0)
    row = next(line for line in render(book, 11.5).splitlines() if line.startswith('amcl '))
    assert row.split()[1:] == ['laptop', 'robot', '(moving)', 'running', '-', 'laptop'], row


def test_status_shows_two_senders_past_the_bound_not_ok(d):
    from anyscale_manager.nodes.status import StatusBook, render
    book = StatusBook(d)
    book.take(p.TOPIC_AGENT_STATE, agent('robot', 4, laser='running', amcl='running').to_json(),
              10.0)
    bound = d.monitoring.duplicate_sender_s

    def row(senders, for_s):
        conn = d.connection('amcl_ekf')
        reading = p.ConnectionReading(rate_hz=conn.freq_opt_hz * 2, bytes_per_s=0.0,
                                      below_for_s=0.0, level=p.OK, senders=senders,
                                      senders_for_s=for_s)
        book.take(p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus(
            scale='robot', stamp=0.0, connections={'amcl_ekf': reading}).to_json(), 10.0)
        return next(line for line in render(book, 10.5).splitlines()
                    if line.startswith('amcl_ekf '))
    assert row(2, bound - 1.0).endswith(' ok')       # within a move's overlap
    assert f'2 SENDERS for {bound + 2:.0f} s (heard on robot); ok' in row(2, bound + 2.0)
    assert row(1, 0.0).endswith(' ok')


def test_the_decider_does_not_count_standby_copies(d):
    book = ObservationBook(d, d.decider, started=0.0)
    book.agent_state(agent('robot', 3, amcl='running'), 1.0)
    book.agent_state(agent('laptop', 3, amcl='standby', ar='standby'), 1.0)
    assert book.running(2.0) == {'amcl': 'robot'}


def test_a_starting_standby_copy_is_not_where_the_node_serves(d):
    # At boot every scale starts a copy of a standby node: the laptop's, still starting, must
    # not be adopted as where AMCL runs (the robot's active copy is), nor AR placed at all.
    book = ObservationBook(d, d.decider, started=0.0)
    book.agent_state(agent('robot', 0, amcl='running', ar='starting', laser='starting'), 1.0)
    book.agent_state(agent('laptop', 0, amcl='starting', ar='starting'), 1.0)
    standby = [n for n in d.node_names if d.standby_scales(n)]
    assert set(standby) == {'amcl', 'ar'}
    assert book.running(2.0, active_only=standby) == {'amcl': 'robot', 'laser': 'robot'}
    assert book.running(2.0)['ar'] in ('robot', 'laptop')      # a plain node's start counts


def link(up=True, kbps=None):
    return p.LinkStatus(master='robot', remote='laptop', stamp=0.0, up=up, rtt_ms=1.0, loss=0.0,
                        bandwidth_available_kbps=kbps, bandwidth_available_age_s=None,
                        bandwidth_used_kbps=0.0)


def test_a_silent_or_restarted_master_agent_is_not_a_cut_link(d):
    """The link monitor runs in the master's agent: its silence, and a new agent's first
    seconds (its monitor waits for a first echo before it reports), say nothing of the link.
    Such a link is neither cut (nothing moves back) nor observed (nothing moves out)."""
    max_age, start = d.decider.observation_max_age_s, p.LINK_MONITOR_START_S
    book = ObservationBook(d, d.decider, started=0.0)
    running = dict(master_layout(d), amcl='laptop')
    # Steady: the master's agent and its monitor report; the link is judged.
    t = start + max_age + 1.0
    book.agent_state(agent('robot', 3, amcl='standby'), t)
    book.agent_state(agent('laptop', 3, amcl='running'), t)
    book.link_status(link(kbps=40000.0), t)
    assert book.snapshot(t + 0.5).unjudged_links == frozenset()
    # The master's agent is killed: its reports and the link's stop together.
    t_dead = t + max_age + 0.5
    book.agent_state(agent('laptop', 3, amcl='running'), t_dead)
    obs = book.snapshot(t_dead)
    assert obs.unjudged_links == {'laptop'}
    report = evaluate(d, d.decider, replace(obs, running=running))
    assert not report.of_kind(LINK_DOWN) and report.links['wifi'].up
    assert not report.links['wifi'].observed
    assert report.links['wifi'].available_kbps == 40000.0      # the last measurement
    # A new master agent speaks; its monitor is silent while it waits for a first echo.
    t_new = t_dead + 1.0
    book.agent_state(agent('robot', 3, amcl='standby'), t_new)
    assert book.snapshot(t_new + start).unjudged_links == {'laptop'}
    # Past the monitor's start-up and the report age, a silent link is silent again: a cut.
    late = t_new + start + max_age + 0.1
    for k in range(1, int((late - t_new) / 0.5) + 1):      # it reports every 0.5 s
        book.agent_state(agent('robot', 3, amcl='standby'), t_new + 0.5 * k)
    obs = book.snapshot(late)
    assert obs.unjudged_links == frozenset()
    (v,) = evaluate(d, d.decider, replace(obs, running=running)).of_kind(LINK_DOWN)
    assert 'silent' in v.reason
    # And a link reported down by a live monitor is down, whatever the agent did before.
    book.link_status(link(up=False), late)
    (v,) = evaluate(d, d.decider, replace(book.snapshot(late), running=running)
                    ).of_kind(LINK_DOWN)
    assert 'reported down' in v.reason


def test_a_master_agent_heard_last_just_after_its_link_monitor_is_not_a_cut(d):
    """Found by the chaos soak: the robot's agent SIGKILLed a moment after its last state and
    just after its monitor's last LinkStatus; the link went stale before the agent counted as
    silent, and both nodes were brought home for a cut that was not there. A stale link report
    is the link's silence only once the agent was heard after it went stale."""
    max_age = d.decider.observation_max_age_s
    running = dict(master_layout(d), amcl='laptop')
    t = 2 * (p.LINK_MONITOR_START_S + max_age)

    def steady():
        book = ObservationBook(d, d.decider, started=0.0)
        for k in range(int(t / 0.5) + 1):               # the agent reports every 0.5 s
            book.agent_state(agent('robot', 3, amcl='standby'), 0.5 * k)
            book.agent_state(agent('laptop', 3, amcl='running'), 0.5 * k)
        book.link_status(link(kbps=40000.0), t)
        assert book.snapshot(t).unjudged_links == frozenset()
        return book
    book = steady()
    book.agent_state(agent('robot', 3, amcl='standby'), t + 0.05)    # then SIGKILL
    for now in (t + max_age + 0.01, t + max_age + 0.04):      # link stale, agent not yet
        book.agent_state(agent('laptop', 3, amcl='running'), now)
        obs = book.snapshot(now)
        assert obs.unjudged_links == {'laptop'}
        assert not evaluate(d, d.decider, replace(obs, running=running)).of_kind(LINK_DOWN)
    # An agent that lives on while its monitor alone falls silent: the link is judged silent
    # once the agent speaks after the report went stale.
    book = steady()
    for k in range(1, int(max_age / 0.5) + 2):
        book.agent_state(agent('robot', 3, amcl='standby'), t + 0.05 + 0.5 * k)
    obs = book.snapshot(t + max_age + 0.6)
    assert obs.unjudged_links == frozenset()
    (v,) = evaluate(d, d.decider, replace(obs, running=running)).of_kind(LINK_DOWN)
    assert 'silent' in v.reason
