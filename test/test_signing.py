"""Every project status topic signed with the deployment's key (protocol_auth): pure checks of
the sealer, the gates and the status view's book, with a hand-made key and clock."""

import json
import time

import pytest

from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.view.status import StatusBook, render

KEY, OTHER = bytes(range(32)), bytes(32)


def messages(now):
    return [
        (p.TOPIC_SCALE_STATUS, p.ScaleStatus(scale='laptop', stamp=now, cpu_total=10.0,
                                             capacity_cpu=700.0, cpu_by_node={}, mem_percent=1.0,
                                             load_1m=0.1)),
        (p.TOPIC_LINK_STATUS, p.LinkStatus(master='robot', remote='laptop', stamp=now, up=True,
                                           rtt_ms=1.0, loss=0.0, bandwidth_available_kbps=None,
                                           bandwidth_available_age_s=None,
                                           bandwidth_used_kbps=0.0)),
        (p.TOPIC_CONNECTION_STATUS, p.ConnectionStatus(scale='robot', stamp=now, connections={
            'laser_amcl': p.ConnectionReading(rate_hz=10.0, bytes_per_s=1.0, below_for_s=0.0,
                                              level=p.OK)})),
        (p.TOPIC_EVENTS, p.Event(stamp=now, kind='migrate', node='amcl', from_scale='robot',
                                 to_scale='laptop', reason='test', generation=2)),
        (p.TOPIC_PLAN_CHECK, p.PlanCheck(stamp=now, nodes={}, overall_deviation=0.0)),
    ]


@pytest.mark.parametrize('index', range(5))
def test_a_sealed_status_passes_its_gate_once_and_nothing_else_does(index):
    now = time.time()
    topic, message = messages(now)[index]
    sealer = auth.Sealer(KEY, 'agent laptop')
    text = sealer.seal(message)
    decoded = type(message).from_json(text, topic)
    assert decoded.sender == sealer.sender and decoded.seq == 1 and decoded.auth
    gate = auth.StatusGate(KEY)
    assert gate.check(text, decoded, now) == ''
    assert 'a replay' in gate.check(text, decoded, now)              # the same message again
    second = type(message).from_json(sealer.seal(message), topic)
    assert second.seq == 2 and gate.check(second.to_json(), second, now) == ''
    # Unsigned (as without a key), altered, or signed with another key: refused.
    plain = auth.Sealer(None, 'x').seal(messages(now)[index][1])
    plain_msg = type(message).from_json(plain, topic)
    assert 'sender' not in json.loads(plain) and 'auth' not in json.loads(plain)
    assert 'not signed' in auth.StatusGate(KEY).check(plain, plain_msg, now)
    data = json.loads(text)
    data['stamp'] = now + 1.0
    assert 'bad authenticator' in auth.StatusGate(KEY).check(json.dumps(data), decoded, now)
    foreign = auth.Sealer(OTHER, 'agent laptop').seal(message)
    assert 'bad authenticator' in auth.StatusGate(KEY).check(
        foreign, type(message).from_json(foreign, topic), now)
    # Stamped outside the window: a replay to a receiver that had not heard the sender yet.
    assert 'outside' in auth.StatusGate(KEY, window_s=30.0).check(text, decoded, now + 60.0)


def test_a_restarted_sender_is_a_new_sender_to_every_guard():
    a, b = auth.Sealer(KEY, 'agent robot'), auth.Sealer(KEY, 'agent robot')
    assert a.sender != b.sender and a.sender.startswith('agent robot/')


@pytest.mark.parametrize('sender', ['', 'x' * 129, 'a\nb'])
def test_a_bad_sender_is_a_protocol_error(sender):
    data = json.loads(messages(time.time())[0][1].to_json())
    data.update(sender=sender, seq=1)
    with pytest.raises(p.ProtocolError, match='sender'):
        p.ScaleStatus.from_json(json.dumps(data))


def test_the_status_view_with_a_key_shows_only_what_is_signed(testbed_path):
    deployment = load_deployment(testbed_path)
    now = time.time()
    book = StatusBook(deployment, key=KEY)
    sealer = auth.Sealer(KEY, 'agent laptop')
    topic, good = messages(now)[0]
    text = sealer.seal(good)
    book.take(topic, text, 0.0, wall=now)
    _, forged = messages(now)[0]
    forged.scale, forged.cpu_total = 'robot', 999.0
    book.take(topic, forged.to_json(), 0.0, wall=now)     # unsigned
    book.take(topic, text, 0.0, wall=now)                 # replayed
    assert set(book.scales) == {'laptop'} and book.refused == 2
    # A signed message judged on a clock a minute later is outside the replay window.
    late = StatusBook(deployment, key=KEY)
    late.take(topic, sealer.seal(messages(now)[0][1]), 0.0, wall=now + 60.0)
    assert not late.scales and late.refused == 1
    assert '2 message(s) refused: unsigned, forged or replayed' in render(book, 0.0)
