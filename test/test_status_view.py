"""The live view: stale figures, bandwidth against the nominal, the layout's age, no RTT on a
down link (pure, on a fake clock); the screen that redraws in place; and ``anyscale-manager
status`` itself under a real pseudo-terminal and through a pipe, against messages this test
publishes over real DDS."""

import fcntl
import io
import os
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import time

import pytest
import yaml

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime.turn import DeciderTurn, LAYOUT_AGE
from anyscale_manager.testbed.record import Record
from anyscale_manager.testbed.report import status_table
from anyscale_manager.view import screen as sc
from anyscale_manager.view.status import StatusBook, bandwidth_text, render, rtt_text
from conftest import REPO

NAME = f'status_view_{os.getpid()}'
LOOPBACK_KBPS = 23456370.0        # what an active probe measured over loopback in the issue


@pytest.fixture
def deployment_path(tmp_path):
    data = {'/**': {'ros__parameters': {
        'deployment': {'name': NAME},
        'scales': {'names': ['robot', 'laptop'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 200.0,
                             'cores': 2},
                   'laptop': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 700.0,
                              'cores': 4}},
        'links': {'names': ['wifi'],
                  'wifi': {'ends': ['robot', 'laptop'], 'bandwidth_kbps': 54000.0}},
        'nodes': {'names': ['sensor', 'worker'],
                  'sensor': {'cpu': 5.0, 'residence': ['robot']},
                  'worker': {'cpu': 50.0}},
        'connections': {'names': ['sensor_worker'],
                        'sensor_worker': {'topic': '/status_view/data', 'publisher': 'sensor',
                                          'subscriber': 'worker', 'freq_min_hz': 5.0,
                                          'tolerance_s': 2.0}},
        'decider': {'observation_max_age_s': 3.0, 'agent_timeout_s': 5.0, 'lease_s': 3.0,
                    'period_s': 0.5},
        'monitoring': {'bandwidth_probe_interval_s': 30.0, 'bandwidth_probe_duration_s': 0.5},
    }}}
    path = tmp_path / 'deployment.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture
def d(deployment_path):
    return load_deployment(deployment_path)


def layout(generation, **where):
    return p.Layout(generation=generation, deployment=NAME,
                    assignments={'sensor': 'robot', 'worker': 'robot', **where},
                    reason='test', stamp=time.time())


def agent(scale, generation, *running):
    report = p.NodeReport(state='running', pid=1, since=0.0, restarts=0, ready=True,
                          exit_reason='')
    return p.AgentState(scale=scale, generation=generation, stamp=time.time(),
                        nodes={n: report for n in running})


def link(up=True, rtt_ms=1.5, kbps=None, age_s=None, used=120.0):
    return p.LinkStatus(master='robot', remote='laptop', stamp=time.time(), up=up,
                        rtt_ms=rtt_ms, loss=0.0 if up else 1.0, bandwidth_available_kbps=kbps,
                        bandwidth_available_age_s=age_s, bandwidth_used_kbps=used)


def scale_status(scale, cpu):
    return p.ScaleStatus(scale=scale, stamp=time.time(), cpu_total=cpu, capacity_cpu=0.0,
                         cpu_by_node={}, mem_percent=0.0, load_1m=0.0)


def readings(scale, rate_hz, below_s=0.0):
    return p.ConnectionStatus(scale=scale, stamp=time.time(), connections={
        'sensor_worker': p.ConnectionReading(rate_hz=rate_hz, bytes_per_s=100.0,
                                             below_for_s=below_s, level=p.OK)})


TOPICS = {p.Layout: p.TOPIC_LAYOUT, p.AgentState: p.TOPIC_AGENT_STATE,
          p.LinkStatus: p.TOPIC_LINK_STATUS, p.ScaleStatus: p.TOPIC_SCALE_STATUS,
          p.ConnectionStatus: p.TOPIC_CONNECTION_STATUS, p.DeciderBeat: p.TOPIC_DECIDER}


def take(book, now, *messages):
    for m in messages:
        book.take(TOPICS[type(m)], m.to_json(), now)


def row(text, first):
    return next(line for line in text.splitlines() if line.startswith(first + ' '))


# --- the view's text, on a fake clock -----------------------------------------------------------

def test_fresh_figures_are_shown_as_current(d):
    book = StatusBook(d)
    take(book, 0.0, layout(3), agent('robot', 3, 'sensor', 'worker'), agent('laptop', 3),
         link(kbps=40000.0, age_s=1.0), scale_status('robot', 50.0), readings('robot', 10.0))
    text = render(book, 1.0)
    assert 'STALE' not in text and 'SILENT' not in text
    assert row(text, 'robot').split()[2:6] == ['50', '/', '200', '(25%)']
    assert 'ok, generation 3, 1.0 s ago' in row(text, 'robot')
    assert row(text, 'wifi').split()[2:8] == ['up', '1.5', 'ms', '40000', '/', '54000']
    assert row(text, 'sensor_worker').split()[1:] == ['10.0', '5', '0.0', '/', '2', 'ok']


def test_the_leading_decider_and_its_standbys_are_shown_from_their_beats(d):
    def beat(name, role, term, deployment=None):
        return p.DeciderBeat(stamp=time.time(), deployment=deployment or d.name,
                             decider=p.DeciderIdentity(name, 'robot', 7, 1.0), role=role,
                             term=term, generation=3)
    book = StatusBook(d)
    take(book, 0.0, layout(3))
    assert 'deciders' not in render(book, 0.5)                    # none heard: no line
    take(book, 1.0, beat('b2', 'standby', 1), beat('a1', 'leader', 2),
         beat('x9', 'leader', 9, deployment='another_robot'))
    assert 'deciders: a1 leader (term 2); b2 standby' in render(book, 1.5).splitlines()
    assert book.foreign == 1
    # The leader killed: only the standby beats on, then it leads at a higher term.
    take(book, 5.0, beat('b2', 'leader', 3))
    assert 'deciders: b2 leader (term 3)' in render(book, 5.5).splitlines()
    assert 'deciders: none heard for 3 s' in render(book, 9.0)


def test_stale_figures_are_marked_with_their_age_not_shown_as_current(d):
    book = StatusBook(d)
    take(book, 0.0, layout(3), agent('robot', 3, 'sensor', 'worker'), agent('laptop', 3),
         link(kbps=40000.0, age_s=1.0), scale_status('robot', 50.0), readings('robot', 10.0))
    # The robot's agent keeps speaking; everything else fell silent 7.2 s ago.
    take(book, 7.0, agent('robot', 3, 'sensor', 'worker'))
    text = render(book, 7.2)
    assert row(text, 'robot').split()[2:] == ['50', '/', '200', '(25%)', 'STALE', '7.2', 's',
                                              'ok,', 'generation', '3,', '0.2', 's', 'ago']
    assert 'SILENT, STALE 7.2 s, generation 3' in row(text, 'laptop')
    wifi = row(text, 'wifi')
    assert 'SILENT, STALE 7.2 s (counts as down)' in wifi
    assert 'ms' not in wifi and ' 120' not in wifi             # no RTT, no used figure
    assert '40000 / 54000 STALE 8.2 s' in wifi                 # measured 1.0 s before it was sent
    conn = row(text, 'sensor_worker')
    assert conn.split()[1] == '-'                              # no rate shown as current
    assert 'STALE 7.2 s (counts as 0 Hz), last 10.0 Hz' in conn
    assert 'layout generation 3' in text and 'decider silent, STALE 7.2 s' in text
    # A node reported by an agent that fell silent is not shown as running now.
    take(book, 0.0, agent('laptop', 3, 'worker'))
    take(book, 7.0, agent('robot', 3, 'sensor'))
    assert 'running, STALE 7.2 s' in row(render(book, 7.2), 'worker')


@pytest.mark.parametrize('measured, up, age_s, shown', [
    (LOOPBACK_KBPS, True, 1.0, '54000 / 54000 >nominal (loopback?)'),
    (40000.0, True, 1.0, '40000 / 54000'),
    (54000.0, True, 1.0, '54000 / 54000'),
    (None, True, None, 'not measured / 54000 (nominal assumed)'),
    # Two probe intervals (2 x 30 s + the 0.5 s probe) without a new measurement: stale.
    (40000.0, True, 61.0, '40000 / 54000 STALE 61.0 s'),
    (40000.0, True, 60.0, '40000 / 54000'),
    # Nothing is measured on a link that is down: the last figure is stale at once.
    (40000.0, False, 2.0, '40000 / 54000 STALE 2.0 s'),
    (LOOPBACK_KBPS, False, 2.0, '54000 / 54000 >nominal (loopback?) STALE 2.0 s'),
])
def test_available_bandwidth_is_shown_against_the_nominal_and_never_above_it(
        d, measured, up, age_s, shown):
    book = StatusBook(d)
    take(book, 10.0, link(up=up, kbps=measured, age_s=age_s))
    wifi = row(render(book, 10.0), 'wifi')
    assert shown in wifi
    assert shown + ' STALE' not in wifi
    assert '23456370' not in wifi


def test_bandwidth_text_in_mbit_for_the_demo():
    assert bandwidth_text(LOOPBACK_KBPS, 54000.0, True, 0.5, 60.5, mbit=True) == \
        '54.0 / 54.0 Mbit/s >nominal (loopback?)'
    assert bandwidth_text(None, 54000.0, True, None, 60.5, mbit=True) == \
        'not measured / 54.0 Mbit/s (nominal assumed)'
    assert bandwidth_text(5000.0, 54000.0, False, None, 60.5, mbit=True) == \
        '5.0 / 54.0 Mbit/s STALE'


def test_layout_age_is_the_time_since_its_generation_changed_not_since_it_was_heard(d):
    book = StatusBook(d)
    # The layout was made before the view started: only a lower bound is known.
    for t in (0.0, 1.0, 2.0, 3.0, 4.0, 5.0):        # the decider re-publishes it (its lease)
        take(book, t, layout(3))
    first = render(book, 5.0).splitlines()[1]
    assert first == 'layout generation 3, made before this view started (over 5.0 s ago)'
    # A new generation at t = 6; its re-publications do not make it younger.
    for t in (6.0, 7.0, 8.0, 9.0):
        take(book, t, layout(4, worker='laptop'))
    assert render(book, 9.5).splitlines()[1] == 'layout generation 4, made 3.5 s ago'
    # The same generation with other assignments is another layout too.
    take(book, 10.0, layout(4))
    assert render(book, 10.5).splitlines()[1] == 'layout generation 4, made 0.5 s ago'
    # A decider silent past its lease: the layout is marked stale, its age still counts.
    assert render(book, 14.0).splitlines()[1] == \
        'layout generation 4, made 4.0 s ago; decider silent, STALE 4.0 s'


@pytest.mark.parametrize('up, rtt_ms, shown', [
    (True, 1.5, '1.5 ms'), (True, None, '-'), (False, 1.5, '-'), (False, None, '-')])
def test_no_rtt_on_a_link_that_is_down(d, up, rtt_ms, shown):
    assert rtt_text(up, rtt_ms) == shown
    book = StatusBook(d)
    take(book, 0.0, link(up=up, rtt_ms=rtt_ms))
    columns = row(render(book, 0.5), 'wifi').split()
    assert columns[2] == ('up' if up else 'DOWN')
    assert ' '.join(columns[3:3 + len(shown.split())]) == shown


def test_the_demo_table_judges_the_link_as_status_does(d):
    record = Record(d)

    def heard(t, message):
        record.ingest({'t': t, 'topic': TOPICS[type(message)], 'data': message.to_json()})

    def monitor_line(now):
        lines = status_table(record, now, 0.0, 'loopback').splitlines()
        assert lines[1].startswith('link wifi: ')
        return lines[2].strip()
    heard(1.0, link(up=True, rtt_ms=0.4, kbps=LOOPBACK_KBPS, age_s=0.5))
    monitor = monitor_line(1.5)
    assert monitor.startswith('monitor: up, rtt 0.4 ms')
    assert 'available 54.0 / 54.0 Mbit/s >nominal (loopback?)' in monitor
    heard(2.0, link(up=False, rtt_ms=0.4, kbps=LOOPBACK_KBPS, age_s=1.5))
    monitor = monitor_line(2.5)
    assert monitor.startswith('monitor: DOWN, rtt -,')
    assert '>nominal (loopback?) STALE 2.0 s' in monitor
    monitor = monitor_line(9.0)
    assert monitor.startswith('monitor: SILENT, STALE 7.0 s, rtt -,')


def test_reports_of_names_the_deployment_does_not_have_are_counted_not_kept(d):
    book = StatusBook(d)
    other = p.ConnectionStatus(scale='robot', stamp=0.0, connections={
        'other': p.ConnectionReading(rate_hz=1.0, bytes_per_s=0.0, below_for_s=0.0, level=0)})
    take(book, 0.0, agent('elsewhere', 1), scale_status('elsewhere', 10.0), other)
    assert not book.agents and not book.scales and not book.readings
    assert render(book, 0.1).endswith(
        '3 report(s) of scales or connections not in this deployment ignored')


# --- what a person can act on -------------------------------------------------------------------

@pytest.mark.parametrize('environ, words', [
    ({}, 'ROS_DOMAIN_ID=0 (unset: the default), ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (unset: '
         'the default; this machine and its subnet)'),
    ({'ROS_DOMAIN_ID': '42', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
     'ROS_DOMAIN_ID=42, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (this machine only)'),
    ({'ROS_LOCALHOST_ONLY': '1'},
     'ROS_DOMAIN_ID=0 (unset: the default), ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (from '
     'ROS_LOCALHOST_ONLY=1; this machine only)'),
])
def test_no_layout_heard_says_where_the_view_listened_and_what_to_check(d, environ, words):
    book = StatusBook(d, environ=environ)
    line = render(book, 1.0).splitlines()[1]
    assert line.startswith(f'no layout heard, nor anything else on {words}: check that the '
                           'decider and the agents run with the same ROS_DOMAIN_ID'), line
    assert line.endswith('; and the same Fast DDS profile (FASTRTPS_DEFAULT_PROFILES_FILE)')
    if 'LOCALHOST' in words:
        assert "LOCALHOST hears this machine's processes only: run the view on the master " \
               'scale' in line
    else:
        assert 'that the scales are on this subnet (else ROS_STATIC_PEERS)' in line
    # Agents heard, no layout: the decider is what to look for.
    take(book, 0.0, agent('robot', 0, 'sensor'))
    line = render(book, 1.0).splitlines()[1]
    assert line.startswith(f'no layout heard on {words}, though agents or monitors of this '
                           'deployment were: is the decider running'), line


def test_a_layout_heard_late_is_as_old_as_the_leading_decider_says(d):
    book = StatusBook(d)
    take(book, 100.0, layout(3))
    assert 'made before this view started (over 1.0 s ago)' in render(book, 101.0)
    # The decider's diagnostics, 0.5 s after the layout: generation 3 made 15.0 s before.
    book.take_decider_values({'generation': '3', LAYOUT_AGE: '15.0'}, 100.5)
    assert render(book, 101.0).splitlines()[1] == 'layout generation 3, made 15.5 s ago'
    # Values of another generation say nothing of this one.
    book.take_decider_values({'generation': '2', LAYOUT_AGE: '99.0'}, 100.8)
    assert 'over 1.0 s ago' in render(book, 101.0)


def test_the_decider_turn_gives_the_age_of_its_layout_in_its_diagnostics(d):
    turn = DeciderTurn(d, d.decider, started=0.0)
    assert turn.values(1.0)[LAYOUT_AGE] == ''
    out = turn.turn(d.decider.agent_timeout_s + 1.0)        # no agent heard: first layout
    assert out.layouts and out.values[LAYOUT_AGE] == 0.0
    made = d.decider.agent_timeout_s + 1.0
    assert turn.turn(made + 15.0).values[LAYOUT_AGE] == 15.0
    assert turn.values(made + 15.0)['generation'] == out.layouts[0][0]


def cpu_status(scale, total, by_node, cores):
    return p.ScaleStatus(scale=scale, stamp=time.time(), cpu_total=total, capacity_cpu=0.0,
                         cpu_by_node=by_node, mem_percent=0.0, load_1m=0.0, cores=cores)


def test_cpu_is_in_reference_percent_and_in_core_percent_where_they_differ(d):
    book = StatusBook(d)
    # One machine of 2 CPUs: the worker takes 0.18 of one on either scale. The robot (200
    # over 2 CPUs) reads it 18, the laptop (700 over the same 2) 63.
    take(book, 0.0, layout(3, worker='laptop'), agent('robot', 3, 'sensor'),
         agent('laptop', 3, 'worker'), cpu_status('robot', 20.0, {'sensor': 2.0}, 2.0),
         cpu_status('laptop', 70.0, {'worker': 63.0}, 2.0))
    text = render(book, 0.5)
    assert row(text, 'robot').split()[2:6] == ['20', '/', '200', '(10%)']
    assert 'core%' not in row(text, 'robot')
    assert row(text, 'laptop').split()[2:9] == ['70', '/', '700', '(10%)', '=', '20', 'core%']
    assert row(text, 'worker').split()[4:7] == ['63', '=', '18']
    assert row(text, 'sensor').split()[4] == '2' and 'core%' not in row(text, 'sensor')
    legend = next(line for line in text.splitlines() if line.startswith('CPU in reference'))
    assert 'one busy CPU reads 350 on laptop (700 over 2 CPUs);' in legend
    assert 'robot' not in legend
    assert "core% is the same load in percent of one of its machine's CPUs" in legend
    # An agent that does not report its CPUs: the declared cores, said so.
    take(book, 1.0, scale_status('laptop', 70.0))
    assert 'one busy CPU reads 175 on laptop (700 over 4 CPUs, as declared)' in render(book, 1.5)


def test_a_copy_that_exits_at_once_is_said_with_its_exit_code_and_its_log_line(d):
    book = StatusBook(d)
    tail = "python3: can't open file '/opt/nodes/worker.py': [Errno 2] No such file or directory"
    down = p.NodeReport(state='backoff', pid=0, since=0.0, restarts=3, ready=False,
                        exit_reason='exited with status 2', exit_code=2, log_tail=tail)
    take(book, 0.0, layout(3), p.AgentState(scale='robot', generation=3, stamp=time.time(),
                                            nodes={'worker': down}))
    lines = render(book, 0.5).splitlines()
    assert f'  backoff (restarts: 3): worker on robot exited unasked, exit code 2; the last ' \
           f'line of its log: {tail}' in lines


# --- the screen --------------------------------------------------------------------------------

class Terminal:
    """Enough of a terminal to replay the view's output: printable text, CR, LF, and the escape
    sequences the view uses; it counts the lines the alternate screen scrolled."""

    CSI = re.compile(r'\x1b\[([?0-9;]*)([A-Za-z])')

    def __init__(self, columns, rows):
        self.columns, self.rows = columns, rows
        self.alternate = False
        self.grid = self._blank()
        self.row = self.col = 0
        self.scrolled = 0
        self.homes = 0
        self.cursor_hidden = False
        self.unknown = []
        self.normal = ''          # what was written on the normal screen
        self.at_leave = None      # the alternate screen's text when it was left

    def _blank(self):
        return [[' '] * self.columns for _ in range(self.rows)]

    def feed(self, data):
        pos = 0
        for m in self.CSI.finditer(data):
            self._text(data[pos:m.start()])
            self._csi(m.group(1), m.group(2))
            pos = m.end()
        self._text(data[pos:])

    def text(self):
        return '\n'.join(''.join(r).rstrip() for r in self.grid).rstrip('\n')

    def _text(self, s):
        for ch in s:
            if not self.alternate:
                self.normal += ch
            elif ch == '\r':
                self.col = 0
            elif ch == '\n':
                self._down()
            elif ch == '\x1b' or ord(ch) < 32:
                self.unknown.append(repr(ch))
            else:
                if self.col >= self.columns:
                    self.col = 0
                    self._down()
                self.grid[self.row][self.col] = ch
                self.col += 1

    def _down(self):
        if self.row == self.rows - 1:
            self.scrolled += 1
            self.grid = self.grid[1:] + [[' '] * self.columns]
        else:
            self.row += 1

    def _csi(self, params, final):
        if params == '?1049' and final in 'hl':
            if final == 'l':
                self.at_leave = self.text()
            self.alternate = final == 'h'
            self.grid, self.row, self.col = self._blank(), 0, 0
        elif params == '?25' and final in 'hl':
            self.cursor_hidden = final == 'l'
        elif not self.alternate:
            self.unknown.append(f'CSI {params}{final} on the normal screen')
        elif (params, final) == ('', 'H'):
            self.row = self.col = 0
            self.homes += 1
        elif (params, final) == ('', 'K'):
            self.grid[self.row][self.col:] = [' '] * (self.columns - self.col)
        elif (params, final) == ('', 'J'):
            self.grid[self.row][self.col:] = [' '] * (self.columns - self.col)
            for r in range(self.row + 1, self.rows):
                self.grid[r] = [' '] * self.columns
        else:
            self.unknown.append(f'CSI {params}{final}')


def test_a_terminal_screen_redraws_in_place_and_gives_the_screen_back():
    out = io.StringIO()
    term = Terminal(40, 6)
    with sc.LiveScreen(out, terminal=True) as screen:
        screen.size = lambda: (40, 6)
        for k in range(5):
            screen.show('\n'.join(f'line {i} of frame {k}' for i in range(3)), float(k))
        screen.show('short', 5.0)
    term.feed(out.getvalue())
    assert term.scrolled == 0 and term.homes == 6 and not term.unknown
    assert term.at_leave == 'short'                     # nothing of the longer frames left
    assert term.normal == 'short\n' and not term.cursor_hidden
    assert out.getvalue().startswith(sc.ENTER) and out.getvalue().count(sc.LEAVE) == 1


def test_a_frame_is_cut_to_the_terminal_so_it_never_scrolls():
    out = io.StringIO()
    term = Terminal(20, 4)
    screen = sc.LiveScreen(out, terminal=True, keep_last=False)
    screen.size = lambda: (20, 4)
    screen.show('\n'.join(f'{i}: ' + 'x' * 30 for i in range(10)), 0.0)
    term.feed(out.getvalue())
    assert term.scrolled == 0 and not term.unknown
    lines = term.text().splitlines()
    assert lines[:3] == ['0: ' + 'x' * 16, '1: ' + 'x' * 16, '2: ' + 'x' * 16]
    assert lines[3].startswith('... 7 more line(s)')


def test_the_screen_is_given_back_on_ctrl_c():
    out = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        with sc.LiveScreen(out, terminal=True) as screen:
            screen.show('the last frame', 0.0)
            raise KeyboardInterrupt
    assert out.getvalue().endswith(sc.LEAVE + 'the last frame\n')


def test_plain_snapshots_when_not_a_terminal():
    out = io.StringIO()
    assert not sc.is_terminal(out)
    with sc.LiveScreen(out, plain_every_s=5.0) as screen:
        shown = [screen.show(f'snapshot {t:g}', t) for t in (0.0, 1.0, 4.9, 5.0, 7.0, 10.5)]
    assert shown == [True, False, False, True, False, True]
    assert out.getvalue() == 'snapshot 0\n\nsnapshot 5\n\nsnapshot 10.5\n\n'


def test_a_dumb_terminal_gets_plain_snapshots(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setenv('TERM', 'dumb')
    assert not sc.is_terminal(Tty())
    monkeypatch.setenv('TERM', 'xterm')
    assert sc.is_terminal(Tty())


# --- `anyscale-manager status`, live, over DDS --------------------------------------------------

class World:
    """Plays the decider, the agents and the monitors: publishes what status reads."""

    def __init__(self, ros):
        from std_msgs.msg import String

        from anyscale_manager.nodes import qos
        self.String = String
        self.node = ros.node(f'status_view_world_{os.getpid()}', spin=False)
        self.layout_pub = self.node.create_publisher(String, p.TOPIC_LAYOUT, qos.LATCHED)
        # One latched writer per agent, as every agent has its own.
        self.agent_pubs = {s: self.node.create_publisher(String, p.TOPIC_AGENT_STATE,
                                                         qos.LATCHED)
                           for s in ('robot', 'laptop')}
        self.pubs = {t: self.node.create_publisher(String, t, qos.STATUS)
                     for t in (p.TOPIC_LINK_STATUS, p.TOPIC_SCALE_STATUS,
                               p.TOPIC_CONNECTION_STATUS)}
        self.generation, self.where = 3, 'robot'
        self.next_beat = 0.0

    def send(self, pub, message):
        pub.publish(self.String(data=message.to_json()))

    def set_layout(self, generation, where):
        self.generation, self.where = generation, where
        self.send(self.layout_pub, layout(generation, worker=where))
        self.beat(force=True)

    def beat(self, force=False):
        """The agents' and monitors' periodic reports, every 0.3 s."""
        if not force and time.monotonic() < self.next_beat:
            return
        self.next_beat = time.monotonic() + 0.3
        g = self.generation
        running = {'robot': ['sensor'], 'laptop': []}
        running[self.where].append('worker')
        for scale, pub in self.agent_pubs.items():
            self.send(pub, agent(scale, g, *running[scale]))
        self.send(self.pubs[p.TOPIC_LINK_STATUS],
                  link(up=False, rtt_ms=1.5, kbps=LOOPBACK_KBPS, age_s=0.5))
        self.send(self.pubs[p.TOPIC_SCALE_STATUS], scale_status('robot', 50.0))
        self.send(self.pubs[p.TOPIC_CONNECTION_STATUS], readings(self.where, 9.5))


@pytest.fixture
def world(ros):
    return World(ros)


def start_status(path, ros_env, **streams):
    return subprocess.Popen([sys.executable, '-m', 'anyscale_manager.cli', 'status',
                             '--params-file', path, '--interval', '0.3'],
                            env=dict(ros_env, TERM='xterm'), cwd=REPO,
                            start_new_session=True, **streams)


def pump(world, fd, chunks, proc, cond, timeout_s, what):
    """Keep the world reporting and read ``fd`` into ``chunks`` until ``cond(text so far)``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        world.beat()
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            try:
                data = os.read(fd, 65536)
            except OSError:          # EIO: the pty's other side is closed
                data = b''
            if not data:
                return b''.join(chunks).decode('utf-8', 'replace')
            chunks.append(data)
        text = b''.join(chunks).decode('utf-8', 'replace')
        if cond(text):
            return text
        if proc.poll() is not None and not ready:
            break
    raise AssertionError(f'status did not show {what} within {timeout_s:g} s '
                         f'(exit {proc.poll()}):\n{b"".join(chunks)[-3000:]!r}')


def frames(text):
    """The frames drawn on the alternate screen, as plain text."""
    body = text.split(sc.ENTER, 1)[-1].split(sc.LEAVE, 1)[0]
    found = re.findall(re.escape(sc.HOME) + '(.*?)' + re.escape(sc.CLEAR_BELOW), body, re.S)
    return [f.replace(sc.CLEAR_LINE, '').replace('\r', '') for f in found]


def stop(proc, sig=signal.SIGINT):
    if proc.poll() is None:
        os.kill(proc.pid, sig)


def reap(proc):
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
        raise


COLUMNS, ROWS = 160, 40


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_status_redraws_one_screen_in_place_under_a_pseudo_terminal(
        deployment_path, ros_env, world, sig):
    world.set_layout(3, 'robot')
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack('HHHH', ROWS, COLUMNS, 0, 0))
    proc = start_status(deployment_path, ros_env, stdin=slave, stdout=slave, stderr=slave)
    os.close(slave)
    chunks = []
    try:
        def shows(generation, placed):
            def cond(text):
                f = frames(text)
                return bool(f) and f'layout generation {generation}' in f[-1] and \
                    'DOWN' in f[-1] and re.search(placed, f[-1]) is not None
            return cond

        pump(world, master, chunks, proc, shows(3, r'\nworker +robot +robot +running'),
             30.0, 'the first layout with the link down')
        world.set_layout(4, 'laptop')
        pump(world, master, chunks, proc, shows(4, r'\nworker +laptop +laptop +running'),
             15.0, 'the new layout')
        count = len(frames(b''.join(chunks).decode('utf-8', 'replace')))
        pump(world, master, chunks, proc,
             lambda text: len(frames(text)) >= count + 2, 10.0, 'two more frames')
        stop(proc, sig)
        text = pump(world, master, chunks, proc, lambda text: False, 15.0, 'its exit') \
            if proc.poll() is None else b''.join(chunks).decode('utf-8', 'replace')
    except AssertionError:
        stop(proc, signal.SIGKILL)
        raise
    finally:
        reap(proc)
        os.close(master)
    assert proc.returncode == 0, text[-2000:]

    # In place: one alternate screen, every frame drawn from the top left, nothing scrolled.
    assert text.count(sc.ENTER) == 1 and text.count(sc.LEAVE) == 1, repr(text[-500:])
    drawn = frames(text)
    alternate = text.split(sc.ENTER, 1)[1].split(sc.LEAVE, 1)[0]
    assert len(drawn) >= 4 and alternate.count(sc.HOME) == len(drawn)
    assert alternate.count(f'deployment {NAME}') == len(drawn)       # one copy per frame
    assert all(len(f.split('\n')) <= ROWS for f in drawn)
    term = Terminal(COLUMNS, ROWS)
    term.feed(text)
    assert term.scrolled == 0 and not term.unknown, term.unknown[:5]
    # The screen showed the last frame whole.
    assert term.at_leave == '\n'.join(line.rstrip() for line in drawn[-1].split('\n')).rstrip()
    # Given back: the cursor shown, the last frame printed once on the normal screen.
    assert not term.cursor_hidden
    assert term.normal.count(f'deployment {NAME}') == 1
    assert drawn[-1].strip() in term.normal.replace('\r', '')

    # The values, judged as the issue asks.
    first = next(f for f in drawn if 'layout generation 3' in f)
    assert 'made before this view started' in first
    last = drawn[-1]
    assert re.search(r'layout generation 4, made \d+\.\d s ago', last)
    wifi = row(last, 'wifi')
    assert wifi.split()[2:4] == ['DOWN', '-']                        # no RTT on a down link
    assert '54000 / 54000 >nominal (loopback?) STALE' in wifi and '23456370' not in wifi
    assert row(last, 'sensor_worker').split()[1:] == ['9.5', '5', '0.0', '/', '2', 'ok']
    assert 'ok, generation 4' in row(last, 'laptop')


def test_status_appends_plain_snapshots_to_a_pipe(deployment_path, ros_env, world):
    world.set_layout(3, 'robot')
    proc = start_status(deployment_path, ros_env, stdin=subprocess.DEVNULL,
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    chunks = []
    try:
        pump(world, proc.stdout.fileno(), chunks, proc,
             lambda text: text.count('DOWN') >= 2, 30.0, 'two snapshots with the link down')
        stop(proc)
        text = pump(world, proc.stdout.fileno(), chunks, proc, lambda text: False, 15.0,
                    'its exit')
    except AssertionError:
        stop(proc, signal.SIGKILL)
        raise
    finally:
        reap(proc)
        err = proc.stderr.read().decode('utf-8', 'replace')
        proc.stdout.close()
        proc.stderr.close()
    assert proc.returncode == 0, err
    assert '\x1b' not in text
    snapshots = text.split('\n\n' + f'deployment {NAME}')
    assert len(snapshots) >= 2 and text.startswith(f'deployment {NAME}\n')
    assert text.endswith('\n\n')
    wifi = row(snapshots[-1], 'wifi')
    assert wifi.split()[2:4] == ['DOWN', '-']
    assert '54000 / 54000 >nominal (loopback?)' in wifi


def test_status_once_hearing_nothing_says_the_domain_and_range_it_listened_on(
        deployment_path, ros_env):
    # A domain of its own, where nothing of this run publishes.
    domain = str(int(ros_env['ROS_DOMAIN_ID']) + 100)
    env = dict(ros_env, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'status', '--params-file',
                        deployment_path, '--once', '--wait', '0.5'],
                       env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    where = f'ROS_DOMAIN_ID={domain}, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (this machine only)'
    assert r.stdout.splitlines()[1].startswith(f'no layout heard, nor anything else on {where}: '
                                               'check that the decider'), r.stdout
    assert f'nothing heard within 0.5 s on {where}' in r.stderr


def test_status_once_takes_a_late_layouts_age_from_the_leading_deciders_diagnostics(
        deployment_path, ros_env, world):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    diag = world.node.create_publisher(DiagnosticArray, p.TOPIC_DIAGNOSTICS, 10)

    def say(name, age_s):
        status = DiagnosticStatus(level=bytes([0]), name=name, message='constraints hold',
                                  values=[KeyValue(key='generation', value='3'),
                                          KeyValue(key=LAYOUT_AGE, value=str(age_s))])
        diag.publish(DiagnosticArray(status=[status]))

    world.set_layout(3, 'robot')
    proc = subprocess.Popen([sys.executable, '-m', 'anyscale_manager.cli', 'status',
                             '--params-file', deployment_path, '--once', '--wait', '5'],
                            env=ros_env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while proc.poll() is None and time.monotonic() < deadline:
            world.beat()
            say(f'anyscale_decider: {NAME}', 15.0)
            say(f'anyscale_decider (standby b2): {NAME}', 99.0)   # a standby's: not its age
            time.sleep(0.1)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    line = out.splitlines()[1]
    assert re.fullmatch(r'layout generation 3, made 1[5-9]\.\d s ago', line), out


def test_a_shared_scale_shows_its_hosts_claims_by_deployment_and_what_it_refuses(d):
    book = StatusBook(d)
    share = p.HostShare(700.0, 4096.0, {'robot_b/amcl': p.ShareClaim(400.0, 70.0, 1, True),
                                        'robot_c/ar': p.ShareClaim(0.0, 70.0, 0, False)},
                        {'worker': 'robot_b/amcl (400 CPU, priority 1) holds it'}, {},
                        {'sensor': 'robot_b/amcl'})
    laptop = agent('laptop', 3, 'sensor')
    laptop.share = share
    take(book, 0.0, layout(3), agent('robot', 3, 'worker'), laptop)
    text = render(book, 1.0)
    assert 'SHARED laptop: host capacity 700 CPU, 4096 MiB' in text
    assert row(text, f'  {NAME}').split()[-2:] == ['sensor', 'running']
    assert row(text, '  robot_b').endswith('amcl 400 CPU 70 MiB (priority 1)')
    assert row(text, '  robot_c').endswith('ar standby 70 MiB (priority 0)')
    assert '  refused here: worker: robot_b/amcl (400 CPU, priority 1) holds it' in text
    assert '  asked to leave: sensor, by robot_b/amcl' in text
    # A scale of its own shows no such block.
    assert 'SHARED robot' not in text
