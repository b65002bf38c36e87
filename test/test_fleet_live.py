"""Two robots share one server, live: two deployments, each with its own decider, agents and ROS
domain, whose 'away' scale is one shared host (capacity 100, one claims ledger). Each robot's
worker (CPU 60) would go there and only one fits. Judged from outside: the worker processes
running under the server's agents (psutil), sampled throughout, the claims in the host's
database, and for a robot whose worker is preempted, the longest gap a subscriber of this test
hears on the worker's output.

- both want the server: one gets it, the other's worker stays home, never two there; then the
  holder's server agent is SIGKILLed (its warden stops its worker): its claim expires with its
  lease and the other robot moves in;
- a robot of a higher priority arrives: the lower one takes its worker home first, then the
  higher one's starts there; never two on the server, and the lower robot's output never
  silent past its Δ.
"""

import os
import signal
import sqlite3
import time

import psutil
import yaml
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import UInt8MultiArray

import home_away as ha
from anyscale_manager.agent.ledger import FILE_NAME
from anyscale_manager.model.capacity import claim_lease_s as lease_s
from anyscale_manager.model.loader import load_deployment

CAPACITY = 100.0
WORKER_CPU = 60.0
RATE_HZ = 10.0
FREQ_MIN_HZ = 5.0
TOLERANCE_S = 2.0
# Long enough for both deciders to have judged the server several times after the first move.
WATCH_S = 12.0


def other_domain(env):
    domain = int(env['ROS_DOMAIN_ID'])
    return str(domain + 100 if domain + 100 <= 230 else domain - 100)


class Fleet:
    """The robots started so far, each a decider and two agents, with the server's agents."""

    def __init__(self, tmp_path, ros_env):
        self.tmp_path = tmp_path
        self.envs = {'robot_a': dict(ros_env),
                     'robot_b': dict(ros_env, ROS_DOMAIN_ID=other_domain(ros_env))}
        self.procs = []
        self.server = {}
        self.paths = {}

    def topic(self, name):
        return f'/{name}_{os.getpid()}/w'

    def write(self, name, priority):
        """Robot ``name``: sensor (home) -> worker (migratable, CPU 60) -> pinned (home), the
        worker's output watched with Δ; its 'away' scale is the shared server."""
        nodes, connections = ha.chain(f'/{name}_{os.getpid()}', RATE_HZ,
                                      freq_min_hz=FREQ_MIN_HZ, tolerance_s=TOLERANCE_S)
        nodes['worker']['cpu'] = WORKER_CPU
        path = ha.write_deployment(
            self.tmp_path, f'{name}_{os.getpid()}', (nodes, connections),
            capacity_cpu=CAPACITY, port_offset=7 * len(self.paths), file_name=f'{name}.yaml',
            agent={'state_dir': str(self.tmp_path / 'host_state'),
                   'log_dir': str(self.tmp_path / name)})
        with open(path) as f:
            data = yaml.safe_load(f)
        params = data['/**']['ros__parameters']
        params['scales']['away']['shared'] = True
        params['deployment']['priority'] = priority
        with open(path, 'w') as f:
            yaml.safe_dump(data, f)
        self.paths[name] = path
        return path

    def start(self, name, priority=0):
        path, env = self.write(name, priority), self.envs[name]
        self.server[name] = ha.start(self.procs, self.tmp_path, env, path, f'{name}_agent_away',
                                     '-p', 'scale:=away')
        ha.start(self.procs, self.tmp_path, env, path, f'{name}_agent_home', '-p',
                 'scale:=home')
        ha.start(self.procs, self.tmp_path, env, path, f'decider_{name}')

    def proc(self, name):
        return next(p for n, p in self.procs if n == name)

    def workers(self, agents):
        """The live worker processes each given agent supervises."""
        return {name: _workers_under(proc.proc.pid) for name, proc in agents.items()}

    def on_server(self):
        return self.workers(self.server)

    def at_home(self, name):
        return self.workers({name: self.proc(f'{name}_agent_home')})[name]

    def claimed_cpu(self):
        path = self.tmp_path / 'host_state' / FILE_NAME
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

    def alive(self, but=()):
        for name, proc in self.procs:
            if name not in but:
                assert proc.proc.poll() is None, f'{name} exited:\n{proc.text()[-3000:]}'

    def outputs(self):
        return '\n'.join(f'--- {n}\n{p.text()[-2500:]}' for n, p in self.procs)

    def stop(self):
        for name, proc in reversed(self.procs):
            proc.stop(signal.SIGINT, timeout=20.0)
        ha.stop_wardens(self.tmp_path)


def _workers_under(pid):
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return 0
    return sum(1 for k in kids if _is_worker(k))


def _is_worker(proc):
    try:
        cmd = proc.cmdline()
        return proc.status() != psutil.STATUS_ZOMBIE and '--name' in cmd \
            and cmd[cmd.index('--name') + 1] == 'worker'
    except (psutil.Error, IndexError):
        return False


class Watch:
    """Samples of the server (workers there, claimed CPU) taken while waiting."""

    def __init__(self, fleet, ros=None):
        self.fleet, self.ros = fleet, ros
        self.samples = []

    def until(self, cond, timeout_s, what, but=()):
        end = time.monotonic() + timeout_s
        while True:
            self.samples.append((sum(self.fleet.on_server().values()),
                                 self.fleet.claimed_cpu()))
            if cond():
                return
            self.fleet.alive(but)
            assert time.monotonic() < end, f'{what}: not within {timeout_s} s\n' + \
                self.fleet.outputs()
            if self.ros is not None:
                self.ros.spin_for(0.2)
            else:
                time.sleep(0.2)

    def never_over(self):
        assert max(n for n, _ in self.samples) <= 1, 'two workers on a server with room for one'
        assert max(c for _, c in self.samples) <= CAPACITY


def test_two_robots_want_one_server_one_gets_it_and_when_its_agent_dies_the_other_moves_in(
        tmp_path, ros_env):
    """Both want the server: one gets it, the other's worker stays home, never two there nor
    claims over the capacity. Then the holder's server agent is SIGKILLed: its warden stops
    its worker, its claim expires with its lease, and the other robot moves in (not before)."""
    fleet = Fleet(tmp_path, ros_env)
    watch = Watch(fleet)
    try:
        fleet.start('robot_a')
        fleet.start('robot_b')
        watch.until(lambda: sum(fleet.on_server().values()), 120.0,
                    'a worker running on the shared server')
        first = time.monotonic()
        watch.until(lambda: time.monotonic() - first > WATCH_S, WATCH_S + 10, 'the watch')
        holder = [n for n, c in fleet.on_server().items() if c]
        assert len(holder) == 1
        # The other robot's decider saw the room taken (or was refused and took the move
        # back): its worker runs home.
        other = next(n for n in fleet.server if n not in holder)
        assert fleet.at_home(other) == 1
        agent = fleet.server[holder[0]]
        worker_pids = [k.pid for k in psutil.Process(agent.proc.pid).children(recursive=True)
                       if _is_worker(k)]
        killed = time.monotonic()
        agent.proc.send_signal(signal.SIGKILL)
        agent.proc.wait(10)
        watch.until(lambda: fleet.on_server().get(other) == 1, 90.0,
                    f"{other}'s worker on the server", but=(f'{holder[0]}_agent_away',))
        moved_in = time.monotonic() - killed
        # Not before the orphaned worker was gone (the warden's fencing), nor before the
        # dead agent's lease ran out (renewed every quarter of a lease: 0.75 to 1 lease).
        assert not any(psutil.pid_exists(pid) and _is_worker(psutil.Process(pid))
                       for pid in worker_pids)
        lease = lease_s(load_deployment(fleet.paths[holder[0]]))
        assert moved_in >= 0.75 * lease - 0.5, moved_in
        watch.never_over()
    finally:
        fleet.stop()


def test_a_higher_priority_robot_takes_the_server_after_the_lower_one_took_its_worker_home(
        tmp_path, ros_env, ros):
    fleet = Fleet(tmp_path, ros_env)
    heard = []
    node = ros.node('fleet_listener')
    node.create_subscription(UInt8MultiArray, fleet.topic('robot_a'),
                             lambda m: heard.append(time.monotonic()), qos_profile_sensor_data)
    watch = Watch(fleet, ros)
    try:
        fleet.start('robot_a', priority=0)
        watch.until(lambda: fleet.on_server()['robot_a'] == 1, 120.0,
                    "robot_a's worker on the server")
        watch.until(lambda: len(heard) > 20, 30.0, "robot_a's worker heard from the server")
        fleet.start('robot_b', priority=1)
        watch.until(lambda: fleet.on_server().get('robot_b') == 1, 120.0,
                    "robot_b's worker on the server")
        watch.until(lambda: fleet.at_home('robot_a') == 1, 10.0, "robot_a's worker home")
        ros.spin_for(1.0)
        watch.never_over()
        assert fleet.on_server() == {'robot_a': 0, 'robot_b': 1}
        gaps = [b - a for a, b in zip(heard, heard[1:])]
        assert max(gaps) < TOLERANCE_S, f'robot_a silent {max(gaps):.2f} s past its Δ'
        decider_a = fleet.proc('decider_robot_a').text()
        assert 'of a higher priority asks away for the room' in decider_a
    finally:
        fleet.stop()
