"""A stand-in for one node of a robot application: its topics, rates, message sizes and CPU.

Entry point ``workload`` (``ros2 run anyscale_manager workload --name amcl --sub /scan ...``).
Each output names its message type and shape, ``--pub /scan:sensor_msgs/msg/LaserScan:682``, and
is filled with plausible content of that type (``workload_messages.py``: a laser scan, a camera
image, odometry, a pose with covariance, a map, ...); each input names the type it subscribes
to, ``--sub /scan:sensor_msgs/msg/LaserScan``. Without a type both are
std_msgs/msg/UInt8MultiArray, of ``--bytes`` bytes for an output.

- A sensor (no ``--sub``) publishes at ``--rate-hz``; with ``--once`` it publishes one latched
  message (a map, an initial pose) and then just stays up.
- A processing node (one or more ``--sub``) is driven by its first ``--sub`` topic: for a new
  input it does ``--work-ms`` of real CPU work and publishes one output, as fast as the CPU it
  gets allows, at most ``--rate-hz``. Its output rate is therefore min(cap, input rate, CPU).

``--work-ms`` is measured at the reference speed: one reference core (the ICAR test-bed's Atom
1.6 GHz core, ``capacity_cpu`` 100) is ``--reference-core`` of one of this machine's cores
(0.3 by default: a current x86 core does roughly three times an Atom's work). The work is a busy
loop that runs until the thread has used ``work_ms * reference_core`` of CPU time, so under a
CPU quota (or on a busy machine) the same work takes longer in wall time, as it would on a
slower computer.

With ``--lifecycle`` the same node is a lifecycle (managed) node, as Nav2's AMCL is, so that a
scale can keep an inactive standby copy of it (``workload_lifecycle.py``); without it, the node
is the plain one below and starts working as soon as it is up.
"""

import argparse
import faulthandler
import math
import signal
import sys
import time
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence, Tuple

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from .workload_messages import (DEFAULT_TYPE, MAX_BYTES, Endpoint, EndpointError,
                                build_message, message_class, parse_endpoint, stamper)
from .workload_pose import PoseTrack, parse_motion, yaw_of
from .input_gaps import InputGaps
from ..interrupt import ignore_interrupts, interrupt_once, restore_ctrl_c, \
    rclpy_stops_on_sigint
from .shutdown import shut_rclpy_down

REFERENCE_CORE = 0.3      # one reference (robot) core as a fraction of one core of this machine
POSE_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'


@dataclass(frozen=True)
class WorkloadSpec:
    name: str
    outputs: Tuple[Endpoint, ...]
    inputs: Tuple[Endpoint, ...]
    rate_hz: float
    work_ms: float
    once: bool
    reference_core: float
    lifecycle: bool = False
    # The AMCL stand-in's state (workload_pose.py): its pose outputs carry a pose moving at
    # (speed m/s, turn rad/s), restored from a pose on ``restore``.
    pose_motion: Optional[Tuple[float, float]] = None
    restore: str = ''

    @property
    def driver(self) -> Optional[str]:
        """The input topic whose messages drive the outputs (the first); None for a sensor."""
        return self.inputs[0].topic if self.inputs else None

    @property
    def is_sensor(self) -> bool:
        return not self.inputs

    @property
    def cpu_s_per_output(self) -> float:
        """Machine CPU seconds one output costs."""
        return self.work_ms / 1000.0 * self.reference_core


def _positive(kind: str) -> Callable[[str], float]:
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{kind}: expected a number, got {text!r}')
        if not value > 0 or value != value or value == float('inf'):
            raise argparse.ArgumentTypeError(f'{kind}: must be a finite number > 0, got {text}')
        return value
    return parse


def _non_negative(kind: str, integer: bool = False, limit: float = float('inf')):
    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f'{kind}: expected {"an integer" if integer else "a number"}, got {text!r}')
        if not 0 <= value <= limit:
            raise argparse.ArgumentTypeError(f'{kind}: must be between 0 and {limit}, '
                                             f'got {text}')
        return value
    return parse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='workload',
        description='Publish and subscribe like one node of a robot application, with real '
                    'CPU work per output.')
    p.add_argument('--name', required=True, help='the ROS node name')
    p.add_argument('--pub', action='append', default=[], metavar='TOPIC[:TYPE[:SHAPE]]',
                   help='topic to publish (repeatable), with its message type (pkg/msg/Type, '
                        f'default {DEFAULT_TYPE}) and shape (BEAMS of a LaserScan, '
                        'WIDTHxHEIGHT:ENCODING of an Image, ...: see workload_messages.py)')
    p.add_argument('--sub', action='append', default=[], metavar='TOPIC[:TYPE]',
                   help='topic to subscribe (repeatable), with its message type; the first '
                        'one drives the outputs')
    p.add_argument('--rate-hz', type=_positive('--rate-hz'), default=10.0,
                   help='publishing rate of a sensor; the cap of a processing node')
    p.add_argument('--bytes', type=_non_negative('--bytes', True, MAX_BYTES), default=None,
                   help=f'payload size of the {DEFAULT_TYPE} outputs without a shape of '
                        'their own (default 64)')
    p.add_argument('--work-ms', type=_non_negative('--work-ms', limit=60000.0), default=0.0,
                   help='CPU work per output, in ms of one reference core')
    p.add_argument('--once', action='store_true',
                   help='publish one latched message, then stay up')
    p.add_argument('--reference-core', type=_positive('--reference-core'),
                   default=REFERENCE_CORE,
                   help='one reference core as a fraction of one core of this machine '
                        f'(default {REFERENCE_CORE})')
    p.add_argument('--lifecycle', action='store_true',
                   help='be a lifecycle (managed) node: unconfigured at start, working only '
                        'while active')
    p.add_argument('--pose-motion', metavar='SPEED,TURN', default=None,
                   help='the geometry_msgs/msg/PoseWithCovarianceStamped outputs carry the '
                        'pose of the robot, moving at SPEED m/s and TURN rad/s (its state)')
    p.add_argument('--restore', metavar='TOPIC', default='',
                   help='with --pose-motion: continue from a PoseWithCovarianceStamped '
                        'received here (subscribed from configure to cleanup)')
    return p


def parse_spec(argv: Sequence[str]) -> WorkloadSpec:
    """Parse workload arguments (ROS arguments already removed); argparse exits 2 on errors."""
    parser = build_parser()
    a = parser.parse_args(list(argv))
    if not a.name or not a.name.replace('_', 'a').isalnum() or a.name[0].isdigit():
        parser.error(f'--name: {a.name!r} is not a valid ROS node name')
    if not a.pub and not a.sub:
        parser.error('nothing to do: give at least one --pub or --sub')
    if a.once and a.sub:
        parser.error('--once is for publishers of one message; it cannot be combined '
                     'with --sub')
    endpoints = {'--pub': [], '--sub': []}
    for option, texts in (('--pub', a.pub), ('--sub', a.sub)):
        for text in texts:
            try:
                endpoints[option].append(parse_endpoint(text, option == '--pub', a.bytes))
            except EndpointError as e:
                parser.error(f'{option} {text}: {e}')
    outputs = tuple(endpoints['--pub'])
    if a.bytes is not None and all(e.msg_type != DEFAULT_TYPE for e in outputs):
        parser.error(f'--bytes sizes {DEFAULT_TYPE} outputs and this node has none: give '
                     'the shape of a typed output after its type (--pub TOPIC:TYPE:SHAPE)')
    motion = None
    if a.pose_motion is not None:
        try:
            motion = parse_motion(a.pose_motion)
        except ValueError as e:
            parser.error(f'--pose-motion: {e}')
        if all(e.msg_type != POSE_TYPE for e in outputs):
            parser.error(f'--pose-motion moves the {POSE_TYPE} outputs and this node has none')
    if a.restore and motion is None:
        parser.error('--restore takes a pose: give --pose-motion too')
    return WorkloadSpec(name=a.name, outputs=outputs, inputs=tuple(endpoints['--sub']),
                        rate_hz=a.rate_hz, work_ms=a.work_ms, once=a.once,
                        reference_core=a.reference_core, lifecycle=a.lifecycle,
                        pose_motion=motion, restore=a.restore)


def burn_cpu(cpu_s: float, clock: Callable[[], float] = time.thread_time) -> int:
    """Busy computation until this thread has used ``cpu_s`` seconds of CPU; returns a checksum."""
    if cpu_s <= 0:
        return 0
    end = clock() + cpu_s
    x = 1
    while clock() < end:
        for _ in range(500):
            x = (x * 1103515245 + 12345) & 0x7fffffff
    return x


class OutputGate:
    """Decides when a processing node may start its next output, capped at ``rate_hz``.

    Outputs are due every 1/rate; an input up to 40% of a period early counts as on time, so a
    10 Hz input under a 5 Hz cap gives 5 Hz and not 3.3 Hz when arrivals jitter. The next
    output is due one period after the later of the previous due time and this output's start,
    so a node whose work takes longer than a period starts the next output as soon as it is
    done (CPU-bound), and one that paused does not catch up with a burst.
    """

    def __init__(self, rate_hz: float):
        self.period_s = 1.0 / rate_hz
        self.next_due: Optional[float] = None

    def ready_at(self) -> float:
        """The earliest time the next output may start (-inf before the first)."""
        return -math.inf if self.next_due is None else self.next_due - 0.4 * self.period_s

    def ready(self, now: float) -> bool:
        return now >= self.ready_at()

    def started(self, now: float) -> None:
        if self.next_due is None:
            self.next_due = now + self.period_s
        else:
            self.next_due = max(self.next_due, now) + self.period_s


def main(args: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    argv = sys.argv if args is None else args
    spec = parse_spec(remove_ros_args(argv)[1:])
    # SIGUSR1 writes every thread's stack to stderr (the node's log under an agent): what a
    # node that stopped serving is doing, without stopping it.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    if spec.lifecycle:
        # Imported here: that module builds on this one.
        from .workload_lifecycle import LifecycleWorkloadNode as node_class
    else:
        node_class = WorkloadNode
    interrupt_once()
    rclpy.init(args=argv)
    rclpy_stops_on_sigint()
    node = None
    try:
        node = node_class(spec)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # A SIGINT shuts the context down (rclpy's handler) maybe while the node is built or
        # a callback publishes (rcl then refuses): that is the shutdown asked for, not a
        # failure.
        if rclpy.ok():
            raise
    finally:
        # A supervisor may repeat its SIGINT while we clean up: finish the cleanup anyway.
        ignore_interrupts()
        if node is not None:
            node.destroy_node()
        shut_rclpy_down()
    return 0


def publisher_qos(spec: WorkloadSpec) -> QoSProfile:
    """Sensors stream best effort (a lost image is not worth resending over a busy link, as
    with sensor-data QoS); a --once message is latched (reliable, transient local) and the
    outputs of processing nodes are reliable. Depth 1: a slow or unreachable reader never
    blocks a writer."""
    if spec.once:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if spec.is_sensor:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def subscriber_qos() -> QoSProfile:
    """Best effort and volatile match every publisher above; only the driving input matters
    for a workload's outputs, so a latched message missed by a late joiner costs nothing."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


class WorkloadBehaviour:
    """What a workload does with its inputs and outputs, shared by the plain node and the
    lifecycle node; each of them decides when its publishers, subscriptions and timers exist."""

    def _init_behaviour(self, spec: WorkloadSpec, clock: Callable[[], float]) -> None:
        self.spec = spec
        self._now = clock
        # Built once: a real driver's data arrives ready-made; only the stamp changes.
        self._msgs = [build_message(e) for e in spec.outputs]
        self._stampers = [stamper(e) for e in spec.outputs]
        self._stamped = any(self._stampers)
        self.outputs = 0
        self.inputs = {e.topic: 0 for e in spec.inputs}
        self.checksum = 0
        self._pubs = []
        self._gate = OutputGate(spec.rate_hz)
        self._pending = False
        self._retry = None
        self._first_output_logged = False
        self.pose = PoseTrack(*spec.pose_motion) if spec.pose_motion else None
        self._posed = [e.msg_type == POSE_TYPE and self.pose is not None for e in spec.outputs]

    def describe(self) -> str:
        spec = self.spec
        return (f'publishing {", ".join(e.describe() for e in spec.outputs) or "nothing"}'
                + (f', driven by {spec.driver}' if spec.driver else '')
                + (f', {spec.work_ms:g} ms of reference CPU work per output'
                   if spec.work_ms else ''))

    def _subscribe_inputs(self) -> list:
        # Raw: a workload's output depends on an input's arrival, not on its content. Each
        # input's gaps as this node lives them are said in its log, afresh from here.
        self._gaps = {e.topic: InputGaps() for e in self.spec.inputs}
        return [self.create_subscription(message_class(e.msg_type), e.topic,
                                         self._make_callback(e.topic), subscriber_qos(),
                                         raw=True)
                for e in self.spec.inputs]

    def _make_callback(self, topic: str):
        driving = topic == self.spec.driver

        def callback(_raw: bytes) -> None:
            self.inputs[topic] += 1
            gap = self._gaps[topic].heard(self._now())
            if gap is not None:
                self.get_logger().warning(f'input {topic}: {gap}')
            if driving:
                self._pending = True
                self._maybe_produce()
        return callback

    def _maybe_produce(self) -> None:
        if not self._pending:
            return
        now = self._now()
        if not self._gate.ready(now):
            # Held back by the cap: come back when it opens (not a polling timer: a node
            # waking up 100 times a second costs a weak robot more than its own work).
            if self._retry.is_canceled():
                self._retry.timer_period_ns = int(max(0.001, self._gate.ready_at() - now) * 1e9)
                self._retry.reset()
            return
        self._pending = False
        self._gate.started(self._now())
        self.checksum ^= burn_cpu(self.spec.cpu_s_per_output)
        self._publish()

    def _on_retry(self) -> None:
        self._retry.cancel()
        self._maybe_produce()

    def _publish(self) -> None:
        # One reading of the clock: a pose is where the robot is at its message's stamp. Two
        # readings put the pose ahead of its stamp by whatever stalled the process between
        # them (a CPU quota's throttling), and a copy handed that pose went on ahead of the
        # robot.
        now = self.get_clock().now()
        if self._stamped:
            stamp_msg = now.to_msg()
            for msg, stamp in zip(self._msgs, self._stampers):
                if stamp is not None:
                    stamp(msg, stamp_msg)
        if self.pose is not None:
            x, y, yaw = self.pose.at(now.nanoseconds / 1e9)
            for msg, posed in zip(self._msgs, self._posed):
                if posed:
                    set_pose(msg, x, y, yaw)
        for pub, msg in zip(self._pubs, self._msgs):
            pub.publish(msg)
        self.outputs += 1
        if not self._first_output_logged:
            self._first_output_logged = True
            self.get_logger().info('first output published')

    def _subscribe_restore(self):
        """The restore input of a node with a state (``--restore``), or None."""
        if not self.spec.restore:
            return None
        from geometry_msgs.msg import PoseWithCovarianceStamped
        return self.create_subscription(PoseWithCovarianceStamped, self.spec.restore,
                                        self._on_restore, 1)

    def _on_restore(self, msg) -> None:
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9
        values = (p.x, p.y, o.z, o.w, stamp_s)
        if not all(math.isfinite(v) for v in values) or abs(o.z) + abs(o.w) == 0.0 \
                or stamp_s <= 0.0:
            # A pose it cannot take is refused with its reason; it goes on with its own.
            self.get_logger().error(f'restore refused: not a pose in the plane with a stamp '
                                    f'(x {p.x}, y {p.y}, qz {o.z}, qw {o.w}, stamp {stamp_s})')
            return
        assert self.pose is not None
        self.pose.restore(p.x, p.y, yaw_of(o.z, o.w), stamp_s)
        self.get_logger().info(f'restored: pose ({p.x:.3f}, {p.y:.3f}) of stamp {stamp_s:.3f}')


def set_pose(msg, x: float, y: float, yaw: float) -> None:
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    msg.pose.pose.orientation.z = math.sin(yaw / 2.0)
    msg.pose.pose.orientation.w = math.cos(yaw / 2.0)


class WorkloadNode(WorkloadBehaviour, Node):
    """The plain node: publishers, subscriptions and timers from the start, for its whole life."""

    def __init__(self, spec: WorkloadSpec, clock: Callable[[], float] = time.monotonic,
                 **kwargs):
        super().__init__(spec.name, **kwargs)
        self._init_behaviour(spec, clock)
        self._pubs = [self.create_publisher(message_class(e.msg_type), e.topic,
                                            publisher_qos(spec))
                      for e in spec.outputs]
        # One timer for an input the cap held back, armed only then: created once, since
        # creating and destroying timers under a spinning executor is a known source of rclpy
        # CPU churn and races.
        self._retry = self.create_timer(1.0, self._on_retry)
        self._retry.cancel()
        self._subscribe_inputs()
        self._subscribe_restore()
        self.get_logger().info(f'up: {self.describe()}')
        if spec.once:
            self._publish()
        elif spec.is_sensor:
            self.create_timer(1.0 / spec.rate_hz, self._publish)


if __name__ == '__main__':
    sys.exit(main())
