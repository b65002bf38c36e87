"""A node that cannot start says why where a person looks: the supervisor reads its exit code
and the last line of its log, the agent's report carries them (bounded, printable), and the
decider says it in one event until the copy serves again. Real short processes for the
supervisor; the decider's turn on a hand-written clock."""

import os
import sys
import time

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.agent.catalogue import base_environment, ENV_NODE, Entry
from anyscale_manager.agent.log_tail import last_line, one_line
from anyscale_manager.agent.procs import describe_exit
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.liveness import NODE_EXIT
from anyscale_manager.runtime.turn import DeciderTurn
from supervision import drive
from test_runtime_turn import agent, feed

MISSING = '/nonexistent/anyscale/worker.py'


# --- the log's last line ------------------------------------------------------------------------

@pytest.mark.parametrize('text, line', [
    ('ok\n', 'ok'),
    ('\x1b[31m[ERROR] [1.0] [n]: no map\x1b[0m\r\n\n\n', '[ERROR] [1.0] [n]: no map'),
    ('a\tb\x00c\x07\n', 'a b c'),
    ('x' * 400 + '\n', 'x' * (p.LOG_TAIL_CHARS - 3) + '...'),
    ('--- worker: starting /usr/bin/python3 /opt/worker.py\n', ''),
    ('--- worker: starting python3 a.py\nTraceback:\n  ...\nImportError: no numpy\n',
     'ImportError: no numpy'),
    ('old run\n--- worker: starting python3 a.py\n', ''),
    (b'caf\xc3\xa9 \xff\n', 'café \ufffd'),
])
def test_the_last_line_is_one_short_printable_line_of_this_start(tmp_path, text, line):
    log = tmp_path / 'worker.log'
    log.write_bytes(text if isinstance(text, bytes) else text.encode())
    assert last_line(str(log)) == line
    assert line == '' or p.NodeReport('backoff', 0, 0.0, 0, False, 'x', exit_code=1,
                                      log_tail=line).to_json()
    assert last_line(str(tmp_path / 'none.log')) == ''


def test_one_line_of_a_long_log_is_read_from_its_end(tmp_path):
    log = tmp_path / 'worker.log'
    log.write_text('--- worker: starting x\n' + 'spam\n' * 10000 + 'the end\n')
    assert last_line(str(log)) == 'the end'
    assert one_line('  a \n b  ') == 'a b'


# --- the wire -----------------------------------------------------------------------------------

def test_a_report_carries_the_exit_code_and_log_line_and_refuses_them_unbounded():
    report = p.NodeReport('backoff', 0, 1.0, 3, False, 'exited with status 2', exit_code=2,
                          log_tail="python3: can't open file")
    assert p.NodeReport.from_json(report.to_json()) == report
    # Unset, they are left out: an agent's healthy report reads as before.
    assert 'log_tail' not in p.NodeReport('running', 1, 1.0, 0, True, '').to_json()
    for field, value, words in [('log_tail', 'a\nb', 'printable'),
                                ('log_tail', 'x' * (p.LOG_TAIL_CHARS + 1), 'at most'),
                                ('exit_code', 256, 'must be in [-128, 255]')]:
        data = dict(report.to_dict(), **{field: value})
        with pytest.raises(p.ProtocolError) as info:
            p.NodeReport.from_dict(data)
        assert f'NodeReport.{field}' in str(info.value) and words in str(info.value)


# --- the supervisor -----------------------------------------------------------------------------

def test_the_supervisor_reports_a_missing_scripts_exit_code_and_log_line(make_sup):
    env = dict(base_environment(os.environ), **{ENV_NODE: 'worker'})
    sup = make_sup([Entry(name='worker', argv=(sys.executable, MISSING), env=env,
                          ros_name='worker')])
    sup.set_wanted(['worker'], time.monotonic())
    # The first exit is restarted at once (the report says starting, with the crash's
    # reason); the second waits its backoff.
    assert drive(sup, lambda: sup.reports()['worker'].restarts >= 2
                 and sup.reports()['worker'].state == p.ProcState.BACKOFF, 20.0)
    r = sup.reports()['worker']
    assert r.exit_reason.startswith('exited with status 2') and r.exit_code == 2
    # Python names itself as it was started: the agent starts the path it resolved.
    assert r.log_tail == f"{sys.executable}: can't open file '{MISSING}': [Errno 2] No such " \
                         'file or directory'

    crashes = [text for level, text in sup.events if 'crashed' in text]
    assert crashes and crashes[0].endswith(f'its last log line: {r.log_tail}')
    # Asked to stop, the copy is no longer one that exited unasked.
    sup.stop('worker', time.monotonic())
    assert drive(sup, lambda: sup.reports()['worker'].state == p.ProcState.STOPPED, 10.0)
    assert sup.reports()['worker'].exit_code is None
    assert sup.reports()['worker'].log_tail is None


# --- the decider ---------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def d():
    from conftest import TESTBED
    return load_deployment(TESTBED)


def crash_loop(d, turn, now, restarts, node='user', state='backoff', code=2,
               tail="python3: can't open file '/opt/user.py': [Errno 2] No such file"):
    """Every report healthy but ``node`` on the robot, which exits at each start."""
    where = master_layout(d)
    feed(turn, d, now, where)
    robot = agent(d, 'robot', where, standby=[n for n in d.node_names
                                              if d.standby_scales(n)])
    robot.nodes[node] = p.NodeReport(state=state, pid=0, since=now, restarts=restarts,
                                     ready=False, exit_reason=describe_exit(code),
                                     exit_code=code, log_tail=tail)
    turn.book.agent_state(robot, now)
    return turn.turn(now)


def exits(out):
    return [e for e in out.events if e[0] == NODE_EXIT]


def test_the_decider_says_a_copys_exit_once_with_its_code_and_log_line(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 1.0, master_layout(d))
    turn.turn(1.0)
    said, logs = [], []
    for k, now in enumerate((2.0, 2.5, 3.0, 4.0, 6.0)):      # crash after crash
        out = crash_loop(d, turn, now, restarts=k + 1)
        said += exits(out)
        logs += [line for line in out.logs if 'exited unasked' in line[1]]
    text = ('user on robot exited unasked, exit code 2; the last line of its log: '
            "python3: can't open file '/opt/user.py': [Errno 2] No such file")
    assert said == [(NODE_EXIT, 'user', 'robot', '', text, turn.generation)]
    assert logs == [('error', text)]
    # Between two exits the copy starts again and its report carries no exit: not news.
    where = master_layout(d)
    feed(turn, d, 6.5, where)
    robot = agent(d, 'robot', where, standby=[n for n in d.node_names if d.standby_scales(n)])
    robot.nodes['user'] = p.NodeReport(state='starting', pid=7, since=6.5, restarts=6,
                                       ready=False, exit_reason='')
    turn.book.agent_state(robot, 6.5)
    assert not exits(turn.turn(6.5))
    assert not exits(crash_loop(d, turn, 6.8, restarts=6))
    # Serving again, then another exit: said again.
    feed(turn, d, 7.0, master_layout(d))
    assert not exits(turn.turn(7.0))
    again = exits(crash_loop(d, turn, 8.0, restarts=6, code=-11, tail=''))
    assert [e[4] for e in again] == ['user on robot exited unasked, exit code -11 (killed by '
                                     'SIGSEGV (Segmentation fault)); it wrote nothing to its '
                                     'log']


def test_a_copy_that_cannot_be_started_is_said_with_its_reason(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    feed(turn, d, 1.0, master_layout(d))
    turn.turn(1.0)
    where = master_layout(d)
    feed(turn, d, 2.0, where)
    robot = agent(d, 'robot', where)
    robot.nodes['user'] = p.NodeReport(state='failed', pid=0, since=2.0, restarts=0,
                                       ready=False, exit_reason="command 'x' not found on PATH")
    turn.book.agent_state(robot, 2.0)
    assert [e[4] for e in exits(turn.turn(2.0))] == [
        "user on robot cannot be started: command 'x' not found on PATH"]


def test_node_reports_carry_the_exit_code_and_log_line():
    from anyscale_manager.agent.turn import node_reports
    reports = {'worker': p.NodeReport(p.ProcState.BACKOFF, 0, 5.0, 2, False,
                                      'exited with status 2', exit_code=2,
                                      log_tail="python3: can't open file"),
               'fine': p.NodeReport(p.ProcState.RUNNING, 9, 5.0, 0, True, '')}
    nodes = node_reports(reports, {}, 100.0)
    assert (nodes['worker'].exit_code, nodes['worker'].log_tail) == (2, "python3: can't open file")
    assert nodes['fine'].exit_code is None and nodes['fine'].log_tail is None
    assert 'exit_code' not in nodes['fine'].to_json()


# --- the real programs ---------------------------------------------------------------------------

def test_a_missing_script_reaches_the_agents_report_and_one_decider_event(tmp_path, ros_env):
    import home_away as ha
    from spinning import spin_until
    name = f'exit_diagnosis_{os.getpid()}'
    nodes, connections = ha.worker_and_pinned(f'/{name}')
    nodes['pinned'] = dict(nodes['pinned'], launch={'command': [sys.executable, MISSING]})
    path = ha.write_deployment(tmp_path, name, (nodes, connections), port_offset=11)
    procs = []
    with ha.listening(f'{name}_listener') as (ex, seen):
        try:
            ha.start_agents(procs, tmp_path, ros_env, path)
            ha.start(procs, tmp_path, ros_env, path, 'decider')

            def report():
                s = seen['states'].get('home')
                return s.nodes.get('pinned') if s is not None else None

            def exits():
                return [e for e in seen['events'] if e.kind == NODE_EXIT]
            spin_until(ex, lambda: report() is not None and report().log_tail, 60.0,
                       "the home agent's report of the missing script", procs, watch=True)
            r = report()
            assert r.exit_code == 2 and r.log_tail == \
                f"{sys.executable}: can't open file '{MISSING}': [Errno 2] No such file or " \
                'directory', r
            spin_until(ex, exits, 30.0, 'the decider says it', procs, watch=True)
            # Two more exits of the crash loop: still said once.
            later = r.restarts + 2
            spin_until(ex, lambda: report().restarts >= later, 30.0, 'two more exits', procs,
                       watch=True)
            (event,) = exits()
            assert (event.node, event.from_scale) == ('pinned', 'home')
            assert event.reason == f'pinned on home exited unasked, exit code 2; the last ' \
                                   f'line of its log: {r.log_tail}'
        finally:
            codes = {n: proc.stop() for n, proc in reversed(procs)}
    assert codes['decider'] == 0
