"""Two robots share one server, live (anyscale_manager/testbed/fleet.py): two deployments, each
with its own decider, agents and ROS domain, whose 'away' scale is one shared host (capacity
100, one claims ledger). Each robot's worker (CPU 60) would go there and only one fits. Judged
from outside: the worker processes running under the server's agents (psutil), sampled
throughout, the claims in the host's database, and for a robot whose worker is preempted, the
longest gap a subscriber of this test hears on the worker's output.

- both want the server: one gets it, the other's worker stays home, never two there; then the
  holder's server agent is SIGKILLed (its warden stops its worker): its claim expires with its
  lease and the other robot moves in;
- a robot of a higher priority arrives: the lower one takes its worker home first, then the
  higher one's starts there; never two on the server, and the lower robot's output never
  silent past its Δ.
"""

import os
import signal
import time

import psutil
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import UInt8MultiArray

from anyscale_manager.model.capacity import claim_lease_s
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.testbed.fleet import (Fleet, FleetShape, HOME, is_worker, other_domain,
                                            SERVER, stretches_past_delta)

SHAPE = FleetShape()
# Long enough for both deciders to have judged the server several times after the first move.
WATCH_S = 12.0


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
            dead = self.fleet.dead(but)
            assert dead is None, dead
            assert time.monotonic() < end, f'{what}: not within {timeout_s} s\n' + \
                self.fleet.outputs()
            if self.ros is not None:
                self.ros.spin_for(0.2)
            else:
                time.sleep(0.2)

    def never_over(self):
        assert max(n for n, _ in self.samples) <= 1, 'two workers on a server with room for one'
        assert max(c for _, c in self.samples) <= SHAPE.capacity_cpu


def domains():
    mine = int(os.environ['ROS_DOMAIN_ID'])
    return {'robot_a': mine, 'robot_b': other_domain(mine)}


def test_two_robots_want_one_server_one_gets_it_and_when_its_agent_dies_the_other_moves_in(
        tmp_path, ros_env):
    """Both want the server: one gets it, the other's worker stays home, never two there nor
    claims over the capacity. Then the holder's server agent is SIGKILLed: its warden stops
    its worker, its claim expires with its lease, and the other robot moves in (not before)."""
    fleet = Fleet(str(tmp_path), ros_env)
    watch = Watch(fleet)
    try:
        for name, domain in domains().items():
            fleet.start(name, domain)
        watch.until(lambda: sum(fleet.on_server().values()), 120.0,
                    'a worker running on the shared server')
        first = time.monotonic()
        watch.until(lambda: time.monotonic() - first > WATCH_S, WATCH_S + 10, 'the watch')
        holder = [n for n, c in fleet.on_server().items() if c]
        assert len(holder) == 1
        # The other robot's decider saw the room taken (or was refused and took the move
        # back): its worker runs home.
        other = next(n for n in fleet.procs if n not in holder)
        assert fleet.workers(other, HOME) == 1
        agent = fleet.procs[holder[0]][SERVER]
        worker_pids = [k.pid for k in psutil.Process(agent.pid).children(recursive=True)
                       if is_worker(k)]
        killed = time.monotonic()
        agent.send_signal(signal.SIGKILL)
        agent.wait(10)
        watch.until(lambda: fleet.on_server().get(other) == 1, 90.0,
                    f"{other}'s worker on the server", but=((holder[0], SERVER),))
        moved_in = time.monotonic() - killed
        # Not before the orphaned worker was gone (the warden's fencing), nor before the
        # dead agent's lease ran out (renewed every quarter of a lease: 0.75 to 1 lease).
        assert not any(psutil.pid_exists(pid) and is_worker(psutil.Process(pid))
                       for pid in worker_pids)
        lease = claim_lease_s(load_deployment(fleet.paths[holder[0]]))
        assert moved_in >= 0.75 * lease - 0.5, moved_in
        watch.never_over()
    finally:
        fleet.close()


def test_a_higher_priority_robot_takes_the_server_after_the_lower_one_took_its_worker_home(
        tmp_path, ros_env, ros):
    fleet = Fleet(str(tmp_path), ros_env)
    heard = []
    node = ros.node('fleet_listener')
    node.create_subscription(UInt8MultiArray, '/robot_a/w',
                             lambda m: heard.append(time.monotonic()), qos_profile_sensor_data)
    watch = Watch(fleet, ros)
    began = time.monotonic()
    try:
        fleet.start('robot_a', domains()['robot_a'], priority=0)
        watch.until(lambda: fleet.on_server()['robot_a'] == 1, 120.0,
                    "robot_a's worker on the server")
        watch.until(lambda: len(heard) > 20, 30.0, "robot_a's worker heard from the server")
        fleet.start('robot_b', domains()['robot_b'], priority=1)
        watch.until(lambda: fleet.on_server().get('robot_b') == 1, 120.0,
                    "robot_b's worker on the server")
        watch.until(lambda: fleet.workers('robot_a', HOME) == 1, 10.0, "robot_a's worker home")
        ros.spin_for(1.0)
        watch.never_over()
        assert fleet.on_server() == {'robot_a': 0, 'robot_b': 1}
        start = next(t for t in heard if t > began)
        past, longest = stretches_past_delta(heard, start, time.monotonic(), SHAPE)
        assert past == 0, f'robot_a below freq_min {longest:.2f} s, past its Δ'
        assert 'of a higher priority asks away for the room' in fleet.text('robot_a', 'decider')
    finally:
        fleet.close()
