"""The IROS case study's planned robot files made runnable (testbed/iros_live.py): every node
launched as a workload whose CPU maps back to the plan, its connections as topics, the server
shared, and the first layouts within the shared server's capacity."""

import os

import pytest

from anyscale_manager.cli import main as cli_main
from anyscale_manager.model import load_mapping
from anyscale_manager.model.yaml_io import read_yaml
from anyscale_manager.nodes.workload import parse_spec
from anyscale_manager.testbed.iros_live import (cpu_of, live_deployment, machine_percent,
                                                pacer_name, reference_percent, work_ms_for)
from conftest import CONFIG

INSTANCE = os.path.join(CONFIG, 'iros2016', 'instance_5.yaml')
FACTOR = 0.15
HOSTS = {'c1': '10.1.0.1', 'c2': '10.2.0.1', 'c3': '10.3.0.1'}


@pytest.fixture(scope='module')
def planned(tmp_path_factory):
    """Each robot's planned file of instance 5, as read."""
    out = tmp_path_factory.mktemp('plan')
    assert cli_main(['plan', '--split-iros', INSTANCE, '--write-dir', str(out)]) == 0
    files = sorted(f for f in os.listdir(out) if f.endswith('.planned.yaml'))
    assert len(files) == 2
    return [read_yaml(str(out / f)) for f in files]


@pytest.fixture(scope='module')
def lives(planned):
    return [live_deployment(p, FACTOR, HOSTS, '/bin/workload') for p in planned]


def params_of(p):
    return p['/**']['ros__parameters']


def test_every_planned_node_is_launched_and_its_cpu_maps_back(planned, lives):
    for p, live in zip(planned, lives):
        nodes = params_of(p)['nodes']
        assert [n.name for n in live.nodes if not n.pacer] == nodes['names']
        for name in nodes['names']:
            command = live.params['nodes'][name]['launch']['command']
            assert command[0] == '/bin/workload'
            spec = parse_spec(command[1:])
            assert spec.name == name
            assert spec.reference_core == FACTOR
            # What the workload burns, per second, in percent of a reference core: the plan's.
            assert cpu_of(spec.work_ms, spec.rate_hz) == pytest.approx(nodes[name]['cpu'],
                                                                       rel=1e-5)
            assert live.node(name).cpu == nodes[name]['cpu']
            assert live.node(name).performance == nodes[name]['performance']
        # The runnable file loads as a deployment.
        load_mapping({'/**': {'ros__parameters': live.params}})


def test_a_frequency_setting_is_the_rate_and_other_nodes_run_at_10_hz(lives):
    robot_1 = lives[0]
    assert robot_1.node('tracker_1').rate_hz == 11.0        # output_frequency_hz=11
    assert robot_1.node('navigation_1').rate_hz == 20.0     # controller_frequency_hz=20
    assert robot_1.node('amcl_1').rate_hz == 10.0           # particles: not a rate
    assert robot_1.node('amcl_1').setting == 'particles=3000'
    assert robot_1.node('navigation_1').work_ms == pytest.approx(work_ms_for(50.0, 20.0))


def test_the_factor_converts_both_ways_and_is_in_the_file(lives):
    assert reference_percent(machine_percent(66.0, FACTOR), FACTOR) == pytest.approx(66.0)
    assert machine_percent(400.0, FACTOR) == pytest.approx(60.0)
    for live in lives:
        assert live.cpu_factor == FACTOR
        assert f'{FACTOR:g} of a core' in live.params['deployment']['description']


def test_connections_are_topics_and_a_pacer_drives_each_node(planned, lives):
    for p, live in zip(planned, lives):
        connections = params_of(p)['connections']
        for c in connections['names']:
            body = connections[c]
            pub = parse_spec(live.params['nodes'][body['publisher']]['launch']['command'][1:])
            sub = parse_spec(live.params['nodes'][body['subscriber']]['launch']['command'][1:])
            assert body['topic'] in [e.topic for e in pub.outputs]
            assert body['topic'] in [e.topic for e in sub.inputs]
        for n in live.nodes:
            if n.pacer:
                continue
            spec = parse_spec(live.params['nodes'][n.name]['launch']['command'][1:])
            pacer_node = pacer_name(n.rate_hz, n.scale)
            assert spec.driver == '/' + pacer_node
            pacer = parse_spec(live.params['nodes'][pacer_node]['launch']['command'][1:])
            assert pacer.is_sensor and pacer.rate_hz == n.rate_hz and pacer.work_ms == 0
            # On the node's own scale: its pace does not cross a link.
            assert live.params['nodes'][pacer_node]['residence'] == [n.scale]
            assert n.output_topic in [e.topic for e in spec.outputs]
    # The model has no outgoing connection: its output is a topic of its own, heard apart.
    assert lives[0].node('model_1').output_topic == '/model_1/output'


def test_the_server_is_shared_and_each_scale_has_its_host(lives):
    for live in lives:
        scales = live.params['scales']
        assert scales['c3']['shared'] is True
        for s in scales['names']:
            assert scales[s]['host'] == HOSTS[s]
    assert [s for s in lives[0].params['scales']['names']] == ['c1', 'c3']
    assert [s for s in lives[1].params['scales']['names']] == ['c2', 'c3']


def test_the_first_layouts_are_the_planners_and_fit_the_shared_server(planned, lives):
    on_server = 0.0
    for p, live in zip(planned, lives):
        planned_layout = params_of(p)['decider']['layout']
        decider = live.params['decider']
        assert decider['initial_layout'] == 'explicit'
        for name, scale in planned_layout.items():
            assert decider['layout'][name] == scale
        # Each pacer on its nodes' scale, claiming nothing there.
        robot = next(s for s in live.params['scales']['names']
                     if live.params['scales'][s]['role'] == 'master')
        for n in live.nodes:
            if n.pacer:
                assert decider['layout'][n.name] == n.scale and n.cpu == 0.0
        on_robot = sum(n.cpu for n in live.nodes if n.scale == robot)
        assert on_robot <= live.params['scales'][robot]['capacity_cpu']
        on_server += sum(n.cpu for n in live.nodes if n.scale == 'c3')
    assert 0 < on_server <= lives[0].params['scales']['c3']['capacity_cpu']


def test_a_file_without_a_planned_layout_is_refused(planned):
    params = params_of(planned[0])
    split = {k: v for k, v in params.items() if k != 'decider'}
    with pytest.raises(ValueError, match='decider.layout'):
        live_deployment(split, FACTOR)
    with pytest.raises(ValueError, match='cpu_factor'):
        live_deployment(planned[0], 0.0)
