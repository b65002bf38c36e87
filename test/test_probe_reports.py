"""What the probes send: readings on a change, else a refresh (ProbeManager, probes.moved).
The pure rule, then a real publisher and a real reader over DDS (loopback only)."""

import dataclasses

import pytest
from std_msgs.msg import String

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.nodes.monitors import STATUS_QOS, ProbeManager
from anyscale_manager.nodes.monitors.common import connection_status_refresh_s, refresh_s
from anyscale_manager.nodes.monitors.probes import moved
from anyscale_manager.nodes.workload_messages import build_message, parse_endpoint

pytestmark = pytest.mark.timeout(60)

STEADY = p.ConnectionReading(rate_hz=10.0, bytes_per_s=1000.0, below_for_s=0.0, level=p.OK,
                             ended_below_s=0.0, recent_bytes_per_s=1000.0)


def with_(**changes):
    return {'c': dataclasses.replace(STEADY, **changes)}


def test_nothing_sent_yet_or_another_set_of_connections_is_a_change():
    assert moved(None, with_())
    assert moved(with_(), {'c': STEADY, 'd': STEADY})
    assert moved({'c': STEADY, 'd': STEADY}, with_())


def test_a_steady_reading_and_small_moves_are_no_change():
    assert not moved(with_(), with_())
    assert not moved(with_(), with_(rate_hz=11.0, bytes_per_s=1200.0, recent_bytes_per_s=800.0))
    # A stretch below that goes on: its readers time it from its start.
    assert not moved(with_(level=p.WARN, below_for_s=0.5),
                     with_(level=p.WARN, below_for_s=1.0, rate_hz=9.0))


@pytest.mark.parametrize('changes', [
    {'level': p.WARN}, {'ended_below_s': 0.3}, {'senders': 2}, {'rate_hz': 7.0},
    {'bytes_per_s': 1300.0}, {'recent_bytes_per_s': 0.0}, {'recent_bytes_per_s': None},
    {'rate_hz': 0.0, 'bytes_per_s': 0.0}])
def test_what_a_reader_acts_on_is_a_change(changes):
    assert moved(with_(), with_(**changes))


def test_a_figure_from_nothing_is_a_change():
    assert moved(with_(rate_hz=0.0), with_(rate_hz=0.1))
    assert moved(with_(senders=2, senders_for_s=0.0), with_(senders=2, senders_for_s=0.4))


def test_two_senders_at_once_go_out_at_every_reading():
    # The decider judges how long two writers overlap by the reading itself.
    assert moved(with_(senders=2, senders_for_s=0.4), with_(senders=2, senders_for_s=0.5))
    assert moved(with_(senders=2, senders_for_s=0.4), with_(senders=1, senders_for_s=0.0))


@pytest.mark.parametrize('scale', ['robot', 'laptop'])
def test_a_steady_topic_is_reported_at_the_refresh_and_its_stop_at_once(
        ros, testbed_path, scale):
    """On the master (robot) the readings go out on a change, else at the refresh; on a remote
    scale (laptop) every one: its readings are a link's delivery evidence at the far end."""
    d = load_deployment(testbed_path)
    d = dataclasses.replace(d, monitoring=dataclasses.replace(
        d.monitoring, probe_window_s=1.0, probe_publish_rate_hz=10.0))
    refresh = refresh_s(d, 0.1)
    assert refresh >= 0.5, refresh           # the file's observation_max_age_s: 2 s
    make = ros.node
    got = []
    make('listener').create_subscription(
        String, p.TOPIC_CONNECTION_STATUS,
        lambda m: got.append(p.ConnectionStatus.from_json(m.data)), STATUS_QOS)
    probes = ProbeManager(make('agent_reports'), d, scale)
    probes.set_connections(['laser_amcl'])
    node = make('laser')
    msg = build_message(parse_endpoint('/scan:sensor_msgs/msg/LaserScan:682', True))
    pub = node.create_publisher(type(msg), '/scan', 10)
    timer = node.create_timer(0.05, lambda: pub.publish(msg))
    taken = []              # every reading the probes took, sent or not

    def took():
        last = probes.last
        if last is not None and (not taken or taken[-1] is not last):
            taken.append(last)
        return last

    def steady():
        took()
        r = got[-1].connections.get('laser_amcl') if got else None
        return r is not None and r.level == p.OK and abs(r.rate_hz - 20.0) < 2.0
    ros.spin_until(steady, 15.0, 'a steady 20 Hz reading')
    sent_before, taken_before = len(got), len(taken)
    ros.spin_until(lambda: took() and len(taken) - taken_before >= 30, 10.0, '30 readings')
    sent = len(got) - sent_before
    if scale == 'robot':
        # 30 readings of a steady topic over about 3 s: a refresh every `refresh` s, and a
        # figure that moved by a quarter now and then at most.
        assert 1 <= sent <= 3.0 / refresh + 3, (sent, refresh)
    else:
        assert sent >= 28, sent             # every reading (two may still be on their way)

    node.destroy_timer(timer)
    ros.spin_until(lambda: took() and took().connections['laser_amcl'].level != p.OK, 10.0,
                   'a reading below freq_min')
    first_below = next(m for m in taken if m.connections['laser_amcl'].level != p.OK)
    ros.spin_until(lambda: any(m.stamp == first_below.stamp for m in got), 2.0,
                   'the first reading below sent at once')
    probes.destroy()


def test_what_the_steps_take_between_two_drains_counts_at_the_next_not_as_a_peak(
        ros, testbed_path, monkeypatch):
    """The agent's steps take the watched topics' messages at any moment (poll_writers); a
    step 55 ms after the last drain that finds three messages of a 40 Hz topic (delivery
    jitter) is no 54 Hz peak: they count with the next timed drain's, over its whole span."""
    from types import SimpleNamespace
    from anyscale_manager.nodes.monitors import probes as probes_module
    clock = [1000.0]
    monkeypatch.setattr(probes_module, 'time', SimpleNamespace(
        monotonic=lambda: clock[0], time=lambda: 1.7e9 + clock[0]))
    inbox = []

    def taken(_subscription, limit):
        while inbox and limit > 0:
            limit -= 1
            yield inbox.pop(0)
    monkeypatch.setattr(probes_module, '_taken', taken)
    d = load_deployment(testbed_path)
    probes = ProbeManager(ros.node('agent_peaks'), d, 'robot', handovers=True)
    probes.set_connections(['amcl_ekf'])                  # AMCL is migratable: watched
    probe = probes._topics['/amcl_pose']
    assert probe.watched
    seq = [0]

    def arrive(count):
        for _ in range(count):
            seq[0] += 1
            inbox.append((b'pose', {'publication_sequence_number': seq[0]}))
    try:
        probes.drain()
        for _ in range(10):
            clock[0] += 0.055
            arrive(3)                                     # a burst right after the drain
            probes.poll_writers()
            clock[0] += 0.445
            arrive(17)                                    # 20 in the drain's 0.5 s: 40 Hz
            probes.drain()
        assert probe.peak_hz == pytest.approx(40.0)
        assert probes.writer_joined_since('amcl_ekf', 0.0) is False   # one writer, heard
    finally:
        probes.destroy()


def test_the_master_refreshes_unchanged_readings_and_a_remote_sends_each(testbed_path):
    d = load_deployment(testbed_path)
    assert connection_status_refresh_s(d, 'robot', 0.25) == refresh_s(d, 0.25) > 0.25
    assert connection_status_refresh_s(d, 'laptop', 0.25) == 0.0
