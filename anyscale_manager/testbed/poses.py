"""The judge of a carried state: a pose (the test-bed's AMCL stand-in's /amcl_pose, heard by the
harness's own observer) never jumps by more than the robot moved in between.

Between two consecutive poses heard, the robot moved at most ``speed_mps`` times the time
between their stamps (or their arrivals, the larger): a copy that took over with the last copy's
pose continues within that; one that started from its own (the start pose, or where its own last
spell ended) jumps by metres. A pose someone set on the node's restore topic (a user's initial
pose, which the agents hand to the copies serving) is a jump asked for: within ``SET_SETTLE_S``
of its stamp, a pose exactly on its track (a copy that took it) is no jump, nor one exactly on
the track it left (a copy serving beside it, in a move's overlap, that has not taken it yet).
A copy serving from its own state beside them still jumps at each turn. Pure.
"""

import math
from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

from ..nodes.workload_pose import PoseTrack, parse_motion

SLACK_M = 0.05          # rounding, and a chord a little shorter than its arc
# A pose set on the restore topic reaches each copy serving within this: its agent hands it on
# at its next step, and a busy robot's copy took it 0.5 s after it was set.
SET_SETTLE_S = 2.0

# (arrival, x, y, stamp, yaw); a heard pose may come without its yaw (an older observer's).
Pose = Tuple[float, ...]


@dataclass(frozen=True)
class Jump:
    t: float                  # the arrival of the pose after the jump
    distance_m: float
    allowed_m: float
    gap_s: float
    # A pose off the track of the last pose set, past SET_SETTLE_S after it (gap_s: since it
    # was set): what was set was lost.
    off_set: bool = False

    @property
    def too_far(self) -> bool:
        return self.distance_m > self.allowed_m

    def __str__(self) -> str:
        if self.off_set:
            return (f'{self.distance_m:.2f} m off the track of the pose set {self.gap_s:.2f} s '
                    f'before, at t={self.t:.2f}')
        return (f'{self.distance_m:.2f} m in {self.gap_s:.2f} s at t={self.t:.2f} '
                f'(at most {self.allowed_m:.2f} m)')


def _jump(p0: Pose, p1: Pose, speed_mps: float, slack_m: float) -> Jump:
    """p0 to p1 measured against how far the robot could move in between (a Jump either way)."""
    gap = max(abs(p1[3] - p0[3]), p1[0] - p0[0])
    return Jump(p1[0], math.hypot(p1[1] - p0[1], p1[2] - p0[2]),
                abs(speed_mps) * gap + slack_m, gap)


def _on_track(p: Pose, anchor: Pose, speed_mps: float, turn_rps: float,
              slack_m: float) -> bool:
    """Whether ``p`` is where a copy that had ``anchor`` (with its yaw) would be at p's
    stamp."""
    return p[3] >= anchor[3] and _off_track_m(p, anchor, speed_mps, turn_rps) <= slack_m


def _off_track_m(p: Pose, anchor: Pose, speed_mps: float, turn_rps: float) -> float:
    """How far ``p`` is from where a copy that had ``anchor`` would be at p's stamp."""
    _, x, y, stamp, yaw = anchor[:5]
    px, py, _ = PoseTrack(speed_mps, turn_rps, x, y, yaw, stamp).at(p[3])
    return math.hypot(p[1] - px, p[2] - py)


def _same_track(a: Pose, b: Pose, speed_mps: float, turn_rps: float, slack_m: float) -> bool:
    """Whether the later of two poses is where the earlier one's track leads."""
    early, late = sorted((a, b), key=lambda p: p[3])
    return len(early) > 4 and _on_track(late, early, speed_mps, turn_rps, slack_m)


def pose_jumps(poses: Sequence[Pose], start: float, end: float, speed_mps: float,
               slack_m: float = SLACK_M, set_poses: Sequence[Pose] = (),
               turn_rps: float = 0.0, settle_s: float = SET_SETTLE_S) -> List[Jump]:
    """Each jump between consecutive poses (arrival, x, y, stamp[, yaw]) arrived within
    [start, end]. ``set_poses``: the poses set on the node's restore topic (arrival, x, y,
    stamp, yaw); a track is followed at ``speed_mps`` (signed) and ``turn_rps``. The poses
    heard before ``start`` are read too, as what came before (the track a pose set at the
    window's start left), and not judged themselves."""
    out = []
    heard = sorted(p for p in poses if p[0] <= end)
    set_sorted = sorted(set_poses, key=lambda u: u[3])
    before = None             # the latest pose of the track the set pose left
    was_off = False
    for i, p1 in enumerate(heard):
        recent = [u for u in set_sorted if 0.0 <= p1[3] - u[3] <= settle_s]
        on = any(_on_track(p1, u, speed_mps, turn_rps, slack_m) for u in recent)
        # A copy yet to take the set pose goes on along the track it left, for a moment.
        behind = bool(recent) and not on and before is not None \
            and _same_track(before, p1, speed_mps, turn_rps, slack_m)
        jumped = False
        if i and p1[0] >= start:
            jump = _jump(heard[i - 1], p1, speed_mps, slack_m)
            jumped = jump.too_far and not on and not behind
            if jumped:
                out.append(jump)
        # Once settled, every copy serves on the track of the last pose set: one off it lost
        # what was set (said once per stretch off it).
        last_set = [u for u in set_sorted if u[3] <= p1[3]]
        off = False
        if last_set and not recent and len(last_set[-1]) > 4:
            off_m = _off_track_m(p1, last_set[-1], speed_mps, turn_rps)
            off = off_m > slack_m
            if off and not was_off and not jumped and p1[0] >= start:
                out.append(Jump(p1[0], off_m, slack_m, p1[3] - last_set[-1][3], off_set=True))
        was_off = off
        if behind or not (on or recent):
            before = p1
    return out


def pose_motion(node_arguments: Sequence[str]) -> Tuple[float, float]:
    """(speed m/s, turn rad/s) of a stand-in's ``--pose-motion SPEED,TURN``."""
    args = list(node_arguments)
    if '--pose-motion' not in args:
        raise ValueError('the node has no --pose-motion: no pose to judge')
    return parse_motion(args[args.index('--pose-motion') + 1])


def pose_speed(node_arguments: Sequence[str]) -> float:
    """The speed a stand-in's ``--pose-motion SPEED,TURN`` gives its robot (m/s)."""
    return abs(pose_motion(node_arguments)[0])


def record_jumps(record, start: float, end: float) -> Dict[str, List[Jump]]:
    """Every jump of each stateful node's pose that ``record``'s observer heard in [start, end]
    (state topic -> its jumps), a jump to a pose set on its restore topic aside."""
    d = record.deployment
    out = {}
    for n in d.nodes:
        if n.state is None or n.state.topic not in record.poses:
            continue
        speed, turn = pose_motion(n.launch.arguments)
        out[n.state.topic] = pose_jumps(record.poses[n.state.topic], start, end, speed,
                                        set_poses=record.set_poses.get(n.state.restore, ()),
                                        turn_rps=turn)
    return out
