"""The parameters file of the decider and the agents: refused before rcl reads it when rcl
could not (file, line, column, what was expected; exit 2), and named in the errors of the
deployment rebuilt from its parameters. Pure checks against rcl's own reading, then the real
programs."""

import os
import subprocess
import sys

import pytest
import rclpy

from anyscale_manager.model.loader import load_from_parameters
from anyscale_manager.model.params_file import (check_params_files, file_problems,
                                                parameters_source, params_files)
from anyscale_manager.model.reader import DeploymentError

BIN = os.path.dirname(sys.executable)

GOOD = ('/**:\n  ros__parameters:\n    a: 1\n    b: [1.0, 2.5, .inf]\n    c: {d: [x, "y"]}\n'
        '    e: [0x1F, -3, +4]\n    f: [yes, off, true]\n')
# (file text, the problem: 'line L, column C: words...'); rcl refuses each of them.
REFUSED_BY_RCL = [
    ('/**:\n  ros__parameters:\n    a: 1\n   b: 2\n',
     'line 4, column 4: invalid YAML: expected <block end>, but found '),
    ('/**:\n  params:\n    a: 1\n',
     "line 3, column 5: 'a' under 'params': a parameter outside ros__parameters: expected "
     '/**: {ros__parameters: {...}} (is ros__parameters: missing or misspelt?)'),
    ('/**:\n  ros_parameters:\n    a: 1\n',
     "line 2, column 3: 'ros_parameters' under '/**': expected ros__parameters (did you mean "
     'ros__parameters?)'),
    ('/**:\n  ros__parameters:\n    a: [x, y]\n',
     'line 3, column 12: a list of strings holds the boolean y: a ROS parameter list holds '
     'one type'),
    ('/**:\n  ros__parameters: 5\n',
     "line 2, column 20: '/**'.ros__parameters: expected a map of parameters, got '5'"),
    ('/**:\n  ros__parameters:\n    a: [1.0, 2]\n',
     'line 3, column 14: a list of floats holds the integer 2: a ROS parameter list holds '
     'one type: write 2.0'),
    ('/**:\n  ros__parameters:\n    a: 1\n  other:\n    ros__parameters:\n      b: 2\n',
     "line 4, column 3: 'other' beside ros__parameters under '/**'"),
    ('/**:\n  ros__parameters:\n    a: 1\n\tb: 2\n', 'line 4, column 1: invalid YAML: '),
]
# Read by rcl, refused here: rcl keeps one of two equal keys, and reads an empty file as none.
STRICTER = [
    ('/**:\n  ros__parameters:\n    a: 1\n    a: 2\n',
     "line 4, column 5: invalid YAML: duplicate key 'a' (first at line 3)"),
    ('', 'empty: expected a ROS 2 parameters file, /**: {ros__parameters: {...}}'),
]


def rcl_reads(path):
    """Whether rclpy.init accepts the file (in a context of this test's own)."""
    ctx = rclpy.Context()
    try:
        rclpy.init(args=['x', '--ros-args', '--params-file', str(path)], context=ctx)
    except Exception:   # noqa: B902 - rclpy raises its RCLError for a file it cannot read
        return False
    rclpy.try_shutdown(context=ctx)
    return True


@pytest.mark.parametrize('text, words', REFUSED_BY_RCL + STRICTER)
def test_a_file_rcl_cannot_read_is_said_with_its_line_and_what_was_expected(
        tmp_path, text, words):
    path = tmp_path / 'd.yaml'
    path.write_text(text)
    found = [str(p) for p in file_problems(str(path))]
    assert len(found) == 1 and found[0].startswith(f'{path}: {words}'), found
    assert '\n' not in found[0]
    if (text, words) in REFUSED_BY_RCL:
        assert not rcl_reads(path)


def test_a_file_rcl_reads_has_no_problem(tmp_path):
    path = tmp_path / 'd.yaml'
    for text in (GOOD, '/ns:\n  node:\n    ros__parameters:\n      a: 1\n'):
        path.write_text(text)
        assert file_problems(str(path)) == [] and rcl_reads(path), text
    assert [str(p) for p in file_problems(str(tmp_path / 'gone.yaml'))] == [
        f'{tmp_path}/gone.yaml: cannot read: No such file or directory']


def test_the_params_files_are_those_of_the_ros_arguments():
    argv = ['decider', '--params-file', 'not_rcl.yaml', '--ros-args', '-p', 'scale:=robot',
            '--params-file', 'a.yaml', '-r', '__node:=x', '--', '--params-file', 'app.yaml',
            '--ros-args', '--params-file', 'b.yaml']
    assert params_files(argv) == ['a.yaml', 'b.yaml']
    assert check_params_files(['decider']) == []
    assert parameters_source(['agent', '--ros-args', '--params-file', 'd.yaml', '-p',
                              'scale:=robot']) == 'd.yaml'
    assert parameters_source(argv) == 'a.yaml, b.yaml'
    assert parameters_source(['agent', '--ros-args', '--params-file', 'd.yaml', '-p',
                              'decider.period_s:=-1']) == 'd.yaml (with -p decider.period_s)'
    assert parameters_source(['agent', '--ros-args', '-p', 'scale:=robot']) == \
        '<ROS parameters>'


def test_a_deployment_from_parameters_names_its_file_in_its_errors():
    flat = {'scales.names': ['robot'], 'scales.robot.role': 'master',
            'scales.robot.kind': 'robot', 'scales.robot.capacity_cpu': -1.0}
    argv = ['agent', '--ros-args', '--params-file', '/etc/anyscale/d.yaml', '-p', 'scale:=robot']
    with pytest.raises(DeploymentError) as info:
        load_from_parameters(flat, argv=argv)
    assert info.value.problems and \
        all(p.source == '/etc/anyscale/d.yaml' for p in info.value.problems), info.value
    with pytest.raises(DeploymentError) as info:
        load_from_parameters(flat, argv=['agent'])
    assert all(p.source == '<ROS parameters>' for p in info.value.problems)


# --- the programs -------------------------------------------------------------------------------

def start_and_wait(argv, env, timeout_s=60.0):
    return subprocess.run(argv, env=env, capture_output=True, text=True, timeout=timeout_s)


@pytest.mark.parametrize('program', ['decider', 'agent'])
def test_a_malformed_file_exits_2_naming_file_line_and_what_was_expected(
        tmp_path, ros_env, program):
    path = tmp_path / 'd.yaml'
    path.write_text(REFUSED_BY_RCL[0][0])
    argv = [os.path.join(BIN, program), '--ros-args', '--params-file', str(path)]
    argv += ['-p', 'scale:=robot'] if program == 'agent' else []
    r = start_and_wait(argv, ros_env)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert f'{path}: line 4, column 4: invalid YAML: expected <block end>' in out, out
    # Not rcl's own words, and no traceback.
    assert 'Error parsing a event' not in out and 'Traceback' not in out, out


@pytest.mark.parametrize('program', ['decider', 'agent'])
def test_a_deployment_that_does_not_validate_names_the_file_not_ros_parameters(
        tmp_path, ros_env, program):
    path = tmp_path / 'd.yaml'
    path.write_text(
        '/**:\n  ros__parameters:\n    deployment: {name: params_file_test}\n'
        '    scales:\n      names: [robot]\n'
        '      robot: {role: master, kind: robot, capacity_cpu: -1.0}\n')
    argv = [os.path.join(BIN, program), '--ros-args', '--params-file', str(path)]
    argv += ['-p', 'scale:=robot'] if program == 'agent' else []
    r = start_and_wait(argv, ros_env)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert f'{path}: scales.robot.capacity_cpu: ' in out, out
    assert '<ROS parameters>' not in out and 'decider parameters' not in out, out
