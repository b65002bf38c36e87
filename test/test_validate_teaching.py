"""validate teaches: "did you mean", why a node is pinned, every problem once and all at once,
what this machine can start, and critical: true."""

import argparse
import copy
import os
import sys

import pytest
import yaml

from anyscale_manager import validate
from anyscale_manager.model import DeploymentError, load_deployment, load_mapping
from anyscale_manager.agent.launch_check import launch_problems
from conftest import CONFIG, TESTBED


def load_testbed():
    with open(TESTBED, encoding='utf-8') as f:
        return yaml.safe_load(f)


def changed(fn, data=None):
    data = copy.deepcopy(data) if data is not None else load_testbed()
    fn(data['/**']['ros__parameters'])
    return data


def problems(data):
    with pytest.raises(DeploymentError) as info:
        load_mapping(data, 't.yaml')
    return [str(p) for p in info.value.problems]


def run_validate(capsys, *argv):
    parser = argparse.ArgumentParser()
    validate.add_arguments(parser)
    code = validate.run(parser.parse_args([str(a) for a in argv]))
    out, err = capsys.readouterr()
    return code, out, err


def write(tmp_path, data, name='d.yaml'):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# --- did you mean ---------------------------------------------------------------------------

def rename_section(p):
    p['nodes']['acml'] = p['nodes'].pop('amcl')


@pytest.mark.parametrize('change, line', [
    (lambda p: p['connections']['laser_amcl'].update(freq_optimal_hz=10.0),
     'connections.laser_amcl.freq_optimal_hz: unknown key (did you mean freq_opt_hz?)'),
    (lambda p: p['nodes']['amcl'].update(critcal=True),
     'nodes.amcl.critcal: unknown key (did you mean critical?)'),
    (lambda p: p['decider'].update(hysteresis=5.0),
     'decider.hysteresis: unknown key (did you mean hysteresis_s?)'),
    (lambda p: p['scales']['robot'].update(role='mastr'),
     "scales.robot.role: expected one of master, remote, got 'mastr' (did you mean master?)"),
    (lambda p: p['connections']['laser_amcl'].update(subscriber='amlc'),
     "connections.laser_amcl.subscriber: unknown node 'amlc' (did you mean amcl?)"),
    (lambda p: p['nodes']['amcl'].update(residence=['laptpo']),
     "nodes.amcl.residence: unknown scale 'laptpo' (did you mean laptop?)"),
    (lambda p: p['nodes']['amcl'].update(coresidence=['navigaton']),
     "nodes.amcl.coresidence: unknown node 'navigaton' (did you mean navigation?)"),
    (lambda p: p['nodes']['amcl'].update(standby=['robot', 'laptpo']),
     "nodes.amcl.standby[1]: unknown scale 'laptpo' (did you mean laptop?)"),
    (lambda p: p['links']['wifi'].update(ends=['robot', 'lapton']),
     "links.wifi.ends: unknown scale 'lapton' (did you mean laptop?)"),
    (lambda p: p['decider'].update(layout={'amlc': 'laptop'}),
     "decider.layout.amlc: unknown node 'amlc' (did you mean amcl?)"),
    (rename_section,
     "nodes.acml: section 'acml' is not listed in nodes.names, which lists 'amcl' with no "
     'section: one of the two is misspelt'),
])
def test_a_misspelling_is_one_line_that_names_the_likely_word(change, line):
    assert problems(changed(change)) == [f't.yaml: {line}']


# --- all at once, once ----------------------------------------------------------------------

KEY_ERRORS_AND_CONTRADICTION = [
    't.yaml: connections.laser_amcl.freq_optimal_hz: unknown key (did you mean freq_opt_hz?)',
    't.yaml: nodes.ekf.residense: unknown key (did you mean residence?)',
    't.yaml: nodes.ar.coresidence: no scale satisfies every node that must share a scale '
    '(camera, ar): camera has residence robot; ar has residence laptop',
]


def key_errors_and_contradiction(p):
    p['connections']['laser_amcl']['freq_optimal_hz'] = 10.0
    p['nodes']['ekf']['residense'] = ['robot']
    # camera may run on the robot only, ar on the laptop only, and they must share a scale.
    p['nodes']['ar'].update(coresidence=['camera'], residence=['laptop'])


def test_key_errors_do_not_hide_a_contradiction_and_each_is_reported_once():
    assert sorted(problems(changed(key_errors_and_contradiction))) == \
        sorted(KEY_ERRORS_AND_CONTRADICTION)


def test_validate_prints_every_problem_once_in_one_run(tmp_path, capsys):
    bad = write(tmp_path, changed(key_errors_and_contradiction))
    code, out, err = run_validate(capsys, bad)
    assert code == 2 and out == ''
    lines = err.splitlines()
    assert lines[0] == f'{bad}: 3 problem(s):'
    for expected in KEY_ERRORS_AND_CONTRADICTION:
        assert lines.count('  ' + expected.replace('t.yaml', str(bad))) == 1, err
    assert len(lines) == 4, err


@pytest.mark.parametrize('change, line', [
    # A section that is not a map: not also each of its keys "missing".
    (lambda p: p['scales'].update(laptop='x'), "scales.laptop: expected a map, got 'x'"),
    # A wrong type: not also what the default put in its place.
    (lambda p: p['links']['wifi'].update(ends='x'),
     "links.wifi.ends: expected a list of strings, got 'x'"),
    (lambda p: p['nodes']['amcl']['launch'].update(package=None),
     'nodes.amcl.launch.package: expected a string, got None'),
    (lambda p: p['connections']['laser_amcl'].update(freq_min_hz='x'),
     "connections.laser_amcl.freq_min_hz: expected a number in Hz, got 'x'"),
    (lambda p: p['connections']['laser_amcl'].update(freq_opt_hz=-1.0),
     'connections.laser_amcl.freq_opt_hz: -1.0 is out of range: expected a value in '
     '[0, 1000000.0] Hz'),
    # A scale that is missing: not also every node that could have run on it.
    (lambda p: p['scales'].pop('laptop'), "scales.laptop: 'laptop' is listed in names but has no "
                                          'section'),
    # A connection not read: its subscriber does not pass for a data provider.
    (lambda p: p['connections']['names'].remove('laser_amcl'),
     "connections.laser_amcl: section 'laser_amcl' is not listed in connections.names"),
    # A role misspelt: not also "no master".
    (lambda p: p['scales']['robot'].update(role='boss'),
     "scales.robot.role: expected one of master, remote, got 'boss'"),
    # Sections without their list: one line, not one per section.
    (lambda p: p['nodes'].pop('names'),
     'nodes.names: required key is missing: a list of the sections in order, such as names: '
     '[laser, odometer, camera, user, map_server, odometry, amcl, ekf, ar, navigation, decision]'),
    # Three nodes that must share a scale none of them allows: one line for the group.
    (lambda p: (p['nodes']['ar'].update(coresidence=['amcl']),
                p['nodes']['amcl'].update(coresidence=['camera'], residence=['laptop'])),
     'nodes.amcl.coresidence: no scale satisfies every node that must share a scale (camera, '
     'amcl, ar): camera has residence robot; amcl has residence laptop'),
])
def test_one_mistake_is_one_line(change, line):
    assert problems(changed(change)) == [f't.yaml: {line}']


def _paths(x, here=()):
    if isinstance(x, dict):
        for k, v in x.items():
            yield here + (k,)
            yield from _paths(v, here + (k,))
    elif isinstance(x, list):
        yield from (here + (i,) for i in range(len(x)))


def test_any_single_wrong_value_gives_problems_never_a_crash_nor_a_line_twice():
    base = load_testbed()
    for path in _paths(base):
        for value in ('x', None, [], {}, 'DELETE'):
            data = copy.deepcopy(base)
            parent = data
            for key in path[:-1]:
                parent = parent[key]
            if value == 'DELETE':
                del parent[path[-1]]
            else:
                parent[path[-1]] = value
            try:
                load_mapping(data, 't.yaml')
            except DeploymentError as e:
                lines = [str(p) for p in e.problems]
                assert len(lines) == len(set(lines)), (path, value, lines)
                assert not any('\n' in line for line in lines), (path, value, lines)


# --- why: critical, data provider, not migratable -------------------------------------------

def node_lines(d):
    return {line.split()[0]: line for line in validate.summary(d).splitlines()
            if line.startswith('    ') and ' cpu ' in line}


def test_summary_says_what_makes_each_node_critical_a_provider_or_not_migratable():
    lines = node_lines(load_deployment(TESTBED))
    assert 'critical (tolerance_s 0 on laser_navigation from laser and ekf_navigation from ' \
           'ekf)' in lines['navigation']
    assert 'critical (tolerance_s 0 on laser_navigation to navigation)' in lines['laser']
    assert 'data provider (subscribes to nothing, publishes laser_amcl and laser_navigation)' \
        in lines['laser']
    assert 'not migratable (no second scale to run on: it has residence robot)' in lines['user']
    assert lines['amcl'].split()[6] == 'migratable,' and 'not migratable' not in lines['amcl']
    assert 'not managed' in lines['decision'] and 'not migratable' not in lines['decision']


def test_a_node_pinned_through_its_coresidence_names_the_node_that_pins_it():
    d = load_mapping(changed(lambda p: p['nodes']['amcl'].update(coresidence=['ekf'],
                                                                 standby=False)), 't.yaml')
    assert 'amcl' not in d.migratable_nodes
    assert d.why_not_migratable('amcl') == (
        'no second scale to run on: it shares a scale with ekf (coresidence), which is critical '
        '(tolerance_s 0 on odometry_ekf from odometry and ekf_navigation to navigation): pinned '
        'to the master robot')
    assert 'not migratable (no second scale to run on: it shares a scale with ekf' \
        in node_lines(d)['amcl']


def test_a_planning_file_without_launches_is_not_called_unmigratable_node_by_node():
    d = load_deployment(os.path.join(CONFIG, 'iros2016', 'instance_1.yaml'))
    assert not any('not migratable' in line for line in node_lines(d).values())


# --- critical: true -------------------------------------------------------------------------

def chain(controller=None, planner=None, tolerance_s=1.0):
    """sensor -> planner -> controller; the controller drives the robot's motors."""
    start = {'command': [sys.executable, '-c', 'pass']}
    nodes = {'names': ['sensor', 'planner', 'controller'],
             'sensor': {'launch': dict(start), 'cpu': 5.0, 'residence': ['robot']},
             'planner': dict({'launch': dict(start), 'cpu': 50.0}, **(planner or {})),
             'controller': dict({'launch': dict(start), 'cpu': 5.0}, **(controller or {}))}
    flows = {'names': ['sensor_planner', 'planner_controller'],
             'sensor_planner': {'topic': '/scan', 'publisher': 'sensor', 'subscriber': 'planner',
                                'freq_min_hz': 5.0, 'tolerance_s': 2.0},
             'planner_controller': {'topic': '/cmd_vel', 'publisher': 'planner',
                                    'subscriber': 'controller', 'freq_min_hz': 5.0,
                                    'tolerance_s': tolerance_s}}
    return {'/**': {'ros__parameters': {
        'scales': {'names': ['robot', 'laptop'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 100.0},
                   'laptop': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 400.0}},
        'links': {'names': ['wifi'], 'wifi': {'ends': ['robot', 'laptop'],
                                              'bandwidth_kbps': 54000.0}},
        'nodes': nodes, 'connections': flows}}}


def test_a_tolerance_0_connection_pins_both_its_ends_and_says_so():
    d = load_mapping(chain(tolerance_s=0.0), 'c.yaml')
    assert d.critical_nodes == ('planner', 'controller') and d.migratable_nodes == ()
    assert d.why_critical('planner') == 'tolerance_s 0 on planner_controller to controller'
    assert d.why_critical('controller') == 'tolerance_s 0 on planner_controller from planner'


def test_critical_true_pins_a_node_without_pinning_the_node_that_feeds_it():
    d = load_mapping(chain(controller={'critical': True}), 'c.yaml')
    assert d.critical_nodes == ('controller',)
    assert d.migratable_nodes == ('planner',)
    assert d.allowed_scales('controller') == ('robot',)
    assert d.why_critical('controller') == 'critical: true'
    assert 'critical (critical: true)' in node_lines(d)['controller']


@pytest.mark.parametrize('data, line', [
    (chain(controller={'critical': True, 'migratable': True}),
     'nodes.controller.migratable: declared migratable, but the node is critical (critical: '
     "true), pinned to the master scale 'robot'"),
    (chain(controller={'critical': True, 'residence': ['laptop']}),
     "nodes.controller.residence: critical node must run on the master scale 'robot' "
     '(critical: true), but residence allows only laptop'),
    (chain(planner={'critical': False}, tolerance_s=0.0),
     'nodes.planner.critical: declared critical: false, but tolerance_s 0 on planner_controller '
     'to controller: a connection that tolerates no outage never crosses a link, so both its '
     'ends stay on the master; to pin only the other end, mark that node critical: true and '
     'give the connection a tolerance_s above 0'),
    (chain(planner={'migratable': True}, tolerance_s=0.0),
     'nodes.planner.migratable: declared migratable, but the node is critical (tolerance_s 0 on '
     "planner_controller to controller), pinned to the master scale 'robot'; to pin only the "
     'other end, mark that node critical: true and give the connection a tolerance_s above 0'),
    (chain(controller={'critical': 'yes'}),
     "nodes.controller.critical: expected true or false, got 'yes'"),
])
def test_critical_is_checked_against_the_rest(data, line):
    assert problems(data) == [f't.yaml: {line}']


# --- what this machine can start ------------------------------------------------------------

def with_command(data, node, command, **launch):
    def change(p):
        p['nodes'][node]['launch'] = dict({'command': command}, **launch)
    return changed(change, data)


def test_launch_problems_resolve_as_an_agent_would(tmp_path):
    plain = tmp_path / 'plain'
    plain.write_text('#!/bin/sh\n')
    tool = tmp_path / 'tool'
    tool.write_text('#!/bin/sh\n')
    tool.chmod(0o755)
    cases = {
        'sensor': ['anyscale-no-such-command'],
        'planner': [str(tmp_path / 'missing' / 'tool')],
        'controller': [str(plain)],
    }
    data = chain()
    for node, command in cases.items():
        data = with_command(data, node, command)
    d = load_mapping(data, 'c.yaml')
    found = {n: str(why) for n, why in launch_problems(d, environ={'PATH': str(tmp_path)})
             .items()}
    assert found == {
        'sensor': "command 'anyscale-no-such-command' not found on PATH",
        'planner': f"command '{tmp_path}/missing/tool' does not exist",
        'controller': f"command '{plain}' is not executable",
    }
    # The launch's own PATH is the one the agent's child gets; the interpreter runs anywhere.
    d = load_mapping(with_command(with_command(chain(), 'sensor', ['tool'],
                                               env={'PATH': str(tmp_path)}),
                                  'planner', [sys.executable, '-c', 'pass']), 'c.yaml')
    assert launch_problems(d, environ={'PATH': '/nonexistent'}) == {}


def test_a_package_executable_is_looked_up_in_the_ament_index_then_beside_python_then_path():
    d = load_mapping(changed(lambda p: p['nodes']['planner'].update(
        launch={'package': 'nowhere_pkg', 'executable': 'no_such_exe'}), chain()), 'c.yaml')
    found = launch_problems(d, environ={'PATH': '/nonexistent'}, ament_prefix=lambda pkg: None)
    assert list(found) == ['planner'] and found['planner'].field == 'executable'
    assert str(found['planner']).startswith(
        "executable 'no_such_exe' of package 'nowhere_pkg' not found (tried ament index "
        "(package 'nowhere_pkg' not found)")


def test_validate_warns_of_a_missing_command_and_fails_for_the_scale_it_validates(
        tmp_path, capsys):
    data = with_command(chain(), 'planner', ['anyscale-no-such-command'])
    data = with_command(data, 'controller', ['anyscale-no-such-either'])
    data = changed(lambda p: p['nodes']['controller'].update(critical=True), data)
    path = write(tmp_path, data)
    code, out, err = run_validate(capsys, '--quiet', path)
    assert code == 0, err
    missing = [line for line in err.splitlines() if '.launch.' in line]
    assert missing == [
        f"warning: {path}: nodes.planner.launch.command[0]: command 'anyscale-no-such-command' "
        'not found on PATH: an agent on this machine cannot start it (validate --scale NAME '
        'makes this an error)',
        f"warning: {path}: nodes.controller.launch.command[0]: command 'anyscale-no-such-either' "
        'not found on PATH: an agent on this machine cannot start it (validate --scale NAME '
        'makes this an error)']
    # The laptop may run the planner, never the critical controller: one error, the planner.
    code, out, err = run_validate(capsys, '--quiet', '--scale', 'laptop', path)
    assert code == 2
    assert err.splitlines() == [
        f'{path}: 1 problem(s):',
        f"  {path}: nodes.planner.launch.command[0]: command 'anyscale-no-such-command' not "
        'found on PATH: the agent of scale laptop, on this machine, cannot start it']
    code, out, err = run_validate(capsys, '--scale', 'robot', path)
    assert code == 2 and '2 problem(s)' in err and out == ''
    code, out, err = run_validate(capsys, '--scale', 'laptpo', path)
    assert code == 2
    assert f"{path}: --scale: unknown scale 'laptpo' (did you mean laptop?); the scales of " \
           'this file are robot, laptop' in err


def script_cases(tmp_path):
    """(command, arguments, field of the problem or None, words of the problem)."""
    here = tmp_path / 'node.py'
    here.write_text('print(1)\n')
    shell = tmp_path / 'run.sh'
    shell.write_text('true\n')
    folder = tmp_path / 'pkg'
    folder.mkdir()
    gone = str(tmp_path / 'gone.py')
    py = sys.executable
    name = os.path.basename(py)
    return [
        ([py, gone], [], 'command[1]', f"script of {name} '{gone}' does not exist"),
        ([py, '-u', '-W', 'ignore', '-Xdev', gone, '--rate', '5'], [], 'command[5]',
         'does not exist'),
        ([py], [gone], 'arguments[0]', 'does not exist'),
        ([py, '--', gone], [], 'command[2]', 'does not exist'),
        ([py, str(folder)], [], 'command[1]', f"'{folder}/__main__.py' does not exist"),
        ([py, str(here)], ['--rate', '5'], None, ''),
        ([py, '-c', 'pass', gone], [], None, ''),
        ([py, '-m', 'no_such_module_is_looked_for'], [], None, ''),
        (['bash', str(tmp_path / 'gone.sh')], [], 'command[1]',
         f"script of bash '{tmp_path}/gone.sh' does not exist"),
        (['bash', '-eu', '-o', 'pipefail', str(tmp_path / 'gone.sh')], [], 'command[4]',
         'does not exist'),
        (['sh', 'gone.sh'], [], 'command[1]',
         "script of sh 'gone.sh' does not exist (a relative path is taken from the agent's "
         'working directory; looked for in'),
        (['bash', str(shell)], [], None, ''),
        (['bash', '-c', 'exec true', gone], [], None, ''),
        ([str(tmp_path)], [], 'command[0]', f"command '{tmp_path}' is not a file"),
    ]


def test_an_interpreter_command_needs_the_script_it_names(tmp_path):
    for command, arguments, where, words in script_cases(tmp_path):
        extra = {'arguments': arguments} if arguments else {}
        d = load_mapping(with_command(chain(), 'planner', command, **extra), 'c.yaml')
        found = launch_problems(d, environ={'PATH': os.environ['PATH']}, cwd=str(tmp_path))
        if where is None:
            assert found == {}, (command, arguments, found)
            continue
        assert list(found) == ['planner'], (command, arguments, found)
        assert found['planner'].field == where, (command, found['planner'])
        assert words in str(found['planner']), (command, found['planner'])


@pytest.mark.skipif(os.geteuid() == 0, reason='root reads every file: nothing is unreadable')
def test_a_script_this_user_cannot_read_is_named(tmp_path):
    secret = tmp_path / 'secret.py'
    secret.write_text('pass\n')
    secret.chmod(0o200)
    d = load_mapping(with_command(chain(), 'planner', [sys.executable, str(secret)]), 'c.yaml')
    assert str(launch_problems(d)['planner']) == \
        f"script of {os.path.basename(sys.executable)} '{secret}' is not readable by this user"


def test_a_script_whose_interpreter_is_missing_is_named(tmp_path):
    tool = tmp_path / 'tool'
    tool.write_text('#!/nonexistent/python9\nprint(1)\n')
    tool.chmod(0o755)
    viaenv = tmp_path / 'viaenv'
    viaenv.write_text('#!/usr/bin/env anyscale-no-such-interpreter\n')
    viaenv.chmod(0o755)
    data = with_command(chain(), 'planner', [str(tool)])
    d = load_mapping(with_command(data, 'controller', [str(viaenv)]), 'c.yaml')
    found = launch_problems(d, environ={'PATH': os.environ['PATH']})
    assert {n: (p.field, str(p)) for n, p in found.items()} == {
        'planner': ('command[0]', f"script '{tool}' is run by '/nonexistent/python9' (its #! "
                                  'line), which does not exist'),
        'controller': ('command[0]', f"script '{viaenv}' is run by "
                                     "'anyscale-no-such-interpreter' (its #! line), not found "
                                     'on PATH')}


def test_ros2_run_needs_its_package_executable_in_the_ament_index(tmp_path):
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    ros2 = bin_dir / 'ros2'
    ros2.write_text('#!/bin/sh\n')
    ros2.chmod(0o755)
    exe = tmp_path / 'prefix' / 'lib' / 'real_pkg' / 'real_exe'
    exe.parent.mkdir(parents=True)
    exe.write_text('#!/bin/sh\n')
    exe.chmod(0o755)
    prefixes = {'real_pkg': str(tmp_path / 'prefix')}
    cases = {
        ('ros2', 'run', 'real_pkg', 'real_exe'): None,
        ('ros2', 'run', '--prefix', 'nice', 'real_pkg', 'real_exe'): None,
        ('ros2', 'run', 'gone_pkg', 'real_exe'): (
            'command[2]', "ros2 run: package 'gone_pkg' not found in the ament index"),
        ('ros2', 'run', 'real_pkg', 'gone_exe'): (
            'command[3]', "ros2 run: executable 'gone_exe' of package 'real_pkg' not found "
                          f'(no executable file {tmp_path}/prefix/lib/real_pkg/gone_exe)'),
    }
    for command, expected in cases.items():
        d = load_mapping(with_command(chain(), 'planner', list(command)), 'c.yaml')
        found = launch_problems(d, environ={'PATH': str(bin_dir)},
                                ament_prefix=prefixes.get)
        if expected is None:
            assert found == {}, (command, found)
        else:
            assert found['planner'].field == expected[0], (command, found)
            assert str(found['planner']).startswith(expected[1]), (command, found)


def test_validate_for_a_scale_fails_on_a_missing_script_naming_file_path_and_script(
        tmp_path, capsys):
    gone = tmp_path / 'nodes' / 'planner.py'
    path = write(tmp_path, with_command(chain(), 'planner', [sys.executable, str(gone)]))
    code, out, err = run_validate(capsys, '--quiet', '--scale', 'laptop', path)
    assert code == 2 and out == ''
    assert err.splitlines() == [
        f'{path}: 1 problem(s):',
        f'  {path}: nodes.planner.launch.command[1]: script of '
        f"{os.path.basename(sys.executable)} '{gone}' does not exist: the agent of scale "
        'laptop, on this machine, cannot start it']
    gone.parent.mkdir()
    gone.write_text('pass\n')
    code, out, err = run_validate(capsys, '--quiet', '--scale', 'laptop', path)
    assert code == 0, err


def test_the_shipped_files_stay_valid(capsys):
    files = [os.path.join(CONFIG, 'icar2015_testbed.yaml')] + sorted(
        os.path.join(CONFIG, 'iros2016', f) for f in os.listdir(os.path.join(CONFIG, 'iros2016')))
    code, out, err = run_validate(capsys, '--quiet', *files)
    assert code == 0, err
    # The IROS files are for planning: no launches, nothing to look for on this machine.
    code, out, err = run_validate(capsys, '--quiet', '--scale', 'c1', *files[1:])
    assert code == 0 and '.launch' not in err, err
