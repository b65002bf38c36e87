"""discovery.mode server (model/discovery.py, agent/discovery.py): where each scale's server is,
the environment the decider and the agents give themselves before they join ROS, the server
each warden keeps running (a real Fast DDS discovery server, real processes). The deployment
running this way over a link with multicast off is test_discovery_netns.py's."""

import json
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
import yaml

from anyscale_manager import config_files
from anyscale_manager.agent import discovery as ad
from anyscale_manager.model import discovery as md
from anyscale_manager.model.loader import load_mapping
from anyscale_manager.model.reader import DeploymentError

from test_agent_supervisor import deployment_dict


def deployment(mode='server', port=11811, hosts=('10.9.0.1', '10.9.0.2')):
    data = deployment_dict({'n': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0}})
    params = data['/**']['ros__parameters']
    for scale, host in zip(('a', 'b'), hosts):
        params['scales'][scale]['host'] = host
    params['discovery'] = {'mode': mode, 'port': port}
    return data


def wait_for(condition, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f'not within {timeout_s} s: {what}'
        time.sleep(0.05)


def test_every_scale_has_a_server_at_its_host_and_port_listed_by_its_index():
    d = load_mapping(deployment(port=12000))
    assert [md.server_port(d, s, 0) for s in ('a', 'b')] == [12000, 12001]
    assert md.client_environment(d, 0) == {
        'ROS_DISCOVERY_SERVER': '10.9.0.1:12000;10.9.0.2:12001'}
    # Another ROS domain (another robot of a fleet sharing a host): other ports.
    assert md.client_environment(d, 3) == {
        'ROS_DISCOVERY_SERVER': '10.9.0.1:12048;10.9.0.2:12049'}
    assert md.client_environment(load_mapping(deployment('multicast')), 0) == {}
    assert md.domain_of({'ROS_DOMAIN_ID': '7'}) == 7 and md.domain_of({}) == 0


def test_a_bad_mode_is_refused_naming_the_setting():
    with pytest.raises(DeploymentError, match='discovery.mode'):
        load_mapping(deployment('broadcast'))


def write(tmp_path, data):
    path = tmp_path / 'deployment.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_a_node_reads_its_servers_from_its_file_and_overrides_before_it_joins(tmp_path):
    path = write(tmp_path, deployment('multicast', hosts=('127.0.0.1', 'localhost')))
    argv = ['agent', '--ros-args', '--params-file', path, '-p', 'scale:=a']
    assert ad.client_setup(argv, {}) == ({}, '')            # multicast: nothing to set
    argv += ['-p', 'discovery.mode:=server', '-p', 'scales.a.host:=10.9.0.7']
    packaged = config_files.find(config_files.DISCOVERY_PROFILE)
    env, said = ad.client_setup(argv, {'FASTRTPS_DEFAULT_PROFILES_FILE': packaged})
    # Host names are resolved (Fast DDS takes addresses); the profile for servers' clients
    # takes the multicast one's place.
    assert env == {'ROS_DISCOVERY_SERVER': '10.9.0.7:11811;127.0.0.1:11812',
                   'FASTRTPS_DEFAULT_PROFILES_FILE':
                       config_files.find(config_files.SERVER_PROFILE)}
    assert '10.9.0.7:11811' in said
    # Servers named by the environment rule, and a user's own profile is kept: both said.
    env, said = ad.client_setup(argv, {'ROS_DISCOVERY_SERVER': '10.0.0.1:11811',
                                       'FASTRTPS_DEFAULT_PROFILES_FILE': '/my/profile.xml'})
    assert env == {} and 'from the environment' in said and '/my/profile.xml is kept' in said
    # A name that cannot be resolved now is left out: Fast DDS would drop the whole list.
    unresolved = argv + ['-p', 'scales.b.host:=no-such-host.invalid']
    env, said = ad.client_setup(unresolved, {'ROS_DOMAIN_ID': '2'})
    assert env['ROS_DISCOVERY_SERVER'] == '10.9.0.7:11843;' and 'cannot resolve' in said
    # A key with dots, as rcl reads it; the agent a super client, its nodes not.
    data = deployment()
    params = data['/**']['ros__parameters']
    params['discovery.mode'] = params.pop('discovery')['mode']
    dotted = write(tmp_path, data)
    env, _ = ad.client_setup(['agent', '--ros-args', '--params-file', dotted], {}, True)
    assert env['ROS_DISCOVERY_SERVER'] == '10.9.0.1:11811;10.9.0.2:11812'
    assert env['ROS_SUPER_CLIENT'] == 'TRUE'
    # A file that cannot be read is the node's own business: nothing set, nothing said here.
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**: {ros__parameters: {scales: 3}}')
    assert ad.client_setup(['agent', '--ros-args', '--params-file', str(bad)], {}) == ({}, '')


def test_a_restart_in_place_computes_what_it_set_again(tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    path = write(tmp_path, deployment())
    argv = ['agent', '--ros-args', '--params-file', path]
    monkeypatch.delenv('ROS_DISCOVERY_SERVER', raising=False)
    monkeypatch.delenv('ROS_SUPER_CLIENT', raising=False)
    monkeypatch.delenv(ad.ENV_SET, raising=False)
    ad.apply_client_setup('agent', argv, super_client=True)
    assert os.environ['ROS_DISCOVERY_SERVER'] == '10.9.0.1:11811;10.9.0.2:11812'
    # The file changed, the process exec'd with the environment it had: the file rules.
    path = write(tmp_path, deployment(hosts=('10.9.0.5', '10.9.0.6')))
    ad.apply_client_setup('agent', argv, super_client=True)
    assert os.environ['ROS_DISCOVERY_SERVER'] == '10.9.0.5:11811;10.9.0.6:11812'
    path = write(tmp_path, deployment('multicast'))
    ad.apply_client_setup('agent', argv, super_client=True)
    assert 'ROS_DISCOVERY_SERVER' not in os.environ and 'ROS_SUPER_CLIENT' not in os.environ
    assert os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] != \
        config_files.find(config_files.SERVER_PROFILE)


def test_the_agents_nodes_are_not_super_clients():
    from anyscale_manager.agent.catalogue import base_environment
    env = base_environment({'ROS_SUPER_CLIENT': 'TRUE', 'ROS_DISCOVERY_SERVER': 'x:1'})
    assert env.get('ROS_DISCOVERY_SERVER') == 'x:1' and 'ROS_SUPER_CLIENT' not in env


def test_the_server_is_found_beside_this_python_or_named_by_the_file(monkeypatch):
    found = ad.server_command('', {'PATH': ''})
    assert os.path.basename(found[0]) == 'fast-discovery-server' and len(found) == 1
    assert ad.server_command('/opt/x/fastdds discovery', {}) == ['/opt/x/fastdds', 'discovery']
    with pytest.raises(ad.DiscoveryError, match='No closing quotation'):
        ad.server_command('"/opt/x/fastdds', {})
    monkeypatch.setattr(ad.shutil, 'which', lambda *a, **k: None)
    with pytest.raises(ad.DiscoveryError, match='discovery.server_command'):
        ad.server_command('', {'PATH': ''})


def test_the_keeper_starts_its_server_again_after_an_exit_with_a_backoff(tmp_path):
    said = []
    keeper = ad.ServerKeeper([sys.executable, '-c', 'raise SystemExit(3)'], os.environ,
                             str(tmp_path / 'discovery.log'), said.append)
    keeper.step(0.0)
    first = keeper.proc
    first.wait(10.0)
    keeper.step(0.5)                      # exited: again after 1 s
    assert keeper.proc is None and 'exited with 3' in said[-1]
    keeper.step(1.0)
    assert keeper.proc is None
    keeper.step(1.6)
    assert keeper.proc is not None and keeper.proc.pid != first.pid
    keeper.proc.wait(10.0)
    keeper.step(2.0)                      # the backoff doubles
    keeper.step(3.9)
    assert keeper.proc is None
    keeper.step(4.1)
    assert keeper.proc is not None
    keeper.proc.wait(10.0)


def test_a_warden_keeps_a_real_discovery_server_and_it_goes_with_the_warden(tmp_path):
    """The warden's server answers on its port while the warden lives, and dies with it
    (SIGKILLed too: the server's parent-death signal), so a new warden can take the port."""
    d = load_mapping(deployment(hosts=('127.0.0.1', '127.0.0.1'), port=24611))
    argv = ad.server_argv(d, 'a', {'PATH': os.environ['PATH'], 'ROS_DOMAIN_ID': '0'})
    assert argv[-6:] == ['-i', '0', '-l', '127.0.0.1', '-p', '24611']
    state = tmp_path / 'agent_unit_a.json'
    state.write_text(json.dumps({'agent_pid': os.getpid(), 'nodes': {}}))
    warden = subprocess.Popen(
        [sys.executable, '-m', 'anyscale_manager.agent.warden', '--state', str(state),
         '--scale', 'a', '--deployment', 'unit', '--host', '127.0.0.1', '--port', '24699',
         '--priority', '1',
         '--discovery-server', json.dumps(argv), '--discovery-log',
         str(tmp_path / 'discovery.log')],
        stdout=open(tmp_path / 'warden.log', 'wb'), stderr=subprocess.STDOUT,
        start_new_session=True)
    try:
        def server():
            kids = psutil.Process(warden.pid).children()
            return kids[0] if kids else None
        wait_for(lambda: server() is not None and any(
            c.laddr.port == 24611 for c in server().net_connections('udp')), 20.0,
            'the server listening on UDP 24611')
        kid = server()
        assert kid.cmdline()[0] == argv[0]
        # The warden at real-time priority (when allowed here), its server at normal.
        if os.sched_getscheduler(warden.pid) == os.SCHED_OTHER:
            print('the warden runs at normal priority here (no CAP_SYS_NICE): the server '
                  'cannot have inherited a real-time one; that check says nothing')
        assert os.sched_getscheduler(kid.pid) == os.SCHED_OTHER
        os.kill(warden.pid, signal.SIGKILL)
        warden.wait(10.0)
        wait_for(lambda: not psutil.pid_exists(kid.pid) or
                 kid.status() == psutil.STATUS_ZOMBIE, 10.0, 'the server gone with its warden')
    finally:
        if warden.poll() is None:
            os.killpg(warden.pid, signal.SIGKILL)
            warden.wait(10.0)
    log = (tmp_path / 'warden.log').read_text()
    assert 'discovery server started' in log, log


def test_validate_says_how_a_shell_joins_the_servers(tmp_path, capsys, monkeypatch):
    from anyscale_manager.cli import main
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    assert main(['validate', write(tmp_path, deployment())]) == 0
    out = capsys.readouterr().out
    assert 'export ROS_DISCOVERY_SERVER="10.9.0.1:11811;10.9.0.2:11812" ' \
           'ROS_SUPER_CLIENT=TRUE' in out


def test_the_demo_refuses_servers_where_it_cannot_run_them(capsys, tmp_path):
    from anyscale_manager.cli import main
    assert main(['demo', '--fleet', '--discovery', 'server',
                 '--out', str(tmp_path / 'out')]) == 2
    assert '--discovery' in capsys.readouterr().err
    assert main(['demo', '--mode', 'loopback', '--discovery', 'server', '--duration', '5',
                 '--out', str(tmp_path / 'out2')]) == 2
    assert 'network namespaces only' in capsys.readouterr().err
    assert not os.path.exists(tmp_path / 'out') and not os.path.exists(tmp_path / 'out2')
