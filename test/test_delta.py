"""The Δ rule (runtime/delta.py) on arrival times written by hand: outages just under and
just over the bound, slow topics, recoveries, and the probe-facing verdicts."""

import math

import pytest

from anyscale_manager.protocol import ERROR, OK, WARN
from anyscale_manager.runtime.delta import STALL_ALLOWANCE_S, DeltaJudge, below_spans


def periodic(rate_hz, start, stop):
    n = int(round((stop - start) * rate_hz))
    return [start + k / rate_hz for k in range(n)]


def with_outage(rate_hz, gap_s, before_s=5.0, after_s=5.0):
    """A topic at rate_hz, then nothing for gap_s (last message to the next), then again."""
    first = periodic(rate_hz, 0.0, before_s)
    resume = first[-1] + gap_s
    return first + [resume + k / rate_hz for k in range(int(after_s * rate_hz))]


def longest(spans):
    return max((b - a for a, b in spans), default=0.0)


@pytest.mark.parametrize('rate_hz, freq_min_hz', [(5, 2.5), (10, 5), (20, 10), (100, 50),
                                                  (10, 10), (30, 1)])
@pytest.mark.parametrize('tolerance_s', [0.0, 1.0, 2.0])
@pytest.mark.parametrize('sign', [+1, -1])
def test_an_outage_just_past_the_bound_is_a_violation_and_just_short_is_not(
        rate_hz, freq_min_hz, tolerance_s, sign):
    gap = tolerance_s + 1.0 / freq_min_hz + sign * 0.1
    arrivals = with_outage(rate_hz, gap)
    spans = below_spans(arrivals, freq_min_hz, 0.0, arrivals[-1])
    past = longest(spans) > tolerance_s
    assert past == (sign > 0), spans
    # The stretch is the outage less 1/freq_min and the allowance, to the microsecond.
    if gap > 1.0 / freq_min_hz + STALL_ALLOWANCE_S:
        assert longest(spans) == pytest.approx(gap - 1.0 / freq_min_hz - STALL_ALLOWANCE_S,
                                               abs=1e-6)


def test_a_steady_topic_at_or_above_freq_min_is_never_below():
    for rate in (5.0, 5.5, 20.0):
        arrivals = periodic(rate, 0.0, 10.0)
        assert below_spans(arrivals, 5.0, 0.0, arrivals[-1]) == []


@pytest.mark.parametrize('rate_hz', [2.0, 3.0, 4.5, 4.9])
def test_a_topic_slower_than_freq_min_stays_below_between_its_messages(rate_hz):
    arrivals = periodic(rate_hz, 0.0, 10.0)
    spans = below_spans(arrivals, 5.0, 0.0, arrivals[-1])
    # Below from its second or third interval to the end, in one stretch.
    assert spans and spans[-1][1] == pytest.approx(arrivals[-1])
    assert spans[-1][0] <= 3.0 / rate_hz + 1e-9


def test_a_recovered_topic_is_judged_on_its_new_intervals():
    arrivals = with_outage(20.0, 3.0)
    resume = arrivals[100]
    spans = below_spans(arrivals, 10.0, 0.0, arrivals[-1])
    assert len(spans) == 1 and spans[0][1] == pytest.approx(resume)


def test_silence_reads_below_and_zero_at_once_in_the_verdict():
    j = DeltaJudge(10.0, 2.0, started=0.0)
    for t in periodic(20.0, 0.0, 2.0):
        j.add(t)
    last = 1.95
    v = j.verdict(last + 0.14)
    assert (v.level, v.silent, v.below_for_s) == (OK, False, 0.0)
    v = j.verdict(last + 0.2)
    assert v.silent and v.level == WARN
    assert v.below_for_s == pytest.approx(0.2 - 0.1 - STALL_ALLOWANCE_S)
    v = j.verdict(last + 2.0 + 0.1 + STALL_ALLOWANCE_S + 0.01)
    assert v.level == ERROR
    j.add(last + 3.0)
    v = j.verdict(last + 3.01)
    assert v.level == OK and v.below_for_s == 0.0
    # The stretch that ended between two verdicts is still reported, once.
    assert v.ended_below_s == pytest.approx(3.0 - 0.1 - STALL_ALLOWANCE_S)
    assert j.verdict(last + 3.02).ended_below_s == 0.0


def test_a_connection_never_heard_is_silent_from_when_listening_began():
    j = DeltaJudge(5.0, 1.0, started=10.0)
    assert j.verdict(10.2).level == OK
    v = j.verdict(10.0 + 0.2 + STALL_ALLOWANCE_S + 1.5)
    assert v.level == ERROR and v.below_for_s == pytest.approx(1.5)


def test_tolerance_zero_tolerates_no_stretch():
    j = DeltaJudge(5.0, 0.0, started=0.0)
    j.add(0.0)
    bound = 0.2 + STALL_ALLOWANCE_S
    assert j.verdict(bound).level == OK
    assert j.verdict(bound + 0.01).level == ERROR


def test_unmonitored_connection_is_always_ok():
    j = DeltaJudge(None, None)
    j.add(1.0)
    assert j.verdict(100.0).level == OK
    assert below_spans([0.0, 50.0], None, 0.0, 100.0) == []


@pytest.mark.parametrize('kwargs', [dict(freq_min_hz=-1.0, tolerance_s=1.0),
                                    dict(freq_min_hz=1.0, tolerance_s=-0.5),
                                    dict(freq_min_hz=math.nan, tolerance_s=1.0),
                                    dict(freq_min_hz=1.0, tolerance_s=1.0, window_s=0.0)])
def test_bad_thresholds_are_refused(kwargs):
    with pytest.raises(ValueError):
        DeltaJudge(**kwargs)


def test_the_online_judge_and_the_spans_agree():
    """The probe's verdicts and the observer's spans are one rule."""
    arrivals = with_outage(10.0, 1.0) + [20.0 + k * 0.3 for k in range(20)]
    j = DeltaJudge(5.0, 1.0, started=0.0)
    ended = []
    for t in arrivals:
        j.add(t)
        ended += j.take_ended()
    assert ended == below_spans(arrivals, 5.0, 0.0, arrivals[-1])[:len(ended)]


def test_a_window_of_old_arrivals_does_not_count_against_a_new_start():
    arrivals = periodic(10.0, 0.0, 3.0)
    spans = below_spans(arrivals, 5.0, 1.0, 3.0)
    assert spans == []
