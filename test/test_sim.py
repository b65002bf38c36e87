"""The simulator: model, link schedules, world semantics, oracle, policies, runner, command."""

import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from anyscale_manager.runtime.observations import MIGRATE, MIGRATE_BACK, Decision
from anyscale_manager.runtime.policy import MigrationPolicy
from anyscale_manager.runtime.turn import DeciderTurn
from anyscale_manager.sim.model import PathModel, robot_speed
from anyscale_manager.sim.oracle import MILP, Assignment, LinkBudget
from anyscale_manager.sim.path import LinkSchedule, always_up, draw_schedule
from anyscale_manager.sim.planner_policy import PlannerPolicy
from anyscale_manager.sim.runner import (HEURISTIC, PLANNER, drive, make_policy, oracle_lap,
                                         run_schedules, run_system)
from anyscale_manager.sim.systems import build_system, fig7_systems
from anyscale_manager.sim.world import SimulationError, World

PATH = PathModel()


@pytest.fixture(scope='module')
def testbed():
    return build_system(6, 2, 2)


@pytest.fixture(scope='module')
def testbed3():
    return build_system(6, 2, 3)


# --- model ------------------------------------------------------------------------------------

def test_testbed_speeds(testbed):
    amcl = testbed.profiles['amcl']
    assert (amcl.rate_base_hz, amcl.rate_opt_hz, amcl.speed_weight) == (2.0, 5.0, 1.0)
    assert testbed.profiles['ar'].speed_weight == 0.0
    p = testbed.profiles
    assert robot_speed(PATH, p, {'amcl': 5.0}) == pytest.approx(0.4)
    assert robot_speed(PATH, p, {'amcl': 2.0}) == pytest.approx(0.2)
    assert robot_speed(PATH, p, {'amcl': 3.5}) == pytest.approx(0.3)
    # cut off: dead reckoning at v_min within Δ (2 s), then a stop
    assert robot_speed(PATH, p, {'amcl': 0.0}, {'amcl': 1.5}) == pytest.approx(0.2)
    assert robot_speed(PATH, p, {'amcl': 0.0}, {'amcl': 2.5}) == 0.0


@pytest.mark.parametrize('bad', [dict(speed_min_mps=0.0), dict(availability_low=0.7),
                                 dict(outages_min=3, outages_max=1), dict(links='mesh'),
                                 dict(throughput_fraction=0.0)])
def test_path_model_rejects_bad_values(bad):
    with pytest.raises(ValueError, match='PathModel'):
        PathModel(**bad)


@pytest.mark.parametrize('seed', range(20))
def test_schedule_draws(seed):
    rng = np.random.default_rng(seed)
    s = draw_schedule(rng, PATH, 24000.0)
    assert 0.45 - 1e-9 <= s.availability <= 0.65 + 1e-9
    assert 1 <= len(s.outages) <= 3
    edges = [e for o in s.outages for e in o]
    assert edges == sorted(edges) and 0 <= edges[0] and edges[-1] <= PATH.length_m
    a, b = s.outages[0]
    assert not s.up((a + b) / 2) and s.available_kbps((a + b) / 2) == 0.0
    # goodput ramps up away from a hole's edge
    if b + PATH.edge_ramp_m < PATH.length_m and all(x >= b + PATH.edge_ramp_m
                                                    for x, _ in s.outages[1:]):
        assert s.available_kbps(b + 1.0) == pytest.approx(24000.0 / PATH.edge_ramp_m)
        assert s.available_kbps(b + PATH.edge_ramp_m) == 24000.0


def test_schedules_reproducible_and_seed_dependent(testbed3):
    a = run_schedules(testbed3, PATH, 7, 0)
    assert a == run_schedules(testbed3, PATH, 7, 0)
    assert a != run_schedules(testbed3, PATH, 8, 0)
    # independent links: each remote scale has its own holes
    assert a['laptop'].outages != a['workstation'].outages
    shared = run_schedules(testbed3, dataclasses.replace(PATH, links='shared'), 7, 0)
    assert shared['laptop'].outages == shared['workstation'].outages


# --- systems ----------------------------------------------------------------------------------

def test_fig7_systems():
    systems = fig7_systems()
    assert [(s.n, s.m, s.k) for s in systems] == [
        (n, m, k) for n, m in ((6, 2), (12, 6), (18, 9)) for k in (2, 3, 4)]
    for s in systems:
        d = s.deployment
        assert len(d.migratable_nodes) == s.m
        assert len(d.scales) == s.k
        gains = [x.gain for x in d.remote_scales]
        powers = [x.power for x in d.remote_scales]
        assert gains == sorted(gains) and len(set(gains)) == len(gains)
        assert powers == sorted(powers) and d.master.gain < gains[0]
        for r in d.remote_scales:
            assert d.link_between(d.master.name, r.name) is not None
        # the baseline (everything on the robot) fits on the robot
        assert sum(n.cpu for n in d.nodes) <= d.master.capacity_cpu * d.decider.cpu_headroom
        assert abs(sum(p.speed_weight for p in s.profiles.values()) - 1.0) < 1e-9
    assert systems[0].deployment.migratable_nodes == ('amcl', 'ar')


def test_testbed_system_is_the_config_file(testbed_path, testbed):
    from anyscale_manager.model.loader import load_deployment
    d = load_deployment(testbed_path)
    assert testbed.deployment.node_names == d.node_names
    assert testbed.deployment.connections == d.connections
    assert [s.name for s in testbed.deployment.scales] == [s.name for s in d.scales]


def test_generated_systems_depend_on_seed_only():
    a, b, c = build_system(12, 6, 2, seed=1), build_system(12, 6, 2, seed=1), \
        build_system(12, 6, 2, seed=2)
    assert a.deployment.nodes == b.deployment.nodes
    assert a.deployment.nodes != c.deployment.nodes


@pytest.mark.parametrize('n,m,k', [(6, 3, 2), (5, 2, 2), (12, 6, 5)])
def test_bad_systems_are_refused(n, m, k):
    with pytest.raises(ValueError):
        build_system(n, m, k)


# --- world ------------------------------------------------------------------------------------

def _schedule(outages):
    return LinkSchedule(PATH.length_m, tuple(outages), 24000.0, PATH.edge_ramp_m)


def test_world_observations_follow_the_link(testbed):
    world = World(testbed, {'laptop': _schedule([(0.0, 10.0)])}, PATH,
                  layout={'amcl': 'laptop'})
    obs = world.observe()
    assert obs.links['laptop'].up is False and obs.links['laptop'].available_kbps == 0.0
    assert obs.connections['laser_amcl'].rate_hz == 0.0    # crosses the down link
    assert obs.connections['amcl_ekf'].rate_hz == 0.0
    assert obs.connections['odometer_odometry'].rate_hz == 40.0
    assert obs.running['amcl'] == 'laptop'
    assert world.speed_mps() == pytest.approx(0.2)          # within Δ: dead reckoning
    for _ in range(5):                                      # 2.5 s > Δ = 2 s
        world.advance(0.5)
    # 2 s at 0.2 m/s, then stopped
    assert world.speed_mps() == 0.0 and world.s == pytest.approx(0.5)
    assert world.observe().connections['amcl_ekf'].below_for_s == pytest.approx(2.5)
    # the laptop's agent is silent beyond agent_timeout_s: the scale is lost
    assert 'laptop' in world.observe().lost_scales


def test_world_rate_depends_on_the_scale_and_its_cpu(testbed):
    world = World(testbed, {'laptop': always_up(PATH, 24000.0)}, PATH, layout={'amcl': 'laptop'})
    assert world.output_hz['amcl'] == 5.0                   # 2 Hz x gain 3.5, capped at opt
    assert world.speed_mps() == pytest.approx(0.4)
    obs = world.observe()
    assert obs.links['laptop'].used_kbps == pytest.approx(224.0 + 15.0)   # laser in, pose out
    assert obs.scales['laptop'].cpu_by_node['amcl'] == 50.0
    # an overloaded master: every node there gets a proportional share and slows down
    heavy = dataclasses.replace(testbed.deployment.master, capacity_cpu=76.5)
    d = dataclasses.replace(testbed.deployment,
                            scales=(heavy,) + testbed.deployment.scales[1:])
    slow = World(dataclasses.replace(testbed, deployment=d), {'laptop': always_up(PATH, 1.0)},
                 PATH)
    assert slow.output_hz['amcl'] == pytest.approx(1.0)     # half the CPU: half the rate


@pytest.mark.parametrize('standby', [True, False])
def test_world_migration_delay(testbed, standby):
    # The test-bed's AMCL keeps an inactive copy on the laptop: activated there, not started.
    if not standby:
        d = testbed.deployment
        nodes = tuple(dataclasses.replace(n, standby=False) if n.name == 'amcl' else n
                      for n in d.nodes)
        testbed = dataclasses.replace(testbed, deployment=dataclasses.replace(d, nodes=nodes))
    world = World(testbed, {'laptop': always_up(PATH, 24000.0)}, PATH)
    world.apply([Decision(MIGRATE, 'amcl', 'robot', 'laptop', 'test')])
    steps = 0
    while world.observe().running['amcl'] != 'laptop':
        world.advance(0.05)
        steps += 1
        assert steps < 1000
    delay = PATH.standby_resume_s if standby else PATH.migration_delay_s
    assert steps * 0.05 == pytest.approx(delay)
    assert world.migrations == 1
    with pytest.raises(SimulationError, match='may not run'):
        world.apply([Decision(MIGRATE, 'ekf', 'robot', 'laptop', 'critical node')])


# --- oracle -----------------------------------------------------------------------------------

@pytest.mark.parametrize('seed', range(6))
def test_oracle_is_exact(seed):
    system = build_system(12, 6, 4)
    rng = np.random.default_rng(seed)
    weights = {n: p.speed_weight for n, p in system.profiles.items()}
    bb = Assignment(system.deployment, system.profiles, weights)
    milp = Assignment(system.deployment, system.profiles, weights, method=MILP)
    remotes = [s.name for s in system.deployment.remote_scales]
    usable = {r: LinkBudget(float(rng.uniform(0, 20000)), float(rng.uniform(0, 1400)))
              for r in remotes if rng.random() < 0.8}
    best = bb.enumerate(usable)
    for layout in (bb.solve(usable), milp.solve(usable)):
        assert bb.feasible(layout, usable)
        assert bb.score(layout) == pytest.approx(bb.score(best), abs=1e-9)


def test_oracle_bounds_the_policies(testbed3):
    for run in range(2):
        schedules = run_schedules(testbed3, PATH, 0, run)
        bound = oracle_lap(testbed3, schedules, PATH).time_s
        for name in (HEURISTIC, PLANNER):
            lap = drive(testbed3, schedules, PATH, make_policy(name, testbed3))
            assert lap.finished and lap.time_s >= bound - 1e-6


# --- policies and runs ------------------------------------------------------------------------

def test_the_policy_is_the_runtime_one(testbed):
    policy = make_policy(HEURISTIC, testbed)
    assert type(policy) is MigrationPolicy
    assert isinstance(make_policy(PLANNER, testbed), PlannerPolicy)
    schedules = run_schedules(testbed, PATH, 0, 0)
    world_log = []
    real_step = policy.step

    def spy(obs):
        out = real_step(obs)
        world_log.extend(out)
        return out

    policy.step = spy
    lap = drive(testbed, schedules, PATH, policy)
    assert lap.finished and lap.migrations > 0
    assert [d for _, d in policy.history] == world_log
    assert world_log[0].node == 'amcl'                      # the paper: AMCL first


@pytest.mark.parametrize('name', [HEURISTIC, PLANNER])
def test_a_lap_runs_the_deciders_turn(testbed, name):
    """The live decider's turn decides in the simulator: its first layout, one layout and one
    event per decision, its violation events, and its cost integral."""
    policy = make_policy(name, testbed)
    schedules = run_schedules(testbed, PATH, 0, 0)
    turns = []
    real_turn = DeciderTurn.turn

    def spy(self, now, observed=None):
        assert self.policy is policy and observed is not None and observed.now == now
        out = real_turn(self, now, observed)
        turns.append(out)
        return out

    said = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DeciderTurn, 'turn', spy)
        lap = drive(testbed, schedules, PATH, policy, said=said)
    assert len(turns) == lap.steps and said == [e for out in turns for e in out.events]
    assert said[0] == ('layout', '', '', '', 'first layout (master)', 1)
    moves = [m for out in turns for m in out.decisions]
    assert moves == [m for _, m in policy.history] and len(moves) == lap.migrations > 0
    assert {MIGRATE, MIGRATE_BACK} <= {m.kind for m in moves}
    assert [e[:5] for e in said if e[0] in {m.kind for m in moves}] == \
        [(m.kind, m.node, m.from_scale, m.to_scale, m.reason) for m in moves]
    # The first layout, then one more for each turn that moved something.
    layouts = [g for out in turns for g, _, _ in out.layouts]
    assert layouts == list(range(1, 2 + sum(1 for out in turns if out.decisions)))
    # The link's holes are said as the live decider says them, and cleared.
    assert any(e[0] == 'violation' and 'link' in e[4] for e in said)
    assert any(e[0] == 'cleared' for e in said)
    assert all(out.plan is not None and out.objective is not None for out in turns)
    assert lap.perf_map_mean == pytest.approx(turns[-1].objective[1] / turns[-1].objective[2],
                                              rel=0.05)


def test_no_migration_is_zero_improvement(testbed3):
    schedules = run_schedules(testbed3, PATH, 0, 1)
    lap = drive(testbed3, schedules, PATH, make_policy(HEURISTIC, testbed3, migration=False))
    assert lap.migrations == 0
    assert lap.time_s == pytest.approx(PATH.length_m / PATH.speed_min_mps)
    result, _ = run_system(testbed3, 1, 0, HEURISTIC, PATH)
    assert result.baseline_time_s == pytest.approx(lap.time_s)
    zero, _ = run_system(testbed3, 1, 0, HEURISTIC,
                         dataclasses.replace(PATH, speed_max_mps=PATH.speed_min_mps))
    assert zero.improvement_pct == pytest.approx(0.0, abs=1e-9)
    assert zero.best_case_improvement_pct == pytest.approx(0.0, abs=1e-9)


def test_runs_are_reproducible(testbed):
    a, _ = run_system(testbed, 2, 5, HEURISTIC, PATH)
    b, _ = run_system(testbed, 2, 5, HEURISTIC, PATH)
    c, _ = run_system(testbed, 2, 6, HEURISTIC, PATH)
    assert a.to_dict() == b.to_dict()
    assert a.to_dict() != c.to_dict()


@pytest.mark.parametrize('n,m,k', [(6, 2, 2), (12, 6, 3)])
def test_best_case_beats_typical(n, m, k):
    result, _ = run_system(build_system(n, m, k), 2, 0, HEURISTIC, PATH)
    assert 0 < result.improvement_pct < result.best_case_improvement_pct
    assert result.best_case_improvement_pct <= 50.0 + 1e-9   # v_max / v_min = 2
    for r in result.runs:
        assert r.oracle_improvement_pct >= r.improvement_pct - 1e-6


def test_planner_closes_the_gap(testbed3):
    # Against Algorithm 1 as the paper writes it (T bars any move out of a node migrated back).
    literal = {'hysteresis_scope': 'node'}
    heuristic, _ = run_system(testbed3, 3, 0, HEURISTIC, PATH, overrides=literal)
    planner, _ = run_system(testbed3, 3, 0, PLANNER, PATH)
    assert planner.gap_to_oracle_pct < heuristic.gap_to_oracle_pct
    assert planner.improvement_pct > heuristic.improvement_pct


def test_hysteresis_per_scale_lets_a_node_use_another_scale(testbed3):
    """With three scales, T barring only the scale a node came back from (the default) gets
    closer to the oracle than the literal rule, which keeps the node home for T."""
    literal, _ = run_system(testbed3, 3, 0, HEURISTIC, PATH,
                            overrides={'hysteresis_scope': 'node'})
    per_scale, _ = run_system(testbed3, 3, 0, HEURISTIC, PATH)
    assert testbed3.deployment.decider.hysteresis_scope == 'scale'
    assert per_scale.improvement_pct > literal.improvement_pct
    assert per_scale.gap_to_oracle_pct < literal.gap_to_oracle_pct


# --- the command ------------------------------------------------------------------------------

def _simulate(args, tmp_path):
    env = dict(os.environ, MPLBACKEND='Agg')
    return subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'simulate', *args,
                           '--out', str(tmp_path)], capture_output=True, text=True, env=env,
                          timeout=120)


def test_simulate_json_shape(tmp_path):
    proc = _simulate(['--runs', '1', '--seed', '3', '--systems', '6x2x2,6x2x3', '--json'],
                     tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert [(s['n'], s['m'], s['k']) for s in out['systems']] == [(6, 2, 2), (6, 2, 3)]
    for s in out['systems']:
        assert isinstance(s['improvement_pct'], float) and len(s['runs']) == 1
    avg = sum(s['improvement_pct'] for s in out['systems']) / 2
    assert out['average_improvement_pct'] == pytest.approx(avg)
    assert out['best_case_improvement_pct'] > out['average_improvement_pct']
    assert out['policy'] == 'heuristic' and out['seed'] == 3
    for name in ('fig7.png', 'fig7.csv', 'runs.csv'):
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / 'fig7.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    rows = (tmp_path / 'fig7.csv').read_text().splitlines()
    assert rows[0].startswith('label,n,m,k') and len(rows) == 3


def test_simulate_table(tmp_path):
    proc = _simulate(['--runs', '1', '--systems', '6x2x2', '--policy', 'planner'], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert '6N x 2M x 2K' in proc.stdout and 'average' in proc.stdout
    assert 'policy planner' in proc.stdout


@pytest.mark.parametrize('args,message', [
    (['--runs', '0'], '--runs must be >= 1'),
    (['--systems', '6x2'], "'6x2' is not NxMxK"),
    (['--systems', '6x3x2'], 'N >= M + 4'),
    (['--testbed', '/nonexistent/testbed.yaml'], 'testbed.yaml'),
    (['--availability', '0.7', '0.5'], 'availability'),
    (['--hysteresis', '-1'], '--hysteresis must be in'),
])
def test_simulate_bad_input(tmp_path, args, message):
    proc = _simulate(args, tmp_path)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not (tmp_path / 'fig7.png').exists()


def test_the_simulator_needs_no_ros():
    code = ('import sys, anyscale_manager.sim.cli, anyscale_manager.sim.runner; '
            'print(any(m == "rclpy" or m.startswith("rclpy.") for m in sys.modules))')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == 'False'


def test_improvement_is_finite_for_every_system_lap():
    # A lap that never finishes would read -inf: a policy must never strand the robot.
    system = build_system(18, 9, 4)
    result, _ = run_system(system, 1, 0, HEURISTIC, PATH, oracle=False)
    assert all(math.isfinite(r.improvement_pct) for r in result.runs)
    assert math.isnan(result.oracle_improvement_pct)
