"""A node's ``state:`` in a deployment file: read, checked against its outputs, every error
naming the file and the path; and the agent's book of the latest state (agent/state.py)."""

import copy

import pytest
import yaml

from anyscale_manager.agent.state import SET_HOLD_S, StateBook
from anyscale_manager.model import DeploymentError, load_mapping
from anyscale_manager.model.types import StateSpec
from conftest import TESTBED

AMCL_STATE = {'topic': '/amcl_pose', 'restore': '/initialpose'}


def amcl_with(**amcl_fields):
    with open(TESTBED, encoding='utf-8') as f:
        data = yaml.safe_load(f)
    amcl = data['/**']['ros__parameters']['nodes']['amcl']
    amcl.update(copy.deepcopy(amcl_fields))
    return data


def problems(data, source='t.yaml'):
    with pytest.raises(DeploymentError) as info:
        load_mapping(data, source)
    return [str(p) for p in info.value.problems]


def test_amcl_state_is_read_and_its_type_comes_from_its_connection():
    d = load_mapping(amcl_with(state=AMCL_STATE), 't.yaml')
    assert d.node('amcl').state == StateSpec('/amcl_pose', '/initialpose')
    assert d.state_msg_type('amcl') == 'geometry_msgs/msg/PoseWithCovarianceStamped'
    assert d.node('ar').state is None and d.state_msg_type('ar') == ''


def test_a_state_topic_that_is_not_an_output_is_refused_with_its_path():
    found = problems(amcl_with(state={'topic': '/amcl_pos', 'restore': '/initialpose'}))
    assert len(found) == 1, found
    assert found[0].startswith("t.yaml: nodes.amcl.state.topic: '/amcl_pos' is not an output "
                               "of 'amcl' (did you mean /amcl_pose?)"), found
    assert 'state.msg_type' in found[0]


def test_a_state_topic_no_connection_declares_is_accepted_with_its_type():
    state = {'topic': '/amcl/particles', 'restore': '/initialpose',
             'msg_type': 'geometry_msgs/msg/PoseArray'}
    d = load_mapping(amcl_with(state=state), 't.yaml')
    assert d.state_msg_type('amcl') == 'geometry_msgs/msg/PoseArray'


@pytest.mark.parametrize('state, path, words', [
    ({'topic': '/amcl_pose'}, 'nodes.amcl.state.restore', 'required'),
    ({'topic': '/amcl_pose', 'restore': '/amcl_pose'}, 'nodes.amcl.state.restore',
     'restores from another topic'),
    ({'topic': '/amcl_pose', 'restore': 'bad topic'}, 'nodes.amcl.state.restore',
     'not a valid name'),
    ({'topic': '/amcl_pose', 'restore': '/initialpose', 'msg_type': 'geometry_msgs/Pose'},
     'nodes.amcl.state.msg_type', 'did you mean geometry_msgs/msg/Pose'),
    ({'topic': '/amcl_pose', 'restore': '/initialpose', 'rate': 2},
     'nodes.amcl.state', 'rate'),
    ('/amcl_pose', 'nodes.amcl.state', ''),
])
def test_a_malformed_state_names_the_file_and_path(state, path, words):
    found = problems(amcl_with(state=state))
    assert any(p.startswith(f't.yaml: {path}') and words in p for p in found), found


def test_an_unmanaged_node_cannot_carry_a_state():
    found = problems(amcl_with(state=AMCL_STATE, managed=False, migratable=False,
                               standby=False, lifecycle=False))
    assert any(p.startswith('t.yaml: nodes.amcl.state: only a node the agents start') for p in
               found), found


# --- the agent's book ----------------------------------------------------------------------

SPECS = {'counter': StateSpec('/counter', '/restore')}


def test_the_latest_state_is_handed_once_per_copy_and_again_after_it_stood_down():
    book = StateBook(SPECS, max_bytes=100, stale_s=5.0)
    handover, lines = book.handover('counter', 41, 0.0)
    assert handover.data is None and 'no state heard yet' in lines[0][1]
    book.heard('counter', b'one', 1.0)
    book.heard('counter', b'two', 2.0)
    assert book.needs('counter', 42)
    handover, lines = book.handover('counter', 42, 2.25)
    assert handover.data == b'two' and handover.age_s == pytest.approx(0.25)
    assert lines[0][0] == 'info' and '0.25 s ago' in lines[0][1]
    book.handed('counter', 42)
    assert not book.needs('counter', 42)
    assert book.needs('counter', 43)          # another copy (a restart in place)
    book.stood_down('counter')
    assert book.needs('counter', 42)          # its next spell of serving
    assert not book.needs('unknown', 42)


def test_a_stale_state_is_handed_with_a_warning_that_says_its_age():
    book = StateBook(SPECS, max_bytes=100, stale_s=5.0)
    book.heard('counter', b'old', 0.0)
    handover, lines = book.handover('counter', 7, 12.0)
    assert handover.data == b'old'
    assert lines[0][0] == 'warn' and '12.0 s old' in lines[0][1], lines


def test_a_state_over_the_bound_is_not_kept_and_said_once():
    book = StateBook(SPECS, max_bytes=4, stale_s=5.0)
    assert book.heard('counter', b'ok', 0.0) == []
    lines = book.heard('counter', b'far too big', 1.0)
    assert lines[0][0] == 'warn' and 'agent.state_max_bytes = 4' in lines[0][1]
    assert 'last one that fitted, 2 bytes' in lines[0][1]
    assert book.heard('counter', b'far too big', 2.0) == []      # once
    assert book.latest('counter').data == b'ok'


def test_two_writers_are_told_from_a_restart_by_their_sequence_numbers():
    book = StateBook(SPECS, max_bytes=100, stale_s=5.0)
    for i, seq in enumerate([10, 11, 12, 1, 2, 3]):          # a copy restarted: one step
        assert book.heard('counter', b'x', i * 0.1, seq) == []
    lines = []
    for i, seq in enumerate([4, 50, 5, 51, 6, 52]):          # two writers interleaved
        lines += book.heard('counter', b'y', 1.0 + i * 0.1, seq)
    assert len(lines) == 1 and 'two writers' in lines[0][1], lines


def test_a_state_set_by_others_holds_against_the_serving_copys_output_for_a_while():
    """A pose set in RViz reaches the serving copy through its agent, and the copy takes it when
    its loop gets to it; until then it publishes from the state it had. What it publishes in
    that time is not the node's state: a copy taking over is handed the set one."""
    book = StateBook(SPECS, max_bytes=100, stale_s=5.0)
    book.heard('counter', b'before', 1.0, 1)
    assert book.set_by_others('counter', b'set', 2.0) == []
    assert book.heard('counter', b'old track', 2.0 + SET_HOLD_S - 0.01, 2) == []
    assert book.latest('counter').data == b'set'
    handover, lines = book.handover('counter', 42, 2.5)
    assert handover.data == b'set'
    assert lines == [('info', 'counter: the state set on /restore 0.50 s ago handed to the copy '
                              '(pid 42)')]
    # Half a second old, past a short state_stale_s: it was set, the serving copy did not stop.
    quick = StateBook(SPECS, max_bytes=100, stale_s=0.2)
    quick.set_by_others('counter', b'set', 2.0)
    assert quick.handover('counter', 42, 2.5)[1][0][0] == 'info'
    book.heard('counter', b'after', 2.0 + SET_HOLD_S, 3)
    assert book.latest('counter').data == b'after'
    lines = book.set_by_others('counter', b'far too big for the bound' * 10, 9.0)
    assert lines[0][0] == 'warn' and 'agent.state_max_bytes' in lines[0][1]
    assert book.latest('counter').data == b'after'
