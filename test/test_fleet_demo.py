"""`demo --fleet`'s pure parts (anyscale_manager/testbed/fleet_demo.py): its schedule, its
judges of a run (over-commit, moves, Δ) and its figure, on records built here; its refusals of
bad input through the command. The live fleet in namespaces is test_fleet_netns.py's."""

import dataclasses
import json
import os

import pytest

from anyscale_manager.cli import main
from anyscale_manager.testbed.fleet import FleetShape, HOME, SERVER
from anyscale_manager.testbed.fleet_demo import (FLEET_SCHEDULE, draw_fleet_timeline,
                                                 event_lines, moves, over_commit_s,
                                                 parse_fleet_schedule, robot_summary)
from anyscale_manager.testbed.fleet_record import (OVER_SPAN_S, FleetRecord, FleetSample,
                                                   over_capacity)

SHAPE = FleetShape()


def test_the_default_schedule_starts_a_cuts_and_restores_its_link_then_b_with_priority():
    steps = parse_fleet_schedule(FLEET_SCHEDULE)
    assert [(s.at_s, s.action, s.robot, s.priority) for s in steps] == [
        (0.0, 'start', 'robot_a', 0), (25.0, 'cut', 'robot_a', 0),
        (40.0, 'restore', 'robot_a', 0), (60.0, 'start', 'robot_b', 1)]


@pytest.mark.parametrize('text, says', [
    ('0:start@robot_c', "unknown robot 'robot_c'"),
    ('x:start@robot_a', "'x' is not a time"),
    ('-1:start@robot_a', 'T >= 0'),
    ('0:jump@robot_a', "unknown action 'jump'"),
    ('0:cut=2@robot_a', "unknown action 'cut=2'"),
    ('0:start=high@robot_a', "priority 'high'"),
    ('0:start@robot_a,5:start@robot_a', 'starts twice'),
    ('0:start@robot_a,5:cut@robot_b', 'robot_b has not started'),
    ('0:start@robot_a,5:restore@robot_a', 'already up'),
    ('0:start@robot_a,5:cut@robot_a,6:cut@robot_a', 'already cut'),
    ('', 'starts no robot'),
])
def test_a_bad_schedule_is_refused_with_the_step_named(text, says):
    with pytest.raises(ValueError, match=says):
        parse_fleet_schedule(text)


def sample(t, a_home=0, a_away=0, b_home=0, b_away=0, a_up=True, claims=None):
    return FleetSample(t, {'robot_a': {HOME: a_home, SERVER: a_away},
                           'robot_b': {HOME: b_home, SERVER: b_away}},
                       {'robot_a': a_up, 'robot_b': True}, claims or {},
                       {'robot_a': ('worker',) * a_away, 'robot_b': ('worker',) * b_away},
                       {'robot_a': SHAPE.worker_cpu * a_away,
                        'robot_b': SHAPE.worker_cpu * b_away})


def test_over_commit_counts_the_time_two_were_on_the_server_or_claims_above_capacity():
    """Claims above capacity count at once; lifecycle copies serving above it once seen so for
    OVER_SPAN_S (the serving judge's resolution: fleet_record.over_capacity), plain ones at
    once."""
    samples = [sample(0.0, a_away=1, claims={'robot_a': 60.0}),
               sample(1.0, a_away=1, b_away=1, claims={'robot_a': 60.0}),
               sample(1.5, a_away=1, claims={'robot_a': 60.0, 'robot_b': 60.0}),
               sample(2.5, b_away=1, claims={'robot_b': 60.0}),
               sample(3.0, a_away=1, b_away=1, claims={'robot_b': 60.0}),
               sample(3.5, a_away=1, b_away=1, claims={'robot_b': 60.0}),
               sample(4.0, b_away=1, claims={'robot_b': 60.0})]
    icar, worker = (dataclasses.replace(SHAPE, graph=g) for g in ('icar', 'worker'))
    assert over_commit_s(samples, icar) == pytest.approx(1.0 + 0.5)
    assert over_commit_s(samples, worker) == pytest.approx(0.5 + 1.0 + 0.5 + 0.5)
    assert over_commit_s(samples[3:5], icar) == 0.0
    # Every 0.2 s, as the fleet test samples: a copy deactivated a moment ago is seen serving in
    # two samples; four in a row (0.6 s) are an over-commit.
    every = [sample(0.2 * k, a_away=1, b_away=int(2 <= k <= 3 or 6 <= k <= 9),
                    claims={'robot_a': 60.0}) for k in range(12)]
    assert over_capacity(every, SHAPE.capacity_cpu, lifecycle=True) == every[9:10]
    assert OVER_SPAN_S == pytest.approx(0.5)


def test_moves_pass_through_both_and_none():
    samples = [sample(0.0, a_home=1), sample(1.0, a_home=1, a_away=1), sample(2.0, a_away=1),
               sample(3.0), sample(4.0, a_home=1)]
    assert moves(samples, 'robot_a') == [(2.0, HOME, SERVER), (4.0, SERVER, HOME)]
    assert moves(samples, 'robot_b') == []


def fed(record, robot, times):
    record.ingest_line(robot, '{"t": 0.0, "ready": true}')
    record.ingest_line(robot, '{"t": %f, "arrivals": {"/%s/w": [%s]}}'
                       % (times[-1], robot, ', '.join(f'{t:.3f}' for t in times)))


def test_a_robots_summary_counts_a_silence_past_its_delta_from_its_first_message():
    record = FleetRecord(0.0)
    # 10 Hz from 2 s to 20 s with a silence of 7 s (Δ 5 s) from 8 s.
    times = [2.0 + 0.1 * k for k in range(181) if not 8.0 < 2.0 + 0.1 * k < 15.0]
    fed(record, 'robot_a', times)
    for t in (0.0, 5.0, 10.0, 16.0):
        record.add(sample(t, a_home=1 if t != 5.0 else 0, a_away=1 if t == 5.0 else 0))
    row = robot_summary(record, 'robot_a', SHAPE, 0.0, 20.0)
    assert row['delta_violations'] == 1 and row['longest_below_s'] == pytest.approx(7.0, 0.05)
    assert row['moves'] == [{'at_s': 5.0, 'from': HOME, 'to': SERVER},
                            {'at_s': 10.0, 'from': SERVER, 'to': HOME}]
    assert robot_summary(record, 'robot_b', SHAPE, 0.0, 20.0)['delta_violations'] is None


def test_the_figure_and_the_event_log_are_written(tmp_path):
    record = FleetRecord(0.0)
    fed(record, 'robot_a', [0.5 + 0.1 * k for k in range(300)])
    for k in range(120):
        t = 0.25 * k
        away = 10.0 <= t < 20.0
        record.add(sample(t, a_home=int(not away), a_away=int(away), a_up=not 15 <= t < 25,
                          claims={'robot_a': 60.0} if away else {}))
    record.mark(0.0, 'robot_a started (priority 0, ROS domain 3)')
    record.mark(15.0, 'link_a cut')
    path = draw_fleet_timeline(record, str(tmp_path / 'timeline.png'), ('robot_a', 'robot_b'),
                               SHAPE, 0.0, 30.0)
    assert os.path.getsize(path) > 20000
    lines = event_lines(record, ('robot_a', 'robot_b'), 0.0, 30.0)
    assert lines == ['   0.00  robot_a started (priority 0, ROS domain 3)',
                     '  10.00  robot_a: worker home -> away', '  15.00  link_a cut',
                     '  20.00  robot_a: worker away -> home']


@pytest.mark.parametrize('argv, says', [
    (['--schedule', '0:start@robot_z'], "unknown robot 'robot_z'"),
    (['--duration', '30'], 'past the run'),
    (['--three-scales'], 'leave out --three-scales'),
    (['--duration', '-4'], 'between 0 and 86400'),
    (['--domain-id', '240'], 'out of range 0..232'),
])
def test_demo_fleet_refuses_bad_input_with_exit_2(argv, says, capsys, tmp_path):
    assert main(['demo', '--fleet', '--out', str(tmp_path / 'out'), *argv]) == 2
    assert says in capsys.readouterr().err
    assert not os.path.exists(tmp_path / 'out')


def test_graph_without_fleet_is_refused_with_exit_2(capsys, tmp_path):
    assert main(['demo', '--graph', 'worker', '--out', str(tmp_path / 'out')]) == 2
    assert '--graph is what each robot of --fleet runs' in capsys.readouterr().err
    assert not os.path.exists(tmp_path / 'out')


def test_an_icar_robots_summary_judges_each_connection():
    """The ICAR graph: every connection the robot's observer hears is judged apart; one
    silent past its Δ (amcl_ekf: 2 s) is named, the others hold."""
    shape = FleetShape(graph='icar')
    record = FleetRecord(0.0)
    record.ingest_line('robot_a', '{"t": 0.0, "ready": true}')
    fast = [1.0 + 0.01 * k for k in range(1900)]
    arrivals = {'/scan': fast, '/wheel_ticks': fast, '/odom': fast, '/pose': fast,
                '/markers': fast,
                '/amcl_pose': [t for t in fast if not 5.0 < t < 9.0]}
    record.ingest_line('robot_a', json.dumps({'t': 20.0, 'arrivals': arrivals}))
    row = robot_summary(record, 'robot_a', shape, 0.0, 19.0)
    assert set(row['connections']) == {'laser_navigation', 'odometer_odometry', 'amcl_ekf',
                                       'odometry_ekf', 'ekf_navigation', 'ar_navigation'}
    assert row['delta_violations'] == 1
    assert row['connections']['amcl_ekf']['delta_violations'] == 1
    assert 3.0 < row['connections']['amcl_ekf']['longest_below_s'] <= 4.0
    assert row['connections']['odometry_ekf']['delta_violations'] == 0
