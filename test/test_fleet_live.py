"""Two robots share one server, live (anyscale_manager/testbed/fleet.py): two deployments, each
with its own decider, agents and ROS domain, whose 'away' scale is one shared host (capacity
100, one claims ledger). Each robot's worker (CPU 60) would go there and only one fits. Judged
from outside: the worker processes running under the server's agents (psutil), sampled
throughout, the claims in the host's database, and for a robot whose worker is preempted, the
longest gap a subscriber of this test hears on the worker's output.

a robot of a higher priority arrives: the lower one takes its worker home first, then the
higher one's starts there; never two on the server, and the lower robot's output never silent
past its Δ. Both robots wanting the server and a server agent SIGKILLed are judged in
namespaces (test_fleet_netns.py).
"""

import os
import time

from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import UInt8MultiArray

from anyscale_manager.testbed.fleet import (Fleet, FleetShape, HOME, other_domain,
                                            stretches_past_delta)

SHAPE = FleetShape()


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
