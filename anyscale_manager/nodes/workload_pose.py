"""The test-bed's AMCL stand-in carries a real state: the robot's pose, integrated over time.

A ``PoseTrack`` moves a planar pose at a constant speed and turn rate (the robot of the test-bed
drives a circle: what its odometer reports), advanced to the stamp of each output. A copy that
is handed a pose on its restore input continues from it, advanced from that pose's own stamp;
a copy that is not starts from where its own last spell ended (or from the map's origin), and
the pose at the consumer jumps: what the end-to-end tests look for. Pure, no ROS.
"""

import math
from dataclasses import dataclass
from typing import Optional, Tuple

# x, y (m), yaw (rad). A copy that was never handed a pose starts at the map's origin, as AMCL
# does before it is given one; the test-bed's user sets SET_POSE (RViz's initial pose), metres
# away, so a copy that lost a set pose, or started from its own, is metres off the robot.
START = (0.0, 0.0, 0.0)
SET_POSE = (2.21, 1.58, 0.31)


def parse_motion(text: str) -> Tuple[float, float]:
    """'SPEED,TURN' (m/s, rad/s) -> the pair; ValueError naming what is wrong."""
    parts = text.split(',')
    if len(parts) != 2:
        raise ValueError(f'expected SPEED,TURN_RATE (m/s,rad/s), got {text!r}')
    try:
        speed, turn = float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f'expected two numbers, got {text!r}') from None
    if not (math.isfinite(speed) and math.isfinite(turn)) or abs(speed) > 10 or abs(turn) > 10:
        raise ValueError(f'speed and turn rate must be finite, at most 10 in size: {text!r}')
    return speed, turn


@dataclass
class PoseTrack:
    speed_mps: float
    turn_rps: float
    x: float = START[0]
    y: float = START[1]
    yaw: float = START[2]
    stamp_s: Optional[float] = None        # the time the pose holds at (None: not yet)

    def at(self, now_s: float) -> Tuple[float, float, float]:
        """The pose advanced to ``now_s`` (and kept there): exact arcs of the circle."""
        if self.stamp_s is not None and now_s > self.stamp_s:
            dt = now_s - self.stamp_s
            v, w = self.speed_mps, self.turn_rps
            if abs(w) < 1e-9:
                self.x += v * dt * math.cos(self.yaw)
                self.y += v * dt * math.sin(self.yaw)
            else:
                yaw = self.yaw + w * dt
                self.x += v / w * (math.sin(yaw) - math.sin(self.yaw))
                self.y -= v / w * (math.cos(yaw) - math.cos(self.yaw))
                self.yaw = math.atan2(math.sin(yaw), math.cos(yaw))
        if self.stamp_s is None or now_s > self.stamp_s:
            self.stamp_s = now_s
        return self.x, self.y, self.yaw

    def restore(self, x: float, y: float, yaw: float, stamp_s: float) -> None:
        """Continue from a pose that held at ``stamp_s``."""
        self.x, self.y, self.yaw, self.stamp_s = x, y, yaw, stamp_s

    def pause(self) -> None:
        """Inactive: the pose stops where it is (a standby copy tracks nothing)."""
        self.stamp_s = None


def yaw_of(qz: float, qw: float) -> float:
    return 2.0 * math.atan2(qz, qw)


def distance(a: Tuple[float, float], b: Tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
