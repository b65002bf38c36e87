"""plan --write: the planner's settings and layout become a deployment the agents run."""

import os
import subprocess
import sys

import yaml

from anyscale_manager.agent.catalogue import build_argv
from anyscale_manager.model import load_deployment, load_mapping
from conftest import CONFIG

INSTANCE_1 = os.path.join(CONFIG, 'iros2016', 'instance_1.yaml')


def plan(*args):
    return subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'plan', *args],
                          capture_output=True, text=True, timeout=300)


def test_write_carries_chosen_parameters_and_layout(tmp_path):
    out = tmp_path / 'configured.yaml'
    r = plan(INSTANCE_1, '--problem', '1', '--json', '--write', str(out))
    assert r.returncode == 0, r.stderr
    chosen = yaml.safe_load(r.stdout)['layout']
    d = load_deployment(str(out))
    assert d.decider.initial_layout == 'explicit'
    assert dict(d.decider.layout) == {n: p['scale'] for n, p in chosen.items()}
    for name, p in chosen.items():
        node = d.node(name)
        if p['parameter'] is None:
            assert p['parameter'] not in node.launch.parameters
            continue
        written = node.launch.parameters[p['parameter']]
        assert abs(written - p['parameter_value']) <= 0.5
        # particles and goals are counts: written as integers, as the node declares them
        if name.startswith(('amcl', 'model')):
            assert isinstance(written, int)


def test_an_agent_passes_the_written_parameter_to_the_node(tmp_path):
    out = tmp_path / 'configured.yaml'
    assert plan(INSTANCE_1, '--write', str(out)).returncode == 0
    data = yaml.safe_load(out.read_text())
    node = data['/**']['ros__parameters']['nodes']['amcl_1']
    node['launch']['command'] = [sys.executable, '-c', 'pass']
    d = load_mapping(data, str(out))
    argv, problem = build_argv(d.node('amcl_1'), os.environ.get('PATH', ''))
    assert not problem
    value = d.node('amcl_1').launch.parameters['particles']
    assert f'particles:={value}' in argv


def test_write_to_an_unwritable_place_exits_2(tmp_path):
    r = plan(INSTANCE_1, '--write', str(tmp_path / 'missing' / 'x.yaml'))
    assert r.returncode == 2
    assert 'cannot write' in r.stderr
