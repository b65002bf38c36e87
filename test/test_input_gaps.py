"""A node's own account of its inputs' silences (nodes/input_gaps.py): pure, the clock given."""

from anyscale_manager.nodes.input_gaps import InputGaps


def feed(gaps, times):
    return [(t, line) for t in times for line in [gaps.heard(t)] if line is not None]


def test_a_gap_well_past_the_usual_interval_is_said_with_its_length():
    gaps = InputGaps()
    ticks = [i * 0.025 for i in range(80)]                 # 40 Hz for 2 s
    said = feed(gaps, ticks + [ticks[-1] + 0.44] + [ticks[-1] + 0.44 + 0.025 * i
                                                    for i in range(1, 40)])
    assert len(said) == 1
    t, line = said[0]
    assert t == ticks[-1] + 0.44
    assert line.startswith('no input for 0.44 s (usually every 0.025 s)')


def test_a_slow_input_at_its_own_pace_and_a_small_stall_are_not_gaps():
    assert feed(InputGaps(), [i * 0.5 for i in range(20)]) == []          # 2 Hz
    ticks = [i * 0.025 for i in range(80)] + [2.0 + 0.12]                 # 0.12 s: below 0.15
    assert feed(InputGaps(), ticks) == []


def test_gaps_are_said_once_per_interval_with_a_count_of_the_others():
    gaps = InputGaps(every_s=10.0)
    times, t = [], 0.0
    for burst in range(4):                  # a 0.3 s gap every 3 s
        for _ in range(120):
            t += 0.025
            times.append(t)
        t += 0.3
        times.append(t)
    t += 10.0                               # one more, past the interval
    times.append(t)
    said = feed(gaps, times)
    assert len(said) == 2
    assert said[0][1].startswith('no input for 0.3')
    assert '3 more gaps in the last' in said[1][1] and 'the longest 0.3' in said[1][1]
