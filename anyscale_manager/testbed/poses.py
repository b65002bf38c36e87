"""The judge of a carried state: a pose (the test-bed's AMCL stand-in's /amcl_pose, heard by the
harness's own observer) never jumps by more than the robot moved in between.

Between two consecutive poses heard, the robot moved at most ``speed_mps`` times the time
between their stamps (or their arrivals, the larger): a copy that took over with the last copy's
pose continues within that; one that started from its own (the start pose, or where its own last
spell ended) jumps by metres. Pure.
"""

import math
from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

SLACK_M = 0.05          # rounding, and a chord a little shorter than its arc


@dataclass(frozen=True)
class Jump:
    t: float                  # the arrival of the pose after the jump
    distance_m: float
    allowed_m: float
    gap_s: float

    def __str__(self) -> str:
        return (f'{self.distance_m:.2f} m in {self.gap_s:.2f} s at t={self.t:.2f} '
                f'(at most {self.allowed_m:.2f} m)')


def pose_jumps(poses: Sequence[Tuple[float, float, float, float]], start: float, end: float,
               speed_mps: float, slack_m: float = SLACK_M) -> List[Jump]:
    """Each jump between consecutive poses (arrival, x, y, stamp) arrived within
    [start, end]."""
    out = []
    heard = sorted(p for p in poses if start <= p[0] <= end)
    for (t0, x0, y0, s0), (t1, x1, y1, s1) in zip(heard, heard[1:]):
        gap = max(abs(s1 - s0), t1 - t0)
        allowed = speed_mps * gap + slack_m
        distance = math.hypot(x1 - x0, y1 - y0)
        if distance > allowed:
            out.append(Jump(t1, distance, allowed, gap))
    return out


def pose_speed(node_arguments: Sequence[str]) -> float:
    """The speed a stand-in's ``--pose-motion SPEED,TURN`` gives its robot (m/s)."""
    args = list(node_arguments)
    if '--pose-motion' not in args:
        raise ValueError('the node has no --pose-motion: no pose to judge')
    return abs(float(args[args.index('--pose-motion') + 1].split(',')[0]))


def record_jumps(record, start: float, end: float) -> Dict[str, List[Jump]]:
    """Every jump of each stateful node's pose that ``record``'s observer heard in [start, end]
    (state topic -> its jumps)."""
    d = record.deployment
    out = {}
    for n in d.nodes:
        if n.state is None or n.state.topic not in record.poses:
            continue
        out[n.state.topic] = pose_jumps(record.poses[n.state.topic], start, end,
                                        pose_speed(n.launch.arguments))
    return out
