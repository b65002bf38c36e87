"""A fleet in simulation (sim/fleet.py): N robots, each its own deployment, decider turn and
world, sharing K servers through the real claims ledger. Small, seeded fleets."""

import json
import subprocess
import sys

import numpy as np
import pytest

from anyscale_manager.sim.fleet import FleetSpec, robot_schedules, robot_system, run_fleet
from anyscale_manager.sim.fleet_figures import jain
from anyscale_manager.sim.model import PathModel
from anyscale_manager.sim.path import LinkSchedule
from anyscale_manager.sim.runner import HEURISTIC, drive, make_policy, run_schedules
from anyscale_manager.sim.systems import build_system, system_parameters
from anyscale_manager.sim.world import World

PATH = PathModel()
# Room for one robot's AMCL (CPU 50), not for two, nor for AMCL and AR (33).
ONE_HEAVY = 60.0


def holders(trace, server='server_0'):
    """(t, the robots with a copy live on the server) of every period."""
    return [(t, {c.split('/')[0] for c in live}) for t, s, live, _ in trace if s == server]


# --- the robots ----------------------------------------------------------------------------------

def test_each_robot_is_the_base_system_with_the_shared_servers():
    spec = FleetSpec(robots=4, servers=3, capacity_cpu=500.0, priority_levels=2)
    base = system_parameters(6, 2)
    robots = [robot_system(spec, i, base) for i in range(4)]
    alone = build_system(6, 2, 2)
    for i, r in enumerate(robots):
        d = r.deployment
        assert d.name == f'robot_{i}' and d.priority == i % 2
        assert [s.name for s in d.remote_scales] == ['server_0', 'server_1', 'server_2']
        assert all(s.shared and s.capacity_cpu == 500.0 for s in d.remote_scales)
        # The laptop's power: AMCL reaches its optimum there, as on the test-bed's laptop.
        assert d.worth('server_0') == alone.deployment.worth('laptop')
        assert d.node_names == alone.deployment.node_names
        assert d.migratable_nodes == alone.deployment.migratable_nodes
    # Each robot its own coverage, the same for the same seed.
    a = [robot_schedules(r, PATH, 0, 0, i) for i, r in enumerate(robots)]
    assert a == [robot_schedules(r, PATH, 0, 0, i) for i, r in enumerate(robots)]
    assert len({s['server_0'].outages for s in a}) == 4


@pytest.mark.parametrize('bad', [dict(robots=0), dict(robots=51), dict(servers=0),
                                 dict(servers=4), dict(capacity_cpu=0.0),
                                 dict(duration_s=-1.0), dict(priority_levels=0)])
def test_a_bad_fleet_is_refused(bad):
    with pytest.raises(ValueError, match='FleetSpec'):
        FleetSpec(**bad)


def test_jain():
    assert jain([3.0, 3.0, 3.0]) == pytest.approx(1.0)
    assert jain([5.0, 0.0, 0.0, 0.0]) == pytest.approx(0.25)
    assert jain([0.0, 0.0]) == 1.0


# --- the world it needs --------------------------------------------------------------------------

def test_a_looping_world_drives_lap_after_lap():
    system = build_system(6, 2, 2)
    world = World(system, run_schedules(system, PATH, 0, 0), PATH, loop=True)
    while len(world.lap_times) < 2:
        world.advance(0.5)
    assert not world.finished
    assert world.driven_m == pytest.approx(2 * PATH.length_m + world.s)
    assert PATH.length_m / PATH.speed_min_mps - 0.5 <= world.lap_times[0] <= \
        PATH.length_m / PATH.speed_min_mps + 0.5


def test_the_world_counts_each_stretch_past_its_delta_once():
    system = build_system(6, 2, 2)
    cut = {'laptop': LinkSchedule(PATH.length_m, ((0.0, PATH.length_m),), 24300.0)}
    world = World(system, cut, PATH, layout={'amcl': 'laptop'})
    for _ in range(8):                       # 4 s cut off: AMCL's connections past Δ = 2 s
        world.advance(0.5)
    assert sorted(c for _, c in world.delta_violations) == ['amcl_ekf', 'laser_amcl']
    assert all(2.0 < t <= 2.5 for t, _ in world.delta_violations)


def test_a_single_robot_lap_reports_its_delta_violations():
    system = build_system(6, 2, 2)
    policy = make_policy(HEURISTIC, system)
    lap = drive(system, run_schedules(system, PATH, 0, 0), PATH, policy)
    assert lap.finished and lap.delta_violations >= 0


# --- the fleet -----------------------------------------------------------------------------------

def test_a_contended_fleet_never_over_commits_a_server():
    spec = FleetSpec(robots=6, servers=2, capacity_cpu=120.0, duration_s=200.0,
                     priority_levels=2, seed=1)
    trace = []
    run = run_fleet(spec, trace=trace)
    assert run.overcommit_s == 0.0
    assert all(claimed <= spec.capacity_cpu for _, _, _, claimed in trace)
    for s in run.servers:
        assert 0 < s.utilisation <= 1.0
        assert s.peak_claimed_cpu <= spec.capacity_cpu
        assert s.peak_running_cpu <= spec.capacity_cpu
    # It was contended: refused, made to wait, and preempted.
    assert run.refused > 0 and run.waiting > 0 and run.preemptions > 0
    assert run.claims == run.granted + run.refused + run.waiting == len(run.claim_s)
    assert 0 < run.fairness <= 1.0
    assert all(r.server_time_s > 0 and r.driven_m > 0 for r in run.robots)


def test_two_robots_one_heavy_node_room_one_holds_it_at_a_time():
    spec = FleetSpec(robots=2, servers=1, capacity_cpu=ONE_HEAVY, duration_s=300.0)
    trace = []
    run = run_fleet(spec, trace=trace)
    held = holders(trace)
    assert max(len(h) for _, h in held) == 1
    # Both had it in turn (each while the other was out of coverage).
    assert {r for _, h in held for r in h} == {'robot_0', 'robot_1'}
    # Both asked for it at the first turn: one was granted, the other refused (no preemption
    # between equals).
    assert run.refused >= 1 and run.preemptions == 0 and run.overcommit_s == 0.0
    assert all(r.server_time_s > 0 for r in run.robots)


def test_a_robot_of_a_higher_priority_preempts():
    spec = FleetSpec(robots=2, servers=1, capacity_cpu=ONE_HEAVY, duration_s=120.0,
                     priority_levels=2, seed=2)
    trace = []
    run = run_fleet(spec, trace=trace)
    assert run.asks, 'robot_1 was never made to wait for robot_0'
    # Only the lower robot is asked, only by the higher.
    assert all(a[2].startswith('robot_0/') and a[3].startswith('robot_1/') for a in run.asks)
    t, _, asked, _ = run.asks[0]
    held = dict(holders(trace))
    assert held[t] == {'robot_0'}
    # Within a decider period and one turn, robot_1's copy serves there, and never beside it.
    assert held[t + 1.0] == {'robot_1'}
    assert max(len(h) for h in held.values()) == 1
    assert run.overcommit_s == 0.0
    assert next(r for r in run.robots if r.name == 'robot_0').delta_violations == 0


def test_a_fleet_run_is_the_same_for_the_same_seed():
    spec = FleetSpec(robots=4, servers=2, capacity_cpu=100.0, duration_s=120.0,
                     priority_levels=2, seed=3)
    a, b = run_fleet(spec), run_fleet(spec)
    assert a.figures() == b.figures()
    c = run_fleet(FleetSpec(robots=4, servers=2, capacity_cpu=100.0, duration_s=120.0,
                            priority_levels=2, seed=4))
    assert a.figures() != c.figures()
    # Another run of the same fleet draws other links.
    assert run_fleet(spec, run=1).figures() != a.figures()


# --- the command ---------------------------------------------------------------------------------

def _simulate(*args):
    return subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'simulate', *args],
                          capture_output=True, text=True, timeout=120)


def test_simulate_fleet_json():
    proc = _simulate('--fleet', '3', '--servers', '2', '--capacity', '100', '--priorities', '2',
                     '--duration', '60', '--runs', '2', '--seed', '5', '--json')
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out['fleet'] == {'robots': 3, 'servers': 2, 'n': 6, 'm': 2, 'capacity_cpu': 100.0,
                            'duration_s': 60.0, 'priority_levels': 2, 'seed': 5}
    assert [r['run'] for r in out['runs']] == [0, 1]
    for r in out['runs']:
        assert [s['name'] for s in r['servers']] == ['server_0', 'server_1']
        assert [x['priority'] for x in r['robots']] == [0, 1, 0]
        assert r['overcommit_s'] == 0.0
        assert r['claim_p95_ms'] >= r['claim_p50_ms'] > 0
    assert out['mean']['runs'] == 2
    assert out['mean']['fairness'] == pytest.approx(np.mean([r['fairness'] for r in out['runs']]))


def test_simulate_fleet_table():
    proc = _simulate('--fleet', '2', '--duration', '30')
    assert proc.returncode == 0, proc.stderr
    assert 'A fleet in simulation: 2 robot(s)' in proc.stdout
    assert "Jain's index" in proc.stdout and 'over-commit s' in proc.stdout


@pytest.mark.parametrize('args,message', [
    (['--fleet', '0'], '--fleet must be in 1..50'),
    (['--fleet', '2', '--servers', '4'], '--servers must be in 1..3'),
    (['--servers', '2'], '--servers needs --fleet N'),
    (['--fleet', '2', '--compare'], '--compare does not apply to --fleet'),
    (['--fleet', '2', '--policy', 'planner'], 'runtime policy only'),
    (['--fleet', '2', '--base', '6x'], "'6x' is not NxM"),
    (['--fleet', '2', '--base', '6x3'], 'N >= M + 4'),
    (['--fleet', '2', '--capacity', '0'], '--capacity must be > 0'),
])
def test_simulate_fleet_bad_input(args, message):
    proc = _simulate(*args)
    assert proc.returncode == 2
    assert message in proc.stderr and proc.stdout == ''
