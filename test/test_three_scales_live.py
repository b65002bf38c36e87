"""Three scales of this one machine, with the real decider, agents and wardens as processes over
real DDS: home (the master), a laptop and a server (the most powerful). The worker goes to the
server; when the server's agent is killed its worker is fenced and placed on the laptop (the
next-best scale), not home; when the server's agent is back, T after that move the worker returns
to it (rebalancing). Each link is reported by the scale that watches it (the laptop watches the
backhaul). Cutting one link of three needs network namespaces: the test-bed's."""

import os

import pytest
import yaml

from anyscale_manager.agent import procs as procs_of

import home_away as ha
from home_away import runs
from spinning import spin_until

RATE_HZ = 10.0
T_S = 6.0


@pytest.fixture
def listener():
    with ha.listening('three_scales_listener') as heard:
        yield heard


def three_scales(tmp_path, topic) -> str:
    """home_away's deployment with its remote scale split in two: laptop and server."""
    path = ha.write_deployment(tmp_path, f'three_{os.getpid()}', ha.chain(topic, RATE_HZ),
                               decider={'hysteresis_s': T_S, 'rebalance_min_gain': 0.0},
                               agent={'adopt_grace_s': 0.5, 'fence_grace_s': 0.5})
    with open(path) as f:
        doc = yaml.safe_load(f)
    params = doc['/**']['ros__parameters']
    scales = params['scales']
    away = scales.pop('away')
    scales['names'] = ['home', 'laptop', 'server']
    scales['laptop'] = dict(away, cores=4, clock_ghz=2.0, gain=3.0)
    scales['server'] = dict(away, cores=8, clock_ghz=3.0, gain=6.0)
    net = params['links'].pop('net')
    params['links'] = {'names': ['wired', 'wifi', 'backhaul'],
                       'wired': dict(net, ends=['home', 'laptop']),
                       'wifi': dict(net, ends=['home', 'server']),
                       'backhaul': dict(net, ends=['laptop', 'server'])}
    with open(path, 'w') as f:
        yaml.safe_dump(doc, f)
    return path


def only_on(seen, scale, node='worker', gone=()):
    """``node`` runs on ``scale`` and is stopped on every other scale but those ``gone``."""
    return runs(seen, scale, node) and all(
        ha.released(seen, s, node) for s in ('home', 'laptop', 'server') if s != scale
        and s not in gone)


@pytest.mark.timeout(240)
def test_a_lost_server_hands_its_node_to_the_laptop_and_gets_it_back(tmp_path, ros_env,
                                                                     listener):
    ex, seen = listener
    path = three_scales(tmp_path, f'/three_{os.getpid()}')
    procs = []
    try:
        agents = {s: ha.start(procs, tmp_path, ros_env, path, f'agent_{s}', '-p', f'scale:={s}')
                  for s in ('home', 'laptop', 'server')}
        ha.start(procs, tmp_path, ros_env, path, 'decider')
        spin_until(ex, lambda: only_on(seen, 'server'), 90.0, 'the worker on the server only',
                   procs)
        # Every link is watched: the master's two, and the backhaul by the laptop (the first
        # of its ends in scales.names), whose agent beats the server's warden.
        spin_until(ex, lambda: {(m.master, m.remote) for _, m in seen['links'] if m.up} >= {
            ('home', 'laptop'), ('home', 'server'), ('laptop', 'server')}, 15.0,
            'each link reported up by its watcher', procs)
        fenced = seen['states']['server'].nodes['worker'].pid
        fenced_start = procs_of.start_ticks(fenced)
        agents['server'].proc.kill()                  # SIGKILL: its warden fences the worker
        spin_until(ex, lambda: only_on(seen, 'laptop', gone=('server',)), 30.0,
                   'the worker on the laptop only', procs)
        # Fenced: the process itself, not only the reports (two copies would serve).
        assert fenced_start is not None and not procs_of.alive(fenced, fenced_start)
        moved = [e for e in seen['events'] if e.node == 'worker']
        assert [(e.kind, e.from_scale, e.to_scale) for e in moved] == [
            ('migrate', 'home', 'server'), ('relocate', 'server', 'laptop')], moved
        assert 'lost' in moved[-1].reason

        ha.start(procs, tmp_path, ros_env, path, 'agent_server_again', '-p', 'scale:=server')
        spin_until(ex, lambda: only_on(seen, 'server'), 60.0, 'the worker back on the server',
                   procs)
        back = [e for e in seen['events'] if e.node == 'worker'][len(moved):]
        assert [(e.kind, e.from_scale, e.to_scale) for e in back] == [
            ('rebalance', 'laptop', 'server')], back
        assert 'the cost function gains' in back[0].reason
        # Not before T after the worker left the server (the decider's clock).
        assert back[0].stamp - moved[-1].stamp >= T_S
    finally:
        for name, pr in reversed(procs):
            pr.stop()
        ha.stop_wardens(tmp_path)
