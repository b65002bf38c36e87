"""The messages a workload node publishes: real ROS message types, filled once with plausible
content of a real sensor's or node's size, and stamped at every output.

An output is ``TOPIC[:TYPE[:SHAPE...]]``; an input is ``TOPIC[:TYPE]``. TYPE is ``pkg/msg/Type``
(or ``pkg/Type``), ``std_msgs/msg/UInt8MultiArray`` when left out. SHAPE depends on the type:

=============================================  ===========================  ====================
type                                           SHAPE                        default
=============================================  ===========================  ====================
std_msgs/msg/UInt8MultiArray                   BYTES of payload             ``--bytes`` (64)
sensor_msgs/msg/LaserScan                      BEAMS                        682 (Hokuyo URG-04LX)
sensor_msgs/msg/Image                          WIDTHxHEIGHT[:ENCODING]      640x480:rgb8
sensor_msgs/msg/JointState                     JOINTS                       4 (youBot base wheels)
nav_msgs/msg/Odometry                          none                         fixed (~700 B)
nav_msgs/msg/OccupancyGrid                     WIDTHxHEIGHT[:RESOLUTION_M]  200x200:0.05
geometry_msgs/msg/PoseWithCovarianceStamped    none                         fixed (~340 B)
geometry_msgs/msg/PoseArray                    POSES                        4
geometry_msgs/msg/Twist                        none                         fixed (48 B)
=============================================  ===========================  ====================

Content is built once per output (a scan of a room, an image with a marker in it, a map with
walls, covariances of the right form) and only the header stamp changes per message, so what an
output costs is what publishing that type costs (conversion and serialisation), as it is for a
real driver whose data arrives ready-made. Inputs may be of any importable message type: the
workload subscribes raw and never deserialises them.
"""

import difflib
import importlib
import math
import re
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Sequence, Tuple

DEFAULT_TYPE = 'std_msgs/msg/UInt8MultiArray'
DEFAULT_BYTES = 64
MAX_BYTES = 16 * 1024 * 1024
_TYPE_RE = re.compile(r'^([A-Za-z_][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z_][A-Za-z0-9_]*)$')

# Bytes per pixel of the encodings sensor_msgs/image_encodings names most often.
ENCODINGS = {
    'mono8': 1, 'mono16': 2, 'rgb8': 3, 'bgr8': 3, 'rgba8': 4, 'bgra8': 4, 'rgb16': 6,
    'bgr16': 6, 'yuv422': 2, 'yuv422_yuy2': 2, 'bayer_rggb8': 1, 'bayer_bggr8': 1,
    'bayer_gbrg8': 1, 'bayer_grbg8': 1, '8UC1': 1, '8UC3': 3, '16UC1': 2, '32FC1': 4,
}


class EndpointError(ValueError):
    """A topic/type/shape argument that cannot be used; the message says why."""


@dataclass(frozen=True)
class Endpoint:
    """One input or output of a workload: its topic, message type and (outputs) shape."""

    topic: str
    msg_type: str = DEFAULT_TYPE
    shape: Tuple = ()

    def describe(self) -> str:
        """'/image (Image 176x144:mono8)': the topic, the type and the shape as written."""
        shape = shape_text(self.msg_type, self.shape)
        return f'{self.topic} ({_short(self.msg_type)}{" " + shape if shape else ""})'


def shape_text(type_name: str, shape: tuple) -> str:
    """A shape as the command line writes it: '682', '176x144:mono8', '200x200:0.05'."""
    if len(shape) == 3:
        return f'{shape[0]}x{shape[1]}:{shape[2]:g}' if isinstance(shape[2], float) \
            else f'{shape[0]}x{shape[1]}:{shape[2]}'
    return ':'.join(str(x) for x in shape)


def _short(type_name: str) -> str:
    return type_name.split('/')[-1]


def canonical_type(text: str) -> str:
    """'pkg/Type' or 'pkg/msg/Type' -> 'pkg/msg/Type'; EndpointError for anything else."""
    match = _TYPE_RE.match(text)
    if not match:
        known = [k for k in KINDS if _short(k) == text]
        raise EndpointError(f'{text!r} is not a message type of the form pkg/msg/Type'
                            + (f' (did you mean {known[0]}?)' if known else ''))
    return f'{match.group(1)}/msg/{match.group(2)}'


def message_class(type_name: str):
    """The class of a message type; EndpointError naming what failed (with a did-you-mean)."""
    name = canonical_type(type_name)
    pkg, _, cls_name = name.split('/')
    try:
        module = importlib.import_module(f'{pkg}.msg')
    except ImportError:
        raise EndpointError(f'{name}: no message package {pkg} here'
                            f'{_did_you_mean(name, KINDS)}') from None
    cls = getattr(module, cls_name, None)
    if cls is None or not hasattr(cls, 'get_fields_and_field_types'):
        raise EndpointError(f'{name}: {pkg} has no message {cls_name}'
                            f'{_did_you_mean(name, KINDS)}')
    return cls


def _did_you_mean(name: str, candidates) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.8)
    if not close:
        lowered = {c.lower(): c for c in candidates}
        close = [lowered[name.lower()]] if name.lower() in lowered else []
    return f' (did you mean {close[0]}?)' if close else ''


# --- parsing ------------------------------------------------------------------------------------

def parse_endpoint(text: str, output: bool, default_bytes: Optional[int] = None) -> Endpoint:
    """``TOPIC[:TYPE[:SHAPE...]]`` (outputs) or ``TOPIC[:TYPE]`` (inputs) -> an Endpoint."""
    topic, *rest = text.split(':')
    if not topic or any(c.isspace() for c in topic):
        raise EndpointError(f'bad topic name {topic!r}')
    if not rest:
        rest = [DEFAULT_TYPE]
    type_name = canonical_type(rest[0])
    shape_args = rest[1:]
    if not output:
        if shape_args:
            raise EndpointError(f'{text}: an input takes TOPIC[:TYPE], no shape')
        message_class(type_name)
        return Endpoint(topic, type_name)
    kind = KINDS.get(type_name)
    if kind is None:
        message_class(type_name)          # says whether the type exists at all
        raise EndpointError(f'{type_name}: a workload cannot fill this type; it publishes '
                            f'{", ".join(sorted(KINDS))}')
    try:
        shape = kind.parse(shape_args, default_bytes)
    except EndpointError as e:
        raise EndpointError(f'{text}: {e} (shape of {_short(type_name)}: '
                            f'{kind.shape_help})') from None
    return Endpoint(topic, type_name, shape)


def _count(args: Sequence[str], default: int, what: str, low: int, high: int) -> Tuple[int]:
    if not args:
        return (default,)
    if len(args) > 1:
        raise EndpointError(f'expected one number of {what}, got {":".join(args)!r}')
    try:
        value = int(args[0])
    except ValueError:
        raise EndpointError(f'expected a whole number of {what}, got {args[0]!r}') from None
    if not low <= value <= high:
        raise EndpointError(f'{what}: {value} is out of range [{low}, {high}]')
    return (value,)


def _size(text: str) -> Tuple[int, int]:
    match = re.match(r'^(\d+)x(\d+)$', text)
    if not match:
        raise EndpointError(f'expected WIDTHxHEIGHT, got {text!r}')
    width, height = int(match.group(1)), int(match.group(2))
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise EndpointError(f'{text}: width and height go from 1 to 16384')
    return width, height


def _no_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    if args:
        raise EndpointError(f'this type has a fixed size, got a shape {":".join(args)!r}')
    return ()


def _bytes_shape(args: Sequence[str], default_bytes: Optional[int]) -> tuple:
    default = DEFAULT_BYTES if default_bytes is None else default_bytes
    return _count(args, default, 'bytes', 0, MAX_BYTES)


def _scan_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    return _count(args, 682, 'beams', 1, 100000)


def _image_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    if len(args) > 2:
        raise EndpointError(f'expected WIDTHxHEIGHT[:ENCODING], got {":".join(args)!r}')
    width, height = _size(args[0]) if args else (640, 480)
    encoding = args[1] if len(args) > 1 else 'rgb8'
    if encoding not in ENCODINGS:
        raise EndpointError(f'unknown encoding {encoding!r}'
                            f'{_did_you_mean(encoding, ENCODINGS)}; known: '
                            f'{", ".join(ENCODINGS)}')
    if width * height * ENCODINGS[encoding] > MAX_BYTES:
        raise EndpointError(f'{width}x{height} {encoding} is over {MAX_BYTES} bytes')
    return (width, height, encoding)


def _grid_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    if len(args) > 2:
        raise EndpointError(f'expected WIDTHxHEIGHT[:RESOLUTION_M], got {":".join(args)!r}')
    width, height = _size(args[0]) if args else (200, 200)
    resolution = 0.05
    if len(args) > 1:
        try:
            resolution = float(args[1])
        except ValueError:
            resolution = float('nan')
        if not 0 < resolution < 1000:
            raise EndpointError(f'resolution: expected metres per cell > 0, got {args[1]!r}')
    if width * height > MAX_BYTES:
        raise EndpointError(f'{width}x{height} cells is over {MAX_BYTES}')
    return (width, height, resolution)


def _joints_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    return _count(args, 4, 'joints', 1, 1000)


def _poses_shape(args: Sequence[str], _default_bytes: Optional[int]) -> tuple:
    return _count(args, 4, 'poses', 0, 100000)


# --- content ------------------------------------------------------------------------------------

def _quaternion(msg, yaw: float) -> None:
    msg.z, msg.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _covariance(diagonal: Sequence[float], xy: float = 0.0) -> list:
    """A 6x6 row-major covariance with this diagonal and an x-y correlation term."""
    cov = [0.0] * 36
    for i, v in enumerate(diagonal):
        cov[i * 7] = v
    cov[1] = cov[6] = xy
    return cov


def _uint8_array(shape: tuple):
    from std_msgs.msg import UInt8MultiArray
    return UInt8MultiArray(data=bytes(shape[0]))


def _laser_scan(shape: tuple):
    """A Hokuyo URG-04LX scan (240 degrees, 1024 steps per turn, 0.02-5.6 m, 10 Hz) from
    inside a 6 m x 4 m room, with centimetre noise."""
    from sensor_msgs.msg import LaserScan
    beams = shape[0]
    increment = 2.0 * math.pi / 1024.0
    msg = LaserScan()
    msg.header.frame_id = 'laser'
    msg.angle_increment = increment
    msg.angle_min = -increment * (beams - 1) / 2.0
    msg.angle_max = msg.angle_min + increment * (beams - 1)
    msg.time_increment = 0.1 / 1024.0
    msg.scan_time = 0.1
    msg.range_min, msg.range_max = 0.02, 5.6
    x0, y0, heading = 2.2, 1.6, 0.3          # where the laser is in the room
    ranges = []
    seed = 12345
    for i in range(beams):
        angle = heading + msg.angle_min + i * increment
        dx, dy = math.cos(angle), math.sin(angle)
        hits = ((6.0 - x0) / dx if dx > 1e-9 else math.inf,
                -x0 / dx if dx < -1e-9 else math.inf,
                (4.0 - y0) / dy if dy > 1e-9 else math.inf,
                -y0 / dy if dy < -1e-9 else math.inf)
        seed = (seed * 1103515245 + 12345) & 0x7fffffff
        distance = min(hits) + (seed / 0x7fffffff - 0.5) * 0.02
        ranges.append(distance if distance <= msg.range_max else math.inf)
    msg.ranges = ranges
    return msg


def _image(shape: tuple):
    """A camera frame: a lit wall (a gradient), with a black square marker and its white
    border near the middle, as an AR node looks for."""
    import numpy
    from sensor_msgs.msg import Image
    width, height, encoding = shape
    channels = ENCODINGS[encoding]
    y, x = numpy.mgrid[0:height, 0:width]
    gray = (60 + 120 * x / max(1, width - 1) + 40 * y / max(1, height - 1)).astype(numpy.uint8)
    side = max(2, min(width, height) // 3)
    top, left = (height - side) // 2, (width - side) // 2
    border = max(1, side // 8)
    gray[top:top + side, left:left + side] = 255
    gray[top + border:top + side - border, left + border:left + side - border] = 0
    pixels = numpy.repeat(gray[:, :, None], channels, axis=2)
    msg = Image()
    msg.header.frame_id = 'camera'
    msg.width, msg.height, msg.encoding = width, height, encoding
    msg.is_bigendian = 0
    msg.step = width * channels
    msg.data = pixels.tobytes()
    return msg


def _joint_state(shape: tuple):
    """A youBot base's wheel encoders: four wheels (more joints are named joint_N)."""
    from sensor_msgs.msg import JointState
    wheels = ['wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br']
    joints = shape[0]
    msg = JointState()
    msg.header.frame_id = 'base_link'
    msg.name = (wheels + [f'joint_{i + 1}' for i in range(len(wheels), joints)])[:joints]
    msg.position = [12.5 + 0.7 * i for i in range(joints)]
    msg.velocity = [4.1 if i % 2 else -4.1 for i in range(joints)]
    msg.effort = [0.35 + 0.01 * i for i in range(joints)]
    return msg


def _odometry(shape: tuple):
    """Wheel odometry of a moving base: pose and twist with the usual planar covariances (the
    unobservable z, roll and pitch left large)."""
    from nav_msgs.msg import Odometry
    msg = Odometry()
    msg.header.frame_id = 'odom'
    msg.child_frame_id = 'base_footprint'
    msg.pose.pose.position.x, msg.pose.pose.position.y = 1.84, -0.62
    _quaternion(msg.pose.pose.orientation, 0.42)
    msg.pose.covariance = _covariance([0.001, 0.001, 1e6, 1e6, 1e6, 0.03])
    msg.twist.twist.linear.x = 0.2
    msg.twist.twist.angular.z = 0.05
    msg.twist.covariance = _covariance([0.0005, 0.0005, 1e6, 1e6, 1e6, 0.01])
    return msg


def _pose_with_covariance(shape: tuple):
    """A localisation estimate in the map frame, as AMCL (or RViz's initial pose) sends it."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from .workload_pose import SET_POSE
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = 'map'
    msg.pose.pose.position.x, msg.pose.pose.position.y = SET_POSE[0], SET_POSE[1]
    _quaternion(msg.pose.pose.orientation, SET_POSE[2])
    msg.pose.covariance = _covariance([0.021, 0.018, 0.0, 0.0, 0.0, 0.0068], xy=0.0012)
    return msg


def _pose_array(shape: tuple):
    """Poses of the markers seen in the camera frame (as ros2_aruco's aruco_poses)."""
    from geometry_msgs.msg import Pose, PoseArray
    msg = PoseArray()
    msg.header.frame_id = 'camera'
    poses = []
    for i in range(shape[0]):
        pose = Pose()
        pose.position.x = -0.3 + 0.2 * i
        pose.position.y = 0.05 * (i % 3)
        pose.position.z = 1.2 + 0.15 * i
        _quaternion(pose.orientation, 0.1 * i)
        poses.append(pose)
    msg.poses = poses
    return msg


def _twist(shape: tuple):
    from geometry_msgs.msg import Twist
    msg = Twist()
    msg.linear.x, msg.angular.z = 0.2, 0.15
    return msg


def _occupancy_grid(shape: tuple):
    """A map of a room with a doorway and two obstacles: walls occupied (100), the inside free
    (0), a margin unknown (-1), as map_server serves a saved map."""
    import numpy
    from nav_msgs.msg import OccupancyGrid
    width, height, resolution = shape
    grid = numpy.full((height, width), -1, dtype=numpy.int8)
    margin = max(1, min(width, height) // 20)
    inner = grid[margin:height - margin, margin:width - margin]
    inner[:, :] = 100
    inner[2:-2, 2:-2] = 0
    if inner.shape[0] > 8:
        door = inner.shape[0] // 2
        inner[door - 2:door + 2, -2:] = 0
    h, w = inner.shape
    inner[h // 4:h // 4 + max(1, h // 10), w // 3:w // 3 + max(1, w // 10)] = 100
    inner[h // 2:h // 2 + max(1, h // 8), 2 * w // 3:2 * w // 3 + max(1, w // 12)] = 100
    msg = OccupancyGrid()
    msg.header.frame_id = 'map'
    msg.info.resolution = resolution
    msg.info.width, msg.info.height = width, height
    msg.info.origin.position.x = -width * resolution / 2.0
    msg.info.origin.position.y = -height * resolution / 2.0
    msg.info.origin.orientation.w = 1.0
    msg.data = grid.tobytes()
    return msg


@dataclass(frozen=True)
class MessageKind:
    """How a workload fills one message type."""

    parse: Callable[[Sequence[str], Optional[int]], tuple]
    build: Callable[[tuple], object]
    shape_help: str
    stamped: bool = True        # has a header whose stamp each output refreshes


KINDS: Dict[str, MessageKind] = {
    DEFAULT_TYPE: MessageKind(_bytes_shape, _uint8_array, 'BYTES (default --bytes)', False),
    'sensor_msgs/msg/LaserScan': MessageKind(_scan_shape, _laser_scan, 'BEAMS (682)'),
    'sensor_msgs/msg/Image': MessageKind(_image_shape, _image,
                                         'WIDTHxHEIGHT[:ENCODING] (640x480:rgb8)'),
    'sensor_msgs/msg/JointState': MessageKind(_joints_shape, _joint_state, 'JOINTS (4)'),
    'nav_msgs/msg/Odometry': MessageKind(_no_shape, _odometry, 'none'),
    'nav_msgs/msg/OccupancyGrid': MessageKind(_grid_shape, _occupancy_grid,
                                              'WIDTHxHEIGHT[:RESOLUTION_M] (200x200:0.05)'),
    'geometry_msgs/msg/PoseWithCovarianceStamped': MessageKind(_no_shape, _pose_with_covariance,
                                                               'none'),
    'geometry_msgs/msg/PoseArray': MessageKind(_poses_shape, _pose_array, 'POSES (4)'),
    'geometry_msgs/msg/Twist': MessageKind(_no_shape, _twist, 'none', False),
}


def build_message(endpoint: Endpoint):
    """A message of the endpoint's type and shape, with its content (stamp left at 0)."""
    return KINDS[endpoint.msg_type].build(endpoint.shape)


def stamper(endpoint: Endpoint) -> Optional[Callable[[object, object], None]]:
    """A function (message, stamp) that refreshes the header stamp, or None for a type
    without a header."""
    if not KINDS[endpoint.msg_type].stamped:
        return None

    def stamp(msg, time_msg) -> None:
        msg.header.stamp = time_msg
    return stamp
