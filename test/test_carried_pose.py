"""The test-bed's AMCL stand-in carries the robot's pose (nodes/workload_pose.py) and the judge
of a carried state (testbed/poses.py): pure, then one real lifecycle workload over DDS handed a
pose on its restore input before it is activated."""

import math

import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from anyscale_manager.model.loader import load_deployment
from anyscale_manager.nodes.workload import parse_spec, set_pose
from anyscale_manager.nodes.workload_pose import parse_motion, PoseTrack, SET_POSE, START, yaw_of
from anyscale_manager.testbed.poses import (pose_jumps, pose_motion, pose_speed, record_jumps,
                                            SET_SETTLE_S)
from anyscale_manager.testbed.record import Record
from conftest import TESTBED
from test_workload import (_start, _stop, ACTIVATE, CONFIGURE, LifecycleProbe, scale_remaps)

POSE = 'geometry_msgs/msg/PoseWithCovarianceStamped'


def test_the_pose_moves_along_exact_arcs_and_holds_still_while_paused():
    track = PoseTrack(0.2, 0.05)
    assert track.at(10.0) == START                      # the first output: the start pose
    x, y, yaw = track.at(20.0)
    chord = math.hypot(x - START[0], y - START[1])
    assert chord == pytest.approx(8.0 * math.sin(0.25))  # an arc of 2 m on a 4-m circle
    assert yaw == pytest.approx(START[2] + 0.5)
    track.pause()
    assert track.at(100.0) == (x, y, yaw)               # inactive: it tracked nothing
    track.restore(1.0, 2.0, 0.0, 200.0)
    x, y, _ = track.at(201.0)
    assert math.hypot(x - 1.0, y - 2.0) == pytest.approx(0.2, abs=1e-3)


@pytest.mark.parametrize('text', ['0.2', 'a,b', '1e9,0', 'nan,0'])
def test_a_bad_motion_is_refused_with_its_reason(text):
    with pytest.raises(ValueError):
        parse_motion(text)


def test_pose_options_are_checked_together(capsys):
    spec = parse_spec(['--name', 'amcl', '--sub', '/scan', '--pub', f'/amcl_pose:{POSE}',
                       '--pose-motion', '0.2,0.05', '--restore', '/initialpose'])
    assert spec.pose_motion == (0.2, 0.05) and spec.restore == '/initialpose'
    for argv, words in ((['--pub', '/x', '--pose-motion', '0.2,0'], 'has none'),
                        (['--pub', f'/x:{POSE}', '--restore', '/y'], '--pose-motion too')):
        with pytest.raises(SystemExit):
            parse_spec(['--name', 'n', *argv])
        assert words in capsys.readouterr().err


def test_the_judge_finds_a_jump_and_passes_a_continued_pose():
    track = PoseTrack(0.2, 0.05)
    heard = []
    for i in range(50):                                  # one copy at 5 Hz
        x, y, _ = track.at(100.0 + i * 0.2)
        heard.append((i * 0.2, x, y, 100.0 + i * 0.2))
    handed = PoseTrack(0.2, 0.05)                        # the copy that took over, 0.6 s later
    handed.restore(heard[-1][1], heard[-1][2], track.yaw, heard[-1][3])
    x, y, _ = handed.at(100.0 + 49 * 0.2 + 0.6)
    continued = heard + [(49 * 0.2 + 0.6, x, y, 100.0 + 49 * 0.2 + 0.6)]
    assert pose_jumps(continued, 0.0, 100.0, 0.2) == []
    fresh = heard + [(49 * 0.2 + 0.6, START[0], START[1], 100.0 + 49 * 0.2 + 0.6)]
    jumps = pose_jumps(fresh, 0.0, 100.0, 0.2)
    assert len(jumps) == 1 and jumps[0].distance_m > 1.5, jumps
    assert pose_speed(['--x', '--pose-motion', '0.25,0.1']) == 0.25


def _heard(start_s, stamps, late_s=0.0, start=START):
    """(arrival, x, y, stamp, yaw) of the outputs at ``stamps`` of a copy on the track that left
    ``start`` at ``start_s`` (arrivals ``late_s`` after their stamps, on another clock)."""
    out = []
    for stamp in stamps:
        track = PoseTrack(0.2, 0.05, *start, stamp_s=start_s)
        x, y, yaw = track.at(stamp)
        out.append((stamp - 100.0 + late_s, x, y, stamp, yaw))
    return out


def test_a_pose_a_user_set_is_no_jump_but_two_copies_on_two_other_states_are():
    """A user sets the robot's pose on /initialpose 1.9 s after AMCL began (the test-bed's user
    is up after the laser), in a move's overlap: the laptop's copy takes it at once, the
    robot's 0.4 s later, both handed it by their agents. The pose jumps 2.7 m, as asked, and
    the robot's copy goes on along the old track for a moment: no jump. A copy that serves from
    its own start pose beside the laptop's, 0.5 s after the pose was set, jumps at each turn."""
    set_at = 101.9
    set_pose = (set_at - 100.0, *SET_POSE[:2], set_at, SET_POSE[2])
    laptop = _heard(100.0, [100.0 + 0.2 * i for i in range(10)]) \
        + _heard(set_at, [102.0 + 0.2 * i for i in range(10)], start=SET_POSE)
    robot = _heard(100.0, [100.1 + 0.2 * i for i in range(12)], 0.01) \
        + _heard(set_at, [102.5], 0.01, start=SET_POSE)
    heard = laptop + robot
    assert len(pose_jumps(heard, 0.0, 100.0, 0.2)) >= 4          # read as jumps without it
    assert pose_jumps(heard, 0.0, 100.0, 0.2, set_poses=[set_pose], turn_rps=0.05) == []
    own = laptop + _heard(102.4, [102.5 + 0.2 * i for i in range(4)], 0.01)
    jumps = pose_jumps(own, 0.0, 100.0, 0.2, set_poses=[set_pose], turn_rps=0.05)
    assert len(jumps) >= 4, jumps
    # ... as does one from its own start pose seconds later, handed nothing.
    late = laptop + _heard(104.5, [104.5])
    assert len(pose_jumps(late, 0.0, 100.0, 0.2, set_poses=[set_pose], turn_rps=0.05)) == 1
    assert pose_motion(['--pose-motion', '-0.2,0.05']) == (-0.2, 0.05)


def test_a_pose_set_that_no_copy_keeps_is_lost_and_said_once_settled():
    """The serving copy stands down before it takes a pose the user set, and the copy taking
    over is handed its output from before: the stream goes on along the old track, with no
    jump. Past SET_SETTLE_S every copy is on the set pose's track, so this one is said (once),
    and a copy that took it is not."""
    set_at = 101.9
    set_pose = (set_at - 100.0, *SET_POSE[:2], set_at, SET_POSE[2])
    old_track = _heard(100.0, [100.0 + 0.2 * i for i in range(30)])
    assert pose_jumps(old_track, 0.0, 100.0, 0.2, turn_rps=0.05) == []
    lost = pose_jumps(old_track, 0.0, 100.0, 0.2, set_poses=[set_pose], turn_rps=0.05)
    assert len(lost) == 1 and lost[0].off_set and lost[0].distance_m > 2.0, lost
    assert 'off the track of the pose set' in str(lost[0])
    assert lost[0].gap_s > SET_SETTLE_S
    taken = _heard(100.0, [100.0 + 0.2 * i for i in range(10)]) \
        + _heard(set_at, [102.0 + 0.2 * i for i in range(20)], start=SET_POSE)
    assert pose_jumps(taken, 0.0, 100.0, 0.2, set_poses=[set_pose], turn_rps=0.05) == []


def test_a_pose_set_at_the_start_of_the_judged_window_is_judged_with_the_track_it_left():
    """A soak judges from its schedule's start, and the test-bed's user set the start pose
    just before it, in a move's overlap: the robot's copy went on along the old track for a
    moment. That track began before the window; the judge reads it as what came before, else
    each turn between the two copies reads as a jump (a CI soak: 0.09 m at 0.45 s)."""
    set_at = 101.9
    set_pose = (set_at - 100.0, *SET_POSE[:2], set_at, SET_POSE[2])
    laptop = _heard(100.0, [100.0 + 0.2 * i for i in range(10)]) \
        + _heard(set_at, [102.0 + 0.2 * i for i in range(10)], start=SET_POSE)
    robot = _heard(100.0, [100.1 + 0.2 * i for i in range(13)], 0.01)
    start = set_at - 100.0 + 0.05          # the window opens just after the pose was set
    assert pose_jumps(laptop + robot, start, 100.0, 0.2, set_poses=[set_pose],
                      turn_rps=0.05) == []
    # Poses before the window are context, never judged themselves.
    assert pose_jumps(_heard(100.0, [100.0]) + _heard(99.0, [101.0]) + robot[-3:], 1.5,
                      100.0, 0.2, turn_rps=0.05) == []


def test_the_record_keeps_the_poses_a_user_set_and_the_judge_reads_them():
    """The observer's lines as the record takes them: AMCL's poses (with their yaw, or without
    from an older observer) and the poses set on its restore topic, /initialpose."""
    record = Record(load_deployment(TESTBED))
    set_pose = (1.9, *SET_POSE[:2], 101.9, SET_POSE[2])
    record.ingest({'t': 2.0, 'set_poses': {'/initialpose': [list(set_pose), [1.0, 2.0]]}})
    heard = _heard(100.0, [100.0 + 0.2 * i for i in range(10)]) \
        + _heard(101.9, [102.0 + 0.2 * i for i in range(10)], start=SET_POSE)
    record.ingest({'t': 5.0, 'poses': {'/amcl_pose': [list(p) for p in heard]}})
    assert record.set_poses == {'/initialpose': [set_pose]}
    assert len(record.poses['/amcl_pose']) == 20
    assert record_jumps(record, 0.0, 100.0) == {'/amcl_pose': []}
    record.set_poses.clear()
    assert len(record_jumps(record, 0.0, 100.0)['/amcl_pose']) == 1
    record.ingest({'t': 6.0, 'poses': {'/amcl_pose': [[5.5, 1.0, 1.0, 105.5]]}})
    assert record.poses['/amcl_pose'][-1] == (5.5, 1.0, 1.0, 105.5)


def test_a_lifecycle_stand_in_continues_from_a_pose_handed_while_inactive(python, ros_env):
    proc = _start(python, ros_env, '--name', 'pose_lc', '--sub', '/pose_lc_in', '--pub',
                  f'/pose_lc_out:{POSE}', '--rate-hz', '20', '--lifecycle', '--pose-motion',
                  '0.2,0.05', '--restore', '/pose_lc_restore', *scale_remaps('robot'))
    probe = LifecycleProbe([], feed='/pose_lc_in')
    poses = []
    probe.node.create_subscription(PoseWithCovarianceStamped, '/pose_lc_out',
                                   lambda m: poses.append(m), 10)
    writer = probe.node.create_publisher(
        PoseWithCovarianceStamped, '/pose_lc_restore',
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    robot = '/pose_lc/robot'
    try:
        assert probe.change(robot, CONFIGURE)
        probe.spin_until(lambda: writer.get_subscription_count() == 1, 10.0,
                         'the restore input of the inactive copy')
        handed = PoseWithCovarianceStamped()
        handed.header.frame_id = 'map'
        handed.header.stamp = probe.node.get_clock().now().to_msg()
        set_pose(handed, -3.0, 4.0, 1.0)
        writer.publish(handed)
        probe.spin_until(lambda: writer.wait_for_all_acked(), 5.0, 'the hand-over taken')
        assert probe.change(robot, ACTIVATE)
        probe.spin_until(lambda: len(poses) >= 3, 15.0, 'three poses of the active copy')
        first = poses[0].pose.pose
        assert math.hypot(first.position.x + 3.0, first.position.y - 4.0) < 0.5, first
        assert yaw_of(first.orientation.z, first.orientation.w) == pytest.approx(1.0, abs=0.1)
    finally:
        probe.close()
        code = _stop(proc)
        log = proc.stdout.read()
        print(log)
    assert code == 0, log
    assert 'restored: pose (-3.000, 4.000)' in log, log
