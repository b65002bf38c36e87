"""A remote agent killed, or restarted in place, with the real decider, agents and wardens as
processes over real DDS: never two copies serving, and a restart is not a cut."""

import os
import signal
import time
from contextlib import contextmanager

import psutil
import pytest
from std_msgs.msg import UInt8MultiArray

import home_away as ha
from home_away import runs
from spinning import spin_until
from anyscale_manager.nodes import qos

RATE_HZ = 10.0


@pytest.fixture
def listener():
    with ha.listening('fencing_listener') as heard:
        yield heard


def deployment(tmp_path, topic):
    return ha.write_deployment(tmp_path, f'fencing_{os.getpid()}', ha.chain(topic, RATE_HZ),
                               decider={'hysteresis_s': 60.0},
                               agent={'adopt_grace_s': 0.5, 'fence_grace_s': 0.5})


def away_worker(seen):
    s = seen['states'].get('away')
    r = s.nodes.get('worker') if s else None
    return r.pid if r is not None and r.state == 'running' else None


@contextmanager
def worker_away(tmp_path, ros_env, listener, topic):
    """Both agents and the decider running, the worker serving on away only; yields (the
    agents by scale, the arrival times of the worker's output at a subscriber of the test's,
    the processes). Everything is stopped afterwards, the wardens too."""
    ex, seen = listener
    path = deployment(tmp_path, topic)
    heard = []
    sub = ex.get_nodes()[0].create_subscription(
        UInt8MultiArray, topic + '/w', lambda _raw: heard.append(time.monotonic()), qos.PROBE,
        raw=True)
    procs = []
    try:
        agents = ha.start_agents(procs, tmp_path, ros_env, path)
        ha.start(procs, tmp_path, ros_env, path, 'decider')
        spin_until(ex, lambda: away_worker(seen) and ha.released(seen, 'home', 'worker'), 90.0,
                   'the worker running on away only', procs)
        # ... and heard here from away (this subscriber discovers the new copy on its own).
        released = time.monotonic()
        spin_until(ex, lambda: len([t for t in heard if t > released]) >= RATE_HZ / 2, 20.0,
                   'the away copy heard here', procs)
        yield agents, heard, procs
    finally:
        ex.get_nodes()[0].destroy_subscription(sub)
        for name, pr in reversed(procs):
            pr.stop()
        ha.stop_wardens(tmp_path)


@pytest.mark.timeout(180)
def test_a_killed_remote_agents_nodes_are_fenced_before_they_run_elsewhere(
        tmp_path, ros_env, listener):
    ex, seen = listener
    with worker_away(tmp_path, ros_env, listener, f'/fencing_{os.getpid()}') as (
            agents, heard, procs):
        old = psutil.Process(away_worker(seen))
        links_down_before = sum(1 for _, s in seen['links'] if not s.up)
        agents['away'].proc.kill()                 # SIGKILL: no chance to stop its nodes
        killed = time.monotonic()
        spin_until(ex, lambda: not old.is_running() or old.status() == psutil.STATUS_ZOMBIE,
                   10.0, "the warden to stop the dead agent's worker", procs)
        fenced_at = time.monotonic()
        spin_until(ex, lambda: runs(seen, 'home', 'worker'), 30.0, 'the worker running home',
                   procs)
        spin_until(ex, lambda: any(t > fenced_at for t in heard), 20.0, 'the home copy heard',
                   procs)
        # The old copy was stopped before the new one was placed: the layout that brought
        # the worker home came after the warden said 'fenced', and the link never went down.
        assert any(s.peer_agent == 'fenced' for _, s in seen['links'])
        assert sum(1 for _, s in seen['links'] if not s.up) == links_down_before
        home = [e for e in seen['events'] if e.node == 'worker' and e.to_scale == 'home']
        assert home and 'lost' in home[-1].reason, home
        first_new = min(t for t in heard if t > killed and t > fenced_at - 0.05)
        last_old = max((t for t in heard if t < fenced_at), default=killed)
        assert last_old <= first_new
        print(f'worker stopped {fenced_at - killed:.2f} s after its agent was killed; home '
              f'copy heard {first_new - killed:.2f} s after')


@pytest.mark.timeout(180)
def test_a_remote_agent_restarted_in_place_is_not_a_cut(tmp_path, ros_env, listener):
    ex, seen = listener
    with worker_away(tmp_path, ros_env, listener, f'/fencing_hup_{os.getpid()}') as (
            agents, heard, procs):
        pid = away_worker(seen)
        generation = seen['layouts'][-1].generation
        events = len(seen['events'])
        instance = seen['states']['away'].instance
        agents['away'].proc.send_signal(signal.SIGHUP)
        hup = time.monotonic()
        spin_until(ex, lambda: seen['states']['away'].instance != instance
                   and away_worker(seen) == pid, 30.0, 'the new agent adopting the worker', procs)
        spin_until(ex, lambda: len([t for t in heard if t > time.monotonic() - 1.0])
                   >= RATE_HZ / 2, 10.0, 'the output steady after the restart', procs)
        assert all(s.up for t, s in seen['links'] if t >= hup)
        assert seen['layouts'][-1].generation == generation
        assert not [e for e in seen['events'][events:] if e.node == 'worker']
        assert seen['states']['away'].nodes['worker'].restarts == 0
        gaps = [b - a for a, b in zip(heard, heard[1:]) if b > hup]
        print(f'longest gap at the consumer across the restart: {max(gaps):.3f} s')
        assert max(gaps) < 1.0 / RATE_HZ + 0.5
