"""A silent agent is not a silent link: the decider's pure core on a fake clock.

``Fleet`` plays the agents of the ICAR test-bed as the decider hears them: each live agent
reports what runs on its scale, its scale's CPU and the connections whose subscriber runs there
(its probes); the master's agent also reports the link (its link monitor). Killing an agent
silences all of that at once, as a SIGKILL does. Decisions are applied at once by the agent of
the gaining scale, if it is alive.
"""

from dataclasses import replace

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.model.loader import load_deployment, load_mapping
from anyscale_manager.runtime.constraints import FREQUENCY
from anyscale_manager.runtime.delta import DeltaTracker
from anyscale_manager.runtime.intake import ObservationBook
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.liveness import (AGENT_BACK, AGENT_SILENT, PLACEABLE, SCALE_LOST,
                                               UNPLACEABLE, LivenessWatch)
from anyscale_manager.runtime.observations import (MIGRATE_BACK, RELOCATE, ConnectionObs,
                                                   LinkObs, Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy


@pytest.fixture(scope='module')
def d():
    from conftest import TESTBED
    return load_deployment(TESTBED)


class Fleet:
    def __init__(self, d, settings=None, running=None):
        self.d = d
        self.settings = settings or d.decider
        self.master = d.master.name
        self.book = ObservationBook(d, self.settings, started=0.0)
        self.policy = MigrationPolicy(d, self.settings)
        self.watch = LivenessWatch(d, self.settings)
        self.running = dict(running or master_layout(d))
        self.dead = set()              # scales whose agent is dead (heard by nobody)
        self.link_up = True
        self.t = 0.0
        self.decisions = []            # (t, Decision)
        self.notices = []              # (t, Notice)
        self.notes = set()

    def hear(self):
        t, book = self.t, self.book
        for s in self.d.scale_names:
            if s in self.dead:
                continue
            here = [n for n, w in self.running.items() if w == s]
            book.agent_state(p.AgentState(scale=s, generation=1, stamp=0.0, nodes={
                n: p.NodeReport(state='running', pid=1, since=0.0, restarts=0, ready=True,
                                exit_reason='') for n in here}), t)
            cpu = sum(self.d.node(n).cpu for n in here)
            book.scale_status(p.ScaleStatus(scale=s, stamp=0.0, cpu_total=cpu,
                                            capacity_cpu=self.d.scale(s).capacity_cpu,
                                            cpu_by_node={}, mem_percent=1.0, load_1m=0.1), t)
            readings = {c.name: p.ConnectionReading(rate_hz=c.freq_opt_hz, bytes_per_s=1.0,
                                                    below_for_s=0.0, level=0)
                        for c in self.d.connections
                        if c.monitored and self.running.get(c.subscriber) == s}
            book.connection_status(p.ConnectionStatus(scale=s, stamp=0.0,
                                                      connections=readings), t)
        if self.master not in self.dead:
            for r in self.d.remote_scales:
                book.link_status(p.LinkStatus(
                    master=self.master, remote=r.name, stamp=0.0, up=self.link_up, rtt_ms=1.0,
                    loss=0.0, bandwidth_available_kbps=None, bandwidth_available_age_s=None,
                    bandwidth_used_kbps=0.0), t)

    def run(self, until, period=0.5):
        while self.t <= until + 1e-9:
            self.hear()
            obs = self.book.snapshot(self.t, self.policy.layout or None)
            for dec in self.policy.step(obs):
                self.decisions.append((self.t, dec))
                if dec.to_scale not in self.dead:
                    self.running[dec.node] = dec.to_scale
            self.notes.update(self.policy.notes)
            self.notices += [(self.t, n) for n in self.watch.update(
                obs, self.policy.unplaceable, self.policy.last_report, self.policy.layout)]
            self.t = round(self.t + period, 9)

    def notices_of(self, kind):
        return [(t, n) for t, n in self.notices if n.kind == kind]


def on_laptop(d):
    return dict(master_layout(d), amcl='laptop', ar='laptop')


def test_the_masters_agent_silent_keeps_the_layout_says_so_and_resumes(d):
    """The robot's agent dies with AMCL and AR on the laptop. Its probes measured AMCL -> EKF
    and AR -> navigation: their silence must not read as 0 Hz past Δ (which would bring both
    to a robot where nothing can start them), and the unjudged link must not read as a cut.
    The layout is kept and said to be kept; when the agent is back, everything is judged again.
    """
    settings = replace(d.decider, agent_timeout_s=10.0)     # well past max_age + every Δ
    fleet = Fleet(d, settings, running=on_laptop(d))
    fleet.run(10.0)
    assert not fleet.decisions and fleet.policy.layout['amcl'] == 'laptop'
    assert not fleet.notices

    fleet.dead.add('robot')
    fleet.run(30.0)
    assert not fleet.decisions, fleet.decisions
    assert fleet.running['amcl'] == 'laptop' and fleet.running['ar'] == 'laptop'
    (t_silent, silent), = fleet.notices_of(AGENT_SILENT)
    assert silent.scale == 'robot' and silent.level == 'warn'
    assert 10.0 + settings.observation_max_age_s < t_silent <= 10.0 + 3.0
    assert 'the agent of robot (the master scale) has been silent' in silent.text
    assert 'no link is judged cut' in silent.text and 'what runs is kept' in silent.text
    (t_lost, lost), = fleet.notices_of(SCALE_LOST)
    assert lost.scale == 'robot' and 'the layout is kept' in lost.text and t_lost > 20.0
    report = fleet.policy.last_report
    assert report.links['wifi'].up and not report.of_kind(FREQUENCY)
    level, message = fleet.watch.summary()
    assert level == p.WARN and message.startswith('agent of robot lost for ')
    assert 'the master: layout kept' in message

    fleet.dead.discard('robot')
    t_back = fleet.t
    fleet.run(40.0)
    (t, back), = fleet.notices_of(AGENT_BACK)
    assert t == t_back and back.scale == 'robot'
    assert 'reports again after 2' in back.text     # silent from 10.0 to 30.0
    assert not fleet.decisions
    assert fleet.watch.summary() == (p.OK, '')
    # Past its monitors' start-up, its probes' connections are judged again (and hold).
    assert fleet.policy.last_report.connections['amcl_ekf'].judged
    # Things resume: a cut link brings both home at once.
    fleet.link_up = False
    fleet.run(41.0)
    assert {(dec.kind, dec.node, dec.to_scale) for _, dec in fleet.decisions} == {
        (MIGRATE_BACK, 'amcl', 'robot'), (MIGRATE_BACK, 'ar', 'robot')}


def test_a_move_back_is_held_while_the_masters_agent_is_silent(d, monkeypatch):
    """Even when a violation calls for it (here the probes' silence counted as 0 Hz, as it was
    before the probes' agent was taken into account), nothing is sent to a master whose agent
    is silent: nothing could start it there."""
    monkeypatch.setattr(ObservationBook, 'unjudged_connections',
                        lambda self, now, running, desired=None: frozenset())
    settings = replace(d.decider, agent_timeout_s=10.0)
    fleet = Fleet(d, settings, running=on_laptop(d))
    fleet.run(5.0)
    fleet.dead.add('robot')
    fleet.run(14.0)
    assert fleet.policy.last_report.of_kind(FREQUENCY)      # the silent probes, past Δ
    assert not fleet.decisions
    assert any(n.startswith('amcl is not brought back to robot: the agent of robot is silent')
               and n.endswith('the layout is kept') for n in fleet.notes), fleet.notes


def test_a_move_not_applied_is_not_undone_towards_a_silent_master(d):
    """The undo of a move the agents did not apply is a move back too: held the same way."""
    fleet = Fleet(d)
    fleet.run(0.0)
    ((_, out),) = fleet.decisions
    assert out.node == 'amcl' and out.to_scale == 'laptop'
    fleet.running['amcl'] = 'robot'              # the laptop never starts it
    fleet.dead.add('robot')
    fleet.run(d.agent.readiness_timeout_s + d.decider.agent_timeout_s + 5.0)
    assert len(fleet.decisions) == 1
    assert 'amcl is not brought back to robot: the agent of robot is lost (silent > 4 s), ' \
        'nothing can start it there; the layout is kept' in fleet.notes


def test_no_move_out_while_the_masters_agent_is_silent(d):
    fleet = Fleet(d)
    fleet.dead.add('robot')
    fleet.book.agent_state(p.AgentState(scale='robot', generation=0, stamp=0.0, nodes={}), 0.0)
    fleet.t = d.decider.observation_max_age_s + 0.5
    fleet.run(fleet.t)
    assert not fleet.decisions
    assert any(n.startswith('no move out: the agent of robot is silent') for n in fleet.notes)


def test_a_remote_agent_silent_while_the_link_is_up(d):
    """The laptop's agent is gone but the link is reported up: it is the agent, not the link.
    Nothing more is placed on the laptop while it is silent; once it is lost its nodes count as
    not running and come home (Algorithm 1: back to the master)."""
    fleet = Fleet(d, running=on_laptop(d))
    fleet.run(5.0)
    fleet.dead.add('laptop')
    fleet.run(5.0 + d.decider.observation_max_age_s + 1.0)
    (_, silent), = fleet.notices_of(AGENT_SILENT)
    assert silent.scale == 'laptop'
    assert 'while link wifi is up: the agent, not the link; nothing is placed on laptop' \
        in silent.text
    assert not fleet.decisions                   # silent, not lost yet: nothing moves
    fleet.run(12.0)
    moved = {dec.node: dec for _, dec in fleet.decisions}
    assert set(moved) == {'amcl', 'ar'}
    for dec in moved.values():
        assert dec.kind == RELOCATE and dec.to_scale == 'robot'
        assert dec.reason.startswith('scale laptop lost: its agent has been silent for ')
        assert 'while link wifi is up: the agent, not the link, is gone' in dec.reason
    assert fleet.notices_of(SCALE_LOST)[0][1].text.startswith('scale laptop lost')


def observed(d, now, running, silent=None, lost=frozenset(), links=None):
    return Observations(
        now=now, running=running,
        scales={s: ScaleObs(cpu_total=10.0, stamp=now) for s in d.scale_names},
        links=links or {r.name: LinkObs(up=True, stamp=now) for r in d.remote_scales},
        connections={c.name: ConnectionObs(rate_hz=c.freq_opt_hz or c.freq_min_hz, stamp=now)
                     for c in d.connections if c.monitored},
        lost_scales=frozenset(lost), silent_agents=silent or {})


def test_nothing_is_placed_on_a_scale_whose_agent_is_silent(d):
    policy = MigrationPolicy(d)
    running = master_layout(d)
    assert not policy.step(observed(d, 0.0, running, silent={'laptop': 2.5}))
    assert any(n.startswith('amcl -> laptop: the agent of laptop is silent') for n in policy.notes)
    (dec,) = policy.step(observed(d, 0.5, running))
    assert (dec.node, dec.to_scale) == ('amcl', 'laptop')


def three_scales():
    def node(**extra):
        return dict({'launch': {'command': ['true']}, 'cpu': 10.0}, **extra)
    return load_mapping({'/**': {'ros__parameters': {
        'deployment': {'name': 'three'},
        'scales': {'names': ['robot', 'laptop', 'server'],
                   'robot': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 200.0},
                   'laptop': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 400.0,
                              'cores': 4},
                   'server': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 800.0,
                              'cores': 8}},
        'links': {'names': ['wifi', 'lan'],
                  'wifi': {'ends': ['robot', 'laptop'], 'bandwidth_kbps': 50000.0},
                  'lan': {'ends': ['robot', 'server'], 'bandwidth_kbps': 50000.0}},
        'nodes': {'names': ['sensor', 'viewer'],
                  'sensor': node(residence=['robot']),
                  'viewer': node(residence=['laptop', 'server'])},
        'connections': {'names': ['sensor_viewer'],
                        'sensor_viewer': {'topic': '/s', 'publisher': 'sensor',
                                          'subscriber': 'viewer', 'freq_min_hz': 1.0,
                                          'tolerance_s': 2.0}},
    }}})


def test_a_node_that_no_live_scale_may_host_is_an_error_not_a_move():
    d = three_scales()
    policy = MigrationPolicy(d)
    watch = LivenessWatch(d, d.decider)
    running = {'sensor': 'robot', 'viewer': 'laptop'}
    policy.reset(running, 0.0, running)
    lan_down = {'laptop': LinkObs(up=True, stamp=10.0), 'server': LinkObs(up=False, stamp=10.0)}
    obs = observed(d, 10.0, {'sensor': 'robot'}, silent={'laptop': 6.0}, lost={'laptop'},
                   links=lan_down)
    assert not policy.step(obs)
    assert policy.layout['viewer'] == 'laptop'               # kept: nowhere else to go
    why = policy.unplaceable['viewer']
    assert why.startswith('allowed scales laptop, server have no live agent or are '
                          'unreachable (the agent of laptop is lost')
    assert 'link lan to server reported down' in why
    notices = watch.update(obs, policy.unplaceable, policy.last_report, policy.layout)
    (bad,) = [n for n in notices if n.kind == UNPLACEABLE]
    assert bad.level == 'error' and bad.node == 'viewer' and bad.scale == 'laptop'
    assert bad.text.startswith('viewer cannot be placed: allowed scales laptop, server')
    assert bad.text.endswith('it stays on laptop in the layout')
    level, message = watch.summary()
    assert level == p.ERROR and message.startswith('cannot be placed: viewer (allowed scales')
    # Said once, not every turn.
    assert not [n for n in watch.update(replace(obs, now=10.5), policy.unplaceable)
                if n.kind == UNPLACEABLE]
    # The server's link comes back: the viewer goes there, and that is said too.
    obs = replace(obs, now=11.0, links={'laptop': LinkObs(up=True, stamp=11.0),
                                        'server': LinkObs(up=True, stamp=11.0)})
    (dec,) = policy.step(obs)
    assert (dec.kind, dec.node, dec.to_scale) == (RELOCATE, 'viewer', 'server')
    assert not policy.unplaceable
    notices = watch.update(obs, policy.unplaceable, policy.last_report, policy.layout)
    assert [(n.kind, n.node) for n in notices] == [(PLACEABLE, 'viewer')]


# --- the observation book -------------------------------------------------------------------

def agent(scale, **nodes):
    return p.AgentState(scale=scale, generation=1, stamp=0.0, nodes={
        n: p.NodeReport(state=s, pid=1, since=0.0, restarts=0, ready=True, exit_reason='')
        for n, s in nodes.items()})


def test_the_book_tells_which_agents_are_silent_and_what_their_probes_measured(d):
    max_age, start = d.decider.observation_max_age_s, p.LINK_MONITOR_START_S
    book = ObservationBook(d, d.decider, started=0.0)
    # Never heard: silent once the start-up allowance is over, counted from the start.
    assert book.silent_agents(max_age) == {}
    assert book.silent_agents(max_age + 1.0) == {'robot': max_age + 1.0,
                                                 'laptop': max_age + 1.0}
    layout = dict(master_layout(d), amcl='laptop')
    robot = {n: 'running' for n, s in layout.items() if s == 'robot'}
    book.agent_state(agent('robot', **robot), 0.5)
    book.agent_state(agent('laptop', amcl='running'), 0.5)
    running = book.running(1.0)
    # First heard at the start: their monitors are not new, everything is judged.
    assert book.unjudged_connections(1.0, running, layout) == frozenset()
    # The laptop's agent falls silent: what its probes measure (laser -> amcl) is not judged;
    # what the robot measures (amcl -> ekf, the subscriber's scale) is.
    t = 0.5 + max_age + 0.5
    for heard in (1.5, 2.5, t):                  # the robot's agent goes on reporting
        book.agent_state(agent('robot', **robot), heard)
    assert set(book.silent_agents(t)) == {'laptop'}
    assert book.unjudged_connections(t, book.running(t), layout) == {'laser_amcl'}
    obs = book.snapshot(t, layout)
    assert obs.unjudged_connections == {'laser_amcl'}
    assert obs.silent_agents == {'laptop': pytest.approx(max_age + 0.5)}
    # Back: its new probes measure from scratch for LINK_MONITOR_START_S + max_age.
    t_back = t + 0.5
    book.agent_state(agent('laptop', amcl='running'), t_back)
    end = t_back + start + max_age
    for k in range(1, int((end - t_back) / 0.5) + 2):         # both report every 0.5 s
        book.agent_state(agent('robot', **robot), t_back + 0.5 * k)
        book.agent_state(agent('laptop', amcl='running'), t_back + 0.5 * k)
    assert book.unjudged_connections(end, running, layout) == {'laser_amcl'}
    assert book.unjudged_connections(end + 0.1, running, layout) == frozenset()


def test_the_delta_timer_does_not_count_time_a_connection_was_not_judged(d):
    """A reading missing while its probe's agent was silent counts as missing only from the
    last turn that did not judge it: the agent's silence is not the connection's."""
    c = d.connection('amcl_ekf')
    tracker = DeltaTracker(d)
    s = d.decider
    old = {c.name: ConnectionObs(rate_hz=5.0, stamp=0.0)}
    assert tracker.update(Observations(now=0.0, running={}, connections=old), s)[c.name] == 0.0
    for now in (5.0, 10.0):
        below = tracker.update(Observations(now=now, running={}, connections=old,
                                            unjudged_connections=frozenset({c.name})), s)
        assert below[c.name] == 0.0
    # Judged again at 10.5 with the reading still the old one: 0.5 s, not 8.5 s.
    below = tracker.update(Observations(now=10.5, running={}, connections=old), s)
    assert below[c.name] == pytest.approx(0.5)


def test_status_does_not_show_a_node_whose_scale_has_no_agent_as_moving(d):
    from anyscale_manager.view.status import StatusBook, render
    book = StatusBook(d)
    book.take(p.TOPIC_LAYOUT, p.Layout(generation=4, deployment=d.name,
                                       assignments=dict(master_layout(d), amcl='laptop'),
                                       reason='x', stamp=0.0).to_json(), 10.0)
    book.take(p.TOPIC_AGENT_STATE, agent('robot').to_json(), 10.0)
    book.take(p.TOPIC_AGENT_STATE, agent('laptop').to_json(), 10.0)
    late = 10.0 + d.decider.agent_timeout_s + 1.0
    book.take(p.TOPIC_AGENT_STATE, agent('robot').to_json(), late)
    row = next(line for line in render(book, late).splitlines() if line.startswith('amcl '))
    assert '(not placed: agent of laptop silent)' in row and '(moving)' not in row


def test_a_new_agent_process_is_a_restart_even_without_a_silence(d):
    """An agent restarted in place (SIGHUP) or by a quick supervisor answers again within
    max_age; its new instance id says its monitors start afresh."""
    book = ObservationBook(d, d.decider, started=0.0)
    layout = dict(master_layout(d), amcl='laptop')
    robot = {n: 'running' for n, s in layout.items() if s == 'robot'}
    for t in (0.5, 1.0, 1.5):
        book.agent_state(replace(agent('robot', **robot), instance='first'), t)
        book.agent_state(replace(agent('laptop', amcl='running'), instance='one'), t)
    assert book.unjudged_connections(1.5, book.running(1.5), layout) == frozenset()
    book.agent_state(replace(agent('robot', **robot), instance='second'), 2.0)
    assert book.back_at['robot'] == 2.0 and book.master_back_at == 2.0
    assert 'amcl_ekf' in book.unjudged_connections(2.0, book.running(2.0), layout)
    assert 'laser_amcl' not in book.unjudged_connections(2.0, book.running(2.0), layout)
    assert book.unjudged_links(2.5) == {'laptop'}      # its link monitor starts afresh too
