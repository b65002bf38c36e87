"""What each robot of a test fleet runs (anyscale_manager/testbed/fleet_graphs.py): the worker
graph and the ICAR 2015 graph as deployment files the package loads, the server's room, the
connections judged; and the record's arrivals by topic (fleet_record.py)."""

import json

import pytest

from anyscale_manager.model.loader import load_mapping
from anyscale_manager.testbed.fleet_graphs import (FleetShape, graph_of, HOME, IcarGraph,
                                                   SERVER, WorkerGraph)
from anyscale_manager.testbed.fleet_record import FleetRecord

HOSTS = {HOME: '10.77.0.1', SERVER: '10.77.0.3'}


def loaded(graph, name='robot_a', priority=0):
    params = graph.params(name, priority, '/run', 7400, HOSTS)
    return load_mapping({'/**': {'ros__parameters': params}}, f'{name}.yaml'), params


def test_the_worker_graph_is_a_deployment_with_one_shared_server():
    d, _ = loaded(WorkerGraph(FleetShape()))
    assert d.name == 'robot_a' and d.master.name == HOME
    assert d.scale(SERVER).shared and d.scale(SERVER).host == '10.77.0.3'
    assert [c.topic for c in d.connections if c.freq_min_hz] == ['/robot_a/w']
    assert [j.topic for j in WorkerGraph(FleetShape()).judged('robot_b')] == ['/robot_b/w']


def test_the_icar_graph_is_the_test_beds_with_the_laptop_turned_into_the_shared_server():
    shape = FleetShape(graph='icar', hysteresis_s=6.0, reference_core=0.2)
    graph = graph_of(shape)
    assert isinstance(graph, IcarGraph)
    d, params = loaded(graph, 'robot_b', priority=1)
    assert d.name == 'robot_b' and d.priority == 1
    assert d.scale_names == (HOME, SERVER) and d.master.name == HOME
    assert d.scale(SERVER).shared and d.scale(SERVER).capacity_cpu == shape.capacity_cpu
    assert d.scale(HOME).host == '10.77.0.1'
    assert d.links[0].ends == (HOME, SERVER)
    # The same eleven nodes and eight connections; the sensors stay home.
    assert len(d.nodes) == 11 and len(d.connections) == 8
    assert d.own_scales('laser') == (HOME,)
    assert set(d.allowed_scales('amcl')) == {HOME, SERVER}
    # Every workload at the fleet's reference core; the robot's quota its capacity at it.
    amcl = params['nodes']['amcl']['launch']['arguments']
    assert amcl[-2:] == ['--reference-core', '0.2']
    assert graph.robot_cores() == pytest.approx(0.4)
    assert d.decider.hysteresis_s == 6.0
    assert d.agent.state_dir == '/run/host_state'
    assert d.monitoring.bandwidth_probe_port == 7400
    # Room on the server for one robot's AMCL and AR, not for two robots' (nor a third node).
    pair = graph.cpu('amcl') + graph.cpu('ar')
    room = shape.capacity_cpu * d.decider.cpu_headroom
    assert pair <= room < pair + min(graph.cpu('amcl'), graph.cpu('ar'))
    # Judged at the robot: every connection with a minimum frequency whose subscriber stays
    # there (camera_ar through AR's output).
    judged = {j.name for j in graph.judged('robot_b')}
    assert judged == {'laser_navigation', 'odometer_odometry', 'amcl_ekf', 'odometry_ekf',
                      'ekf_navigation', 'ar_navigation'}


def test_an_unknown_graph_is_refused():
    with pytest.raises(ValueError, match="unknown fleet graph 'ros1'"):
        FleetShape(graph='ros1')


def test_the_record_keeps_each_topics_arrivals_apart():
    rec = FleetRecord(0.0)
    rec.ingest_line('robot_a', json.dumps({'t': 2.0, 'arrivals': {'/scan': [1.0, 1.1],
                                                                  '/odom': [1.05]}}))
    rec.ingest_line('robot_a', json.dumps({'t': 3.0, 'arrivals': {'/scan': [2.1],
                                                                  '/odom': 'bad'}}))
    assert rec.heard('robot_a', '/scan') == [1.0, 1.1, 2.1]
    assert rec.heard('robot_a', '/odom') == [1.05]
    assert rec.heard('robot_a') == [1.0, 1.05, 1.1, 2.1]
    assert rec.heard('robot_b', '/scan') == []
