"""Where a bench's ROS processes run: all on this machine's loopback, or on two scales.

``Loopback``: every process here, DDS on loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
which makes Fast DDS announce by unicast to 32 ports of 127.0.0.1 and carry data over shared
memory); the bench's own process is a consumer on neither scale.

``Namespaces``: scale ``a`` is the test-bed's "robot" network namespace and ``b`` its "laptop"
namespace, joined by a veth pair shaped at the WiFi's 54 Mbit/s (anyscale_manager.testbed.netns);
DDS runs over UDP on the pair as on two computers (multicast discovery on the link, the other
scale's address as a static peer), as the test-bed runs it. The bench's process runs on ``a``
(``run_inside`` re-executes it there) and a ``Listener`` process on ``b``: a consumer on each
scale, so a copy started on either one is heard by a consumer on the other. No CPU quotas: the
figures are the mechanism's, not a weak computer's.
"""

import os
import subprocess
import sys
import threading
from typing import List, Optional, Sequence, Tuple

# The end of the small programs bench_agent and the listener run with ``python -c``: spin ``node``
# until SIGINT or shutdown, then leave cleanly.
SPIN = r'''
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


LISTENER = r'''
import sys, time
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node('bench_listener')


def subscribe(topic):
    def heard(msg):
        print(f'heard {time.monotonic():.6f} {topic} {msg.data}', flush=True)

    def matched(event):
        if event.current_count_change > 0:
            print(f'matched {time.monotonic():.6f} {topic}', flush=True)

    node.create_subscription(String, topic, heard, 10,
                             event_callbacks=SubscriptionEventCallbacks(matched=matched))


for topic in sys.argv[1:]:
    subscribe(topic)
print('ready', flush=True)
''' + SPIN


class Loopback:
    """Every process on this machine's loopback; the bench's process hears every copy."""

    here = None                 # the bench's process is on neither scale

    def describe(self) -> str:
        return ('loopback: both scales on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST);'
                ' the consumer is this process, on neither scale')

    def prepare_environment(self) -> None:
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        os.environ.pop('ROS_STATIC_PEERS', None)

    def popen(self, scale: str, argv: Sequence[str], **kwargs) -> subprocess.Popen:
        return subprocess.Popen(list(argv), **kwargs)


class Namespaces:
    """Scale ``a`` in the robot namespace (with the bench's process), ``b`` in the laptop one."""

    here = 'a'
    NAMESPACE = {'a': 'robot', 'b': 'laptop'}

    def __init__(self, tag: str, domain_id: int, log_dir: str, profile: bool = True):
        from anyscale_manager.testbed import netns
        self.net = netns.Network(tag=tag)      # built by run_inside's process; used, not owned
        self.domain_id, self.log_dir, self.profile = domain_id, log_dir, profile

    def describe(self) -> str:
        return (f'netns: scale a = namespace {self.net.namespaces["robot"]}, scale b = '
                f'{self.net.namespaces["laptop"]}, a veth link shaped at '
                f'{self.net.link.rate_kbps / 1000:g} Mbit/s, DDS over UDP on the link; '
                'consumers: this process on a, a listener on b; a figure is taken at the '
                'consumer on the scale the new copy did not start on')

    def env(self, scale: str) -> dict:
        return scale_env(self.net, self.NAMESPACE[scale], self.domain_id, self.log_dir,
                         self.profile)

    def popen(self, scale: str, argv: Sequence[str], **kwargs) -> subprocess.Popen:
        """argv in ``scale``'s namespace, same pid (nsenter execs into it)."""
        kwargs.setdefault('env', self.env(scale))
        return subprocess.Popen(self.net.command(self.NAMESPACE[scale], argv, cpu_quota=False),
                                **kwargs)


def scale_env(net, namespace: str, domain_id: int, log_dir: str, profile: bool) -> dict:
    """The test-bed's environment for a ROS process in ``namespace`` (the other end as its
    static peer); without ``profile``, the packaged discovery profile left out."""
    from anyscale_manager import config_files
    from anyscale_manager.testbed.harness import child_env
    other = 'laptop' if namespace == 'robot' else 'robot'
    env = child_env(domain_id, log_dir, peer=net.addresses[other])
    if not profile:
        for var in config_files.PROFILE_VARS:
            if not os.environ.get(var):
                env.pop(var, None)
    return env


def run_inside(argv: Sequence[str], domain_id: int, profile: bool) -> int:
    """Build the namespaces, run ``argv + ['--inside', tag]`` on scale a, remove everything."""
    import tempfile

    from anyscale_manager.testbed import netns
    with tempfile.TemporaryDirectory(prefix='bench_scales_') as log_dir, \
            netns.Network() as net:
        env = scale_env(net, 'robot', domain_id, log_dir, profile)
        cmd = net.command('robot', list(argv) + ['--inside', net.tag], cpu_quota=False)
        return subprocess.run(cmd, env=env).returncode


def choose(requested: Optional[str]) -> Tuple[str, str]:
    """('netns' or 'loopback', why): namespaces when asked or, unasked, when they can be built."""
    if requested == 'loopback':
        return 'loopback', 'asked for'
    from anyscale_manager.testbed import netns
    ok, why = netns.available()
    if ok:
        return 'netns', why
    if requested == 'netns':
        raise SystemExit(f'--scales netns: {why}')
    return 'loopback', f'network namespaces unavailable ({why})'


class Listener:
    """A consumer on scale b: the LISTENER program's lines, read by a thread."""

    def __init__(self, scales: Namespaces, topics: Sequence[str], log_path: str):
        self.heard: List[Tuple[float, str]] = []       # (monotonic time, data) of every message
        self.matched: List[Tuple[float, str]] = []     # (monotonic time, topic)
        self.ready = threading.Event()
        self.log_path = log_path
        self._log = open(log_path, 'a')
        self.proc = scales.popen('b', [sys.executable, '-c', LISTENER] + list(topics),
                                 stdout=subprocess.PIPE, stderr=self._log,
                                 stdin=subprocess.DEVNULL, text=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            parts = line.rstrip('\n').split(' ', 3)
            if parts[0] == 'ready':
                self.ready.set()
            elif parts[0] == 'heard' and len(parts) == 4:
                self.heard.append((float(parts[1]), parts[3]))
            elif parts[0] == 'matched' and len(parts) >= 3:
                self.matched.append((float(parts[1]), parts[2]))

    def close(self, stop) -> None:
        stop(self.proc, 10.0)
        self._log.close()
