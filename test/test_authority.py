"""One decider, signed layouts (pure): key files, canonical form, HMAC, replay window, the
agents' follow rule (lease and term fence) and the generation bounds. No ROS. The deciders'
leadership rule: test_leadership.py."""

import json
import os
import stat
import subprocess
import sys

import pytest
import yaml

from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.agent.authority import Follower
from anyscale_manager.agent.reconcile import Reconciler
from anyscale_manager.protocol import MAX_GENERATION_STEP
from anyscale_manager.model.advice import warnings
from anyscale_manager.model.loader import DeploymentError, load_deployment, load_mapping
from conftest import TESTBED

KEY = bytes(range(32))


def ident(name='a', started=100.0, pid=1):
    return p.DeciderIdentity(id=name, host='robot', pid=pid, started=started)


def layout(generation=1, decider=None, seq=None, stamp=1000.0, assignments=None,
           deployment='d'):
    return p.Layout(generation=generation, deployment=deployment,
                    assignments=assignments or {'amcl': 'robot'}, reason='r', stamp=stamp,
                    decider=decider, seq=seq)


# --- protocol ---------------------------------------------------------------------------------

def test_an_older_layout_still_decodes_and_a_new_one_round_trips():
    old = '{"generation": 3, "deployment": "d", "assignments": {}, "reason": "", "stamp": 0}'
    lay = p.Layout.from_json(old)
    assert lay.decider is None and lay.seq is None and lay.auth is None
    assert 'decider' not in json.loads(lay.to_json())       # an older agent reads it
    new = layout(decider=ident(), seq=7)
    back = p.Layout.from_json(new.to_json())
    assert back == new and back.decider.describe() == 'a (host robot, pid 1)'
    state = p.AgentState(scale='robot', generation=2, stamp=1.0, nodes={}, decider='a')
    assert p.AgentState.from_json(state.to_json()).decider == 'a'
    assert p.AgentState.from_json(json.dumps(
        {'scale': 'robot', 'generation': 2, 'stamp': 1.0, 'nodes': {}})).decider is None


@pytest.mark.parametrize('field, value, error', [
    ('generation', 2 ** 53 + 1, 'beyond the bound 2**53'),
    ('generation', 10 ** 40, 'beyond the bound 2**53'),
    ('seq', -1, 'seq: must be in'),
    ('decider', {'id': '', 'host': 'h', 'pid': 1, 'started': 0.0}, 'bad decider identity'),
    ('decider', {'id': 'x', 'host': 'h', 'pid': 1}, "missing field 'started'"),
])
def test_bounds_and_identities_are_checked(field, value, error):
    data = json.loads(layout().to_json())
    data[field] = value
    with pytest.raises(p.ProtocolError, match=error.replace('*', r'\*')):
        p.Layout.from_json(json.dumps(data))


# --- key files --------------------------------------------------------------------------------

def test_keygen_writes_an_owner_only_key_and_refuses_to_overwrite(tmp_path):
    path = tmp_path / 'key'
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'keygen', str(path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert len(auth.load_key(str(path))) == auth.KEY_BYTES
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'keygen', str(path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and 'not overwriting' in r.stderr


def test_a_key_readable_by_others_or_malformed_is_refused(tmp_path):
    path = tmp_path / 'key'
    auth.write_key(str(path))
    os.chmod(path, 0o640)
    with pytest.raises(auth.KeyFileError, match='mode 0640 lets group or others read it'):
        auth.load_key(str(path))
    os.chmod(path, 0o600)
    path.write_text('not hex\n')
    with pytest.raises(auth.KeyFileError, match='not a hex key'):
        auth.load_key(str(path))
    path.write_text('00ff\n')
    with pytest.raises(auth.KeyFileError, match='at least 16 needed'):
        auth.load_key(str(path))
    with pytest.raises(auth.KeyFileError, match='cannot read'):
        auth.load_key(str(tmp_path / 'missing'))


# --- HMAC -------------------------------------------------------------------------------------

def test_canonical_form_ignores_field_order_spaces_and_auth():
    a = auth.canonical({'b': 1, 'a': {'y': 2.5, 'x': 'é'}, 'auth': 'zz'})
    b = auth.canonical(json.loads('{ "a" : {"x": "\\u00e9", "y": 2.5}, "b": 1 }'))
    assert a == b == b'{"a":{"x":"\\u00e9","y":2.5},"b":1}'


def test_a_sealed_layout_verifies_and_any_change_breaks_it():
    text = auth.seal(KEY, layout(decider=ident(), seq=1))
    assert auth.check_signature(KEY, text) == ''
    # Re-ordered and re-spaced on the way: still the same payload.
    assert auth.check_signature(KEY, json.dumps(json.loads(text), indent=2)) == ''
    data = json.loads(text)
    data['assignments'] = {'amcl': 'laptop'}
    assert 'bad authenticator' in auth.check_signature(KEY, json.dumps(data))
    assert 'bad authenticator' in auth.check_signature(bytes(32), text)
    assert 'not signed' in auth.check_signature(KEY, layout(decider=ident(), seq=1).to_json())
    assert auth.seal(None, layout()) == layout().to_json()     # no key: as before


def test_replay_guard_refuses_old_stamps_and_repeated_sequences():
    guard = auth.ReplayGuard(window_s=30.0)
    assert guard.check('a', 1, stamp=1000.0, now_wall=1010.0) == ''
    guard.accept('a', 1)
    assert 'not above 1' in guard.check('a', 1, stamp=1000.0, now_wall=1010.0)
    assert guard.check('a', 2, stamp=1000.0, now_wall=1010.0) == ''
    assert 'outside the 30 s window' in guard.check('a', 5, stamp=1000.0, now_wall=1031.0)
    assert 'outside the 30 s window' in guard.check('a', 5, stamp=1040.0, now_wall=1000.0)
    assert guard.check('b', 1, stamp=1000.0, now_wall=1000.0) == ''    # per sender
    assert 'no sequence number' in guard.check('a', None, stamp=1000.0, now_wall=1000.0)
    small = auth.ReplayGuard(max_senders=2)
    for name in 'xyz':
        small.accept(name, 1)
    assert small.last('x') is None and small.last('z') == 1


def test_layout_gate_drops_forged_unsigned_and_replayed_layouts():
    gate = auth.LayoutGate(KEY, window_s=30.0)
    good = layout(decider=ident(), seq=4, stamp=1000.0)
    text = auth.seal(KEY, good)
    assert gate.check(text, good, now_wall=1001.0) == ''
    assert 'a replay' in gate.check(text, good, now_wall=1002.0)            # same message again
    forged = layout(generation=10 ** 15, decider=ident(), seq=99, stamp=1000.0,
                    assignments={'amcl': 'laptop'})
    assert 'not signed' in gate.check(forged.to_json(), forged, now_wall=1001.0)
    assert 'bad authenticator' in gate.check(auth.seal(bytes(32), forged), forged, 1001.0)
    later = layout(decider=ident(), seq=5, stamp=1000.0)
    assert 'window' in gate.check(auth.seal(KEY, later), later, now_wall=1100.0)
    anonymous = layout(seq=1)
    assert 'names no decider' in gate.check(auth.seal(KEY, anonymous), anonymous, 1000.0)
    assert auth.LayoutGate(None).check('anything', forged, 0.0) == ''       # no key: as today


def test_each_reason_a_gate_gives_has_its_own_kind_from_a_fixed_set():
    """The throttled logs key on it: a forgery and a replay in one interval are two lines."""
    gate = auth.LayoutGate(KEY, window_s=30.0)
    good = layout(decider=ident(), seq=4, stamp=1000.0)
    forged = layout(decider=ident(), seq=9, stamp=1000.0, assignments={'amcl': 'laptop'})
    late = layout(decider=ident(), seq=7, stamp=1000.0)
    anonymous = layout(seq=1)
    gate.check(auth.seal(KEY, good), good, 1001.0)
    reasons = [gate.check('[1]', good, 1001.0), gate.check('{', good, 1001.0),
               gate.check(forged.to_json(), forged, 1001.0),
               gate.check(auth.seal(bytes(32), forged), forged, 1001.0),
               gate.check(auth.seal(KEY, anonymous), anonymous, 1001.0),
               gate.check(auth.seal(KEY, late), late, 1100.0),
               gate.check(auth.seal(KEY, good), good, 1001.0),
               auth.ReplayGuard().check('a', None, 1000.0, 1000.0)]
    kinds = [auth.refusal_kind(f'dropped layout generation 3 of decider x: {why}')
             for why in reasons]
    assert len(set(kinds)) == len(reasons) and set(kinds) <= set(auth.REFUSALS), kinds
    # Nothing of a message's own text makes a new kind.
    assert auth.refusal_kind("scale 'bad: authenticator 1': whatever it says") == 'malformed'


# --- the agents' follow rule ------------------------------------------------------------------

def test_an_agent_follows_one_decider_and_switches_only_after_its_lease():
    f = Follower(lease_s=3.0)
    v = f.consider(ident('a'), 0.0)
    assert v.accept and v.switched and 'following decider a' in v.reason
    assert f.consider(ident('a'), 1.0) == (True, False, '') or f.consider(ident('a'), 1.0).accept
    v = f.consider(ident('b', started=150.0), 2.0)
    assert not v.accept and 'following a (host robot, pid 1) (term 0), heard 1.0 s ago' \
        in v.reason
    v = f.consider(None, 3.5)                              # a plain script: refused as well
    assert not v.accept and 'without identity' in v.reason
    v = f.consider(ident('b', started=150.0), 4.0)        # a silent for 3 s: lease lapsed
    assert v.accept and v.switched and 'silent for 3.0 s' in v.reason
    assert f.followed_id == 'b'
    assert not f.consider(ident('a'), 4.5).accept          # and a back: refused now


def test_a_higher_term_is_followed_at_once_and_a_lower_one_refused_while_the_lease_holds():
    f = Follower(lease_s=3.0)
    assert f.consider(ident('a'), 0.0, term=4).accept and f.term == 4
    # The standby that took over: a higher term, followed at once (no lease to wait out).
    v = f.consider(ident('b', started=150.0), 0.5, term=5)
    assert v.accept and v.switched and 'leads at term 5, above term 4' in v.reason
    assert (f.followed_id, f.term) == ('b', 5)
    # The old leader back from a stall: its term is lower, refused whatever it says.
    v = f.consider(ident('a'), 0.6, term=4)
    assert not v.accept and '(term 4) ignored: following b' in v.reason
    assert f.consider(ident('b', started=150.0), 1.0, term=5).accept
    # Two that took the lead together at one term: the one started first, on both sides.
    v = f.consider(ident('c', started=120.0), 1.1, term=5)
    assert v.accept and v.switched and 'started before it' in v.reason
    assert not f.consider(ident('b', started=150.0), 1.2, term=5).accept
    # A lone decider restarted with no memory of terms: followed once c's lease lapsed.
    assert not f.consider(ident('d', started=900.0), 2.0, term=1).accept
    v = f.consider(ident('d', started=900.0), 4.2, term=1)
    assert v.accept and v.switched and 'silent for 3.1 s' in v.reason and f.term == 1


def test_without_identities_the_anonymous_decider_is_followed_as_before():
    f = Follower(lease_s=3.0)
    assert f.consider(None, 0.0).switched
    assert f.consider(None, 100.0) == (True, False, '') or f.consider(None, 100.0).accept
    assert f.followed_id == ''


# --- generations ------------------------------------------------------------------------------

def test_generations_are_compared_per_decider_and_bounded():
    d = load_deployment(TESTBED)
    r = Reconciler(d, 'robot', ('amcl',), readiness_timeout_s=5.0, agent_timeout_s=5.0)
    assert r.apply_layout(layout(50, deployment=d.name), 0.0).applied
    v = r.apply_layout(layout(50 + MAX_GENERATION_STEP + 1, deployment=d.name), 1.0)
    assert not v.applied and 'jumps more than' in v.warnings[0]
    assert r.apply_layout(layout(50 + MAX_GENERATION_STEP, deployment=d.name), 1.0).applied
    # A new decider's first layout is taken whatever its number.
    assert r.apply_layout(layout(1, deployment=d.name), 2.0, new_decider=True).applied
    assert r.generation == 1


# --- the deployment ---------------------------------------------------------------------------

def _testbed():
    with open(TESTBED) as f:
        return yaml.safe_load(f)


def test_security_settings_are_read_checked_and_warned_about():
    data = _testbed()
    params = data['/**']['ros__parameters']
    d = load_mapping(data, 'x.yaml')
    assert d.security.key_file == '' and d.decider.lease_s == 3.0
    assert d.decider.discovery_s == 5.0
    assert any('security.key_file is not set' in w for w in warnings(d))
    params['security'] = {'key_file': '/etc/anyscale/key', 'replay_window_s': 10.0}
    params['decider']['lease_s'] = 2.0
    d = load_mapping(data, 'x.yaml')
    assert d.security.replay_window_s == 10.0 and d.decider.lease_s == 2.0
    assert not any('security' in w for w in warnings(d))
    params['security'] = {'key_file': 'relative/key', 'replay_window_s': 0.0, 'x': 1}
    with pytest.raises(DeploymentError) as info:
        load_mapping(data, 'x.yaml')
    text = str(info.value)
    assert 'security.key_file: expected an absolute path' in text
    assert 'security.replay_window_s' in text and 'security.x' in text


def test_validate_refuses_a_key_file_open_to_others(tmp_path):
    key = tmp_path / 'key'
    auth.write_key(str(key))
    data = _testbed()
    data['/**']['ros__parameters']['security'] = {'key_file': str(key)}
    path = tmp_path / 'd.yaml'
    path.write_text(yaml.safe_dump(data))
    run = [sys.executable, '-m', 'anyscale_manager.cli', 'validate', '--quiet', str(path)]
    r = subprocess.run(run, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and 'security' not in r.stderr, r.stderr
    os.chmod(key, 0o644)
    r = subprocess.run(run, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and 'lets group or others read it' in r.stderr


def test_agent_states_and_objectives_are_sealed_and_checked_like_layouts():
    gate = auth.Gate(KEY, window_s=30.0)
    state = p.AgentState(scale='away', generation=3, stamp=1000.0, nodes={}, decider='a',
                         instance='i1', seq=1)
    text = auth.seal(KEY, state)
    back = p.AgentState.from_json(text)
    assert back.instance == 'i1' and back.seq == 1 and back.auth
    assert gate.check_from(text, 'away/i1', back.seq, back.stamp, 1001.0) == ''
    assert 'a replay' in gate.check_from(text, 'away/i1', back.seq, back.stamp, 1001.0)
    assert 'not signed' in gate.check_from(state.to_json(), 'away/i1', 2, 1000.0, 1001.0)
    objective = p.Objective(stamp=1000.0, perf_map=1.0, integral=2.0, elapsed_s=3.0,
                            decider='a', seq=1)
    text = auth.seal(KEY, objective)
    assert p.Objective.from_json(text).decider == 'a'
    assert gate.check_from(text, 'a', 1, 1000.0, 1000.0) == ''
    assert 'names no sender' in gate.check_from(text, None, 1, 1000.0, 1000.0)
    # Without the new fields both read as before.
    plain = p.Objective(stamp=1.0, perf_map=1.0, integral=2.0, elapsed_s=3.0)
    assert set(json.loads(plain.to_json())) == {'stamp', 'perf_map', 'integral', 'elapsed_s'}
