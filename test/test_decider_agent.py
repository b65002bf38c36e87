"""The real decider and the real agents (with their monitors) as processes over real DDS.

Two scales on this machine: the layout is published, applied by the agents, reported back,
and re-published on change (a move out, then the remote agent's end brings the node home).
"""

import os
import signal

import psutil
import pytest
from std_msgs.msg import String

from anyscale_manager import protocol as p
import home_away as ha
from home_away import runs
from spinning import spin_until


def write_deployment(tmp_path):
    return ha.write_deployment(tmp_path, f'decider_agent_{os.getpid()}',
                               ha.worker_and_pinned(f'/decider_agent_{os.getpid()}'))


@pytest.fixture
def listener():
    with ha.listening('decider_agent_listener') as heard:
        yield heard


def wait(ex, cond, timeout, what, procs=()):
    """Until ``cond()``; the decider's end ends the wait (agents are stopped on purpose)."""
    spin_until(ex, cond, timeout, what, procs, watch=('decider',))


def test_layout_applied_reported_back_and_republished(tmp_path, ros_env, listener):
    ex, seen = listener
    deployment = write_deployment(tmp_path)
    procs = []
    try:
        ha.start_agents(procs, tmp_path, ros_env, deployment)
        decider = ha.start(procs, tmp_path, ros_env, deployment, 'decider')
        agents = dict(procs[:2])

        wait(ex, lambda: seen['layouts'], 40.0, 'the first layout', procs)
        first = seen['layouts'][0]         # latched: the newest one when we matched
        assert first.assignments['pinned'] == 'home' and set(first.assignments) == {
            'worker', 'pinned'}
        # The decider moves the worker out once the link is observed, and the agents apply it:
        # the away agent reports it running, the home agent no longer does.
        wait(ex, lambda: runs(seen, 'away', 'worker') and not runs(seen, 'home', 'worker'),
             60.0, 'worker running on away', procs)
        moved = [lay for lay in seen['layouts'] if lay.assignments['worker'] == 'away']
        assert moved and moved[0].generation >= first.generation
        # The pinned node stays home throughout (it may still be reporting 'starting' under load).
        wait(ex, lambda: runs(seen, 'home', 'pinned'), 20.0, 'pinned running home', procs)
        assert seen['states']['home'].nodes['pinned'].restarts == 0
        wait(ex, lambda: seen['states']['away'].generation >= moved[0].generation, 10.0,
             'the away agent reporting the new generation', procs)

        # The away agent ends (and stops what it runs): the worker comes home, re-published.
        agents['agent_away'].stop(signal.SIGINT)
        wait(ex, lambda: seen['layouts'][-1].assignments['worker'] == 'home', 30.0,
             'the worker placed home again', procs)
        assert seen['layouts'][-1].generation > moved[-1].generation
        wait(ex, lambda: runs(seen, 'home', 'worker'), 30.0, 'worker running home', procs)
        # Another topic than the layout's: a lost packet of a reliable burst comes back only
        # with the writer's next heartbeat, so wait for it.

        def backs():
            return [e for e in seen['events'] if e.node == 'worker'
                    and e.kind in ('migrate_back', 'relocate')]
        wait(ex, backs, 10.0, 'the event that brought the worker home', procs)
        assert all(e.reason for e in backs())
        assert decider.proc.poll() is None
    finally:
        codes = {name: pr.stop() for name, pr in reversed(procs)}
    assert codes['decider'] == 0, procs[2][1].text()[-3000:]


def write_chain_deployment(tmp_path):
    """sensor (home) -> worker (migratable) -> pinned (home): the home agent's probe measures
    worker -> pinned, so when that agent dies the connection's readings stop with it."""
    # Without the agent's liveness, its probe's silence would read as 0 Hz past Δ after
    # max_age + Δ = 8 s, well before the scale is lost (12 s). Δ also covers the chain's cold
    # start on a loaded machine.
    graph = ha.chain(f'/decider_liveness_{os.getpid()}', 4.0, freq_min_hz=0.5, tolerance_s=6.0)
    return ha.write_deployment(
        tmp_path, f'decider_liveness_{os.getpid()}', graph,
        decider={'grace_s': 4.0, 'agent_timeout_s': 12.0, 'observation_max_age_s': 2.0},
        monitoring={'heartbeat_misses_down': 8}, port_offset=7, file_name='liveness.yaml')


def test_a_killed_master_agent_is_not_a_cut_link(tmp_path, ros_env, listener):
    """The robot's (home's) agent is SIGKILLed while the worker runs away: the decider says the
    agent is silent, does not send the worker home (no agent there to start it; its probe's
    silence is not a slow connection; its link monitor's silence is not a cut), and the worker
    runs on. The agent restarted adopts what it ran; the decider says so and acts again: the
    away agent's end then brings the worker home, where it now runs."""
    ex, seen = listener
    deployment = write_chain_deployment(tmp_path)
    procs = []

    def agent(scale):
        return ha.start([], tmp_path, ros_env, deployment, f'agent_{scale}_{len(procs)}',
                        '-p', f'scale:={scale}')

    def events(kind, scale):
        return [e for e in seen['events'] if e.kind == kind and e.from_scale == scale]
    try:
        procs.append(('agent_home', agent('home')))
        procs.append(('agent_away', agent('away')))
        ha.start(procs, tmp_path, ros_env, deployment, 'decider')
        wait(ex, lambda: runs(seen, 'away', 'worker') and not runs(seen, 'home', 'worker')
             and runs(seen, 'home', 'pinned') and runs(seen, 'home', 'sensor'), 60.0,
             'worker running away, sensor and pinned home', procs)
        worker = seen['states']['away'].nodes['worker'].pid
        pinned = seen['states']['home'].nodes['pinned'].pid
        # The decider judges worker -> pinned on the home agent's probe: wait until it flows.
        rates = {}

        def reading(msg):
            status = p.ConnectionStatus.from_json(msg.data)
            if 'worker_pinned' in status.connections:
                rates[status.scale] = status.connections['worker_pinned'].rate_hz
        ex.get_nodes()[0].create_subscription(String, p.TOPIC_CONNECTION_STATUS, reading, 10)
        wait(ex, lambda: rates.get('home', 0.0) >= 0.5, 30.0, 'worker -> pinned measured home',
             procs)
        layouts_before = len(seen['layouts'])

        procs[0][1].proc.kill()                      # the robot's agent dies hard
        procs[0][1].proc.wait(10)
        wait(ex, lambda: events('agent_silent', 'home'), 15.0, 'the agent_silent event', procs)
        (silent,) = events('agent_silent', 'home')
        assert 'the agent of home (the master scale) has been silent' in silent.reason
        # Past max_age + Δ of worker -> pinned, and past agent_timeout_s: the scale is lost.
        wait(ex, lambda: events('scale_lost', 'home'), 20.0, 'home declared lost', procs)
        assert seen['layouts'][-1].assignments['worker'] == 'away'
        assert all(lay.assignments['worker'] == 'away' for lay in seen['layouts'][layouts_before:])
        assert not [e for e in seen['events'] if e.node == 'worker' and e.kind in (
            'migrate_back', 'relocate', 'migrate')][1:]      # only the move out, long before
        state = seen['states']['away'].nodes['worker']
        assert state.state == 'running' and state.pid == worker and state.restarts == 0
        assert psutil.pid_exists(pinned)             # unsupervised, but left running

        procs.append(('agent_home_2', agent('home')))
        wait(ex, lambda: events('agent_back', 'home'), 30.0, 'the agent_back event', procs)
        wait(ex, lambda: runs(seen, 'home', 'pinned')
             and seen['states']['home'].nodes['pinned'].pid == pinned, 20.0,
             'pinned adopted by the new home agent', procs)
        assert f'pinned: adopted pid {pinned}' in procs[-1][1].text()
        assert seen['states']['away'].nodes['worker'].pid == worker
        assert len([lay for lay in seen['layouts'][layouts_before:]
                    if lay.assignments['worker'] != 'away']) == 0

        # The decider acts again, with a live home agent: the away agent's end brings the
        # worker home, and it runs there.
        procs[1][1].stop(signal.SIGINT)
        wait(ex, lambda: seen['layouts'][-1].assignments['worker'] == 'home', 30.0,
             'the worker placed home again', procs)
        wait(ex, lambda: runs(seen, 'home', 'worker'), 30.0, 'worker running home', procs)
        assert procs[2][1].proc.poll() is None
    finally:
        codes = {name: pr.stop() for name, pr in reversed(procs)}
        # A failure before the home agent was restarted leaves the nodes of the killed one
        # running (by design): they are this test's, found by its topic.
        marker = f'/decider_liveness_{os.getpid()}/'
        for proc in psutil.process_iter(['cmdline']):
            if any(marker in arg for arg in proc.info['cmdline'] or ()):
                proc.kill()
    assert codes['decider'] == 0, procs[2][1].text()[-3000:]
