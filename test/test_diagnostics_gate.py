"""/diagnostics at ROS's usual once a second, a change of level at once (runtime/diagnostics)."""

import pytest

from anyscale_manager.runtime.diagnostics import DiagnosticsGate

OK, WARN, ERROR = 0, 1, 2


def test_a_status_goes_out_once_a_period_while_its_level_holds():
    gate = DiagnosticsGate(1.0)
    sent = [t / 10 for t in range(35) if gate.due('link', OK, t / 10)]
    assert sent == [0.0, 1.0, 2.0, 3.0]


def test_a_change_of_level_goes_out_at_once_and_starts_a_new_period():
    gate = DiagnosticsGate(1.0)
    assert gate.due('link', OK, 0.0)
    assert not gate.due('link', OK, 0.3)
    assert gate.due('link', ERROR, 0.4)          # the cut is said at once
    assert not gate.due('link', ERROR, 0.9)
    assert gate.due('link', OK, 1.0)             # and its end
    assert gate.due('link', WARN, 1.05)


def test_each_status_name_has_its_own_period():
    gate = DiagnosticsGate(1.0)
    assert gate.due('a', OK, 0.0) and gate.due('b', OK, 0.5)
    assert not gate.due('b', OK, 1.2) and gate.due('a', OK, 1.2)


def test_a_period_of_zero_lets_everything_through_and_a_negative_one_is_refused():
    gate = DiagnosticsGate(0.0)
    assert all(gate.due('a', OK, t) for t in (0.0, 0.0, 0.1))
    with pytest.raises(ValueError, match='diagnostics period'):
        DiagnosticsGate(-1.0)
