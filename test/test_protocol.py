"""Project topics' payloads: round trips and hostile input."""

import json

import pytest

from anyscale_manager import protocol as p


def sample_messages():
    return [
        p.Layout(generation=4, deployment='d', assignments={'amcl': 'laptop'}, reason='r',
                 stamp=1.5),
        p.AgentState(scale='robot', generation=4, stamp=2.0,
                     nodes={'amcl': p.NodeReport('running', 42, 1.0, 0, True, '')}),
        p.ScaleStatus('robot', 1.0, 55.0, 200.0, {'amcl': 50.0}, 40.0, 0.5),
        p.LinkStatus('robot', 'laptop', 1.0, True, 2.5, 0.0, 20000.0, 3.0, 150.0),
        p.ConnectionStatus('robot', 1.0, {'laser_amcl': p.ConnectionReading(9.9, 2.5e4, 0.0, 0)}),
        p.Event(1.0, 'migrate', 'amcl', 'robot', 'laptop', 'most CPU-hungry', 5),
        p.Objective(1.0, 225.0, 1000.0, 10.0),
        p.PlanCheck(1.0, {'amcl_1': p.PlanNode(2.5, 2.4, 50.0, 48.0, -0.04)}, -0.04,
                    {'c1': 1.2}),
        p.DeciderBeat(1.0, 'd', p.DeciderIdentity('ab12', 'robot', 7, 100.0), 'leader', 3, 9),
    ]


@pytest.mark.parametrize('msg', sample_messages(), ids=lambda m: type(m).__name__)
def test_round_trip(msg):
    assert type(msg).from_json(msg.to_json()) == msg


@pytest.mark.parametrize('text, words', [
    ('not json', 'not valid JSON'),
    ('[1, 2]', 'expected a JSON object'),
    ('{"generation": 1}', "missing field 'deployment'"),
    ('{"generation": "1", "deployment": "d", "assignments": {}, "reason": "", "stamp": 0}',
     'generation: expected an integer'),
    ('{"generation": -1, "deployment": "d", "assignments": {}, "reason": "", "stamp": 0}',
     'must be >= 0'),
    ('{"generation": 1, "deployment": "d", "assignments": {"a": 3}, "reason": "", "stamp": 0}',
     'assignments.a: expected a string'),
    ('{"generation": 1, "deployment": "d", "assignments": {}, "reason": "", "stamp": Infinity}',
     'not valid JSON'),
    ('{"generation": 1, "deployment": "d", "assignments": {}, "reason": "", "stamp": 0, '
     '"command": "rm -rf /"}', "unknown field 'command'"),
    ('[' * 100000 + ']' * 100000, 'not valid JSON'),
])
def test_hostile_layouts_are_refused_with_a_reason(text, words):
    with pytest.raises(p.ProtocolError) as info:
        p.Layout.from_json(text, p.TOPIC_LAYOUT)
    assert words in str(info.value)


def test_oversized_payload_is_refused_before_parsing():
    text = json.dumps({'x': 'a' * (p.MAX_PAYLOAD_BYTES + 1)})
    with pytest.raises(p.ProtocolError, match='over the'):
        p.AgentState.from_json(text)


def test_node_report_state_must_be_known():
    bad = p.AgentState('robot', 1, 1.0, {'n': p.NodeReport('dancing', 1, 1.0, 0, True, '')})
    with pytest.raises(p.ProtocolError, match='state'):
        p.AgentState.from_json(bad.to_json())
