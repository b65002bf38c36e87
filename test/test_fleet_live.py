"""Two robots share one server, live: two deployments, each with its own decider, agents and ROS
domain, whose 'away' scale is one shared host (capacity 100, one claims ledger). Each robot's
worker (CPU 60) would go there; one gets it, the other's decider sees the room taken and keeps
its worker home. Judged from outside: the worker processes running under the server's agents
(psutil), sampled throughout, and the claims in the host's database."""

import os
import signal
import sqlite3
import time

import psutil

import home_away as ha
from anyscale_manager.agent.ledger import FILE_NAME

CAPACITY = 100.0
WORKER_CPU = 60.0
# Long enough for both deciders to have judged the server several times after the first move.
WATCH_S = 25.0


def fleet_member(tmp_path, name, offset):
    """Robot ``name``'s deployment: home (its robot) and away, the shared server."""
    nodes, _ = ha.worker_and_pinned(f'/{name}_{os.getpid()}')
    nodes['worker']['cpu'] = WORKER_CPU
    path = ha.write_deployment(
        tmp_path, f'{name}_{os.getpid()}', (nodes, {}), capacity_cpu=CAPACITY,
        port_offset=offset, file_name=f'{name}.yaml',
        agent={'state_dir': str(tmp_path / 'host_state'), 'log_dir': str(tmp_path / name)})
    with open(path) as f:
        text = f.read().replace('kind: server\n', 'kind: server\n        shared: true\n')
    assert 'shared: true' in text
    with open(path, 'w') as f:
        f.write(text)
    return path


def other_domain(env):
    domain = int(env['ROS_DOMAIN_ID'])
    return str(domain + 100 if domain + 100 <= 230 else domain - 100)


def workers_on_server(agents):
    """The live worker processes each server agent supervises, by deployment."""
    out = {}
    for name, proc in agents.items():
        try:
            kids = psutil.Process(proc.proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            kids = []
        out[name] = sum(1 for k in kids if _is_worker(k))
    return out


def _is_worker(proc):
    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE \
            and '--name' in proc.cmdline() and 'worker' in proc.cmdline()
    except psutil.Error:
        return False


def claimed_cpu(tmp_path):
    path = tmp_path / 'host_state' / FILE_NAME
    if not path.exists():
        return 0.0
    con = sqlite3.connect(str(path))
    try:
        return con.execute('SELECT COALESCE(SUM(cpu), 0) FROM claims WHERE active = 1'
                           ).fetchone()[0]
    except sqlite3.OperationalError:
        return 0.0
    finally:
        con.close()


def test_two_robots_wanting_one_server_one_gets_it_and_nothing_is_over_committed(
        tmp_path, ros_env):
    envs = {'robot_a': dict(ros_env), 'robot_b': dict(ros_env, ROS_DOMAIN_ID=other_domain(
        ros_env))}
    procs, server = [], {}
    try:
        for offset, (name, env) in enumerate(envs.items()):
            path = fleet_member(tmp_path, name, offset * 7)
            server[name] = ha.start(procs, tmp_path, env, path, f'{name}_agent_away',
                                    '-p', 'scale:=away')
            ha.start(procs, tmp_path, env, path, f'{name}_agent_home', '-p', 'scale:=home')
            ha.start(procs, tmp_path, env, path, f'decider_{name}')
        samples, end, first = [], time.monotonic() + 120.0, None
        while time.monotonic() < end:
            counts = workers_on_server(server)
            samples.append((sum(counts.values()), claimed_cpu(tmp_path)))
            if first is None and sum(counts.values()):
                first = time.monotonic()
            if first is not None and time.monotonic() - first > WATCH_S:
                break
            for name, proc in procs:
                assert proc.proc.poll() is None, f'{name} exited:\n{proc.text()[-3000:]}'
            time.sleep(0.2)
        assert first is not None, 'no worker ever ran on the shared server:\n' + '\n'.join(
            f'--- {n}\n{p.text()[-2000:]}' for n, p in procs)
        assert max(n for n, _ in samples) == 1, 'two workers on a server with room for one'
        assert max(c for _, c in samples) <= CAPACITY
        holder = [n for n, c in workers_on_server(server).items() if c]
        assert len(holder) == 1
        # The other robot's decider saw the room taken (or was refused and took the move
        # back): its worker runs home.
        loser = next(n for n in server if n not in holder)
        home = next(p for n, p in procs if n == f'{loser}_agent_home')
        assert workers_on_server({loser: home}) == {loser: 1}
    finally:
        for name, proc in reversed(procs):
            proc.stop(signal.SIGINT, timeout=20.0)
        ha.stop_wardens(tmp_path)
