"""Project topics' payloads: round trips and hostile input."""

import dataclasses
import json
import typing

import pytest

from anyscale_manager import protocol as p


def sample_messages():
    return [
        p.Layout(generation=4, deployment='d', assignments={'amcl': 'laptop'}, reason='r',
                 stamp=1.5),
        p.AgentState(scale='robot', generation=4, stamp=2.0,
                     nodes={'amcl': p.NodeReport('running', 42, 1.0, 0, True, '')}),
        p.AgentState(scale='server', generation=4, stamp=2.0, nodes={}, share=p.HostShare(
            100.0, 2048.0, {'robot_b/amcl': p.ShareClaim(60.0, 70.0, 1, True)},
            {'ar': 'no room'}, {}, {'amcl': 'robot_b/amcl'})),
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


def test_the_readers_of_one_message_share_one_decoding():
    """The same text object (one delivery, several readers) is decoded once; an equal text
    that is another object (the next message) and another class are decoded anew."""
    text = sample_messages()[1].to_json()
    first = p.AgentState.from_json(text)
    assert p.AgentState.from_json(text) is first
    again = p.AgentState.from_json(''.join(list(text)))
    assert again == first and again is not first
    with pytest.raises(p.ProtocolError):
        p.Layout.from_json(text)              # another class: checked, not handed the last


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


def test_each_kind_of_malformed_layout_has_its_own_kind_from_a_fixed_set():
    """The throttled logs key on it: bad JSON, an unknown field and a NaN within 10 s are three
    lines, not one and a count."""
    base = {'generation': 1, 'deployment': 'd', 'assignments': {}, 'reason': '', 'stamp': 0}
    texts = ['not json', '[1, 2]', '{"generation": 1}',
             json.dumps(dict(base, generation='1')), json.dumps(dict(base, generation=-1)),
             json.dumps(dict(base, assignments={'a': 3})),
             json.dumps(base).replace('"stamp": 0', '"stamp": NaN'),
             json.dumps(dict(base, command='rm -rf /')),
             json.dumps({'x': 'a' * (p.MAX_PAYLOAD_BYTES + 1)})]
    kinds = []
    for text in texts:
        with pytest.raises(p.ProtocolError) as info:
            p.Layout.from_json(text, p.TOPIC_LAYOUT)
        kinds.append(p.error_kind(str(info.value)))
    assert len(set(kinds)) == len(texts) and set(kinds) <= set(p.DECODE_ERRORS), kinds
    assert p.error_kind('something else went wrong') == 'malformed'


def test_oversized_payload_is_refused_before_parsing():
    text = json.dumps({'x': 'a' * (p.MAX_PAYLOAD_BYTES + 1)})
    with pytest.raises(p.ProtocolError, match='over the'):
        p.AgentState.from_json(text)


def test_node_report_state_must_be_known():
    bad = p.AgentState('robot', 1, 1.0, {'n': p.NodeReport('dancing', 1, 1.0, 0, True, '')})
    with pytest.raises(p.ProtocolError, match='state'):
        p.AgentState.from_json(bad.to_json())


# --- the schema is derived from the fields: nothing declared is dropped -------------------------

def every_message_class():
    return sorted((c for c in vars(p).values() if isinstance(c, type)
                   and issubclass(c, p.Message) and c is not p.Message),
                  key=lambda c: c.__name__)


def valid_bodies():
    """A valid JSON object of every message class, the nested ones included."""
    out = {}

    def walk(message):
        out.setdefault(type(message), message.to_dict())
        for f in dataclasses.fields(message):
            value = getattr(message, f.name)
            for item in value.values() if isinstance(value, dict) else [value]:
                if isinstance(item, p.Message):
                    walk(item)
    for message in sample_messages():
        walk(message)
    return out


VALID = valid_bodies()
MESSAGES = every_message_class()


def test_every_message_class_has_a_valid_sample():
    assert set(VALID) == set(MESSAGES)


@pytest.mark.parametrize('cls', MESSAGES, ids=lambda c: c.__name__)
def test_every_field_is_in_the_derived_schema_with_its_rules(cls):
    hints = typing.get_type_hints(cls)
    assert list(cls.SCHEMA) == [f.name for f in dataclasses.fields(cls)]
    for f in dataclasses.fields(cls):
        optional = type(None) in typing.get_args(hints[f.name])
        assert (cls.SCHEMA[f.name][0] == 'optional' if optional
                else not isinstance(cls.SCHEMA[f.name], tuple) or
                cls.SCHEMA[f.name][0] == 'map'), f.name
        assert cls.RULES.get(f.name, ()) == tuple(f.metadata.get('rules', ())), f.name


def refused_by(rule):
    """Values of the right type that ``rule`` must refuse."""
    if isinstance(rule, p.Within):
        return [rule.lo - 1] + ([] if rule.hi is None else [rule.hi + 1])
    if isinstance(rule, p.OneOf):
        if all(isinstance(c, str) for c in rule.choices):
            return ['not ' + rule.choices[0]]
        return [max(rule.choices) + 1, min(rule.choices) - 1]
    if isinstance(rule, p.Text):
        return (['x' * (rule.max_len + 1)] + ([''] if rule.min_len else [])
                + (['a\nb'] if rule.printable else []))
    if isinstance(rule, p.Keys):
        return [{key: 'x'} for key in refused_by(rule.rule)]
    raise AssertionError(f'no bad values known for {rule!r}: add them here')


def accepted_by(rule):
    """Values at the edges of what ``rule`` lets through."""
    if isinstance(rule, p.Within):
        return [rule.lo] + ([] if rule.hi is None else [rule.hi])
    if isinstance(rule, p.OneOf):
        return list(rule.choices)
    if isinstance(rule, p.Text):
        return ['x' * rule.min_len, 'x' * rule.max_len]
    if isinstance(rule, p.Keys):
        return [{key: 'x'} for key in accepted_by(rule.rule)]
    raise AssertionError(f'no good values known for {rule!r}: add them here')


RULED = [(cls, name, rule) for cls in MESSAGES for name, rules in cls.RULES.items()
         for rule in rules]


def test_the_rules_the_wire_relies_on_are_declared():
    ruled = {f'{cls.__name__}.{name}' for cls, name, _ in RULED}
    assert {'Layout.generation', 'Layout.term', 'Layout.seq', 'Layout.auth',
            'Layout.assignments', 'AgentState.generation', 'AgentState.host',
            'ScaleStatus.sender', 'ScaleStatus.cpu_source', 'ConnectionReading.level',
            'ConnectionReading.senders', 'DeciderBeat.role', 'DeciderBeat.term',
            'Objective.seq', 'PlanCheck.sender'} <= ruled
    signed = [cls for cls in MESSAGES if 'sender' in cls.SCHEMA]
    assert len(signed) >= 6 and all(set(p.SIGNED_FIELDS) <= set(cls.RULES) for cls in signed)


@pytest.mark.parametrize('cls, name, rule', RULED,
                         ids=[f'{c.__name__}.{n}-{type(r).__name__}' for c, n, r in RULED])
def test_every_declared_rule_is_enforced(cls, name, rule):
    def body(value):
        if isinstance(rule, p.Keys) and VALID[cls][name]:
            # A map's keys are checked: its values are the sample's own.
            sample = next(iter(VALID[cls][name].values()))
            value = {k: sample for k in value}
        return json.dumps(dict(VALID[cls], **{name: value}))
    for bad in refused_by(rule):
        with pytest.raises(p.ProtocolError) as info:
            cls.from_json(body(bad))
        assert str(info.value).startswith(f'{cls.__name__}.{name}'), (bad, info.value)
    for good in accepted_by(rule):
        cls.from_json(body(good))


def mistyped(kind):
    """A JSON value of another kind than ``kind``."""
    if isinstance(kind, tuple):
        return [] if kind[0] == 'map' else mistyped(kind[1])
    if kind in (int, float):
        return '1'
    if kind is bool:
        return 1
    if kind is str or issubclass(kind, str):
        return 5
    return []    # a nested message


FIELDS = [(cls, name) for cls in MESSAGES for name in cls.SCHEMA]


@pytest.mark.parametrize('cls, name', FIELDS, ids=[f'{c.__name__}.{n}' for c, n in FIELDS])
def test_a_mistyped_or_missing_field_is_refused(cls, name):
    kind = cls.SCHEMA[name]
    with pytest.raises(p.ProtocolError, match=rf'^{cls.__name__}\.{name}: expected'):
        cls.from_json(json.dumps(dict(VALID[cls], **{name: mistyped(kind)})))
    absent = {k: v for k, v in VALID[cls].items() if k != name}
    if isinstance(kind, tuple) and kind[0] == 'optional':
        assert getattr(cls.from_json(json.dumps(dict(absent, **{name: None}))), name) is None
        assert getattr(cls.from_json(json.dumps(absent)), name) is None
    else:
        with pytest.raises(p.ProtocolError, match=f"missing field '{name}'"):
            cls.from_json(json.dumps(absent))
        with pytest.raises(p.ProtocolError, match=rf'^{cls.__name__}\.{name}: expected'):
            cls.from_json(json.dumps(dict(absent, **{name: None})))


def test_a_rule_that_cannot_run_on_its_field_is_refused_where_it_is_declared():
    @dataclasses.dataclass
    class Misdeclared(p.Message):
        name: str = dataclasses.field(metadata={'rules': (p.Within(0, 1),)})

    with pytest.raises(TypeError, match='Misdeclared.name'):
        p._wire(Misdeclared)

    @dataclasses.dataclass
    class Untranslatable(p.Message):
        names: typing.List[str]

    with pytest.raises(TypeError, match='Untranslatable.names: no wire form'):
        p._wire(Untranslatable)


def test_unset_optional_fields_are_left_out_but_a_link_keeps_its_null_readings():
    layout = json.loads(sample_messages()[0].to_json())
    assert set(layout) == {'generation', 'deployment', 'assignments', 'reason', 'stamp'}
    link = p.LinkStatus('robot', 'laptop', 1.0, False, None, 1.0, None, None, 0.0)
    sent = json.loads(link.to_json())
    assert sent['rtt_ms'] is None and sent['peer_agent'] is None and 'sender' not in sent
    state = p.AgentState('robot', 1, 1.0, {'n': p.NodeReport('running', 1, 1.0, 0, True, '')})
    assert json.loads(state.to_json())['nodes']['n']['lifecycle'] is None


def _asdict_json(message):
    """The JSON ``to_json`` wrote when it built its objects with ``dataclasses.asdict``: the
    oracle for the faster walk (protocol._plain)."""
    def nested(value):
        if isinstance(value, p.Message):
            out = dataclasses.asdict(value)
            for key in type(value).OMIT_WHEN_NONE:
                if out.get(key) is None:
                    out.pop(key, None)
            return out
        if isinstance(value, dict):
            return {k: nested(v) for k, v in value.items()}
        return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
    if isinstance(message, p.LinkStatus):
        out = dataclasses.asdict(message)
        for key in p.SIGNED_FIELDS:
            if out[key] is None:
                del out[key]
    else:
        out = {f.name: nested(getattr(message, f.name)) for f in dataclasses.fields(message)
               if getattr(message, f.name) is not None
               or not p._is_optional(message.SCHEMA[f.name])}
    return json.dumps(out, separators=(',', ':'), sort_keys=True)


@pytest.mark.parametrize('msg', sample_messages() + [
    p.AgentState(scale='robot', generation=4, stamp=2.0, seq=3, auth='k',
                 nodes={'amcl': p.NodeReport('crashed', 0, 1.0, 2, False, 'exited 1',
                                             exit_code=1, log_tail='boom')}),
    p.ConnectionStatus('robot', 1.0, {'amcl_ekf': p.ConnectionReading(
        2.0, 1e3, 0.5, 1, ended_below_s=0.2, recent_bytes_per_s=900.0, senders=2,
        senders_for_s=0.4)}),
    p.LinkStatus('robot', 'laptop', 1.0, False, None, 1.0, None, None, 0.0,
                 peer_agent='gone', peer_agent_for_s=2.0)],
    ids=lambda m: type(m).__name__)
def test_the_json_is_the_one_dataclasses_asdict_gave(msg):
    assert msg.to_json() == _asdict_json(msg)
    assert type(msg).from_json(msg.to_json()) == msg
