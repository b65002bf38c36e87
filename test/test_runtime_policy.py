"""Algorithm 1 on the ICAR test-bed: scripted traces through the pure core, injected clock.

The ``BedTrace`` below is not a simulator: a small, explicit model of what the monitors would
report, so that each test can script the link (up, down, throttled, silent) and read what the
policy decided and when.

- The link monitor reports the link's state ``detect_s`` late (heartbeat misses).
- A probe measures a connection's rate over a ``window_s`` window, so after the link is cut the
  reported rate decays to 0 over the window, as a real windowed probe does.
- A probe runs on the subscriber's scale; when that is the remote scale and the link is down,
  its readings stop arriving (they go stale).
- A throttled link delivers a crossing connection at ``available / required`` of its rate.
- A decision takes effect ``apply_s`` after it is made (an agent starting the node).
- A scale monitor reports every period while its scale is reachable; ``scale_silent`` pauses
  it (the decider keeps its last, ageing, report), as does a cut link.
"""

from dataclasses import replace
from typing import Callable, Dict, List, Optional, Tuple

import pytest

from anyscale_manager.model.loader import load_deployment
from anyscale_manager.model.types import Deployment
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (MIGRATE, MIGRATE_BACK, MOVE_AWAY,
                                                   RELOCATE, ConnectionObs, Decision, LinkObs,
                                                   Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy


class BedTrace:
    def __init__(self, deployment: Deployment, settings=None, period_s: float = 0.5,
                 apply_s: float = 1.0, detect_s: float = 0.75, window_s: float = 2.0,
                 running: Optional[Dict[str, str]] = None):
        self.d = deployment
        self.policy = MigrationPolicy(deployment, settings)
        self.settings = self.policy.settings
        self.master = deployment.master.name
        self.remote = deployment.remote_scales[0].name
        self.running = dict(running) if running is not None else master_layout(deployment)
        self.period_s, self.apply_s = period_s, apply_s
        self.detect_s, self.window_s = detect_s, window_s
        self.t = 0.0
        self.link_schedule: List[Tuple[float, bool, Optional[float]]] = [(-1e9, True, None)]
        self.link_silent: List[Tuple[float, float]] = []     # (from, to) no link reports
        self.scale_silent: List[Tuple[str, float, float]] = []   # (scale, from, to) no reports
        self.rate_factor: Dict[str, Callable[[float], float]] = {}   # connection -> f(t)
        self.cpu_extra: Dict[str, Callable[[float], float]] = {}     # scale -> f(t)
        self.lost: Callable[[float], frozenset] = lambda t: frozenset()
        self.inflight: List[Tuple[float, str, str]] = []
        self.log: List[Tuple[float, Decision]] = []
        self.applied: List[Tuple[float, str, str]] = []
        self.below_at: Dict[float, Dict[str, float]] = {}     # decision time -> Δ timers
        self._last_link: Optional[LinkObs] = None
        self._last_reading: Dict[str, ConnectionObs] = {}
        self._last_scale: Dict[str, ScaleObs] = {}
        self._below_since: Dict[str, float] = {}
        self._down_since: Optional[float] = None

    # --- scripting ----------------------------------------------------------------------------
    def set_link(self, at: float, up: bool, available_kbps: Optional[float] = None) -> None:
        self.link_schedule.append((at, up, available_kbps))
        self.link_schedule.sort(key=lambda e: e[0])

    def link_at(self, t: float) -> Tuple[bool, Optional[float]]:
        state = self.link_schedule[0]
        for entry in self.link_schedule:
            if entry[0] <= t:
                state = entry
        return state[1], state[2]

    def cut_time_before(self, t: float) -> Optional[float]:
        """When the link last went down at or before ``t`` (None if up at ``t``)."""
        up, _ = self.link_at(t)
        if up:
            return None
        down_at = None
        for at, u, _ in self.link_schedule:
            if at <= t:
                down_at = None if u else (down_at if down_at is not None else at)
        return down_at

    # --- the model ----------------------------------------------------------------------------
    def _true_rate(self, c, t: float) -> float:
        nominal = c.freq_opt_hz or c.freq_min_hz or 1.0
        a, b = self.running.get(c.publisher), self.running.get(c.subscriber)
        if a is None or b is None:
            return 0.0
        rate = nominal * self.rate_factor.get(c.name, lambda _t: 1.0)(t)
        if a != b:
            up, available = self.link_at(t)
            if not up:
                cut = self.cut_time_before(t)
                left = max(0.0, self.window_s - (t - cut)) / self.window_s
                return rate * left
            if available is not None:
                required = sum(x.bandwidth_kbps for x in self.d.connections
                               if {self.running.get(x.publisher), self.running.get(x.subscriber)}
                               == {a, b})
                if required > available:
                    rate *= available / required
        return rate

    def observe(self) -> Observations:
        t = self.t
        seen_up, seen_available = self.link_at(t - self.detect_s)
        truly_up, _ = self.link_at(t)
        silent = any(a <= t < b for a, b in self.link_silent)
        if not silent:
            self._last_link = LinkObs(up=seen_up, stamp=t, available_kbps=seen_available)
        links = {self.remote: self._last_link} if self._last_link is not None else {}
        for c in self.d.connections:
            if not c.monitored:
                continue
            rate = self._true_rate(c, t)
            if rate < c.freq_min_hz:
                self._below_since.setdefault(c.name, t)
            else:
                self._below_since.pop(c.name, None)
            probe_home = self.running.get(c.subscriber, self.master)
            if probe_home != self.master and not truly_up:
                continue                     # the reading cannot reach the decider
            below = t - self._below_since[c.name] if c.name in self._below_since else 0.0
            self._last_reading[c.name] = ConnectionObs(rate_hz=rate, stamp=t, below_for_s=below,
                                                       below=c.name in self._below_since)
        for s in self.d.scale_names:
            if s != self.master and not truly_up:
                continue
            if any(x == s and a <= t < b for x, a, b in self.scale_silent):
                continue
            cpu = sum(self.d.node(n).cpu for n, w in self.running.items() if w == s)
            cpu += self.cpu_extra.get(s, lambda _t: 0.0)(t)
            self._last_scale[s] = ScaleObs(cpu_total=cpu, stamp=t)
        return Observations(now=t, running=dict(self.running), scales=dict(self._last_scale),
                            links=links, connections=dict(self._last_reading),
                            lost_scales=self.lost(t))

    def run(self, until: float) -> List[Tuple[float, Decision]]:
        new = []
        while self.t <= until + 1e-9:
            for entry in sorted(self.inflight):
                if entry[0] <= self.t + 1e-9:
                    self.inflight.remove(entry)
                    self.running[entry[1]] = entry[2]
                    self.applied.append(entry)
            for d in self.policy.step(self.observe()):
                self.below_at[self.t] = dict(self.policy.below_for)
                self.log.append((self.t, d))
                new.append((self.t, d))
                self.inflight.append((self.t + self.apply_s, d.node, d.to_scale))
            self.t = round(self.t + self.period_s, 9)
        return new

    # --- reading the log ----------------------------------------------------------------------
    def moves(self, kind: Optional[str] = None, node: Optional[str] = None):
        return [(t, d) for t, d in self.log
                if (kind is None or d.kind == kind) and (node is None or d.node == node)]

    def first_below(self, connection: str) -> Optional[float]:
        return self._below_since.get(connection)


# --- the story of the paper's test-bed --------------------------------------------------------

@pytest.fixture(scope='module')
def testbed(testbed_path=None):
    from conftest import TESTBED
    return load_deployment(TESTBED)


def both_out(testbed, **kw):
    bed = BedTrace(testbed, **kw)
    bed.run(20.0)
    assert bed.running['amcl'] == 'laptop' and bed.running['ar'] == 'laptop', bed.log
    return bed


def test_link_up_amcl_moves_first_then_ar(testbed):
    bed = BedTrace(testbed)
    bed.run(20.0)
    outs = bed.moves(MIGRATE)
    assert outs[0][0] == 0.0          # link and both CPUs observed: no fixed wait at the start
    assert [d.node for _, d in outs] == ['amcl', 'ar']
    assert all(d.to_scale == 'laptop' and d.from_scale == 'robot' for _, d in outs)
    # one move out at a time: AR only after AMCL runs there and the laptop's CPU was measured
    # after that (the next period's reading)
    amcl_there = next(t for t, n, s in bed.applied if n == 'amcl' and s == 'laptop')
    assert outs[1][0] >= amcl_there + bed.period_s - 1e-9
    assert 'most CPU-intensive' in outs[0][1].reason and 'wifi' in outs[1][1].reason
    assert not bed.moves(MIGRATE_BACK)
    assert bed.policy.migrated == [('amcl', 'laptop'), ('ar', 'laptop')]


def test_ar_stays_home_when_the_link_cannot_carry_its_6_mbits(testbed):
    bed = BedTrace(testbed)
    bed.set_link(0.0, True, 5000.0)          # 5000 x margin 0.8 = 4000 < 6268 with AR out
    bed.run(60.0)
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl']
    assert bed.running['ar'] == 'robot' and bed.running['amcl'] == 'laptop'
    assert any('ar -> laptop' in n and 'wifi' in n for n in bed.policy.notes)


def test_link_cut_brings_both_back_before_their_tolerance_runs_out(testbed):
    bed = both_out(testbed)
    cut = 30.0
    bed.set_link(cut, False)
    bed.run(40.0)
    backs = {d.node: t for t, d in bed.moves(MIGRATE_BACK)}
    assert set(backs) == {'amcl', 'ar'}
    for node, at in backs.items():
        # the link-down path, not Δ: decided within detection + one period of the cut
        assert at - cut <= bed.detect_s + bed.period_s + 1e-9
        reason = next(d.reason for t, d in bed.moves(MIGRATE_BACK, node))
        assert 'link wifi' in reason and 'down' in reason
        applied = next(t for t, n, s in bed.applied if n == node and s == 'robot')
        for c in testbed.connections_of(node):
            if not c.monitored:
                continue
            below = bed.first_below(c.name)
            if below is None:
                continue
            # applied on the robot before the connection's Δ would run out
            assert applied < below + c.tolerance_s, (node, c.name, applied, below)
    assert bed.running['amcl'] == 'robot' and bed.running['ar'] == 'robot'


def test_link_cut_acts_on_the_link_not_on_delta(testbed):
    """Rates that drop to 0 at once: AR (Δ 1 s) is decided back before its Δ is exceeded."""
    bed = both_out(testbed, window_s=1e-6)
    bed.set_link(30.0, False)
    bed.run(36.0)
    (t, d), = bed.moves(MIGRATE_BACK, 'ar')
    assert 'link wifi' in d.reason
    assert bed.below_at[t]['camera_ar'] <= 1.0       # Δ not exceeded when it was decided


def test_throttled_below_ar_need_brings_ar_back_and_amcl_stays(testbed):
    bed = both_out(testbed)
    bed.set_link(30.0, True, 3000.0)        # usable 2400: AMCL's 206 fits, AR's 6062 not
    bed.run(90.0)
    backs = bed.moves(MIGRATE_BACK)
    assert [d.node for _, d in backs] == ['ar']
    assert 'required' in backs[0][1].reason and 'usable' in backs[0][1].reason
    assert bed.running['amcl'] == 'laptop' and bed.running['ar'] == 'robot'
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl', 'ar']   # AR never re-tried in


@pytest.mark.parametrize('half_period_s', [1.0, 3.0, 7.0])
def test_a_link_flapping_faster_than_T_does_not_oscillate(testbed, half_period_s):
    bed = BedTrace(testbed)
    duration = 200.0
    t, up = 10.0, False
    while t < duration:
        bed.set_link(t, up)
        t += half_period_s
        up = not up
    bed.run(duration)
    T = testbed.decider.hysteresis_s
    for node in ('amcl', 'ar'):
        outs = [t for t, _ in bed.moves(MIGRATE, node)]
        backs = [t for t, _ in bed.moves(MIGRATE_BACK, node)]
        assert len(outs) <= duration / T + 1, (node, outs)
        for b in backs:
            assert not [o for o in outs if b < o < b + T], (node, b, outs)
    assert len(bed.log) <= 2 * 2 * (duration / T + 1)


def test_frequency_below_min_for_less_than_delta_is_no_violation(testbed):
    bed = both_out(testbed)
    # laser -> amcl at 3 Hz (min 5, Δ 2 s) for 1.5 s
    bed.rate_factor['laser_amcl'] = lambda t: 0.3 if 30.0 <= t < 31.5 else 1.0
    bed.run(40.0)
    assert not bed.moves(MIGRATE_BACK)
    assert bed.policy.last_report.frequency_ok


def test_frequency_below_min_past_delta_brings_the_node_back(testbed):
    bed = both_out(testbed)
    bed.rate_factor['laser_amcl'] = lambda t: 0.3 if t >= 30.0 else 1.0
    bed.run(40.0)
    backs = bed.moves(MIGRATE_BACK)
    assert [d.node for _, d in backs] == ['amcl']
    t, d = backs[0]
    assert 30.0 + 2.0 < t <= 30.0 + 2.0 + bed.period_s + 1e-9
    assert 'laser_amcl' in d.reason and 'tolerance 2 s' in d.reason


def test_grace_after_a_move_then_judged(testbed):
    """A moved node whose input never arrives there is not judged in its grace, then sent
    back."""
    bed = BedTrace(testbed)
    bed.rate_factor['laser_amcl'] = lambda t: 1.0 if bed.running['amcl'] == bed.master else 0.0
    bed.run(15.0)
    outs, backs = bed.moves(MIGRATE, 'amcl'), bed.moves(MIGRATE_BACK, 'amcl')
    assert outs and backs
    assert backs[0][0] - outs[0][0] >= testbed.decider.grace_s
    assert 'laser_amcl' in backs[0][1].reason


def test_remote_cpu_overload_brings_back_the_last_moved(testbed):
    bed = both_out(testbed)
    bed.cpu_extra['laptop'] = lambda t: 560.0 if t >= 30.0 else 0.0   # 643 > 630 usable
    bed.run(40.0)
    backs = bed.moves(MIGRATE_BACK)
    assert [d.node for _, d in backs] == ['ar']        # 560 + 50 = 610 fits again
    assert 'CPU' in backs[0][1].reason


def test_master_cpu_overload_is_reported_but_not_blocking(testbed):
    bed = BedTrace(testbed)
    bed.cpu_extra['robot'] = lambda t: 150.0       # 150 + nominal > 180 usable on the robot
    bed.run(testbed.decider.grace_s + 1.0)
    report = bed.policy.last_report
    assert not report.cpu_ok
    assert report.of_kind('cpu')[0].subject == 'robot' and not report.of_kind('cpu')[0].nodes
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl', 'ar']


def test_no_room_on_the_remote_cpu_means_no_move(testbed):
    bed = BedTrace(testbed)
    bed.cpu_extra['laptop'] = lambda t: 600.0      # 600 + 50 > 630
    bed.run(10.0)
    assert not bed.moves(MIGRATE)
    assert any('CPU' in n for n in bed.policy.notes)


def test_a_silent_link_is_a_down_link(testbed):
    bed = both_out(testbed)
    bed.link_silent.append((30.0, 1e9))       # link reports stop; the link itself is fine
    bed.run(36.0)
    backs = {d.node: t for t, d in bed.moves(MIGRATE_BACK)}
    max_age = testbed.decider.observation_max_age_s
    assert set(backs) == {'amcl', 'ar'}
    for t in backs.values():
        assert 30.0 + max_age - bed.period_s < t <= 30.0 + max_age + bed.period_s + 1e-9
    reason = bed.moves(MIGRATE_BACK)[0][1].reason
    assert 'silent' in reason


def test_never_reported_link_gates_migration(testbed):
    bed = BedTrace(testbed)
    bed.link_silent.append((0.0, 1e9))
    bed.run(10.0)
    assert not bed.log
    assert any('silent' in n or 'not observed' in n for n in bed.policy.notes)


def test_migration_false_is_the_no_migration_baseline(testbed):
    settings = replace(testbed.decider, migration=False)
    bed = BedTrace(testbed, settings=settings)
    bed.run(30.0)
    assert not bed.log


def test_a_move_the_agents_never_apply_is_undone(testbed):
    bed = BedTrace(testbed, apply_s=1e9)
    bed.run(30.0)
    outs, backs = bed.moves(MIGRATE, 'amcl'), bed.moves(MIGRATE_BACK, 'amcl')
    assert outs and backs
    wait = testbed.agent.readiness_timeout_s + testbed.decider.agent_timeout_s
    assert backs[0][0] - outs[0][0] > wait
    assert 'not running on laptop' in backs[0][1].reason


def test_lost_scale_relocates_its_nodes(testbed):
    bed = both_out(testbed)
    bed.lost = lambda t: frozenset({'laptop'}) if t >= 30.0 else frozenset()
    bed.run(32.0)
    moved = {d.node: d for t, d in bed.log if t >= 30.0}
    assert set(moved) == {'amcl', 'ar'}
    assert all(d.kind == RELOCATE and d.to_scale == 'robot' for d in moved.values())
    assert 'lost' in moved['amcl'].reason


def test_adopts_what_runs_instead_of_moving_it(testbed):
    running = dict(master_layout(testbed), amcl='laptop')
    bed = BedTrace(testbed, running=running)
    bed.run(0.0)
    assert not [d for _, d in bed.log if d.node == 'amcl']      # AMCL is not restarted
    assert bed.policy.layout['amcl'] == 'laptop'
    assert bed.policy.migrated[0] == ('amcl', 'laptop')
    # what runs is what the readings measure: AR may follow at once, judged with AMCL there
    assert [d.node for _, d in bed.log] == ['ar']
    assert 'CPU 50 + ' in bed.log[0][1].reason


def test_every_decision_has_a_reason(testbed):
    bed = both_out(testbed)
    bed.set_link(30.0, False)
    bed.set_link(35.0, True, 3000.0)
    bed.run(80.0)
    assert len(bed.log) >= 3
    assert all(d.reason and len(d.reason) > 10 for _, d in bed.log)


def test_settings_change_at_run_time_takes_effect(testbed):
    bed = BedTrace(testbed)
    bed.run(0.0)
    bed.policy.update_settings(replace(bed.settings, migration=False))
    bed.run(30.0)
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl']


# --- when a move out may follow: observations, not a fixed delay ------------------------------

def test_next_move_out_one_period_after_the_first_settles(testbed):
    """A fresh laptop reading after AMCL runs there: AR follows one period later, not grace_s."""
    bed = BedTrace(testbed)
    bed.run(10.0)
    (t_amcl, _), (t_ar, ar) = bed.moves(MIGRATE)
    amcl_there = next(t for t, n, s in bed.applied if n == 'amcl' and s == 'laptop')
    assert t_amcl == 0.0 and amcl_there == t_amcl + bed.apply_s
    assert t_ar == pytest.approx(amcl_there + bed.period_s)
    assert t_ar - t_amcl < testbed.decider.grace_s
    assert 'CPU 50 + 33' in ar.reason          # judged with AMCL's load on the laptop


def test_next_move_out_waits_for_a_cpu_reading_taken_after_the_move(testbed):
    """The laptop's monitor pauses around AMCL's arrival: AR waits for its next reading."""
    bed = BedTrace(testbed)
    bed.scale_silent.append(('laptop', 0.75, 3.25))    # last reading 0.5, next one 3.5
    bed.run(2.5)
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl']
    assert bed.running['amcl'] == 'laptop'
    # a fresh reading (at most 2 s old), but taken before AMCL started there: wait
    assert any('not measured since amcl started there' in n for n in bed.policy.notes), \
        bed.policy.notes
    bed.run(3.0)
    assert [d.node for _, d in bed.moves(MIGRATE)] == ['amcl']
    assert any('no fresh CPU report from laptop' in n for n in bed.policy.notes)
    bed.run(10.0)
    (t_ar, _), = bed.moves(MIGRATE, 'ar')
    assert t_ar == 3.5                              # the first reading after the pause


def test_first_move_waits_for_link_and_cpu_observations_not_a_grace_period(testbed):
    bed = BedTrace(testbed)
    bed.link_silent.append((0.0, 1.0))              # the link monitor's first report at 1.0
    bed.scale_silent.append(('laptop', 0.0, 1.5))   # the laptop's first CPU report at 1.5
    bed.run(0.5)
    assert not bed.log
    assert any('waiting' in n and 'not observed' in n for n in bed.policy.notes)
    bed.run(1.0)
    assert not bed.log
    assert any('no CPU report from laptop yet' in n for n in bed.policy.notes)
    bed.run(5.0)
    assert bed.moves(MIGRATE)[0][0] == 1.5 and bed.moves(MIGRATE)[0][1].node == 'amcl'


def test_first_move_waits_for_the_masters_cpu_at_most_the_observation_age(testbed):
    early = BedTrace(testbed)
    early.scale_silent.append(('robot', 0.0, 1.0))
    early.run(5.0)
    assert early.moves(MIGRATE)[0][0] == 1.0
    never = BedTrace(testbed)
    never.scale_silent.append(('robot', 0.0, 1e9))
    never.run(5.0)
    max_age = testbed.decider.observation_max_age_s
    first = never.moves(MIGRATE)[0][0]
    assert max_age < first <= max_age + never.period_s    # then ranked by nominal CPU


def test_a_scale_whose_cpu_is_never_reported_hosts_nothing(testbed):
    bed = BedTrace(testbed)
    bed.scale_silent.append(('laptop', 0.0, 1e9))
    bed.run(10.0)
    assert not bed.log
    assert any('no fresh CPU report from laptop (last never' in n for n in bed.policy.notes)


def _all_observed(d, now, scales=None, running=None):
    running = running or master_layout(d)
    scales = d.scale_names if scales is None else scales
    cpu = {s: sum(d.node(n).cpu for n, w in running.items() if w == s) for s in scales}
    return Observations(
        now=now, running=running,
        scales={s: ScaleObs(cpu_total=cpu[s], stamp=now) for s in scales},
        links={r.name: LinkObs(up=True, stamp=now) for r in d.remote_scales},
        connections={c.name: ConnectionObs(rate_hz=c.freq_opt_hz or c.freq_min_hz, stamp=now)
                     for c in d.connections if c.monitored})


def test_waiting_for_the_best_scale_does_not_fall_through_to_a_lesser_one():
    """Two remote scales: a move out waits for the more powerful one's readings rather than
    choosing the other on a partial view; also after a node moved there."""
    from anyscale_manager.sim.systems import build_system
    d = build_system(6, 2, 3).deployment          # robot, laptop, workstation (most powerful)
    policy = MigrationPolicy(d)
    assert not policy.step(_all_observed(d, 0.0, scales=['robot', 'laptop']))
    assert any('amcl -> workstation: waiting: no CPU report' in n for n in policy.notes)
    (out,) = policy.step(_all_observed(d, 0.5))
    assert (out.node, out.to_scale) == ('amcl', 'workstation')
    # AMCL runs on the workstation from 1.5; the workstation's reading is still the one of 1.0
    running = dict(master_layout(d), amcl='workstation')
    seen = _all_observed(d, 1.5, running=running)
    stale_ws = dict(seen.scales, workstation=ScaleObs(cpu_total=0.0, stamp=1.0))
    assert not policy.step(replace(seen, scales=stale_ws))
    assert any('ar -> workstation: waiting: CPU of workstation not measured since amcl' in n
               for n in policy.notes), policy.notes
    (ar,) = policy.step(_all_observed(d, 2.0, running=running))
    assert (ar.node, ar.to_scale) == ('ar', 'workstation')


@pytest.mark.parametrize('scope', ['scale', 'node'])
def test_hysteresis_scope_after_a_link_drop(scope):
    """AMCL leaves the workstation when its link drops. Scope 'scale' (default): it goes to
    the next-best scale, the laptop, whose link is up, at once, and not back to the workstation
    within T. Scope 'node' (the paper's literal rule): it comes back to the robot and stays
    there for T."""
    from anyscale_manager.sim.systems import build_system
    d = build_system(6, 2, 3).deployment
    settings = replace(d.decider, hysteresis_scope=scope)
    policy = MigrationPolicy(d, settings)
    home = dict(master_layout(d))
    moves, notes = [], []

    def turn(now, ws_up=True):
        obs = _all_observed(d, now, running=home)
        if not ws_up:
            obs = replace(obs, links=dict(obs.links, workstation=LinkObs(up=False, stamp=now)))
        for dec in policy.step(obs):
            moves.append((now, dec.kind, dec.node, dec.to_scale))
            home[dec.node] = dec.to_scale      # the agents apply it before the next turn
        notes.extend(policy.notes)

    for now in (0.0, 0.5, 1.0, 1.5):          # AR follows once AMCL's load is measured
        turn(now)
    assert [m[2:] for m in moves] == [('amcl', 'workstation'), ('ar', 'workstation')]
    T = settings.hysteresis_s
    now = 3.0
    while now < 3.0 + T - 1.0:
        turn(now, ws_up=False)
        now += 0.5
    first = [m[1:] for m in moves if m[0] == 3.0]
    later = [m for m in moves if m[0] > 3.0]
    assert not [m for m in later if m[3] == 'workstation'], later
    if scope == 'scale':
        assert first == [(MOVE_AWAY, 'amcl', 'laptop'), (MOVE_AWAY, 'ar', 'laptop')], first
        assert later == []
    else:
        assert first == [(MIGRATE_BACK, 'amcl', 'robot'), (MIGRATE_BACK, 'ar', 'robot')]
        assert later == []
        assert any('amcl: amcl migrated back from workstation' in n for n in notes), notes
