"""The monitors' pure statistics, driven by a hand-written clock."""

import math
import random

import pytest

from anyscale_manager.runtime import cpu
from anyscale_manager.runtime.bandwidth import (CONGESTION, PROBE, BandwidthEstimate,
                                                crossing_connections, delivered_kbps,
                                                steady_throughput_bps, used_kbps)
from anyscale_manager.runtime.rates import (HeartbeatTracker, RateWindow, SenderOverlap,
                                            WriterStreams, live_window_s)


def feed(window, rate_hz, start, stop, nbytes=100, jitter_s=0.0, seed=1):
    """Periodic arrivals at rate_hz in [start, stop); returns the last arrival time."""
    rng = random.Random(seed)
    period = 1.0 / rate_hz
    k, t = 0, start
    last = None
    while t < stop:
        last = t + (rng.uniform(-jitter_s, jitter_s) if jitter_s else 0.0)
        window.add(last, nbytes)
        k += 1
        t = start + k * period
    return last


# --- RateWindow --------------------------------------------------------------------------------

@pytest.mark.parametrize('rate_hz', [0.5, 1.0, 10.0, 100.0, 1000.0])
@pytest.mark.parametrize('window_s', [1.0, 2.0, 5.0])
def test_steady_rate_is_exact(rate_hz, window_s):
    w = RateWindow(window_s)
    last = feed(w, rate_hz, 0.0, 20.0, nbytes=250)
    # Read between arrivals, right after one and just before the next.
    for now in (last, last + 0.5 / rate_hz, last + 0.99 / rate_hz):
        assert w.rate_hz(now) == pytest.approx(rate_hz, rel=1e-9)
        assert w.bytes_per_s(now) == pytest.approx(250 * rate_hz, rel=1e-9)


@pytest.mark.parametrize('rate_hz', [1.0, 10.0, 100.0, 1000.0])
def test_jittered_rate_within_one_percent(rate_hz):
    w = RateWindow(2.0)
    # Timer jitter of 2 ms (at most a tenth of the period) on every message.
    last = feed(w, rate_hz, 0.0, 10.0, jitter_s=min(0.1 / rate_hz, 0.002))
    assert w.rate_hz(last + 0.2 / rate_hz) == pytest.approx(rate_hz, rel=0.01)


@pytest.mark.parametrize('rate_hz', [1.0, 10.0, 100.0, 1000.0])
@pytest.mark.parametrize('window_s', [1.0, 2.0])
def test_stopped_topic_reads_zero_within_one_window(rate_hz, window_s):
    w = RateWindow(window_s)
    last = feed(w, rate_hz, 0.0, 10.0)
    previous = w.rate_hz(last)
    # One window, or two of its own periods for a topic slower than half the window.
    zero_after = max(window_s, 2.0 / rate_hz)
    for k in range(1, 101):                           # decays, never rises
        now = last + zero_after * k / 100.0 + 1e-9
        r = w.rate_hz(now)
        assert r <= previous + 1e-9
        previous = r
    assert w.rate_hz(last + zero_after - 1e-3) > 0.0
    assert w.rate_hz(last + zero_after + 1e-6) == 0.0
    assert w.bytes_per_s(last + zero_after + 1e-6) == 0.0


@pytest.mark.parametrize('stall_s', [0.01, 0.03, 0.05])
def test_receiver_stall_at_the_window_edge_barely_moves_the_rate(stall_s):
    # 1 kHz; the receiver stalls and then stamps a batch of messages at once, right where the
    # window begins. End-to-end counting would be off by stall/window; the fit is not.
    w = RateWindow(2.0)
    period = 1e-3
    now = 10.0
    stall_end = now - 2.0 + 0.002
    for k in range(int(4.0 / period) + 1):
        t = now - 4.0 + k * period
        w.add(stall_end if stall_end - stall_s <= t <= stall_end else t, 100)
    naive = (len(w._times) - 1) / (w._times[-1] - w._times[0])
    assert abs(naive - 1000.0) / 1000.0 > 0.4 * stall_s / 2.0
    assert w.rate_hz(now) == pytest.approx(1000.0, rel=0.15 * stall_s / 2.0)


@pytest.mark.parametrize('stall_s', [0.02, 0.05, 0.09])
def test_receiver_busy_at_reading_time_is_not_a_slower_topic(stall_s):
    w = RateWindow(2.0)
    last = feed(w, 1000.0, 0.0, 5.0)
    assert w.rate_hz(last + stall_s) == pytest.approx(1000.0, rel=1e-6)


def test_slow_topic_is_slow_not_dead():
    w = RateWindow(2.0)
    last = feed(w, 0.5, 0.0, 30.0, jitter_s=0.05)
    # Between two messages of a 0.5 Hz topic (2 s apart) the window is empty, yet it reads 0.5.
    for dt in (0.1, 1.0, 1.9, 2.04):
        assert w.rate_hz(last + dt) == pytest.approx(0.5, rel=0.06)
    # Stopped: it decays once the silence is longer than its period, 0 after two periods.
    assert 0.0 < w.rate_hz(last + 3.0) < 0.45
    assert w.rate_hz(last + 4.2) == 0.0


def test_rate_recovers_after_a_pause():
    w = RateWindow(2.0)
    feed(w, 10.0, 0.0, 5.0)
    last = feed(w, 10.0, 100.0, 103.0)
    assert w.rate_hz(last) == pytest.approx(10.0, rel=1e-9)


def test_fewer_than_two_messages_read_zero():
    w = RateWindow(2.0)
    assert w.rate_hz(0.0) == 0.0
    w.add(1.0, 10)
    assert w.rate_hz(1.5) == 0.0
    assert w.bytes_per_s(1.5) == 0.0


def test_clock_going_backwards_is_clamped():
    w = RateWindow(2.0)
    w.add(5.0)
    w.add(4.0)         # clamped to 5.0: never a negative span
    w.add(5.5)
    assert math.isfinite(w.rate_hz(5.5)) and w.rate_hz(5.5) >= 0.0


def test_burst_with_one_stamp_is_finite():
    w = RateWindow(2.0)
    for _ in range(5):
        w.add(1.0, 10)
    assert w.rate_hz(1.0) == pytest.approx(5 / 2.0)


@pytest.mark.parametrize('bad', [0, -1.0, math.inf, math.nan, 'x'])
def test_window_must_be_positive(bad):
    with pytest.raises(ValueError, match='window_s'):
        RateWindow(bad)


def test_bytes_per_second_follows_message_size():
    w = RateWindow(2.0)
    last = feed(w, 10.0, 0.0, 5.0, nbytes=1000)
    last = feed(w, 10.0, last + 0.1, last + 5.0, nbytes=3000)
    assert w.bytes_per_s(last) == pytest.approx(30000.0, rel=1e-9)


# --- HeartbeatTracker --------------------------------------------------------------------------

@pytest.mark.parametrize('rate_hz, misses', [(4.0, 3), (2.0, 3), (10.0, 5), (1.0, 1)])
def test_link_goes_down_after_misses_and_up_on_echo(rate_hz, misses):
    period = 1.0 / rate_hz
    hb = HeartbeatTracker(period, misses)
    assert not hb.up(0.0)                              # nothing proves it works yet
    rtt = 0.01
    now = 0.0
    for _ in range(20):
        seq = hb.next_beat(now)
        assert hb.echo(now + rtt, seq) == pytest.approx(rtt)
        now += period
    assert hb.up(now) and hb.loss(now) == 0.0
    assert hb.rtt_s() == pytest.approx(rtt)
    last_echo = now - period + rtt                    # the link is cut right after it
    down_at = None
    t = now
    while down_at is None:
        hb.next_beat(t)
        for k in range(8):                            # check 8 times per period
            probe = t + k * period / 8
            if not hb.up(probe):
                down_at = probe
                break
        t += period
    # Down once misses_down periods passed without an echo, not a check earlier.
    assert hb.up(last_echo + misses * period)
    assert misses * period < down_at - last_echo <= (misses + 1 / 8) * period + 1e-9
    # A beat is counted lost once its echo is misses_down periods late.
    t += misses * period
    hb.next_beat(t)
    assert hb.loss(t) > 0.0
    seq = hb.next_beat(t)
    hb.echo(t + rtt, seq)
    assert hb.up(t + rtt)


def test_a_down_verdict_says_what_it_rests_on():
    period, misses, rtt = 0.1, 3, 0.002
    hb = HeartbeatTracker(period, misses)
    assert hb.silence(0.0) == 'no echo yet (0 beats sent)'
    now = _beats(hb, 0.0, 10, lambda k: rtt, period)
    last_echo = now - period + rtt
    for at in (0.0, 0.1, 0.28):                       # the third beat went out late
        hb.next_beat(now + at)
    t = now + 0.29
    assert not hb.up(t)
    assert hb.silence(t) == (f'no echo for {t - last_echo:.2f} s, 3 beats unanswered, sent '
                             '0.10-0.18 s apart (period 0.1 s)')


def test_a_stall_of_the_judging_process_is_not_a_cut():
    period, misses, rtt = 0.25, 3, 0.01
    hb = HeartbeatTracker(period, misses)
    now = _beats(hb, 0.0, 20, lambda k: rtt, period)
    last_echo = now - period + rtt
    # The process sends one more beat, then is not scheduled for 2 s: no beats go out, and the
    # echo of the one it sent waits in its queue. At wake-up, before reading that echo:
    seq = hb.next_beat(now)
    wake = now + 2.0
    assert wake - last_echo > hb.timeout_s
    assert hb.up(wake)                                # one beat unanswered proves nothing
    hb.echo(wake + 0.001, seq)
    assert hb.up(wake + 0.001)
    # The link really is cut from then on: down once misses_down more beats go unanswered.
    t = wake + 0.001
    for k in range(misses - 1):
        hb.next_beat(t + k * period)
    assert hb.up(t + 10.0)                            # misses_down - 1 beats: still not proven
    hb.next_beat(t + (misses - 1) * period)
    assert not hb.up(t + misses * period + 0.01)


def test_loss_fraction_counts_unanswered_beats():
    hb = HeartbeatTracker(0.25, 3, loss_window=40)
    now = 0.0
    for k in range(40):
        seq = hb.next_beat(now)
        if k % 4 != 0:                                # one in four lost
            hb.echo(now + 0.005, seq)
        now += 0.25
    hb.next_beat(now + 1.0)                           # let the last ones expire
    assert hb.loss(now + 1.0) == pytest.approx(0.25, abs=0.03)
    assert hb.up(now)                                 # scattered loss is not a down link


def test_foreign_and_late_echoes_are_ignored():
    hb = HeartbeatTracker(0.25, 3)
    seq = hb.next_beat(0.0)
    assert hb.echo(0.01, 999) is None
    assert hb.echo(0.01, 'x') is None
    assert not hb.up(0.02)
    for k in range(1, 6):
        hb.next_beat(0.25 * k)
    assert hb.echo(1.3, seq) is None                   # expired: counted lost, proves nothing
    assert not hb.up(1.3)
    assert hb.echo(-5.0, hb.next_beat(1.5)) is None     # an echo before its beat is nonsense


def test_an_echo_read_late_is_filed_at_its_arrival_and_later_beats_still_wait():
    """The monitor reads echoes just before it judges, each with the kernel's arrival time:
    an echo that came long ago answers its own beat, not the ones sent after it came."""
    hb = HeartbeatTracker(0.25, 3)
    first = hb.next_beat(0.0)
    for k in range(1, 4):
        hb.next_beat(0.25 * k)                         # 0.25, 0.5, 0.75: never answered
    assert hb.echo(0.01, first) == pytest.approx(0.01)   # read at 0.76, arrived at 0.01
    assert not hb.up(0.8)                              # three beats unanswered since 0.01
    assert 'no echo for 0.79 s, 3 beats unanswered' in hb.silence(0.8)


def test_an_allowance_holds_a_silence_up_that_long_and_no_longer():
    """The watcher's own bandwidth probe fills the link: its beats wait behind the data."""
    hb = HeartbeatTracker(0.1, 3)
    hb.echo(0.005, hb.next_beat(0.0))
    for k in range(1, 10):
        hb.next_beat(0.1 * k)                          # 0.1 .. 0.9: no echo comes back
    assert not hb.up(0.4)                              # 0.395 s of silence > 0.3 s
    assert hb.up(0.4, allowance_s=0.6)                 # ... within 0.3 + 0.6 s
    assert not hb.up(0.95, allowance_s=0.6)            # 0.945 s > 0.9 s: a cut after all


def test_echoes_read_late_in_a_burst_keep_a_working_link_up():
    hb = HeartbeatTracker(0.1, 3)
    seqs = [hb.next_beat(0.1 * k) for k in range(6)]     # 0.0 .. 0.5
    for k, seq in enumerate(seqs[:5]):                     # each answered 10 ms later ...
        hb.echo(0.1 * k + 0.01, seq)                       # ... all read at 0.55
    assert hb.up(0.55)
    assert hb.rtt_s() == pytest.approx(0.01)


@pytest.mark.parametrize('period, misses', [(0, 3), (0.25, 0), (0.25, 1.5)])
def test_heartbeat_tracker_rejects_bad_settings(period, misses):
    with pytest.raises(ValueError):
        HeartbeatTracker(period, misses)


def test_rtt_is_median_of_recent():
    hb = HeartbeatTracker(0.25, 3)
    for k, rtt in enumerate([0.01, 0.01, 0.5, 0.01, 0.02]):
        seq = hb.next_beat(k * 0.25)
        hb.echo(k * 0.25 + rtt, seq)
    assert hb.rtt_s() == pytest.approx(0.01)


def _beats(hb, start, count, rtt_of, period=0.25):
    """Send ``count`` beats from ``start``; rtt_of(k) is the k-th echo's RTT, None = lost."""
    now = start
    for k in range(count):
        seq = hb.next_beat(now)
        rtt = rtt_of(k)
        if rtt is not None:
            hb.echo(now + rtt, seq)
        now += period
    return now


def test_queueing_delay_is_rtt_beyond_the_base_reached_by_three_of_four_beats():
    hb = HeartbeatTracker(0.25, 3)
    assert hb.queueing_delay_s(0.0) is None                       # nothing sent
    now = _beats(hb, 0.0, 20, lambda k: 0.002)
    assert hb.base_rtt_s() == pytest.approx(0.002)
    assert hb.queueing_delay_s(now) == pytest.approx(0.0)
    # One late echo in four (a scheduling hiccup) is not a queue.
    now = _beats(hb, now, 4, lambda k: 0.2 if k == 1 else 0.002)
    assert hb.queueing_delay_s(now) == pytest.approx(0.0)
    # A queue of about 100 ms holds every beat.
    now = _beats(hb, now, 4, lambda k: 0.1 + 0.01 * k)
    assert hb.queueing_delay_s(now) == pytest.approx(0.11 - 0.002)
    assert hb.base_rtt_s() == pytest.approx(0.002)                 # the base is the least


def test_queueing_delay_counts_a_beat_still_unanswered_as_waiting():
    hb = HeartbeatTracker(0.25, 3)
    now = _beats(hb, 0.0, 10, lambda k: 0.002)
    # Tail drop: three of four lost; a lost beat has waited since it was sent.
    now = _beats(hb, now, 4, lambda k: 0.002 if k == 0 else None)
    assert hb.queueing_delay_s(now) == pytest.approx(0.25 - 0.002)   # the latest, 0.25 s ago
    # ... but beats sent before ``since`` (a cut, a probe) say nothing.
    assert hb.queueing_delay_s(now, since=now - 0.5) is None


@pytest.mark.parametrize('recent, agree, base_window',
                         [(4, 0, 240), (4, 5, 240), (0, 0, 240), (4, 3, 39)])
def test_queueing_delay_rejects_bad_settings(recent, agree, base_window):
    with pytest.raises(ValueError):
        HeartbeatTracker(0.25, 3, loss_window=40, base_window=base_window, recent=recent,
                         agree=agree)


def test_base_outlives_the_rtt_median_window():
    hb = HeartbeatTracker(0.25, 3, loss_window=4, base_window=12)
    now = _beats(hb, 0.0, 2, lambda k: 0.001)
    now = _beats(hb, now, 8, lambda k: 0.05)          # a standing queue since
    assert hb.rtt_s() == pytest.approx(0.05)           # the last 4
    assert hb.base_rtt_s() == pytest.approx(0.001)     # the last 12
    assert hb.queueing_delay_s(now) == pytest.approx(0.049)


# --- bandwidth -----------------------------------------------------------------------------

def test_steady_throughput_skips_the_bucket_burst():
    rate = 625000.0                                    # 5 Mbit/s
    samples = [(0.0, 0), (0.001, 32000)]               # a 32 kB token bucket at line rate
    t, b = 0.001, 32000
    while t < 0.5:
        t += 0.01
        b += int(rate * 0.01)
        samples.append((t, b))
    naive = samples[-1][1] / samples[-1][0]
    assert naive > 1.1 * rate
    assert steady_throughput_bps(samples) == pytest.approx(rate, rel=0.01)


@pytest.mark.parametrize('samples', [[], [(0.0, 0)], [(1.0, 0), (1.0, 100)],
                                     [(0.0, 0), (1.0, 0)]])
def test_steady_throughput_needs_data(samples):
    assert steady_throughput_bps(samples) is None


def test_bandwidth_probe_schedule():
    est = BandwidthEstimate(interval_s=30.0, nominal_kbps=54000.0, busy_fraction=0.75)
    assert est.age_s(0.0) is None and est.available_kbps is None
    assert not est.due(0.0, link_up=False, used_kbps=0.0)
    assert not est.due(0.0, link_up=True, used_kbps=45000.0)     # near full: never probe
    assert est.due(0.0, link_up=True, used_kbps=1000.0)
    est.started(0.0)
    assert not est.due(10.0, True, 0.0)
    assert est.record(0.6, 19000.0, used_kbps=1000.0) == pytest.approx(20000.0)
    assert est.age_s(10.6) == pytest.approx(10.0)
    assert not est.due(29.0, True, 0.0)
    assert est.due(30.0, True, 1000.0)
    assert not est.due(30.0, True, 16000.0)            # 80% of the measured 20000
    est.started(30.0)
    assert est.failed(31.0, 'refused') == pytest.approx(20000.0)   # the old one stands
    assert est.age_s(40.6) == pytest.approx(40.0) and est.last_error == 'refused'
    assert est.record(61.0, math.nan) == pytest.approx(20000.0) and est.failures == 2


def test_used_bandwidth_counts_only_crossing_connections():
    conns = [('a_b', 'a', 'b'), ('a_c', 'a', 'c'), ('b_a', 'b', 'a'), ('x_y', 'x', 'y')]
    placed = {'a': {'robot'}, 'b': {'laptop'}, 'c': {'robot'}}
    crossing = crossing_connections(conns, placed, 'robot', 'laptop')
    assert crossing == {'a_b': 'laptop', 'b_a': 'robot'}     # where each is received
    assert used_kbps({'a_b': 1000.0, 'b_a': 250.0, 'a_c': 1e6}, crossing) == pytest.approx(10.0)
    assert crossing_connections(conns, placed, 'robot', 'robot') == {}


def test_a_node_handed_over_still_receives_across_the_link_until_its_far_copy_stops():
    """AR sent home: its robot copy serves, its laptop copy is not yet deactivated. The camera
    still feeds the laptop's copy across the link, whichever scale reported first."""
    conns = [('camera_ar', 'camera', 'ar'), ('ar_nav', 'ar', 'nav'),
             ('camera_viewer', 'camera', 'viewer')]
    overlap = {'camera': {'robot'}, 'ar': {'robot', 'laptop'}, 'nav': {'robot'},
               'viewer': {'robot'}}
    assert crossing_connections(conns, overlap, 'robot', 'laptop') == \
        {'camera_ar': 'laptop', 'ar_nav': 'robot'}
    home = dict(overlap, ar={'robot'})
    assert crossing_connections(conns, home, 'robot', 'laptop') == {}
    # Both ends of a connection with a copy on both scales: it crosses both ways; read at the
    # first end's subscriber.
    both = {'camera': {'robot', 'laptop'}, 'ar': {'robot', 'laptop'}}
    assert crossing_connections(conns[:1], both, 'robot', 'laptop') == {'camera_ar': 'robot'}


# --- cpu normalisation ---------------------------------------------------------------------

@pytest.mark.parametrize('capacity, cores, busy, expected', [
    (200.0, 2, 1.0, 100.0),      # one robot core fully busy = 100 reference percent
    (700.0, 4, 1.0, 175.0),      # one laptop core is worth 1.75 robot cores
    (700.0, 4, 4.0, 700.0),      # a full laptop reads its capacity
    (200.0, 0.57, 0.57, 200.0),  # a cgroup quota of 0.57 CPUs, fully used
    (100.0, 1, -0.1, 0.0),
])
def test_reference_percent(capacity, cores, busy, expected):
    assert cpu.reference_percent(busy, capacity, cores) == pytest.approx(expected)


def test_effective_cores_and_quota_parsing():
    assert cpu.effective_cores(4) == 4.0
    assert cpu.effective_cores(4, 1.5) == 1.5
    assert cpu.effective_cores(2, 8.0) == 2.0
    assert cpu.quota_cores_v1('-1\n', '100000\n') is None
    assert cpu.quota_cores_v1('50000\n', '100000\n') == 0.5
    assert cpu.quota_cores_v1('garbage', '100000') is None
    assert cpu.quota_cores_v2('max 100000\n') is None
    assert cpu.quota_cores_v2('150000 100000\n') == 1.5
    groups = cpu.parse_proc_cgroup('4:memory:/x\n2:cpu,cpuacct:/robot\n0::/u\n')
    assert groups['cpu'] == groups['cpuacct'] == '/robot' and groups[''] == '/u'
    with pytest.raises(ValueError):
        cpu.effective_cores(0)


def test_cpu_counter_primes_then_rates():
    c = cpu.CpuCounter()
    assert c.update(0.0, 100.0) is None                # psutil's meaningless first 0.0, avoided
    assert c.update(0.5, 100.75) == pytest.approx(1.5)  # above one core is fine
    assert c.update(0.5, 101.0) is None                # no time passed
    assert c.update(1.0, 50.0) is None                 # reset counter primes again
    assert c.update(2.0, 50.5) == pytest.approx(0.5)


def test_process_group_cpu_sums_children_and_tolerates_churn():
    g = cpu.ProcessGroupCpu()
    assert g.update(0.0, {'amcl': {10: 1.0, 11: 2.0}}) == {}
    out = g.update(1.0, {'amcl': {10: 1.5, 11: 2.25}, 'ar': {20: 5.0}})
    assert out == {'amcl': pytest.approx(0.75)}         # ar is new: primed only
    out = g.update(2.0, {'amcl': {10: 2.0, 12: 9.0}, 'ar': {20: 5.5}})
    assert out == {'amcl': pytest.approx(0.5), 'ar': pytest.approx(0.5)}
    out = g.update(3.0, {'amcl': {10: 0.1, 12: 9.5}, 'ar': {20: 5.5}})  # pid 10 reused
    assert out == {'amcl': pytest.approx(0.5), 'ar': pytest.approx(0.0)}
    out = g.update(4.0, {'amcl': {}, 'ar': {20: 6.0}})                   # amcl is gone
    assert out == {'ar': pytest.approx(0.5)}
    g.update(5.0, {'ar': {20: 6.5}, 'gone': {}})
    assert g.update(6.0, {'ar': {20: 7.0}, 'gone': {}}) == {'ar': pytest.approx(0.5)}


def test_a_congested_link_is_never_probed_and_a_shortfall_lowers_its_figure_at_once():
    est = BandwidthEstimate(interval_s=30.0, nominal_kbps=54000.0, min_gap_s=1.0,
                            shortfall=0.9, settle_s=2.0)
    est.started(0.0)
    est.record(0.5, 53000.0, used_kbps=500.0)
    assert est.source == PROBE
    # Congested: no probe, whatever the interval says.
    assert not est.due(40.0, True, 100.0, congested=True)
    # Delivering 90 % of the need or more is no evidence: nothing learnt.
    assert est.congested(10.0, 5500.0, 6100.0) is None
    assert est.available_kbps == pytest.approx(53500.0)
    # Below it: the link carries less than the need, whatever the (lossy) delivery says.
    assert est.congested(10.1, 80.0, 6100.0) == pytest.approx(5490.0)
    assert est.source == CONGESTION and est.age_s(10.1) == 0.0
    # Not lowered again while what was sent back takes effect (the queue drains) ...
    assert est.congested(11.0, 10.0, 300.0) is None
    # ... but after settle_s, still short: what was sent back was not enough, and the link
    # carries at most what arrives now.
    assert est.congested(12.2, 200.0, 300.0) == pytest.approx(180.0)
    # Never raised by a congestion: the lower of the last figure and the new evidence.
    assert est.congested(14.3, 250.0, 6100.0) == pytest.approx(180.0)
    # Probed again once no longer congested, min_gap_s after the figure (not at the routine
    # interval), and then back to the routine schedule.
    assert not est.due(14.5, True, 200.0, congested=True)
    assert not est.due(14.5, True, 200.0)
    assert est.due(15.3, True, 200.0)
    est.started(15.3)
    est.record(15.8, 4700.0, used_kbps=250.0)
    assert est.source == PROBE and est.available_kbps == pytest.approx(4950.0)
    assert not est.due(20.0, True, 200.0) and est.due(45.4, True, 200.0)
    # Nonsense is no evidence.
    for delivered, needed in ((math.nan, 100.0), (10.0, 0.0), (10.0, math.inf)):
        assert est.congested(50.0, delivered, needed) is None
    # A link back from an outage is measured again at once.
    est.started(60.0)
    assert not est.due(61.0, True, 0.0)
    est.remeasure()
    assert est.due(61.0, True, 0.0)


def test_a_congestion_that_outlasts_what_was_sent_back_takes_the_link_to_what_arrives():
    # A throttle below what DDS discovery alone puts on the link: the first figure sends the
    # largest flow back; a second later the rest still delivers nothing, so it all goes back.
    est = BandwidthEstimate(interval_s=30.0, nominal_kbps=54000.0, shortfall=0.9, settle_s=1.0)
    assert est.congested(0.4, 5000.0, 6400.0) == pytest.approx(5760.0)
    assert est.congested(1.0, 0.0, 240.0) is None              # settling
    assert est.congested(1.5, 0.0, 240.0) == pytest.approx(0.0)


def test_a_reading_that_has_not_come_through_lately_delivers_nothing():
    # (B/s, age s, stale past s): each reading by the bound of the scale that sent it
    assert delivered_kbps({'laser_amcl': (28000.0, 0.3, 1.0),
                           'camera_ar': (760000.0, 1.6, 1.0)}) == pytest.approx(224.0)
    assert delivered_kbps({'laser_amcl': (28000.0, 0.3, 1.0),
                           'camera_ar': (760000.0, 1.6, 2.0)}) == pytest.approx(224.0 + 6080.0)
    assert delivered_kbps({}) == 0.0


def test_recent_bytes_count_only_the_last_span():
    w = RateWindow(2.0)
    for k in range(20):                 # 10 Hz, 1000 B, for 2 s
        w.add(k * 0.1, 1000)
    for k in range(20, 25):             # then 10 Hz of 100 B for 0.5 s
        w.add(k * 0.1, 100)
    assert w.recent_bytes_per_s(2.45, 0.5) == pytest.approx(5 * 100 / 0.5)
    assert w.bytes_per_s(2.45) > 3000.0         # the window still remembers the 1000 B
    assert w.recent_bytes_per_s(2.45, 10.0) == pytest.approx(w.recent_bytes_per_s(2.45, 2.0))
    assert RateWindow(2.0).recent_bytes_per_s(1.0, 0.5) == 0.0


# --- WriterStreams -----------------------------------------------------------------------------

def test_writer_streams_tell_a_newly_started_writer_from_the_old_one():
    w = WriterStreams(forget_s=3.0)
    t = 0.0
    for seq in range(500, 520):                  # the old copy, running for a while
        w.add(t, seq)
        t += 0.1
    assert w.streams == 1 and not w.joined_since(0.0)   # the first writer heard is no news
    moved = t
    # The new copy's first messages were lost (volatile, before the match): it is heard from 7
    # on, interleaved with the old copy, with losses on both.
    for old, new in [(520, 7), (522, 8), (523, 10), (525, None)]:
        w.add(t, old)
        if new is not None:
            w.add(t + 0.01, new)
        t += 0.1
    assert w.streams == 2 and w.joined_since(moved) and not w.joined_since(t)
    # Numbers the middleware does not give are ignored.
    for seq in (None, -1, 'x', True, 3.5):
        w.add(t, seq)
    assert w.streams == 2


def test_writer_streams_forget_a_stopped_writer():
    w = WriterStreams(forget_s=3.0)
    for k in range(10):
        w.add(0.1 * k, 50 + k)                  # a copy that stopped at 0.9 s
    for k in range(10):
        w.add(5.0 + 0.1 * k, 300 + k)           # the other copy, alone for long
    # A new copy heard later, numbered past where the stopped one left off: it is new, not the
    # stopped one's continuation.
    w.add(7.0, 70)
    assert w.joined_since(6.5)


def test_writer_streams_a_new_copy_catching_up_with_stopped_ones_is_one_sender():
    """A handover, then a relocation: copy A stopped at 7 after B started, B was killed at 6,
    and C starts at 1 and passes both numbers within forget_s. Each of C's messages continues
    C, never a stopped writer (seen in CI: two senders counted for 6 s at home)."""
    w = WriterStreams(forget_s=3.0)
    for k in range(1, 8):
        w.add(0.1 * k, k)                        # A: 0.1 .. 0.7 s
    for k in range(1, 7):
        w.add(0.45 + 0.1 * k, k)                 # B: 0.55 .. 1.05 s
    t = 2.0
    for k in range(1, 41):                       # C: from 2.0 s at 10 Hz
        w.add(t, k)
        if t >= 1.05 + 3.0 + 0.1:                # A and B no longer within the live window
            assert w.live(t, 3.0) == 1, (t, w._streams)
        t += 0.1


def test_writer_streams_a_writer_heard_first_is_no_news():
    w = WriterStreams()
    w.add(1.0, 3)
    w.add(1.1, 4)
    assert not w.joined_since(0.0)
    w.add(1.2, 1)                               # another writer, started later
    assert w.joined_since(1.2) and not w.joined_since(1.21)
    with pytest.raises(ValueError):
        WriterStreams(forget_s=0)


def test_link_monitor_trackers_judge_congestion_over_half_a_second_at_any_beat_rate():
    from anyscale_manager.nodes.monitors.link import heartbeat_tracker
    slow, fast = heartbeat_tracker(0.25, 3), heartbeat_tracker(0.1, 3)
    assert (slow.recent, slow.agree) == (4, 3)     # at 4 Hz: the four-beat minimum
    assert (fast.recent, fast.agree) == (5, 4)
    assert fast.timeout_s == pytest.approx(0.3)    # a cut is still seen after 3 beats
    # A 0.3 s stall of the judging scale delays 3 beats of 5: no verdict of congestion.
    now, rtts = 0.0, [0.002] * 66 + [0.3, 0.2, 0.1, 0.002]
    for rtt in rtts:
        seq = fast.next_beat(now)
        fast.echo(now + rtt, seq)
        now += 0.1
    assert fast.queueing_delay_s(now + 0.3) < 0.05
    # The same three beats are 3 of the last 4 at 4 Hz's window: they would make it.
    strict = HeartbeatTracker(0.1, 3, recent=4, agree=3)
    now = 0.0
    for rtt in rtts:
        seq = strict.next_beat(now)
        strict.echo(now + rtt, seq)
        now += 0.1
    assert strict.queueing_delay_s(now + 0.3) > 0.05


def test_a_stall_of_the_judge_is_no_queue_on_the_link():
    """Four beats go out on time, then the judging process is starved until 6.75 s: their
    echoes are read then, 0.45-0.75 s after they were sent, as a full queue would return them.
    Its next beat, late by more than the congestion threshold (0.05 s), starts the judgement
    afresh: no verdict until five beats after it, and they find no queue. Without the
    threshold the stall reads as 0.45 s of queueing delay. A real queue is still seen."""
    from anyscale_manager.nodes.monitors.link import heartbeat_tracker
    judge, blind = heartbeat_tracker(0.1, 3, 0.05), heartbeat_tracker(0.1, 3)
    for hb in (judge, blind):
        now = 0.0
        for _ in range(60):
            hb.echo(now + 0.002, hb.next_beat(now))
            now += 0.1
        for seq in [hb.next_beat(6.0 + 0.1 * i) for i in range(4)]:
            hb.echo(6.75, seq)
        hb.echo(6.752, hb.next_beat(6.75))
    assert blind.queueing_delay_s(6.76) == pytest.approx(0.45 - 0.002)
    assert judge.queueing_delay_s(6.76) is None
    now = 6.75
    for _ in range(4):
        now += 0.1
        judge.echo(now + 0.002, judge.next_beat(now))
    assert judge.queueing_delay_s(now + 0.01) == pytest.approx(0.0)
    for _ in range(5):          # beats on time, their echoes 0.2 s late: a queue
        now += 0.1
        judge.echo(now + 0.2, judge.next_beat(now))
    assert judge.queueing_delay_s(now + 0.3) == pytest.approx(0.2 - 0.002)


def test_beats_sent_in_one_burst_after_a_stall_are_no_cut():
    """The judging process was not scheduled for a second: its beat timer catches up with
    three beats at once, and the echoes of the beats before the stall wait in its queue. Down
    only once beats spread over their periods have gone unanswered."""
    period, misses, rtt = 0.1, 3, 0.002
    hb = HeartbeatTracker(period, misses)
    now = _beats(hb, 0.0, 10, lambda k: rtt, period)
    stalled_until = now + 1.2
    for _ in range(3):
        hb.next_beat(stalled_until)
    assert hb.up(stalled_until + 0.01)
    for k in range(1, 3):                       # beats go on, still unanswered: a cut
        hb.next_beat(stalled_until + k * period)
    assert not hb.up(stalled_until + 2 * period + 0.01)


def test_writer_streams_count_the_writers_heard_lately():
    w = WriterStreams(forget_s=3.0)
    for k in range(20):
        w.add(0.1 * k, 500 + k)                 # a copy serving for a while
    assert w.live(1.9, 0.5) == 1
    for k in range(10):                          # a second copy, both heard
        w.add(2.0 + 0.1 * k, 520 + k)
        w.add(2.05 + 0.1 * k, 1 + k)
    assert w.live(2.95, 0.5) == 2
    # The first one stops: it counts no more once it has not been heard for the window,
    # though it is remembered for forget_s.
    for k in range(10):
        w.add(3.0 + 0.1 * k, 11 + k)
    assert w.live(3.9, 0.5) == 1 and w.streams == 2


def test_live_window_is_two_periods_at_the_minimum_rate_within_bounds():
    forget = WriterStreams().forget_s
    assert live_window_s(2.0, forget) == 1.0
    assert live_window_s(100.0, forget) == 0.5
    assert live_window_s(0.1, forget) == forget and live_window_s(None, forget) == forget
    assert live_window_s(0.1, 2.5) == 2.5


def test_sender_overlap_counts_from_the_first_reading_with_two():
    o = SenderOverlap()
    assert o.update(1.0, 1) == 0.0
    assert o.update(1.5, 2) == 0.0
    assert o.update(2.0, 2) == 0.5 and o.update(4.5, 3) == 3.0
    assert o.update(5.0, 1) == 0.0
    assert o.update(5.5, 2) == 0.0                # a new overlap starts afresh


def test_sender_overlap_ends_when_two_were_last_heard_not_a_live_window_later():
    """A copy handed over after 5 s of overlap: heard at once 5 s, though the old writer
    counts as live for the window after its last message (the probe read 6.4 s for a 5 s
    overlap, past the 6 s bound)."""
    w, o, window = WriterStreams(forget_s=3.0), SenderOverlap(), 2.0
    messages = [(0.1 * k, 500 + k) for k in range(101)]          # the old copy until 10 s
    messages += [(5.05 + 0.1 * k, 1 + k) for k in range(70)]      # the new one from 5.05 s
    readings, heard = [], sorted(messages)
    for t in (3.0, 5.5, 7.0, 9.0, 10.5, 11.5):
        while heard and heard[0][0] <= t:
            w.add(*heard.pop(0))
        readings.append(o.update(t, w.live(t, window), w.together_at(t, window)))
    assert readings[0] == 0.0
    assert w.live(11.5, window) == 2               # still live: the window's doing
    assert readings[-1] == pytest.approx(10.0 - 5.45, abs=0.01)   # 6.0 by the readings
    assert w.together_at(11.5, window) == pytest.approx(10.0)
    one = WriterStreams()
    one.add(1.0, 7)
    assert one.together_at(1.5, window) is None
