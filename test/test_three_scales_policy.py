"""The policy on three scales (robot, a laptop on Ethernet, a server over WiFi), on hand-written
observations with an injected clock: the next-best scale when a node must leave one, and the
rebalancing that uses a returning server again. No ROS.

``World`` applies each decision one period after it is made (the agents starting the copy) and
reports every scale's CPU as the nominal sum of its nodes (plus optional noise)."""

import dataclasses
import os
import random
from typing import Callable, Dict, List, Optional, Tuple

import pytest
import yaml

from anyscale_manager.model.loader import load_deployment, load_mapping
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (MIGRATE, MIGRATE_BACK, MOVE_AWAY, REBALANCE,
                                                   RELOCATE, ConnectionObs, Decision, LinkObs,
                                                   Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy, with_settings

HERE = os.path.dirname(os.path.abspath(__file__))
THREE = os.path.join(HERE, '..', 'config', 'three_scales_testbed.yaml')


@pytest.fixture(scope='module')
def d():
    return load_deployment(THREE)


class World:
    def __init__(self, d, settings=None, period_s: float = 0.5):
        self.d = d
        self.policy = MigrationPolicy(d, settings)
        self.running: Dict[str, str] = dict(master_layout(d))
        self.t = 0.0
        self.period_s = period_s
        # Keyed as Observations.links: the links from the master by their remote end, the
        # backhaul between laptop and server (watched by the laptop) as 'laptop-server'.
        self.link_up = {'laptop': True, 'server': True, 'laptop-server': True}
        self.link_kbps: Dict[str, float] = {}        # measured; none: the nominal
        self.agent_alive = {s: True for s in d.scale_names}
        self.cpu_extra: Dict[str, float] = {}
        self.noise: Optional[Callable[[], float]] = None
        self.heard: Dict[str, float] = {s: 0.0 for s in d.scale_names}
        self.inflight: List[Tuple[float, Decision]] = []
        self.log: List[Tuple[float, Decision]] = []

    def observe(self) -> Observations:
        t, d = self.t, self.d
        for s, alive in self.agent_alive.items():
            reachable = s == d.master.name or self.link_up[s]
            if alive and reachable:
                self.heard[s] = t
        scales = {}
        for s in d.scale_names:
            if self.heard[s] < t:
                continue
            cpu = sum(d.node(n).cpu for n, w in self.running.items() if w == s)
            cpu += self.cpu_extra.get(s, 0.0) + (self.noise() if self.noise else 0.0)
            scales[s] = ScaleObs(cpu_total=max(0.0, cpu), stamp=t)
        links = {s: LinkObs(up=up, stamp=t, available_kbps=self.link_kbps.get(s))
                 for s, up in self.link_up.items()}
        conns = {c.name: ConnectionObs(rate_hz=c.freq_opt_hz, stamp=t)
                 for c in d.connections if c.monitored}
        silent = {s: t - h for s, h in self.heard.items()
                  if t - h > self.policy.settings.observation_max_age_s}
        lost = frozenset(s for s, h in self.heard.items()
                         if t - h > self.policy.settings.agent_timeout_s)
        running = {n: s for n, s in self.running.items() if s not in lost}
        return Observations(now=t, running=running, scales=scales, links=links,
                            connections=conns, silent_agents=silent, lost_scales=lost)

    def run(self, until: float) -> List[Tuple[float, Decision]]:
        start = len(self.log)
        while self.t < until:
            for when, dec in list(self.inflight):
                if when <= self.t and self.agent_alive[dec.to_scale]:
                    self.running[dec.node] = dec.to_scale
                    self.inflight.remove((when, dec))
            for dec in self.policy.step(self.observe()):
                self.log.append((self.t, dec))
                self.inflight.append((self.t + self.period_s, dec))
            self.t = round(self.t + self.period_s, 6)
        return self.log[start:]


def moves(log) -> List[Tuple[str, str, str, str]]:
    return [(dec.kind, dec.node, dec.from_scale, dec.to_scale) for _, dec in log]


def settled_on_server(d) -> World:
    w = World(d)
    out = w.run(30.0)
    assert sorted((k, n, t) for k, n, _, t in moves(out)) == [
        (MIGRATE, 'amcl', 'server'), (MIGRATE, 'ar', 'server')]
    assert w.running['amcl'] == w.running['ar'] == 'server'
    return w


def test_the_heavy_nodes_go_to_the_most_powerful_scale(d):
    settled_on_server(d)


def test_a_cut_server_link_sends_its_nodes_to_the_laptop_not_home(d):
    w = settled_on_server(d)
    w.link_up['server'] = False
    out = w.run(w.t + 2.0)
    assert sorted(moves(out)) == [(MOVE_AWAY, 'amcl', 'server', 'laptop'),
                                  (MOVE_AWAY, 'ar', 'server', 'laptop')]
    assert all('the next-best scale' in dec.reason and 'link wifi' in dec.reason
               for _, dec in out)
    assert w.running['amcl'] == w.running['ar'] == 'laptop'
    # One move each: nothing went home on the way.
    assert not [m for m in moves(w.run(w.t + 10.0))]


def test_a_node_sent_on_from_a_cut_server_is_not_sent_again_while_its_old_copy_runs_there(d):
    """The turn after the one that sent AMCL and AR on to the laptop comes a moment later (a
    report wakes it), before the laptop reports them serving: the cut-off server's copies are
    still the last ones reported. Nothing moves again (it once sent both home from the laptop,
    and they came back out only after the hysteresis: 9 s without them on the laptop)."""
    w = settled_on_server(d)
    w.link_up['server'] = False
    first = w.policy.step(w.observe())
    assert sorted((dec.kind, dec.node, dec.to_scale) for dec in first) == [
        (MOVE_AWAY, 'amcl', 'laptop'), (MOVE_AWAY, 'ar', 'laptop')]
    for _ in range(5):
        w.t = round(w.t + 0.05, 6)
        assert w.policy.step(w.observe()) == []


def test_a_lost_server_agent_relocates_to_the_laptop(d):
    w = settled_on_server(d)
    w.agent_alive['server'] = False
    out = w.run(w.t + 6.0)
    assert sorted((k, n, f, t) for k, n, f, t in moves(out)) == [
        (RELOCATE, 'amcl', 'server', 'laptop'), (RELOCATE, 'ar', 'server', 'laptop')]


def test_with_the_laptop_full_the_nodes_go_home(d):
    w = settled_on_server(d)
    w.cpu_extra['laptop'] = 600.0           # 630 usable: neither fits
    w.link_up['server'] = False
    out = w.run(w.t + 2.0)
    assert sorted(moves(out)) == [(MIGRATE_BACK, 'amcl', 'server', 'robot'),
                                  (MIGRATE_BACK, 'ar', 'server', 'robot')]
    assert all('laptop: CPU' in dec.reason for _, dec in out)


def test_the_laptop_takes_what_fits_and_the_rest_goes_home(d):
    w = settled_on_server(d)
    w.cpu_extra['laptop'] = 560.0           # 630 usable: room for AMCL (50), not then AR (33)
    w.link_up['server'] = False
    out = w.run(w.t + 2.0)
    where = {n: t for _, n, _, t in moves(out)}
    assert sorted(where.values()) == ['laptop', 'robot']


def test_a_returning_server_is_used_again_after_the_hysteresis(d):
    w = settled_on_server(d)
    w.link_up['server'] = False
    cut_at = w.t
    w.run(w.t + 2.0)
    w.link_up['server'] = True
    T = w.policy.settings.hysteresis_s
    early = w.run(cut_at + T - 1.0)
    assert not moves(early)                 # within T of leaving it: the server is held
    out = w.run(cut_at + T + 5.0)
    assert sorted(moves(out)) == [(REBALANCE, 'amcl', 'laptop', 'server'),
                                  (REBALANCE, 'ar', 'laptop', 'server')]
    assert 'the cost function gains' in out[0][1].reason
    assert w.running['amcl'] == w.running['ar'] == 'server'


def test_a_held_rebalance_says_which_check_holds_it(d):
    w = settled_on_server(d)
    w.link_up['server'] = False
    w.run(w.t + 2.0)
    w.link_up['server'] = True
    w.link_up['laptop-server'] = False      # the handover from the laptop needs the backhaul
    T = w.policy.settings.hysteresis_s
    assert not moves(w.run(w.t + T + 5.0))
    assert any(n.startswith('amcl stays on laptop: moving it to server would gain')
               and n.endswith('held by the handover check') for n in w.policy.notes), \
        w.policy.notes
    w.link_up['laptop-server'] = True
    assert sorted(moves(w.run(w.t + 2.0))) == [(REBALANCE, 'amcl', 'laptop', 'server'),
                                               (REBALANCE, 'ar', 'laptop', 'server')]


def test_no_rebalance_below_the_least_gain_or_when_turned_off(d):
    for settings in (with_settings(d, rebalance_min_gain=1000.0),
                     with_settings(d, rebalance=False)):
        w = World(d, settings)
        w.run(30.0)
        w.link_up['server'] = False
        w.run(w.t + 2.0)
        w.link_up['server'] = True
        assert not moves(w.run(w.t + 60.0))
        assert w.running['amcl'] == w.running['ar'] == 'laptop'


def test_no_needless_move_in_ten_minutes_of_noisy_cpu(d):
    rng = random.Random(7)
    w = World(d)
    w.noise = lambda: rng.gauss(0.0, 15.0)
    w.run(30.0)
    assert not moves(w.run(630.0))


def test_a_server_that_appears_late_takes_the_nodes_from_the_laptop(d):
    w = World(d)
    w.agent_alive['server'] = False
    w.link_up['server'] = False
    out = w.run(40.0)
    assert sorted((k, n, t) for k, n, _, t in moves(out)) == [
        (MIGRATE, 'amcl', 'laptop'), (MIGRATE, 'ar', 'laptop')]
    arrived = max(t for t, _ in out)
    assert w.t > arrived + w.policy.settings.hysteresis_s     # settled there for over T
    w.agent_alive['server'] = True
    w.link_up['server'] = True
    back_at = w.t
    out = w.run(w.t + 5.0)
    assert sorted((k, n, t) for k, n, _, t in moves(out)) == [
        (REBALANCE, 'amcl', 'server'), (REBALANCE, 'ar', 'server')]
    assert all(t - back_at <= 2.0 for t, _ in out)     # one per turn, once it is observed


def amcl_feeds_ar():
    """The three-scale file with one more connection, AMCL's pose into AR: when the two run
    on the laptop and the server, it crosses the backhaul."""
    with open(THREE) as f:
        data = yaml.safe_load(f)
    conns = data['/**']['ros__parameters']['connections']
    conns['names'].append('amcl_ar')
    conns['amcl_ar'] = {'topic': '/amcl_pose', 'publisher': 'amcl', 'subscriber': 'ar',
                        'msg_type': 'geometry_msgs/msg/PoseWithCovarianceStamped',
                        'freq_min_hz': 2.0, 'freq_opt_hz': 5.0, 'tolerance_s': 2.0,
                        'bandwidth_kbps': 15.0}
    return load_mapping(data, 'three scales, amcl feeding ar')


def split_over_the_backhaul(d) -> World:
    w = World(d)
    # Room on the server for AMCL (the first to move) and not then for AR: AR takes the laptop.
    w.cpu_extra['server'] = 1530.0 - 60.0
    w.run(30.0)
    assert (w.running['amcl'], w.running['ar']) == ('server', 'laptop')
    return w


def test_a_cut_backhaul_moves_only_what_crosses_it_and_not_across_the_cut():
    d = amcl_feeds_ar()
    w = split_over_the_backhaul(d)
    w.link_up['laptop-server'] = False
    out = w.run(w.t + 2.0)
    # One node moves, home: straight to the server (or the laptop) would be a handover over
    # the cut link. The last migrated goes; the other stays where it is.
    assert moves(out) == [(MIGRATE_BACK, 'ar', 'laptop', 'robot')]
    reason = out[0][1].reason
    assert 'link backhaul between laptop and server reported down' in reason
    assert 'the handover from laptop needs it' in reason
    assert w.running['amcl'] == 'server'
    # Nothing crosses the cut link, and nothing goes back over it while it is down.
    assert not moves(w.run(w.t + 60.0))
    assert (w.running['amcl'], w.running['ar']) == ('server', 'robot')


def test_a_cut_backhaul_that_carries_nothing_moves_nothing(d):
    w = split_over_the_backhaul(d)          # no connection between AMCL and AR here
    w.link_up['laptop-server'] = False
    assert not moves(w.run(w.t + 10.0))


def test_a_backhaul_never_reported_counts_as_down_but_cuts_off_no_scale():
    d = amcl_feeds_ar()
    w = split_over_the_backhaul(d)
    del w.link_up['laptop-server']          # its watcher, the laptop's agent, never says
    out = w.run(w.t + 4.0)
    assert moves(out) == [(MIGRATE_BACK, 'ar', 'laptop', 'robot')]
    assert 'link backhaul between laptop and server silent' in out[0][1].reason


def test_a_down_link_nothing_can_relieve_does_not_hold_back_an_overloaded_one():
    """A pair of nodes pinned one to the laptop, one to the server, talk over the backhaul
    (first in the file's links); it is cut: nothing can move for it. The server's WiFi then
    shrinks below what AR needs: AR still comes off it."""
    with open(THREE) as f:
        data = yaml.safe_load(f)
    params = data['/**']['ros__parameters']
    params['links']['names'] = ['backhaul', 'ethernet', 'wifi']
    nodes, conns = params['nodes'], params['connections']
    for name, scale in (('mapper', 'laptop'), ('planner', 'server')):
        nodes['names'].append(name)
        nodes[name] = dict(nodes['user'], cpu=5.0, residence=[scale])
    conns['names'].append('mapper_planner')
    conns['mapper_planner'] = dict(conns['amcl_ekf'], publisher='mapper', subscriber='planner',
                                   topic='/plan_map')
    d = load_mapping(data, 'three scales, a pinned pair over the backhaul')
    w = settled_on_server(d)
    w.link_up['laptop-server'] = False
    assert not moves(w.run(w.t + 2.0))                # nothing to move for it
    w.link_kbps = {'server': 5000.0}                  # AR's 6 Mbit/s no longer fits
    out = w.run(w.t + 2.0)
    # Home (the laptop is across the cut backhaul from the server), then out to the laptop,
    # which home reaches: two handovers where the cut forbids the direct one.
    assert moves(out) == [(MIGRATE_BACK, 'ar', 'server', 'robot'),
                          (MIGRATE, 'ar', 'robot', 'laptop')], moves(out)
    assert 'link wifi: required' in out[0][1].reason
    assert 'the handover from server needs it' in out[0][1].reason


def without_gains(d):
    """The test-bed as a user writes it who sets no ``gain``: each scale's worth comes from its
    power (cores x GHz over the robot's)."""
    return dataclasses.replace(d, scales=tuple(dataclasses.replace(s, gain=None)
                                               for s in d.scales))


def test_with_no_gain_a_scale_is_worth_its_power_and_every_move_uses_that_one_rule(d):
    plain = without_gains(d)
    worth = {s: plain.worth(s) for s in plain.scale_names}
    assert worth['robot'] == 1.0 and worth['robot'] < worth['laptop'] < worth['server']
    assert worth['laptop'] == pytest.approx(3.5) and worth['server'] == pytest.approx(8.5)
    # A gain given rules over the power.
    assert d.worth('server') == 6.0
    settled_on_server(plain)


def test_with_no_gain_nodes_return_to_the_server_after_its_agent_came_back(d):
    """Heavy nodes placed on the server, its agent killed and restarted: they come back to it
    from the laptop (rebalancing weighs the same worth that placed them)."""
    w = settled_on_server(without_gains(d))
    w.agent_alive['server'] = False
    w.run(w.t + 6.0)
    assert w.running['amcl'] == w.running['ar'] == 'laptop'
    w.agent_alive['server'] = True
    out = w.run(w.t + w.policy.settings.hysteresis_s + 10.0)
    assert sorted(moves(out)) == [(REBALANCE, 'amcl', 'laptop', 'server'),
                                  (REBALANCE, 'ar', 'laptop', 'server')]
