"""One owner of the Δ rule (runtime/delta.py): its verdict type and helpers, pure, and a check
that no other module judges by the thresholds itself.

A connection's thresholds are compared with something (a rate, a time below, None) only where
the rule and its facts live: runtime/delta.py judges; model/ declares and validates them and
owns the facts ``Connection.monitored`` and ``Connection.pins_both_ends`` (and advises on a Δ
shorter than a move); profiling/suggest.py proposes them. Everyone else calls these.
"""

import ast
import math
import os

import pytest

from anyscale_manager.model.types import Connection, DeciderSettings
from anyscale_manager.protocol import ERROR, OK, STALE, WARN
from anyscale_manager.runtime.delta import (ConnectionVerdict, DeltaJudge, below_start,
                                            min_period_s, past_delta, rate_below,
                                            stretch_start, time_below)
from anyscale_manager.runtime.observations import ConnectionObs
from conftest import REPO

THRESHOLDS = ('freq_min_hz', 'tolerance_s')
# Where a threshold may be compared: the rule, the model's declaration and facts, the advice on
# a Δ against a move's cost, the thresholds' suggestion (its own dataclass of that name).
OWNERS = ('anyscale_manager/runtime/delta.py', 'anyscale_manager/model/types.py',
          'anyscale_manager/model/sections.py', 'anyscale_manager/model/advice.py',
          'anyscale_manager/profiling/suggest.py')
# Tests for None that choose a text, not a verdict; each should become Connection.monitored.
TEXT_ONLY = {('anyscale_manager/nodes/monitors/probes.py', 'conn.freq_min_hz is not None')}


def threshold_comparisons():
    """(path, source, is a test for None) of every comparison of a threshold in the package
    and the benches."""
    out = []
    for top in ('anyscale_manager', 'bench'):
        for folder, dirs, files in os.walk(os.path.join(REPO, top)):
            dirs[:] = sorted(d for d in dirs if not d.startswith(('.', '__')))
            for name in sorted(f for f in files if f.endswith('.py')):
                path = os.path.join(folder, name)
                rel = os.path.relpath(path, REPO).replace(os.sep, '/')
                with open(path, encoding='utf-8') as f:
                    tree = ast.parse(f.read(), rel)
                for node in ast.walk(tree):
                    if not isinstance(node, ast.Compare):
                        continue
                    operands = [node.left, *node.comparators]
                    if any(isinstance(o, ast.Attribute) and o.attr in THRESHOLDS
                           for o in operands):
                        is_none = all(isinstance(op, (ast.Is, ast.IsNot)) for op in node.ops)
                        out.append((rel, ast.unparse(node), is_none))
    return out


def test_only_the_owners_compare_a_connections_thresholds():
    found = threshold_comparisons()
    assert ('anyscale_manager/model/types.py', 'self.tolerance_s == 0', False) in found
    others = [(rel, src) for rel, src, is_none in found
              if rel not in OWNERS and not (is_none and (rel, src) in TEXT_ONLY)]
    assert others == [], ('judge by runtime/delta.py (rate_below, past_delta, '
                          'ConnectionVerdict.judge) and Connection.monitored / pins_both_ends')


def test_a_tolerance_of_zero_is_read_only_as_pins_both_ends():
    found = [(rel, src) for rel, src, _ in threshold_comparisons()
             if src.replace(' ', '').endswith(('tolerance_s==0', 'tolerance_s==0.0'))]
    assert found == [('anyscale_manager/model/types.py', 'self.tolerance_s == 0')]


# --- the verdict type ---------------------------------------------------------------------------

@pytest.mark.parametrize('below_for_s, tolerance_s, below, level', [
    (0.0, 2.0, None, OK),
    (1.0, 2.0, None, WARN),
    (2.0, 2.0, None, WARN),            # Δ itself is still allowed
    (2.000001, 2.0, None, ERROR),      # a microsecond past it is not
    (0.0, 0.0, True, WARN),            # Δ = 0: below, yet no stretch has lasted
    (0.000001, 0.0, None, ERROR),
    (1e9, None, None, WARN),           # no Δ: never past it
    (5.0, 2.0, False, OK),             # not below: the stretch does not count
])
def test_a_verdict_is_judged_by_its_stretch_against_delta(
        below_for_s, tolerance_s, below, level):
    v = ConnectionVerdict.judge(below_for_s, tolerance_s, below)
    assert v.level == level
    assert v.past_delta == (level == ERROR)
    assert v.below == (level != OK)
    assert v.below_for_s == (below_for_s if level != OK else 0.0)


@pytest.mark.parametrize('level, below_for_s, below', [
    (OK, 0.0, False), (WARN, 0.0, True), (ERROR, 3.0, True), (STALE, 0.0, False),
    (OK, 0.5, True)])
def test_a_probes_reading_is_below_when_its_verdict_says_so(level, below_for_s, below):
    assert ConnectionVerdict(below_for_s, level).below == below


def test_the_online_judge_returns_the_rules_verdict():
    j = DeltaJudge(5.0, 1.0, started=0.0)
    j.add(0.0)
    assert j.verdict(0.1) == ConnectionVerdict(0.0, OK, False, 0.0)
    silence = 0.2 + j.stall_allowance_s
    v = j.verdict(3.0)
    assert v == ConnectionVerdict.judge(3.0 - silence, 1.0, True, silent=True)
    assert v.past_delta and v.below_for_s == pytest.approx(3.0 - silence)


@pytest.mark.parametrize('tolerance_s, stretch_s, past', [
    (0.0, 0.0, False), (0.0, 1e-6, True), (2.0, 2.0, False), (2.0, 2.000001, True),
    (None, 1e9, False)])
def test_past_delta_is_strictly_longer_than_delta(tolerance_s, stretch_s, past):
    assert past_delta(stretch_s, tolerance_s) == past


def test_rates_and_stretches():
    assert rate_below(5.0, 4.999) and not rate_below(5.0, 5.0) and not rate_below(None, 0.0)
    assert not rate_below(5.0, 4.9999, slack_hz=1e-3) and rate_below(5.0, 4.99, 1e-3)
    assert min_period_s(4.0) == 0.25 and math.isinf(min_period_s(0.0))
    assert math.isinf(min_period_s(None))
    since = None
    for t, below in ((1.0, False), (2.0, True), (3.0, True)):
        since = stretch_start(since, t, below)
    assert since == 2.0 and time_below(since, 3.5) == 1.5
    assert stretch_start(since, 4.0, False) is None and time_below(None, 4.0) == 0.0


@pytest.mark.parametrize('reading, heard_from, now, expected', [
    (ConnectionObs(rate_hz=1.0, stamp=10.0, below_for_s=1.5, below=True), 0.0, 10.0, 8.5),
    (ConnectionObs(rate_hz=9.0, stamp=10.0), 0.0, 10.0, None),
    (ConnectionObs(rate_hz=9.0, stamp=6.0), 0.0, 10.0, 8.0),        # stale: missing from 8
    (None, 5.0, 10.0, 7.0),                                         # never heard since 5
    (None, 9.0, 10.0, None),                                        # not missing yet
    (None, -math.inf, 10.0, -math.inf),                             # missing at once
])
def test_below_start_from_one_reading(reading, heard_from, now, expected):
    settings = DeciderSettings(observation_max_age_s=2.0)
    assert below_start(reading, now, settings, heard_from) == expected


def test_a_connection_with_delta_zero_pins_both_ends():
    def conn(tolerance_s):
        return Connection('c', '/c', 'a', 'b', 1.0, freq_min_hz=1.0, tolerance_s=tolerance_s)
    assert conn(0.0).pins_both_ends and conn(0.0).monitored
    assert not conn(0.5).pins_both_ends and not conn(None).pins_both_ends
    assert not conn(None).monitored
