"""Single-machine mode: scales that share one machine (two agents on a laptop).

Pure: the host identity and who shares a machine, the decider's notices, a scale's CPU as its
agent's process tree on fake process tables, the cap of a loopback bandwidth at the link's
nominal in the constraints and the policy's reasons, the status view and ``validate``. Then one
real run on loopback: two agents and the decider as processes, a CPU hog the test owns outside
either scale, and no node moved back for CPU.
"""

import os
import subprocess
import sys
import time
from dataclasses import replace

import psutil
import pytest
import yaml

from anyscale_manager import protocol as p
from anyscale_manager.agent.host import this_host
from anyscale_manager.model.advice import single_machine
from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime import cpu
from anyscale_manager.runtime.constraints import BANDWIDTH, capped_kbps, evaluate, link_capacity
from anyscale_manager.runtime.hosts import (HostBook, SingleMachineWatch, identity_from,
                                            shared_groups)
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (MIGRATE, MIGRATE_BACK, ConnectionObs,
                                                   LinkObs, Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy
from anyscale_manager.view.status import StatusBook, render
from conftest import REPO, TESTBED
import home_away as ha
from home_away import runs
from spinning import spin_until

LOOPBACK_KBPS = 23456370.0        # what an active probe measured over loopback in the issue


# --- who shares a machine ---------------------------------------------------------------------

@pytest.mark.parametrize('boot, machine, name, expected', [
    ('b6c8-01', '3d12', 'vm', 'boot:b6c8-01'),
    ('', '3d12\n', 'vm', 'machine:3d12'),
    ('  ', '', 'vm', 'name:vm'),
    ('', '', '', ''),
])
def test_the_identity_prefers_the_kernels_boot_id(boot, machine, name, expected):
    assert identity_from(boot, machine, name) == expected


def test_this_host_reads_the_boot_id_then_the_machine_id(tmp_path):
    boot, machine = tmp_path / 'boot_id', tmp_path / 'machine-id'
    boot.write_text('b6c83af4-f902\n')
    machine.write_text('3d1219c7\n')
    assert this_host(str(boot), str(machine))[0] == 'boot:b6c83af4-f902'
    assert this_host(str(tmp_path / 'none'), str(machine))[0] == 'machine:3d1219c7'
    host_id, name = this_host(str(tmp_path / 'none'), str(tmp_path / 'none'))
    assert host_id == f'name:{name}' and name
    # On this machine: two agents read the same identity.
    assert this_host() == this_host() and this_host()[0]


def test_groups_of_scales_on_one_machine_in_deployment_order():
    hosts = {'server': 'boot:b', 'laptop': 'boot:a', 'robot': 'boot:a', 'old': ''}
    assert shared_groups(hosts, ['robot', 'laptop', 'server']) == (('robot', 'laptop'),)
    assert shared_groups({'a': 'boot:x', 'b': 'boot:y'}) == ()
    # An agent that reports no identity (an older one) shares nothing.
    assert shared_groups({'a': '', 'b': ''}) == ()


def test_an_agent_sees_the_scales_heard_lately_on_its_machine():
    book = HostBook()
    book.heard('laptop', 'boot:a', 'vm', now=10.0)
    book.heard('server', 'boot:b', 'rack', now=10.0)
    assert book.sharing('robot', 'boot:a', now=11.0, max_age_s=3.0) == ('laptop',)
    assert book.sharing('robot', 'boot:a', now=14.0, max_age_s=3.0) == ()   # silent since
    assert book.sharing('robot', '', now=11.0, max_age_s=3.0) == ()
    book.heard('laptop', None, None, now=15.0)                               # an older agent
    assert book.sharing('robot', 'boot:a', now=15.0, max_age_s=3.0) == ()


def test_the_decider_says_single_machine_mode_once_and_when_it_ends():
    watch = SingleMachineWatch(['robot', 'laptop'])
    assert watch.update({'robot': ('boot:a', 'vm')}) is None
    text = watch.update({'robot': ('boot:a', 'vm'), 'laptop': ('boot:a', 'vm')})
    assert text.startswith('single-machine mode: scales robot, laptop on host vm share one '
                           'machine')
    assert "own agent's process tree" in text and 'capped at the nominal' in text
    assert watch.update({'robot': ('boot:a', 'vm'), 'laptop': ('boot:a', 'vm')}) is None
    assert watch.summary() == 'robot, laptop on host vm'
    ended = watch.update({'robot': ('boot:a', 'vm'), 'laptop': ('boot:z', 'other')})
    assert ended.startswith('single-machine mode ended: scales robot, laptop')
    assert watch.summary() == '' and not watch.groups


def test_agent_state_carries_the_host_and_refuses_a_hostile_one():
    state = p.AgentState(scale='robot', generation=1, stamp=1.0, nodes={}, host_id='boot:a',
                         host='vm')
    back = p.AgentState.from_json(state.to_json())
    assert (back.host_id, back.host) == ('boot:a', 'vm')
    assert 'host' not in p.AgentState(scale='robot', generation=1, stamp=1.0,
                                      nodes={}).to_dict()
    with pytest.raises(p.ProtocolError, match='host_id'):
        p.AgentState.from_dict(dict(state.to_dict(), host_id='boot:\x1b[2J'))
    with pytest.raises(p.ProtocolError, match='cpu_source'):
        p.ScaleStatus.from_dict(dict(scale='robot', stamp=1.0, cpu_total=1.0,
                                     capacity_cpu=2.0, cpu_by_node={}, mem_percent=1.0,
                                     load_1m=0.1, cpu_source='guess'))


# --- a scale's CPU on a shared machine --------------------------------------------------------

@pytest.mark.parametrize('quota, shared, source', [
    (True, True, cpu.CGROUP),          # the test-bed: cgroups on one machine
    (True, False, cpu.CGROUP),
    (False, True, cpu.PROCESSES),      # two agents on a laptop
    (False, False, cpu.MACHINE),       # one scale per machine, as the paper
])
def test_which_cpu_a_scale_measures(quota, shared, source):
    assert cpu.cpu_source(quota, shared) == source


def table(cpu_s):
    """A fake process table: pid -> (parent, CPU seconds). 100 is this scale's agent, 101 its
    node with a child 102 and a grandchild 103; 200 a node it adopted (init's child since the
    agent that started it was killed); 300 a hog no scale started; 400 the other scale's agent
    with its node 401."""
    parents = {1: 0, 100: 1, 101: 100, 102: 101, 103: 102, 200: 1, 300: 1, 400: 1, 401: 400}
    return {pid: (parent, cpu_s.get(pid, 0.0)) for pid, parent in parents.items()}


def test_a_scale_counts_its_agents_process_tree_and_nothing_else():
    own = cpu.own_cpu_seconds(table({100: 1.0, 101: 2.0, 103: 3.0, 200: 4.0, 300: 99.0}),
                              roots=[100, 200, 999])           # 999: a node gone meanwhile
    assert own == {100: 1.0, 101: 2.0, 102: 0.0, 103: 3.0, 200: 4.0}


def test_a_hog_outside_the_scale_leaves_its_cpu_alone():
    group = cpu.ProcessGroupCpu()
    roots = [100, 200]
    before = {100: 10.0, 101: 20.0, 103: 5.0, 200: 1.0, 300: 0.0, 401: 0.0}
    assert group.update(0.0, {'scale': cpu.own_cpu_seconds(table(before), roots)}) == {}
    # Over 2 s the hog spends 2 CPU seconds (a whole core), the other scale's node 1.5; this
    # scale's agent 0.1, its node's grandchild 0.3, the adopted node 0.2.
    after = {100: 10.1, 101: 20.0, 103: 5.3, 200: 1.2, 300: 2.0, 401: 1.5}
    rate = group.update(2.0, {'scale': cpu.own_cpu_seconds(table(after), roots)})['scale']
    assert rate == pytest.approx(0.3)
    # Against a capacity of 200 on a 2-CPU machine: 30, where the machine's busy time (4.1
    # core-seconds in 2 s) would have read 205.
    assert cpu.reference_percent(rate, 200.0, 2) == pytest.approx(30.0)
    assert cpu.reference_percent(4.1 / 2.0, 200.0, 2) > 200.0 * 0.9


# --- a loopback bandwidth capped at the nominal ------------------------------------------------

@pytest.fixture(scope='module')
def bed():
    return load_deployment(TESTBED)


def slow_link(d, nominal_kbps):
    links = tuple(replace(link, bandwidth_kbps=nominal_kbps) for link in d.links)
    return replace(d, links=links)


def observed(d, now, running, available_kbps):
    cpu_of = {s: sum(d.node(n).cpu for n, w in running.items() if w == s) for s in d.scale_names}
    return Observations(
        now=now, running=running,
        scales={s: ScaleObs(cpu_total=cpu_of[s], stamp=now) for s in d.scale_names},
        links={r.name: LinkObs(up=True, stamp=now, available_kbps=available_kbps)
               for r in d.remote_scales},
        connections={c.name: ConnectionObs(rate_hz=c.freq_opt_hz or c.freq_min_hz, stamp=now)
                     for c in d.connections if c.monitored})


def test_capped_kbps():
    assert capped_kbps(LOOPBACK_KBPS, 54000.0) == 54000.0
    assert capped_kbps(5000.0, 54000.0) == 5000.0
    assert capped_kbps(-1.0, 54000.0) == 0.0


def test_a_measurement_above_the_nominal_counts_as_the_nominal_and_says_so(bed):
    d = slow_link(bed, 5000.0)
    running = dict(master_layout(d), ar='laptop')
    obs = observed(d, 10.0, running, LOOPBACK_KBPS)
    (link,) = d.links
    assert link_capacity(d, d.decider, obs, link) == (True, True, 5000.0, '')
    report = evaluate(d, d.decider, obs)
    load = report.links[link.name]
    assert load.available_kbps == 5000.0 and load.measured_kbps == LOOPBACK_KBPS
    assert load.capped and load.usable_kbps == pytest.approx(5000.0 * d.decider.bandwidth_margin)
    # AR's 6 Mbit/s does not fit 5 Mbit/s: a violation the loopback figure would have hidden.
    (v,) = report.of_kind(BANDWIDTH)
    assert v.nodes == ('ar',)
    assert '(measured 23456370 kbit/s, above the nominal: capped at 5000)' in v.reason
    # Below the nominal the measurement stands, and nothing is said.
    low = evaluate(d, d.decider, observed(d, 10.0, running, 3000.0)).links[link.name]
    assert low.available_kbps == 3000.0 and not low.capped and low.cap_note == ''


def test_the_policys_reasons_use_the_capped_figure(bed):
    d = slow_link(bed, 5000.0)
    # Out: AMCL fits the capped 4000 kbit/s usable, AR (6 Mbit/s) does not; both say why.
    policy = MigrationPolicy(d)
    running = master_layout(d)
    (out,) = policy.step(observed(d, 0.0, running, LOOPBACK_KBPS))
    assert (out.kind, out.node) == (MIGRATE, 'amcl')
    assert 'kbit/s (measured 23456370 kbit/s, above the nominal: capped at 5000)' in out.reason
    running = dict(running, amcl='laptop')
    policy.step(observed(d, 0.5, running, LOOPBACK_KBPS))
    assert not policy.step(observed(d, 1.0, running, LOOPBACK_KBPS))
    assert any(n.startswith('ar -> laptop: link wifi would need') and 'capped at 5000' in n
               for n in policy.notes), policy.notes
    # Back: AR placed out (a layout from before), the do ... while brings it home on the
    # capped figure, and its reason says so.
    policy = MigrationPolicy(d)
    running = dict(master_layout(d), ar='laptop')
    policy.reset(running, 0.0, running)
    decisions = policy.step(observed(d, 0.5, running, LOOPBACK_KBPS))
    back = [x for x in decisions if x.kind == MIGRATE_BACK]
    assert [x.node for x in back] == ['ar'], decisions
    assert 'usable 4000 kbit/s (measured 23456370 kbit/s, above the nominal: capped at 5000)' \
        in back[0].reason


# --- what the user sees: status and validate ---------------------------------------------------

def state(scale, host_id):
    return p.AgentState(scale=scale, generation=1, stamp=time.time(), nodes={},
                        host_id=host_id, host='vm')


def test_status_shows_single_machine_mode_and_a_cpu_of_its_own_processes(bed):
    book = StatusBook(bed)
    book.take(p.TOPIC_AGENT_STATE, state('robot', 'boot:a').to_json(), 0.0)
    assert 'single-machine mode' not in render(book, 0.5)
    book.take(p.TOPIC_AGENT_STATE, state('laptop', 'boot:a').to_json(), 0.0)
    book.take(p.TOPIC_SCALE_STATUS, p.ScaleStatus(
        scale='laptop', stamp=time.time(), cpu_total=12.0, capacity_cpu=700.0, cpu_by_node={},
        mem_percent=1.0, load_1m=0.1, cpu_source='processes').to_json(), 0.0)
    text = render(book, 0.5)
    assert 'single-machine mode: robot, laptop on host vm' in text
    assert '12 / 700 (2%) = 7 core% own processes' in text
    book.take(p.TOPIC_AGENT_STATE, state('laptop', 'boot:b').to_json(), 1.0)
    assert 'single-machine mode' not in render(book, 1.5)


def test_validate_says_what_one_host_for_two_scales_means(bed, tmp_path):
    assert single_machine(bed) == ''        # the test-bed's scales have hosts of their own
    scales = (replace(bed.scales[0], host='localhost'), replace(bed.scales[1], host='127.0.0.1'))
    text = single_machine(replace(bed, scales=scales))
    assert text.startswith('single machine: scales robot, laptop on localhost')
    assert "own agent's processes" in text and 'capped' in text
    with open(TESTBED) as f:
        data = yaml.safe_load(f)
    for s in data['/**']['ros__parameters']['scales']['names']:
        data['/**']['ros__parameters']['scales'][s].pop('host', None)   # the default
    path = tmp_path / 'one_machine.yaml'
    path.write_text(yaml.safe_dump(data))
    r = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'validate', str(path)],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    (first,) = [i for i, line in enumerate(lines) if line.startswith('  single machine: ')]
    assert 'single machine: scales robot, laptop on localhost' in lines[first]
    assert all(len(line) <= 99 for line in lines[first:])      # wrapped, as the summary


# --- a real run on this machine ---------------------------------------------------------------

CAPACITY = 200.0
HEADROOM = 0.4                      # usable 80: one busy core of this machine's reads 100+
NOMINAL_KBPS = 54000.0


def write_deployment(tmp_path):
    """No host for either scale: both default to localhost, as a user's first file."""
    graph = ha.chain(f'/single_machine_{os.getpid()}', 2.0, {'bandwidth_kbps': 100.0})
    return ha.write_deployment(
        tmp_path, f'single_machine_{os.getpid()}', graph, capacity_cpu=CAPACITY,
        link_kbps=NOMINAL_KBPS,
        # A grace long enough for the moved worker's own start (a Python process: about a core
        # for a second or more here) to pass before its scale's CPU is judged.
        decider={'cpu_headroom': HEADROOM, 'agent_timeout_s': 4.0, 'grace_s': 4.0},
        monitoring={'bandwidth_probe_duration_s': 0.3}, port_offset=13)


@pytest.fixture
def listener():
    with ha.listening('single_machine_listener') as heard:
        yield heard


def wait(ex, cond, timeout, what, procs=()):
    """Until ``cond()``; any process's end ends the wait."""
    spin_until(ex, cond, timeout, what, procs, watch=True)


@pytest.mark.timeout(240)
def test_a_load_outside_both_scales_moves_nothing_back(tmp_path, ros_env, listener):
    """Two scales on this machine: the decider says single-machine mode, each scale monitor
    measures its agent's own processes, and a busy process started by this test (on neither
    scale) never brings the worker back for CPU, although the machine's busy time would have
    put the remote scale past its usable CPU. The loopback probe's figure is capped in the
    reason of the move out."""
    ex, seen = listener
    deployment = write_deployment(tmp_path)
    env = dict(ros_env)     # with the packaged discovery profile (conftest)
    procs, hog = [], None
    try:
        ha.start_agents(procs, tmp_path, env, deployment)
        # Each agent hears the other and measures its own processes from then on.
        wait(ex, lambda: {'home', 'away'} <= {s.scale for _, s in seen['scales'][-8:]
                                              if s.cpu_source == 'processes'},
             60.0, 'both scale monitors measuring their own processes', procs)
        assert seen['states']['home'].host_id == seen['states']['away'].host_id \
            == this_host()[0]
        # The link's one throughput probe, over loopback: far above the nominal.
        wait(ex, lambda: any(ls.bandwidth_available_kbps for _, ls in seen['links']), 60.0,
             "the link monitor's throughput probe", procs)
        measured = next(ls.bandwidth_available_kbps for _, ls in seen['links']
                        if ls.bandwidth_available_kbps)
        assert measured > NOMINAL_KBPS, measured

        ha.start(procs, tmp_path, env, deployment, 'decider')
        wait(ex, lambda: runs(seen, 'away', 'worker') and not runs(seen, 'home', 'worker')
             and runs(seen, 'home', 'pinned') and runs(seen, 'home', 'sensor'), 90.0,
             'the worker running away', procs)
        moved = time.monotonic()
        (out,) = [e for e in seen['events'] if e.kind == 'migrate' and e.node == 'worker']
        assert 'above the nominal: capped at 54000' in out.reason, out.reason
        wait(ex, lambda: [e for e in seen['events'] if e.kind == 'single_machine'], 10.0,
             'the single_machine event', procs)
        (mode,) = [e for e in seen['events'] if e.kind == 'single_machine']
        assert mode.reason.startswith('single-machine mode: scales home, away on host ')
        wait(ex, lambda: seen['diagnostics'].get('single machine', 'no') != 'no', 10.0,
             "single-machine mode in the decider's diagnostics", procs)
        assert seen['diagnostics']['single machine'].startswith('home, away on host ')
        assert 'single-machine mode: scales home, away on host' in procs[2][1].text()

        # The worker's own start (a Python node: about a core for a second) is over before the
        # window opens: it is away's load, not the hog's, and the decider may say so.
        usable = CAPACITY * HEADROOM

        def settled():
            recent = [s for t, s in seen['scales'] if s.scale == 'away' and t > moved + 1.5][-3:]
            return len(recent) == 3 and all(s.cpu_source == 'processes'
                                            and s.cpu_total < usable for s in recent)
        wait(ex, settled, 30.0, 'three readings of away below its usable CPU after the '
             "worker's start", procs)
        # A busy process of this test's own, on neither scale.
        layouts, events = len(seen['layouts']), len(seen['events'])
        machine_before = psutil.cpu_times()
        started = time.monotonic()
        hog = subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                               stdin=subprocess.DEVNULL)
        hog_cpu = psutil.Process(hog.pid)
        objectives = seen['objectives']

        def window_over():
            after = [s for t, s in seen['scales'] if t > started + 1.0 and s.scale == 'away']
            return seen['objectives'] - objectives >= 24 and len(after) >= 12
        # At least 24 decider turns (6 s at 0.25 s) and 12 readings of away with the hog on.
        wait(ex, window_over, 60.0, 'a window of decider turns with the hog running', procs)
        elapsed = time.monotonic() - started
        machine_after = psutil.cpu_times()
        hog_seconds = sum(hog_cpu.cpu_times()[:2])

        def busy(t):
            return sum(t) - t.idle - getattr(t, 'iowait', 0.0) - getattr(t, 'guest', 0.0) \
                - getattr(t, 'guest_nice', 0.0)
        machine_reading = cpu.reference_percent(
            (busy(machine_after) - busy(machine_before)) / elapsed, CAPACITY,
            psutil.cpu_count() or 1)
        # The hog did load the machine: read as the machine, away was past its usable CPU.
        assert hog_seconds >= 0.5 * elapsed, (hog_seconds, elapsed)
        assert machine_reading > usable, machine_reading
        # Read as its own processes, it was not, and nothing came back.
        away = [s for t, s in seen['scales'] if t > started + 1.0 and s.scale == 'away']
        assert all(s.cpu_source == 'processes' and s.cpu_total < usable for s in away), \
            [round(s.cpu_total) for s in away]
        new_events = seen['events'][events:]
        # A remote scale past its CPU is what brings a node back (the master's has no node to
        # send home); neither happened, nor any other move back.
        assert not [e for e in new_events if (e.kind == 'migrate_back' and 'CPU' in e.reason)
                    or e.reason.startswith('cpu: scale away')], new_events
        assert not [e for e in new_events if e.kind == 'migrate_back'], new_events
        home = [round(s.cpu_total) for t, s in seen['scales']
                if t > started + 1.0 and s.scale == 'home']
        print(f'machine {machine_reading:.0f}, away {[round(s.cpu_total) for s in away]}, '
              f'home {home} (usable {usable:g})')
        assert all(lay.assignments['worker'] == 'away' for lay in seen['layouts'][layouts:])
        assert runs(seen, 'away', 'worker')
        assert all(pr.proc.poll() is None for _, pr in procs)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait(10)
        codes = {name: pr.stop() for name, pr in reversed(procs)}
    assert codes.get('decider') == 0, procs[-1][1].text()[-3000:]
