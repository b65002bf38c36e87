"""Bad input everywhere: every project topic, the agent's state file, its state and log folders,
a full disk, catalogue commands that do not exist or exit at once.

Each is refused or worked around with one clear log line (throttled where it can repeat),
nothing that runs is disturbed, and no process of the project crashes. The pure paths are tested
without ROS; two tests run the real decider and agents.
"""

import json
from collections import Counter
import os
import subprocess
import sys
import time

import psutil
import pytest
import yaml
from std_msgs.msg import String

from anyscale_manager import protocol as p
from anyscale_manager import protocol_auth as auth
from anyscale_manager.agent import procs
from anyscale_manager.agent.catalogue import base_environment, build_catalogue, Entry
from anyscale_manager.agent.supervisor import MAX_STATE_BYTES, Supervisor
from anyscale_manager.model.loader import load_deployment, load_mapping
from anyscale_manager.nodes import qos
from anyscale_manager.nodes.throttled_log import MAX_KINDS, ThrottledLog
from anyscale_manager.runtime.intake import MAX_IGNORED_KINDS, ObservationBook
from conftest import TESTBED
from home_away import ONE_DECIDER_DISCOVERY_S
from processes import LoggedProcess
from supervision import drive, FAST, py_entry, SLEEPER
from test_decider_agent import write_deployment
from test_protocol import sample_messages

BIN = os.path.dirname(sys.executable)

# Every project topic and the message it carries (/diagnostics is typed: not JSON).
DECODERS = {
    p.TOPIC_LAYOUT: p.Layout, p.TOPIC_AGENT_STATE: p.AgentState,
    p.TOPIC_SCALE_STATUS: p.ScaleStatus, p.TOPIC_LINK_STATUS: p.LinkStatus,
    p.TOPIC_CONNECTION_STATUS: p.ConnectionStatus, p.TOPIC_EVENTS: p.Event,
    p.TOPIC_OBJECTIVE: p.Objective, p.TOPIC_PLAN_CHECK: p.PlanCheck,
    p.TOPIC_DECIDER: p.DeciderBeat,
}
VALID = {type(m): m for m in sample_messages()}


def test_every_project_topic_has_a_decoder_here():
    topics = {v for k, v in vars(p).items() if k.startswith('TOPIC_')} - {p.TOPIC_DIAGNOSTICS}
    assert topics == set(DECODERS)


# --- the protocol, without ROS ----------------------------------------------------------------

def hostile(cls):
    """(label, payload) pairs that ``cls``'s decoder must refuse."""
    good = VALID[cls].to_dict()
    number = next(k for k, kind in cls.SCHEMA.items() if kind is float)
    other = p.PlanNode(1.0, 1.0, 1.0, 1.0, 0.0)         # a message of no topic

    def with_(key, raw):
        body = dict(good)
        body[key] = '@@'
        return json.dumps(body).replace('"@@"', raw)

    nested = '[' * 40 + ']' * 40
    return [
        ('empty', ''), ('garbage', '\x00\xff\ufffd garbage'), ('a list', '[1, 2]'),
        ('null', 'null'), ('a string', '"text"'), ('a number', '5'),
        ('oversized', json.dumps(dict(good, padding='a' * p.MAX_PAYLOAD_BYTES))),
        ('nested past the recursion limit', '[' * 100000 + ']' * 100000),
        ('nested in a field', with_(number, nested)),
        ('nested objects', '{"a": ' * 50 + '1' + '}' * 50),
        ('NaN', with_(number, 'NaN')), ('Infinity', with_(number, 'Infinity')),
        ('-Infinity', with_(number, '-Infinity')), ('overflowing to inf', with_(number, '1e400')),
        ('huge', with_(number, '1e300')),
        ('integer of 5000 digits', with_(number, '1' * 5000)),
        ('another kind of message', other.to_json()),
        ('unknown field', json.dumps(dict(good, command='rm -rf /'))),
        ('a key with a newline', json.dumps(dict(good, **{'fake\n[ERROR] line': 1}))),
        ('missing field', json.dumps({k: v for k, v in good.items() if k != number})),
    ]


CASES = [(topic, label, text) for topic, cls in DECODERS.items() for label, text in hostile(cls)]


@pytest.mark.parametrize('topic, label, text', CASES,
                         ids=[f'{topic}-{label}' for topic, label, _ in CASES])
def test_hostile_payload_refused_in_one_bounded_line(topic, label, text):
    with pytest.raises(p.ProtocolError) as info:
        DECODERS[topic].from_json(text, topic)
    why = str(info.value)
    assert why.startswith(topic) and '\n' not in why and len(why) < 400, why


@pytest.mark.parametrize('cls', sorted(set(DECODERS.values()), key=lambda c: c.__name__),
                         ids=lambda c: c.__name__)
def test_valid_messages_still_decode(cls):
    assert cls.from_json(VALID[cls].to_json()) == VALID[cls]


def test_deep_nesting_is_refused_from_a_deep_call_stack():
    """A callback runs some frames deep: nesting near the recursion limit must still be a
    ProtocolError there, never a RecursionError out of the decoder."""
    def deep(n):
        return p.Layout.from_json('{"reason": ' + '[' * 960 + ']' * 960 + '}', 'x') \
            if n == 0 else deep(n - 1)
    for frames in (0, 30, 100, 200):
        with pytest.raises(p.ProtocolError, match='nested deeper|not valid JSON'):
            deep(frames)


@pytest.mark.parametrize('cls, body, words', [
    (p.AgentState, {'scale': 'a', 'generation': 1, 'stamp': 1.0, 'nodes': {'n': {
        'state': 'exploding', 'pid': 1, 'since': 1.0, 'restarts': 0, 'ready': True,
        'exit_reason': ''}}}, 'state: expected one of'),
    (p.ConnectionStatus, {'scale': 'a', 'stamp': 1.0, 'connections': {'c': {
        'rate_hz': 1.0, 'bytes_per_s': 1.0, 'below_for_s': 0.0, 'level': 9}}}, 'level'),
    (p.ScaleStatus, {'scale': 'a', 'stamp': 1.0, 'cpu_total': 1.0, 'capacity_cpu': 1.0,
                     'cpu_by_node': {'n': 1e308}, 'mem_percent': 1.0, 'load_1m': 1.0},
     'beyond the bound'),
])
def test_unknown_kinds_and_unbounded_numbers_are_refused(cls, body, words):
    with pytest.raises(p.ProtocolError, match=words):
        cls.from_json(json.dumps(body))


def test_bounds_leave_real_readings_alone():
    status = p.ScaleStatus('robot', time.time(), 350.0, 400.0, {'amcl': 1e12}, 40.0, 0.5)
    assert p.ScaleStatus.from_json(status.to_json()) == status


def test_the_decider_book_keeps_a_bounded_count_of_what_it_skipped():
    d = load_deployment(TESTBED)
    book = ObservationBook(d, d.decider, 0.0)
    report = p.NodeReport('running', 1, 1.0, 0, True, '')
    for i in range(20):
        names = {f'ghost{i}_{j}': report for j in range(100)}
        book.agent_state(p.AgentState(d.master.name, 1, 1.0, names), float(i))
    assert len(book.ignored) <= MAX_IGNORED_KINDS + 1
    assert sum(book.ignored.values()) == 2000


# --- the throttled log, without ROS -----------------------------------------------------------

class FakeLogger:
    def __init__(self):
        self.lines = []

    def warning(self, text):
        self.lines.append(('warn', text))

    def error(self, text):
        self.lines.append(('error', text))


def test_throttled_log_says_once_per_interval_with_a_count():
    now = [0.0]
    logger = FakeLogger()
    log = ThrottledLog(logger, interval_s=10.0, clock=lambda: now[0])
    for i in range(500):
        now[0] = i * 0.01
        log.warn('/anyscale/layout: malformed', f'bad layout {i}')
    log.error('/anyscale/agent_state: refused', 'forged state')     # another kind: at once
    log.flush()
    assert logger.lines == [('warn', 'bad layout 0'), ('error', 'forged state')]
    now[0] = 10.5
    log.flush()
    assert logger.lines[-1] == ('warn', 'bad layout 499 [499 more like this in the last 10 s]')
    log.flush()
    assert len(logger.lines) == 3            # nothing held back since
    now[0] = 30.0
    log.warn('/anyscale/layout: malformed', 'bad layout again')
    assert logger.lines[-1] == ('warn', 'bad layout again')
    assert log.total == 502


def test_throttled_log_keeps_a_bounded_number_of_kinds():
    logger = FakeLogger()
    log = ThrottledLog(logger, interval_s=10.0, clock=lambda: 0.0)
    for i in range(MAX_KINDS * 3):
        log.warn(f'kind {i}', 'x')
    assert len(log._kinds) <= MAX_KINDS


def test_a_kind_forgotten_for_room_says_what_it_held_back_first():
    logger = FakeLogger()
    log = ThrottledLog(logger, interval_s=10.0, clock=lambda: 0.0)
    log.warn('kind 0', 'first')
    log.warn('kind 0', 'second')                 # held back
    for i in range(1, MAX_KINDS + 1):
        log.warn(f'kind {i}', 'x')               # the last one makes room: kind 0 goes
    assert ('warn', 'second [1 more like this in the last 0 s]') in logger.lines


def test_every_key_a_node_can_make_fits_the_throttle():
    """The decider's four status topics and the agent's signed topics, each with every kind
    of bad input: no kind is forgotten (and said again at once) while a sender cycles them."""
    kinds = len(p.DECODE_ERRORS) + len(auth.REFUSALS) + 2
    assert 6 * kinds <= MAX_KINDS


# --- the agent's state file ---------------------------------------------------------------------

def live_record(pid):
    return {'pid': pid, 'start_ticks': procs.start_ticks(pid), 'instance': 'x',
            'argv': ['x'], 'restarts': 0}


def state_text(records, version=1):
    return json.dumps({'version': version, 'deployment': 'd', 'scale': 's', 'nodes': records})


STATE_FILES = [
    ('truncated', lambda: state_text({'n': live_record(os.getpid())})[:40], 'unreadable'),
    ('corrupt', lambda: '\x00\x01garbage\xff{', 'unreadable'),
    ('empty', lambda: '', 'unreadable'),
    ('deeply nested', lambda: '[' * 100000 + ']' * 100000, 'unreadable'),
    ('not an object', lambda: '[1, 2]', 'unreadable'),
    ('another version', lambda: state_text({'n': live_record(os.getpid())}, version=7),
     'version 7, this agent reads version 1'),
    ('no map of nodes', lambda: json.dumps({'version': 1, 'nodes': [1]}), 'no map of nodes'),
    ('oversized', lambda: state_text({'pad': 'a' * MAX_STATE_BYTES}), 'over'),
]


@pytest.mark.parametrize('label, content, words', STATE_FILES, ids=[c[0] for c in STATE_FILES])
def test_a_bad_state_file_adopts_nothing_and_is_kept_aside(make_sup, label, content, words):
    sup = make_sup([py_entry('n', SLEEPER)])
    os.makedirs(os.path.dirname(sup.state_path), exist_ok=True)
    with open(sup.state_path, 'w', encoding='utf-8', errors='surrogateescape') as f:
        f.write(content())
    notes = sup.adopt(time.monotonic())
    assert len(notes) == 1 and words in notes[0] and sup.state_path in notes[0], notes
    assert sup.pids() == {} and sup.wanted() == ()
    # Kept for a person to read; the next save writes a fresh one.
    assert os.path.exists(sup.state_path + '.unreadable')
    sup.start('n', time.monotonic())
    with open(sup.state_path) as f:
        assert list(json.load(f)['nodes']) == ['n']


@pytest.mark.parametrize('record', [
    {'pid': float('inf'), 'started': 1.0, 'instance': 'x', 'argv': ['x']},
    {'pid': 'me', 'started': 1.0, 'instance': 'x', 'argv': ['x']},
    {'pid': 10 ** 30, 'started': float('nan'), 'instance': 'x', 'argv': 5},
    {'pid': 5, 'start_ticks': 'soon', 'instance': 'x', 'argv': ['x']},
    {'pid': 5, 'start_ticks': -1, 'instance': 'x', 'argv': ['x']},
    'a string', [1, 2], None,
], ids=['pid Infinity', 'pid a word', 'huge pid', 'ticks a word', 'ticks negative', 'a string',
        'a list', 'null'])
def test_a_bad_state_record_is_ignored_alone(make_sup, record):
    sleeper = subprocess.Popen([sys.executable, '-c', SLEEPER])
    try:
        sup = make_sup([py_entry('n', SLEEPER)])
        os.makedirs(os.path.dirname(sup.state_path), exist_ok=True)
        with open(sup.state_path, 'w') as f:
            # json writes Infinity and NaN as Python's reader accepts them.
            f.write(state_text({'bad': record, 'n': live_record(sleeper.pid)}))
        notes = sup.adopt(time.monotonic())
        assert 'bad: malformed state record; ignored' in notes, notes
        assert sleeper.poll() is None       # never signalled: its token does not match
    finally:
        sleeper.kill()
        sleeper.wait()


# --- the state and log folders, and a full disk -------------------------------------------------

def errors(sup, words):
    return [text for level, text in sup.events if level == 'error' and words in text]


def test_an_unwritable_state_folder_keeps_the_nodes_running(make_sup, tmp_path):
    blocker = tmp_path / 'blocker'
    blocker.write_text('a regular file where the state folder should be')
    sup = make_sup([py_entry('n', SLEEPER)], state_path=blocker / 'state' / 'agent.json')
    sup.start('n', time.monotonic())
    pid = sup.pids()['n']
    for _ in range(20):                 # a save is tried at every step while it fails
        sup.step(time.monotonic())
    assert sup.pids() == {'n': pid} and psutil.pid_exists(pid)
    said = errors(sup, 'cannot write the state file')
    assert len(said) == 1 and str(blocker) in said[0] and 'keep running' in said[0]
    assert not list(tmp_path.glob('**/*.tmp'))
    blocker.unlink()                    # the folder becomes usable: written at the next step
    sup.step(time.monotonic())
    assert any('written again' in text for _, text in sup.events)
    with open(sup.state_path) as f:
        assert json.load(f)['nodes']['n']['pid'] == pid


def test_an_unwritable_log_folder_still_starts_the_node(make_sup, tmp_path):
    blocker = tmp_path / 'blocker'
    blocker.write_text('a regular file where the log folder should be')
    sup = make_sup([py_entry('n', SLEEPER)], log_dir=blocker / 'log')
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running')
    said = errors(sup, 'cannot write its log file')
    assert len(said) == 1 and str(blocker / 'log' / 'n.log') in said[0]
    assert 'output discarded' in said[0]


@pytest.fixture
def full_disk(tmp_path):
    """A 64 KiB tmpfs, filled up (root only); unmounted after the test."""
    mount = tmp_path / 'tiny'
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip('a full disk is emulated with a tmpfs mount, which needs root')
    r = subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=64k', 'tmpfs', str(mount)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f'cannot mount a tmpfs here: {r.stderr.strip()}')
    try:
        (mount / 'state').mkdir()
        (mount / 'log').mkdir()
        filler = mount / 'filler'
        with open(filler, 'wb', buffering=0) as f:
            try:
                while True:
                    f.write(bytes(4096))
            except OSError:
                pass
        yield mount, filler
    finally:
        subprocess.run(['umount', '-l', str(mount)], check=False)


def test_a_full_disk_keeps_the_node_running_and_recovers(make_sup, full_disk):
    mount, filler = full_disk
    entry = py_entry('n', SLEEPER)
    sup = make_sup([entry], log_dir=mount / 'log',
                   state_path=mount / 'state' / 'agent.json')
    sup.start('n', time.monotonic())
    assert drive(sup, lambda: sup.reports()['n'].state == 'running')
    pid = sup.pids()['n']
    assert len(errors(sup, 'cannot write its log file')) == 1
    said = errors(sup, 'cannot write the state file')
    assert len(said) == 1 and 'No space left on device' in said[0]
    filler.unlink()                     # room again: the state is written at the next step
    sup.step(time.monotonic())
    with open(sup.state_path) as f:
        assert json.load(f)['nodes']['n']['pid'] == pid
    # And a restarted agent adopts it from there.
    again = Supervisor({'n': entry}, FAST, str(mount / 'log'), state_path=sup.state_path,
                       identity={'deployment': 'd', 'scale': 's'})
    assert again.adopt(time.monotonic()) == [f'n: adopted pid {pid}']


# --- catalogue commands -------------------------------------------------------------------------

def test_missing_and_failing_commands_leave_the_others_running(make_sup, tmp_path):
    d = load_mapping({'/**': {'ros__parameters': {
        'deployment': {'name': 'unit'},
        'scales': {'names': ['a'], 'a': {'role': 'master', 'kind': 'robot',
                                         'capacity_cpu': 100.0}},
        'nodes': {'names': ['ghost'],
                  'ghost': {'launch': {'command': ['no-such-command-anywhere']}, 'cpu': 1.0}},
    }}})
    ghost = build_catalogue(d, 'a')['ghost']
    assert not ghost.startable and 'not found on PATH' in ghost.problem
    entries = [ghost, py_entry('steady', SLEEPER), py_entry('quitter', 'raise SystemExit(3)'),
               Entry(name='vanished', argv=(str(tmp_path / 'no' / 'such' / 'binary'),),
                     env=base_environment(os.environ))]
    sup = make_sup(entries)
    sup.set_wanted([e.name for e in entries], time.monotonic())
    steady = sup.pids()['steady']
    drive(sup, lambda: False, timeout=3.0)
    reports = sup.reports()
    assert sup.pids().get('steady') == steady and reports['steady'].restarts == 0
    assert reports['ghost'].state == 'failed' and 'not found' in reports['ghost'].exit_reason
    assert reports['vanished'].state == 'failed'
    assert 'No such file or directory' in reports['vanished'].exit_reason
    assert reports['quitter'].restarts >= 2
    # One line per attempt, and the attempts are spaced by the backoff: a handful in 3 s.
    for name in ('ghost', 'vanished', 'quitter'):
        lines = [text for level, text in sup.events if level == 'error' and name in text]
        assert 1 <= len(lines) <= 8, lines


# --- the real processes -------------------------------------------------------------------------

def ros_child_env(ros_env, **extra):
    env = dict(ros_env)     # with the packaged discovery profile (conftest)
    env.update(extra)
    return env


@pytest.mark.parametrize('program, extra, words', [
    ('agent', ['-p', 'agent.state_dir:={blocker}/state'], 'cannot use the state folder'),
    ('agent', [], 'failed to initialize logging'),
    ('decider', [], 'failed to initialize logging'),
], ids=['agent state folder', 'agent ROS log folder', 'decider ROS log folder'])
def test_unusable_folders_at_start_exit_2_with_one_line(tmp_path, ros_env, program, extra,
                                                        words):
    blocker = tmp_path / 'blocker'
    blocker.write_text('a regular file')
    path = write_deployment(tmp_path)
    env = ros_child_env(ros_env)
    if not extra:
        env['ROS_LOG_DIR'] = str(blocker / 'log')
    argv = [os.path.join(BIN, program), '--ros-args', '--params-file', path]
    argv += ['-p', 'scale:=home'] if program == 'agent' else []
    argv += [a.format(blocker=blocker) for a in extra]
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60)
    out = r.stdout + r.stderr
    assert r.returncode == 2 and words in out and 'Traceback' not in out, out


def hostile_burst(name):
    """Bad messages for every topic: garbage, oversized, nested, non-finite, unknown kinds, a
    layout of another deployment, a scale the deployment does not have."""
    now = time.time()
    return [
        '', 'garbage \x00\xff', '[' * 100000 + ']' * 100000, '{"a": ' * 50 + '1' + '}' * 50,
        '{"generation": NaN, "stamp": Infinity}',
        p.PlanNode(1.0, 1.0, 1.0, 1.0, 0.0).to_json(),
        json.dumps({'stamp': now, 'kind': 'self_destruct', 'node': 'worker'}),
        p.Layout(generation=10 ** 6, deployment=f'not_{name}', reason='elsewhere', stamp=now,
                 assignments={'worker': 'home', 'pinned': 'away'}).to_json(),
        json.dumps({'scale': 'home', 'stamp': now, 'cpu_total': 1e308, 'capacity_cpu': 1.0,
                    'cpu_by_node': {'worker': 1e308}, 'mem_percent': 1.0, 'load_1m': 1.0}),
        p.AgentState(scale='ghost', generation=1, stamp=now, nodes={}).to_json(),
        json.dumps({'scale': 'home', 'stamp': now, 'connections': {'c': {
            'rate_hz': 1.0, 'bytes_per_s': 1.0, 'below_for_s': 0.0, 'level': 99}}}),
    ]


def test_decider_and_agents_survive_hostile_messages_on_every_topic(tmp_path, ros_env, ros):
    path = write_deployment(tmp_path)
    with open(path) as f:
        data = yaml.safe_load(f)
    params = data['/**']['ros__parameters']
    name = params['deployment']['name'] = f'bad_input_{os.getpid()}'
    # A loaded machine may hold a callback for a while: not this test's subject, so silence is
    # judged over 10 s rather than 3.
    params['decider'].update(agent_timeout_s=10.0, observation_max_age_s=5.0,
                             discovery_s=ONE_DECIDER_DISCOVERY_S)
    params['monitoring'].update(heartbeat_misses_down=40)
    with open(path, 'w') as f:
        yaml.safe_dump(data, f)
    state_dir = tmp_path / 'state'
    state_dir.mkdir()
    (state_dir / f'agent_{name}_away.json').write_text('{"version": 1, "nodes": {"wor')
    blocker = tmp_path / 'blocker'
    blocker.write_text('a regular file where the log folder should be')
    env = ros_child_env(ros_env)

    node = ros.node('bad_input_listener')
    seen = {'layouts': [], 'states': {}}

    def on_layout(m):
        try:
            layout = p.Layout.from_json(m.data)
        except p.ProtocolError:
            return
        if layout.deployment == name:       # not the hostile one of another deployment
            seen['layouts'].append(layout)

    def on_state(m):
        try:
            s = p.AgentState.from_json(m.data)
        except p.ProtocolError:
            return
        if s.scale in ('home', 'away'):
            seen['states'][s.scale] = s
    node.create_subscription(String, p.TOPIC_LAYOUT, on_layout, qos.LATCHED_READER)
    node.create_subscription(String, p.TOPIC_AGENT_STATE, on_state, qos.LATCHED_READER)
    ex = ros.executor
    procs = {}

    def wait(cond, timeout, what):
        """Until ``cond()``; any process's end ends the wait."""
        ros.spin_until(cond, timeout, what, procs, watch=True)

    def serving():
        return {(s, n): (r.pid, r.restarts) for s, st in seen['states'].items()
                for n, r in st.nodes.items() if r.state == 'running' and r.ready}

    try:
        # home: its log folder is unusable; away: its state file was left truncated.
        procs['agent_home'] = LoggedProcess(
            tmp_path / 'agent_home.out', [os.path.join(BIN, 'agent'), '--ros-args',
                                          '--params-file', path, '-p', 'scale:=home', '-p',
                                          f'agent.log_dir:={blocker}/log'], env)
        procs['agent_away'] = LoggedProcess(
            tmp_path / 'agent_away.out', [os.path.join(BIN, 'agent'), '--ros-args',
                                          '--params-file', path, '-p', 'scale:=away'], env)
        procs['decider'] = LoggedProcess(
            tmp_path / 'decider.out', [os.path.join(BIN, 'decider'), '--ros-args',
                                       '--params-file', path], env)
        wait(lambda: {('away', 'worker'), ('home', 'pinned')} == set(serving()), 90.0,
             'worker serving away and pinned home, and nothing else')
        before = serving()
        assert 'output discarded' in procs['agent_home'].text()
        assert 'adoption: state file' in procs['agent_away'].text()

        pubs = {}
        for topic in DECODERS:
            profile = qos.LATCHED if topic in (p.TOPIC_LAYOUT, p.TOPIC_AGENT_STATE) else \
                qos.STATUS
            pubs[topic] = node.create_publisher(String, topic, profile)
        # Every topic but the decider's events and plan check has a reader in the project.
        wait(lambda: all(pub.get_subscription_count() for topic, pub in pubs.items()
                         if topic not in (p.TOPIC_EVENTS, p.TOPIC_PLAN_CHECK)),
             20.0, 'the hostile publishers matched')
        # A layout of another deployment, alone (the layout topic keeps one message): said by
        # each, once.
        pubs[p.TOPIC_LAYOUT].publish(String(data=p.Layout(
            generation=10 ** 6, deployment=f'not_{name}', reason='elsewhere', stamp=time.time(),
            assignments={'worker': 'home', 'pinned': 'away'}).to_json()))
        wait(lambda: all('ignored a layout of deployment' in pr.text() for pr in procs.values()),
             20.0, 'the layout of another deployment ignored by each')
        payloads = hostile_burst(name)
        oversized = json.dumps({'x': 'a' * (p.MAX_PAYLOAD_BYTES + 1)})
        burst_start = time.monotonic()
        for i in range(10):
            for pub in pubs.values():
                for text in payloads + ([oversized] if i < 2 else []):
                    pub.publish(String(data=text))
            ex.spin_once(timeout_sec=0.01)
        seq = max(lay.seq or 0 for lay in seen['layouts'])

        # The decider keeps publishing (its lease renewals) and nothing moved or restarted.
        wait(lambda: max(lay.seq or 0 for lay in seen['layouts']) > seq + 2, 20.0,
             'the decider publishing its layout again')
        assert seen['layouts'][-1].assignments == {'worker': 'away', 'pinned': 'home'}
        # Each bad kind was said at once, then held back and counted: the count comes out once
        # the 10 s interval is over.
        wait(lambda: all('more like this' in pr.text() for pr in procs.values()), 30.0,
             'the counts of the messages held back')
        wait(lambda: serving() == before, 10.0, 'the same processes serving as before')
        for pr in procs.values():
            assert pr.proc.poll() is None
        elapsed = time.monotonic() - burst_start
        budget = 2 + int(elapsed / 10.0)       # the first line, then one per 10 s
        for who, pr in procs.items():
            text = pr.text()
            assert 'Traceback' not in text and 'callback failed' not in text, text[-3000:]
            for words in ('ignored a layout message', 'ignored an agent state message',
                          'ignored a message on /anyscale/scale_status',
                          'ignored a malformed layout', 'link monitor: ignoring'):
                lines = [line for line in text.splitlines() if words in line]
                # Each kind of bad input its own line and count (protocol.DECODE_ERRORS).
                per_kind = Counter(p.error_kind(line) for line in lines)
                assert max(per_kind.values(), default=0) <= budget, (who, words, lines)
        assert 'ignored a message on /anyscale/scale_status' in procs['decider'].text()
    finally:
        codes = {n: pr.stop() for n, pr in reversed(list(procs.items()))}
    assert set(codes.values()) <= {0}, codes
