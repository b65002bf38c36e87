"""The deployment model: loading, every class of validation error, derived sets."""

import copy
import os
import subprocess
import sys

import pytest
import yaml

from anyscale_manager.model import DeploymentError, load_deployment, load_mapping
from anyscale_manager.model.iros2016 import INSTANCES, build_instance
from conftest import CONFIG, TESTBED


def load_testbed_dict():
    with open(TESTBED, encoding='utf-8') as f:
        return yaml.safe_load(f)


def params(data):
    return data['/**']['ros__parameters']


def problems_of(data, source='t.yaml'):
    with pytest.raises(DeploymentError) as info:
        load_mapping(data, source)
    return [str(p) for p in info.value.problems]


def test_testbed_loads_and_derives_the_papers_sets():
    d = load_deployment(TESTBED)
    assert d.name == 'icar2015_testbed'
    assert d.master.name == 'robot'
    assert [s.name for s in d.remote_scales] == ['laptop']
    assert len(d.nodes) == 11
    assert len(d.connections) == 8
    assert d.migratable_nodes == ('amcl', 'ar')
    assert set(d.critical_nodes) == {'laser', 'odometer', 'odometry', 'ekf', 'navigation'}
    assert set(d.data_providers) == {'laser', 'odometer', 'camera'}
    assert d.allowed_scales('amcl') == ('robot', 'laptop')
    assert d.allowed_scales('camera') == ('robot',)
    assert d.link_between('laptop', 'robot').bandwidth_kbps == 54000.0
    # Table I exactly.
    table1 = {
        ('laser', 'amcl'): (5, 10, 2), ('laser', 'navigation'): (2, 10, 0),
        ('odometer', 'odometry'): (10, 40, 0), ('camera', 'ar'): (1, 30, 1),
        ('amcl', 'ekf'): (2, 5, 2), ('odometry', 'ekf'): (5, 10, 0),
        ('ekf', 'navigation'): (2, 5, 0), ('ar', 'navigation'): (1, 30, 1),
    }
    got = {(c.publisher, c.subscriber): (c.freq_min_hz, c.freq_opt_hz, c.tolerance_s)
           for c in d.connections}
    assert got == table1


def test_loaded_values_are_frozen():
    d = load_deployment(TESTBED)
    with pytest.raises(Exception):
        d.scales[0].capacity_cpu = 1.0
    with pytest.raises(TypeError):
        d.decider.layout['amcl'] = 'laptop'


@pytest.mark.parametrize('number', sorted(INSTANCES))
def test_iros_instances_match_the_case_study(number):
    computers, robots, cameras = INSTANCES[number]
    d = load_deployment(os.path.join(CONFIG, 'iros2016', f'instance_{number}.yaml'))
    assert len(d.scales) == computers
    assert len(d.nodes) == 1 + cameras + 6 * robots
    assert sum(n.configurable for n in d.nodes) == cameras + 3 * robots
    wireless = [link for link in d.links if link.medium == 'wireless']
    assert all(link.bandwidth_kbps == 54000 // len(wireless) for link in wireless)
    robots_ = [s for s in d.scales if s.kind == 'robot']
    assert len(robots_) == robots and all(s.capacity_cpu == 100 for s in robots_)
    assert d.node('tracker_1').cpu == 120 and d.node('tracker_1').performance == 70
    assert d.allowed_scales('planner_1') == d.allowed_scales('navigation_1')
    assert d.allowed_scales('youbot_core_1') == ('c1',)


def test_shipped_iros_files_are_what_the_generator_makes():
    for number in INSTANCES:
        with open(os.path.join(CONFIG, 'iros2016', f'instance_{number}.yaml'),
                  encoding='utf-8') as f:
            assert yaml.safe_load(f) == build_instance(number), number


# --- every class of validation error --------------------------------------------------------

def mutate(fn):
    data = load_testbed_dict()
    fn(params(data))
    return data


@pytest.mark.parametrize('change, path, words', [
    (lambda p: p['scales']['robot'].update(speed=3), 'scales.robot.speed', 'unknown key'),
    (lambda p: p.update(extras={'a': 1}), 'extras', 'unknown key'),
    (lambda p: p['scales']['robot'].update(capacity_cpu='lots'), 'scales.robot.capacity_cpu',
     'expected a number'),
    (lambda p: p['scales']['robot'].update(capacity_cpu=-5.0), 'scales.robot.capacity_cpu',
     'out of range'),
    (lambda p: p['scales']['robot'].update(cores=0), 'scales.robot.cores', 'out of range'),
    (lambda p: p['scales']['robot'].update(role='boss'), 'scales.robot.role', 'expected one of'),
    (lambda p: p['scales']['robot'].pop('capacity_cpu'), 'scales.robot.capacity_cpu',
     'required key is missing'),
    (lambda p: p['links']['wifi'].update(bandwidth_kbps=0.0), 'links.wifi.bandwidth_kbps',
     'out of range'),
    (lambda p: p['links']['wifi'].update(ends=['robot', 'moon']), 'links.wifi.ends',
     "unknown scale 'moon'"),
    (lambda p: p['connections']['laser_amcl'].update(subscriber='ghost'),
     'connections.laser_amcl.subscriber', "unknown node 'ghost'"),
    (lambda p: p['connections']['laser_amcl'].update(freq_min_hz=-1.0),
     'connections.laser_amcl.freq_min_hz', 'out of range'),
    (lambda p: p['connections']['laser_amcl'].update(freq_opt_hz=1.0),
     'connections.laser_amcl.freq_opt_hz', 'below freq_min_hz'),
    (lambda p: p['connections']['laser_amcl'].update(tolerance_s=True),
     'connections.laser_amcl.tolerance_s', 'expected a number'),
    (lambda p: p['connections']['laser_amcl'].update(msg_type='sensor_msgs/LaserScan'),
     'connections.laser_amcl.msg_type', 'did you mean sensor_msgs/msg/LaserScan?'),
    (lambda p: p['connections']['laser_amcl'].update(msg_type='sensor_msgs::msg::LaserScan'),
     'connections.laser_amcl.msg_type', 'did you mean sensor_msgs/msg/LaserScan?'),
    (lambda p: p['connections']['laser_amcl'].update(msg_type='nav_msgs/srv/GetMap'),
     'connections.laser_amcl.msg_type', 'a topic carries messages'),
    (lambda p: p['connections']['laser_amcl'].update(msg_type='LaserScan'),
     'connections.laser_amcl.msg_type', 'expected package/msg/Type'),
    (lambda p: p['nodes']['amcl'].update(residence=['mars']), 'nodes.amcl.residence',
     "unknown scale 'mars'"),
    (lambda p: p['nodes']['amcl'].update(coresidence=['nobody']), 'nodes.amcl.coresidence',
     "unknown node 'nobody'"),
    (lambda p: p['nodes']['amcl'].update(residence=[]), 'nodes.amcl.residence',
     'empty list'),
    (lambda p: p['nodes']['navigation'].update(migratable=True), 'nodes.navigation.migratable',
     'tolerance_s 0'),
    (lambda p: p['nodes']['navigation'].update(residence=['laptop']),
     'nodes.navigation.residence', 'critical node must run on the master'),
    (lambda p: p['nodes']['ar'].update(coresidence=['camera'], residence=['laptop']),
     'nodes.ar.coresidence', 'no scale satisfies'),
    (lambda p: p['nodes']['camera'].update(migratable=True), 'nodes.camera.migratable',
     'no second scale'),
    (lambda p: p['nodes']['ekf'].update(standby=True), 'nodes.ekf.standby',
     'only for a migratable node'),
    (lambda p: p['nodes']['amcl'].update(lifecycle=False), 'nodes.amcl.standby',
     'set lifecycle: true'),
    (lambda p: p['nodes']['amcl'].update(standby=['robot', 'moon']), 'nodes.amcl.standby[1]',
     "unknown scale 'moon'"),
    (lambda p: p['nodes']['amcl'].update(standby=['robot', 'laptop'], residence=['robot']),
     'nodes.amcl.standby', 'cannot migrate'),
    (lambda p: p['nodes']['amcl'].update(lifecycle='yes'), 'nodes.amcl.lifecycle',
     'expected true or false'),
    (lambda p: p['nodes']['decision'].update(lifecycle=True), 'nodes.decision.lifecycle',
     'only a node the agents start'),
    (lambda p: p['agent'].update(lifecycle_timeout_s=0.0), 'agent.lifecycle_timeout_s',
     'out of range'),
    (lambda p: p['nodes']['names'].append('ghost'), 'nodes.ghost', 'has no section'),
    (lambda p: p['nodes'].update(stray={'cpu': 1.0}), 'nodes.stray', 'not listed'),
    (lambda p: p['nodes']['names'].append('bad name'), 'nodes.names', 'not a valid name'),
    (lambda p: p['nodes']['amcl']['launch'].update(command=['x']), 'nodes.amcl.launch',
     'either command or package'),
    (lambda p: p['scales']['laptop'].update(role='master'), 'scales',
     'exactly one scale with role master'),
    (lambda p: p['decider'].update(cpu_headroom=1.5), 'decider.cpu_headroom', 'out of range'),
    (lambda p: p['decider'].update(initial_layout='random'), 'decider.initial_layout',
     'expected one of'),
    (lambda p: p['decider'].update(hysteresis_scope='link'), 'decider.hysteresis_scope',
     'expected one of'),
    (lambda p: p['decider'].update(layout={'navigation': 'laptop'}), 'decider.layout.navigation',
     'may not run on'),
    (lambda p: p['monitoring'].update(heartbeat_misses_down=0),
     'monitoring.heartbeat_misses_down', 'out of range'),
    (lambda p: p['agent'].update(sigint_grace_s='soon'), 'agent.sigint_grace_s',
     'expected a number'),
    (lambda p: p['scales']['laptop'].update(port=70000), 'scales.laptop.port', 'out of range'),
    (lambda p: [p['scales'][s].update(host='127.0.0.1' if s == 'robot' else 'localhost',
                                      port=47000) for s in ('robot', 'laptop')],
     'scales.laptop.port', "port 47000 on host 'localhost' is also the port of scale 'robot'"),
    (lambda p: [p['scales']['laptop'].update(host='robot'),
                p['scales']['robot'].update(port=47802)],
     'scales.laptop.port', "is also the port of scale 'robot'"),
    (lambda p: p['monitoring'].update(bandwidth_probe_port=65534), 'scales.laptop.port',
     'past 65535'),
])
def test_validation_error_names_file_path_and_expectation(change, path, words):
    found = problems_of(mutate(change))
    assert any(p.startswith(f't.yaml: {path}: ') and words in p for p in found), found


def test_mixed_int_and_decimal_list_is_refused_as_ros_parameters_would():
    data = copy.deepcopy(build_instance(1))
    params(data)['nodes']['model_1']['settings']['cpu'] = [17, 39.5, 59]
    found = problems_of(data)
    assert any('nodes.model_1.settings.cpu' in p and 'mixes integers' in p for p in found)


def test_all_errors_are_reported_at_once():
    def change(p):
        p['scales']['robot']['capacity_cpu'] = 'x'
        p['links']['wifi']['medium'] = 'smoke'
        p['connections']['camera_ar']['tolerance_s'] = -2.0
    found = problems_of(mutate(change))
    assert len(found) >= 3
    assert any('scales.robot.capacity_cpu' in p for p in found)
    assert any('links.wifi.medium' in p for p in found)
    assert any('connections.camera_ar.tolerance_s' in p for p in found)


def test_file_must_be_a_ros_parameters_file():
    found = problems_of(params(load_testbed_dict()))
    assert any('ROS 2 parameters file' in p for p in found)


def test_settings_lengths_must_agree():
    data = copy.deepcopy(build_instance(1))
    params(data)['nodes']['amcl_1']['settings']['performance'] = [1.0, 2.0]
    found = problems_of(data)
    assert any('nodes.amcl_1.settings.performance' in p and 'expected 3 values' in p
               for p in found)


def test_yaml_syntax_and_duplicate_keys_name_the_line(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters:\n    scales: [unclosed\n')
    with pytest.raises(DeploymentError) as info:
        load_deployment(str(bad))
    assert str(bad) in str(info.value) and 'invalid YAML' in str(info.value)
    dup = tmp_path / 'dup.yaml'
    dup.write_text('/**:\n  ros__parameters:\n    nodes: {}\n    nodes: {}\n')
    with pytest.raises(DeploymentError) as info:
        load_deployment(str(dup))
    assert 'duplicate key' in str(info.value) and 'line 4' in str(info.value)
    with pytest.raises(DeploymentError) as info:
        load_deployment(str(tmp_path / 'missing.yaml'))
    assert 'cannot read' in str(info.value)


# --- the command ----------------------------------------------------------------------------

def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', *args],
                          capture_output=True, text=True, timeout=120)


def test_validate_prints_a_summary_and_exits_0():
    r = run_cli('validate', TESTBED)
    assert r.returncode == 0, r.stderr
    assert 'migratable: amcl, ar' in r.stdout
    assert 'laser_amcl' in r.stdout and 'tolerance 2 s' in r.stdout


def test_validate_says_who_watches_each_link_and_what_may_cross_it(tmp_path):
    three = os.path.join(CONFIG, 'three_scales_testbed.yaml')
    with open(three) as f:
        data = yaml.safe_load(f)
    params(data)['links']['names'].remove('backhaul')
    del params(data)['links']['backhaul']
    path = tmp_path / 'two_links.yaml'
    path.write_text(yaml.safe_dump(data))
    r = run_cli('validate', three, str(path))
    assert r.returncode == 0, r.stderr
    whole, cut = r.stdout.split('two_links.yaml: deployment')
    assert 'laptop <-> server 54000 kbit/s wireless, watched by laptop' in whole
    assert 'robot <-> server 54000 kbit/s wireless, watched by robot' in whole
    assert 'host server port 47803' in whole
    assert 'camera -> ar on /image' in whole and '6096 kbit/s, may cross ethernet, wifi' in whole
    assert 'laser -> navigation on /scan: min 2 Hz, opt 10 Hz, tolerance 0 s, 224 kbit/s\n' \
        in whole                                # both ends on the robot: crosses nothing
    assert 'no link' not in whole
    assert 'no link: laptop <-> server (a connection between nodes placed there' in cut


def test_validate_warns_when_a_cold_move_cannot_meet_a_tolerance(tmp_path):
    data = mutate(lambda p: (p['nodes']['amcl'].update(standby=False, lifecycle=False),
                             p['connections']['laser_amcl'].update(tolerance_s=1.0)))
    cold = tmp_path / 'cold.yaml'
    cold.write_text(yaml.safe_dump(data))
    r = run_cli('validate', '--quiet', str(cold))
    assert r.returncode == 0, r.stderr
    lines = [line for line in r.stderr.splitlines()
             if line.startswith('warning: ') and 'security.key_file' not in line]
    assert len(lines) == 1, r.stderr
    assert f'{cold}: nodes.amcl: a cold move cannot meet the tolerance_s of laser_amcl (1 s)' \
        in lines[0]
    from anyscale_manager.model.advice import cold_move_budget_s
    budget = cold_move_budget_s(load_deployment(str(cold)))
    assert 'lifecycle node with standby: true' in lines[0] \
        and f'at least {budget:.1f} s' in lines[0]
    # With standby the same tolerance is met by an activation: no warning.
    r = run_cli('validate', '--quiet', TESTBED)
    assert r.returncode == 0 and 'cold move' not in r.stderr, r.stderr


def test_validate_exits_2_with_every_error(tmp_path):
    data = mutate(lambda p: (p['scales']['robot'].update(capacity_cpu=-1.0),
                             p['nodes']['amcl'].update(weight='heavy')))
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump(data))
    r = run_cli('validate', TESTBED, str(bad))
    assert r.returncode == 2
    assert f'{bad}: scales.robot.capacity_cpu' in r.stderr
    assert f'{bad}: nodes.amcl.weight' in r.stderr
    assert 'deployment' in r.stdout   # the good file is still summarised


def test_standby_scales_are_every_allowed_scale_or_the_listed_ones():
    d = load_deployment(TESTBED)
    assert d.node('amcl').lifecycle and d.standby_scales('amcl') == ('robot', 'laptop')
    assert d.standby_scales('ekf') == ()
    only_robot = load_mapping(mutate(lambda p: p['nodes']['amcl'].update(standby=['robot'])),
                              't.yaml')
    assert only_robot.standby_scales('amcl') == ('robot',)
    assert only_robot.standby_scales('ar') == ('robot', 'laptop')


def test_a_standby_node_without_a_lifecycle_is_said_with_every_other_problem():
    """A node's own contradictions are reported at once, not once the rest of the file is
    right: two masters (which stops the derived checks) and a standby plain node."""
    data = mutate(lambda p: (p['nodes']['amcl'].update(lifecycle=False),
                             p['scales']['laptop'].update(role='master')))
    with pytest.raises(DeploymentError) as e:
        load_mapping(data, 'two.yaml')
    text = str(e.value)
    assert 'expected exactly one scale with role master' in text
    assert 'nodes.amcl.standby: a standby copy is an inactive lifecycle node' in text


STANDBY_PLAIN = ('t.yaml: nodes.ekf.standby: a standby copy is an inactive lifecycle node: set '
                 'lifecycle: true (and make the node a lifecycle node, docs/lifecycle.md)')


@pytest.mark.parametrize('change, other', [
    # A name in nodes.names that is not a string: the other nodes are still read and checked.
    (lambda p: p['nodes']['names'].__setitem__(0, 7), 't.yaml: nodes.names[0]: expected '
                                                      'strings, got 7'),
    (lambda p: p['nodes']['ekf'].update(wieght=2.0),
     't.yaml: nodes.ekf.wieght: unknown key (did you mean weight?)'),
    (lambda p: p['decider'].update(period_s=0.0),
     't.yaml: decider.period_s: 0.0 is out of range: expected a value in (0, 3600] s'),
    (lambda p: p['connections']['names'].__setitem__(0, None),
     't.yaml: connections.names[0]: expected strings, got None'),
])
def test_a_standby_plain_node_is_reported_with_an_unrelated_problem_in_one_go(change, other):
    found = problems_of(mutate(lambda p: (p['nodes']['ekf'].update(standby=True), change(p))))
    assert other in found and STANDBY_PLAIN in found, found


def test_a_names_list_with_a_bad_entry_reports_each_and_reads_the_rest():
    found = problems_of(mutate(lambda p: (p['nodes']['names'].__setitem__(0, 7),
                                          p['nodes']['names'].__setitem__(1, None),
                                          p['nodes']['amcl'].update(weight=-1.0))))
    assert found[:2] == ['t.yaml: nodes.names[0]: expected strings, got 7',
                         't.yaml: nodes.names[1]: expected strings, got None']
    assert any(p.startswith('t.yaml: nodes.amcl.weight: -1.0 is out of range') for p in found)
    # The sections of the unreadable names are left out, not reported as unlisted as well.
    assert not any('not listed' in p for p in found), found


# --- one declaration per setting --------------------------------------------------------------

def _live_settings():
    from dataclasses import fields
    from anyscale_manager.model.types import DeciderSettings
    return [f.name for f in fields(DeciderSettings) if f.metadata.get('live')]


@pytest.mark.parametrize('name', _live_settings())
@pytest.mark.parametrize('value', [-1.0, 0.0, 0.5, 7, 1e12, True, 'node', 'x', None])
def test_a_live_change_is_checked_as_the_same_key_in_a_file_is(name, value):
    """The decider's run-time changes and the loader read a setting through one declaration:
    whatever one accepts the other does, with the same words for what it refuses."""
    from anyscale_manager.model.sections import settings_with
    d = load_deployment(TESTBED)
    try:
        changed = settings_with(d.decider, {name: value})
    except ValueError as e:
        refused = str(e)
    else:
        refused = None
    try:
        loaded = load_mapping(mutate(lambda p: p['decider'].update({name: value})), 't.yaml')
    except DeploymentError as e:
        assert refused is not None, f'the file refuses what a live change takes: {e}'
        assert f't.yaml: {refused}' in [str(p) for p in e.problems]
    else:
        assert refused is None, f'a live change refuses what the file takes: {refused}'
        assert changed == loaded.decider


def test_a_setting_not_taken_while_the_decider_runs_is_refused():
    from anyscale_manager.model.sections import settings_with
    d = load_deployment(TESTBED)
    with pytest.raises(ValueError, match='decider.lease_s: cannot be changed while the decider'):
        settings_with(d.decider, {'lease_s': 2.0})


# --- the validate command's output -------------------------------------------------------------

class _Streams:
    """stdout and stderr as one reader that merges the two sees them: each write a chunk."""

    def __init__(self):
        self.chunks = []

    def stream(self, name):
        streams = self

        class Stream:
            def write(self, text):
                streams.chunks.append((name, text))
                return len(text)

            def flush(self):
                pass
        return Stream()


def test_validate_writes_whole_lines_so_a_warning_starts_its_own_line(tmp_path, monkeypatch):
    """However stdout (the summary) and stderr (the warnings) are merged, a warning never starts
    inside a line of the summary: each write validate makes ends its lines."""
    import argparse
    from anyscale_manager import validate
    data = load_testbed_dict()
    for s in params(data)['scales']['names']:
        params(data)['scales'][s].pop('host', None)   # both on this machine: the summary says so
    path = tmp_path / 'one_machine.yaml'
    path.write_text(yaml.safe_dump(data))
    streams = _Streams()
    monkeypatch.setattr(sys, 'stdout', streams.stream('out'))
    monkeypatch.setattr(sys, 'stderr', streams.stream('err'))
    parser = argparse.ArgumentParser()
    validate.add_arguments(parser)
    assert validate.run(parser.parse_args([str(path)])) == 0
    written = [(name, text) for name, text in streams.chunks if text]
    assert [name for name, _ in written] == ['out', 'err']
    assert all(text.endswith('\n') for _, text in written), written
    merged = ''.join(text for _, text in written)
    assert '(docs/monitoring.md)\nwarning: ' in merged
    assert all(line.startswith('warning: ') for line in written[1][1].splitlines())


# --- the pure core knows nothing of ROS nor of the agent --------------------------------------

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       'anyscale_manager')
CORE = ('model', 'planning', 'runtime')
FORBIDDEN = ('rclpy', 'anyscale_manager.agent', 'anyscale_manager.nodes')


def _core_modules():
    for part in CORE:
        for name in sorted(os.listdir(os.path.join(PACKAGE, part))):
            if name.endswith('.py'):
                yield os.path.join(PACKAGE, part, name), \
                    f'anyscale_manager.{part}.{name[:-3]}'.replace('.__init__', '')


def _imports(path, module):
    """Every module ``path`` imports, at its top or inside a function, as an absolute name."""
    import ast
    with open(path, encoding='utf-8') as f:
        tree = ast.parse(f.read(), path)
    package = module if path.endswith('__init__.py') else module.rpartition('.')[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package
            for _ in range(node.level - 1):
                base = base.rpartition('.')[0]
            here = f'{base}.{node.module}' if node.level and node.module else \
                base if node.level else node.module
            yield here
            yield from (f'{here}.{alias.name}' for alias in node.names)


def _forbidden(name):
    return any(name == f or name.startswith(f'{f}.') for f in FORBIDDEN)


@pytest.mark.parametrize('path, module', list(_core_modules()))
def test_no_core_module_imports_ros_or_the_agent(path, module):
    assert not [n for n in _imports(path, module) if _forbidden(n)]


def test_importing_the_whole_core_loads_neither_ros_nor_the_agent():
    names = [module for _, module in _core_modules()]
    code = ('import importlib, sys\n'
            f'for name in {names!r}:\n'
            '    importlib.import_module(name)\n'
            'print("\\n".join(sorted(sys.modules)))\n')
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120,
                       cwd=os.path.dirname(PACKAGE))
    assert r.returncode == 0, r.stderr
    assert not [m for m in r.stdout.split() if _forbidden(m)]


def test_a_remote_robot_is_said_with_the_fleet_that_keeps_each_robot_its_own_master():
    from anyscale_manager.model.advice import warnings
    d = load_deployment(os.path.join(CONFIG, 'iros2016', 'instance_5.yaml'))
    said = [w for w in warnings(d) if 'a remote robot' in w]
    assert len(said) == 1 and 'scales c2: a remote robot: the decider on c1' in said[0]
    assert 'shared: true' in said[0]
    one_robot = load_deployment(TESTBED)
    assert not [w for w in warnings(one_robot) if 'a remote robot' in w]


def test_a_shared_master_is_refused_naming_the_key():
    data = {'/**': {'ros__parameters': {
        'scales': {'names': ['robot', 'server'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0,
                             'shared': True},
                   'server': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 400.0,
                              'shared': True}},
        'nodes': {'names': ['n'], 'n': {'cpu': 1.0}}}}}
    with pytest.raises(DeploymentError) as info:
        load_mapping(data)
    assert "scales.robot.shared: the master scale 'robot' cannot be shared" in str(info.value)
    assert 'scales.server.shared' not in str(info.value)
