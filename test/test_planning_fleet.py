"""plan --fleet: Problem 1 over several robots' deployments that share a server.

The fleet's plan keeps the robots' use of a shared server within its capacity, all robots
together, where each robot planned alone takes the whole server; files that contradict each
other about a shared server are refused naming them; an IROS 2016 instance splits into one
deployment per robot without losing a node or a connection.
"""

import json
import os

import pytest
import yaml

from anyscale_manager.cli import main as cli_main
from anyscale_manager.model import load_deployment, load_mapping
from anyscale_manager.model.iros2016 import INSTANCES, split_fleet
from anyscale_manager.model.yaml_io import read_yaml
from anyscale_manager.planning import check_layout, solve
from anyscale_manager.planning.fleet import FleetError, merge, solve_fleet
from conftest import CONFIG

IROS = os.path.join(CONFIG, 'iros2016')
SERVER_CAPACITY = 100.0


def robot(name, server_capacity=SERVER_CAPACITY, headroom=1.0, server_role='remote',
          server_shared=True, home_host=None):
    """A robot's deployment: a sensor pinned to its robot and a worker (20-60 CPU) that does
    better the more CPU it has, and has more room on the server than at home."""
    server = {'role': server_role, 'kind': 'server', 'capacity_cpu': server_capacity,
              'cores': 4, 'clock_ghz': 3.0, 'host': 'server-host'}
    if server_shared and server_role != 'master':
        server['shared'] = True
    home_role = 'remote' if server_role == 'master' else 'master'
    return {'/**': {'ros__parameters': {
        'deployment': {'name': name},
        'scales': {'names': ['home', 'server'],
                   'home': {'role': home_role, 'kind': 'robot', 'capacity_cpu': 40.0,
                            'cores': 2, 'clock_ghz': 1.6,
                            'host': home_host or f'{name}-host'},
                   'server': server},
        'links': {'names': ['wifi'], 'wifi': {'ends': ['home', 'server'],
                                              'bandwidth_kbps': 10000.0,
                                              'medium': 'wireless'}},
        'nodes': {'names': ['sensor', 'worker'],
                  'sensor': {'cpu': 10.0, 'performance': 1.0, 'residence': ['home']},
                  'worker': {'settings': {'parameter': 'rate_hz', 'values': [5.0, 10.0, 15.0],
                                          'cpu': [20.0, 40.0, 60.0],
                                          'performance': [30.0, 70.0, 100.0],
                                          'form': 'log'}}},
        'connections': {'names': ['sensor_worker'],
                        'sensor_worker': {'topic': f'/{name}/s', 'publisher': 'sensor',
                                          'subscriber': 'worker', 'bandwidth_kbps': 10.0}},
        'decider': {'cpu_headroom': headroom},
    }}}


def write(tmp_path, name, data):
    path = tmp_path / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def fleet_files(tmp_path, **changes):
    """Two robots' files; ``changes`` are robot_b's keyword arguments to ``robot``."""
    return [write(tmp_path, 'robot_a', robot('robot_a')),
            write(tmp_path, 'robot_b', robot('robot_b', **changes))]


# --- the fleet's plan ---------------------------------------------------------------------------
@pytest.mark.parametrize('solver', ['greedy', 'exact'])
def test_the_fleet_plan_fits_the_shared_server_where_each_robot_alone_overcommits_it(
        tmp_path, solver):
    members = [load_deployment(p) for p in fleet_files(tmp_path)]
    alone = [solve(d, problem=1, solver=solver) for d in members]
    assert sum(p.scale_load['server'] for p in alone) > SERVER_CAPACITY
    fp = solve_fleet(members, solver=solver)
    assert fp.feasible
    use = fp.shared_use()['server']
    assert set(use) == {'robot_a', 'robot_b'}
    assert sum(use.values()) <= SERVER_CAPACITY + 1e-9
    assert not check_layout(fp.fleet.merged, fp.plan.assignment(),
                            {n: p.cpu for n, p in fp.plan.layout.items()})
    for d in members:
        part = fp.members[d.name]
        # each robot's part is in its own names and keeps its own file's rules
        assert set(part.layout) == set(d.node_names)
        assert part.layout['sensor'].scale == 'home'
        assert part.scale_load['home'] <= 40.0 + 1e-9
    assert fp.plan.objective == pytest.approx(sum(p.objective for p in fp.members.values()))
    if solver == 'exact':
        assert fp.plan.optimal


def test_the_strictest_headroom_of_the_files_rules_a_shared_server(tmp_path):
    members = [load_deployment(p) for p in fleet_files(tmp_path, headroom=0.5)]
    fleet = merge(members)
    assert fleet.shared['server'].usable_cpu == pytest.approx(0.5 * SERVER_CAPACITY)
    fp = solve_fleet(members, solver='exact', fleet=fleet)
    assert sum(fp.shared_use()['server'].values()) <= 0.5 * SERVER_CAPACITY + 1e-9
    # robot_a keeps its own headroom at home (1.0), robot_b its own (0.5)
    assert fp.members['robot_b'].scale_load['home'] <= 20.0 + 1e-9


def test_robots_own_scales_of_one_name_and_host_stay_apart(tmp_path):
    """Both robots call their robot 'home' on one host (not shared, as on a single machine's
    loopback fleet): two scales, and neither robot's nodes may run on the other's."""
    paths = [write(tmp_path, name, robot(name, home_host='localhost'))
             for name in ('robot_a', 'robot_b')]
    fleet = merge([load_deployment(p) for p in paths])
    assert set(fleet.merged.scale_names) == {'robot_a/home', 'robot_b/home', 'server'}
    assert set(fleet.merged.allowed_scales('robot_b/worker')) == {'robot_b/home', 'server'}


# --- files that cannot be planned together ------------------------------------------------------
def problems_of(paths):
    with pytest.raises(FleetError) as e:
        merge([load_deployment(p) for p in paths])
    return e.value.problems


def test_files_that_disagree_on_a_shared_capacity_are_refused_naming_both(tmp_path):
    a, b = fleet_files(tmp_path, server_capacity=80.0)
    [problem] = problems_of([a, b])
    assert problem.source == b
    assert problem.path == 'scales.server.capacity_cpu'
    assert '80 here but 100 in' in problem.message and a in problem.message


def test_a_shared_scale_that_is_another_files_master_is_refused(tmp_path):
    a, b = fleet_files(tmp_path, server_role='master')
    [problem] = problems_of([a, b])
    assert (problem.source, problem.path) == (b, 'scales.server.role')
    assert f'shared in {a}' in problem.message and 'master' in problem.message


def test_a_shared_scale_not_marked_shared_in_another_file_is_refused(tmp_path):
    a, b = fleet_files(tmp_path, server_shared=False)
    [problem] = problems_of([a, b])
    assert (problem.source, problem.path) == (b, 'scales.server.shared')
    assert a in problem.message


def test_two_files_of_one_deployment_name_are_refused(tmp_path):
    a = write(tmp_path, 'robot_a', robot('robot_a'))
    again = write(tmp_path, 'copy', robot('robot_a'))
    [problem] = problems_of([a, again])
    assert (problem.source, problem.path) == (again, 'deployment.name')
    assert a in problem.message


# --- an IROS instance as a fleet ----------------------------------------------------------------
MULTI_ROBOT = [n for n, (_, robots, _) in INSTANCES.items() if robots > 1]


@pytest.mark.parametrize('number', MULTI_ROBOT)
def test_splitting_an_instance_loses_no_node_or_connection(number):
    data = read_yaml(os.path.join(IROS, f'instance_{number}.yaml'))
    params = data['/**']['ros__parameters']
    split = split_fleet(data)
    robots = [s for s in params['scales']['names'] if params['scales'][s]['kind'] == 'robot']
    assert [r for r, _ in split.members] == robots
    nodes, connections = [], list(split.crossing)
    for r, (robot_scale, member) in enumerate(split.members, start=1):
        d = load_mapping(member, f'robot {r}')     # each part is a valid deployment
        assert d.master.name == robot_scale
        assert all(s.shared for s in d.remote_scales)
        assert not [s for s in d.scales if s.kind == 'robot' and s.name != robot_scale]
        mine = member['/**']['ros__parameters']
        for n in d.node_names:
            assert mine['nodes'][n] == params['nodes'][n]       # the node as the instance has it
        for c in d.connections:
            assert mine['connections'][c.name] == params['connections'][c.name]
        nodes += d.node_names
        connections += [c.name for c in d.connections]
    assert sorted(nodes) == sorted(params['nodes']['names'])
    assert sorted(connections) == sorted(params['connections']['names'])
    # what no file holds joins two robots' nodes; the experiment and the trackers are robot 1's
    for name in split.crossing:
        c = params['connections'][name]
        assert split.owner[c['publisher']] != split.owner[c['subscriber']]
    shared = [n for n in params['nodes']['names'] if n == 'experiment' or n.startswith('tracker')]
    assert {split.owner[n] for n in shared} == {robots[0]}


@pytest.mark.parametrize('number', [5, 10])
def test_an_instance_planned_as_a_fleet_fits_its_server_and_scores_at_most_the_single(number):
    path = os.path.join(IROS, f'instance_{number}.yaml')
    split = split_fleet(read_yaml(path))
    members = [load_mapping(m, f'{path} robot {r}') for r, m in split.members]
    fp = solve_fleet(members, solver='exact')
    single = solve(load_deployment(path), problem=1, solver='exact')
    assert fp.plan.optimal and single.optimal
    # the fleet's layouts are a subset of the single deployment's (a robot's nodes never on
    # another robot), and no link can bind here: never above it
    assert fp.plan.objective <= single.objective + 1e-6
    [(server, use)] = fp.shared_use().items()
    assert sum(use.values()) <= 400.0 + 1e-9
    alone = [solve(d, problem=1, solver='exact').scale_load[server] for d in members]
    assert sum(alone) > 400.0
    if number == 5:
        assert fp.plan.objective == pytest.approx(single.objective)


# --- the command --------------------------------------------------------------------------------
def test_plan_fleet_prints_each_robot_and_the_server_use(tmp_path, capsys):
    a, b = fleet_files(tmp_path)
    assert cli_main(['plan', '--fleet', a, b, '--solver', 'exact']) == 0
    out = capsys.readouterr().out
    for word in (f'robot_a ({a})', f'robot_b ({b})', 'rate_hz=', 'shared scales',
                 'server (host server-host): capacity 100, usable 100', 'together',
                 'fleet objective:', 'proven optimal'):
        assert word in out


def test_plan_fleet_writes_one_configured_file_per_robot(tmp_path, capsys):
    a, b = fleet_files(tmp_path)
    out_dir = tmp_path / 'planned'
    assert cli_main(['plan', '--fleet', a, b, '--solver', 'exact', '--json',
                     '--write-dir', str(out_dir)]) == 0
    data = json.loads(capsys.readouterr().out)
    on_server = 0.0
    for name in ('robot_a', 'robot_b'):
        d = load_deployment(str(out_dir / f'{name}.planned.yaml'))
        layout = data['deployments'][name]['layout']
        assert d.decider.initial_layout == 'explicit'
        assert dict(d.decider.layout) == {n: p['scale'] for n, p in layout.items()}
        # the planned share is the node's cpu: what its claim on the shared host counts
        assert d.node('worker').cpu == layout['worker']['cpu']
        on_server += sum(d.node(n).cpu for n, s in d.decider.layout.items() if s == 'server')
    assert on_server <= SERVER_CAPACITY + 1e-9
    assert data['shared']['server']['total_cpu'] == pytest.approx(on_server)


def test_plan_fleet_exits_2_on_a_missing_file(tmp_path, capsys):
    a = write(tmp_path, 'robot_a', robot('robot_a'))
    missing = str(tmp_path / 'nowhere.yaml')
    assert cli_main(['plan', '--fleet', a, missing]) == 2
    assert f'{missing}: cannot read' in capsys.readouterr().err


def test_plan_fleet_exits_2_on_disagreeing_files_naming_them(tmp_path, capsys):
    a, b = fleet_files(tmp_path, server_capacity=80.0)
    assert cli_main(['plan', '--fleet', a, b]) == 2
    err = capsys.readouterr().err
    assert f'{b}: scales.server.capacity_cpu: 80 here but 100 in {a}' in err


@pytest.mark.parametrize('extra, said', [
    (['--problem', '2'], 'Problem 1'),
    (['--write', 'x.yaml'], '--write-dir'),
])
def test_plan_fleet_refuses_options_it_does_not_take(tmp_path, capsys, extra, said):
    a, b = fleet_files(tmp_path)
    assert cli_main(['plan', '--fleet', a, b, *extra]) == 2
    assert said in capsys.readouterr().err


def test_several_files_without_fleet_exit_2(tmp_path, capsys):
    a, b = fleet_files(tmp_path)
    assert cli_main(['plan', a, b]) == 2
    assert '--fleet' in capsys.readouterr().err


def test_plan_split_iros_exits_2_on_a_file_that_is_not_an_instance(capsys):
    path = os.path.join(CONFIG, 'icar2015_testbed.yaml')
    assert cli_main(['plan', '--split-iros', path]) == 2
    assert 'not an IROS 2016 instance' in capsys.readouterr().err


def test_plan_split_iros_prints_the_fleet_beside_the_single_deployment(tmp_path, capsys):
    path = os.path.join(IROS, 'instance_5.yaml')
    assert cli_main(['plan', '--split-iros', path, '--solver', 'exact',
                     '--write-dir', str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert 'the instance as one deployment' in out and '(100.00% of it)' in out
    assert 'experiment__environment_2' in out
    for r in (1, 2):
        assert load_deployment(str(tmp_path / f'instance_5_robot_{r}.yaml'))
        assert load_deployment(str(tmp_path / f'instance_5_robot_{r}.planned.yaml'))
