"""A starting decider moves nothing out while the graph boots (``decider.bringup_s``), on
hand-written observations of the ICAR test-bed (no ROS): every node at home, the camera not
delivering yet."""

import dataclasses

import pytest

from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (MIGRATE, ConnectionObs, LinkObs,
                                                   Observations, ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy

BOOTING = ('camera_ar', 'ar_navigation')      # the camera's images, and so AR's markers


@pytest.fixture(scope='module')
def d():
    from anyscale_manager.model.loader import load_deployment
    from conftest import TESTBED
    return load_deployment(TESTBED)


def observe(d, now, running, silent=BOOTING):
    """Every monitored connection at its freq_opt but those of ``silent`` (0 Hz, never heard
    since they are below from the start)."""
    conns = {}
    for c in d.connections:
        if not c.monitored:
            continue
        if c.name in silent:
            conns[c.name] = ConnectionObs(rate_hz=0.0, stamp=now, below_for_s=now, below=True)
        else:
            conns[c.name] = ConnectionObs(rate_hz=c.freq_opt_hz, stamp=now)
    return Observations(now=now, running=dict(running),
                        scales={s: ScaleObs(cpu_total=10.0, stamp=now) for s in d.scale_names},
                        links={'laptop': LinkObs(up=True, stamp=now, available_kbps=40000.0)},
                        connections=conns)


def run(policy, d, running, start, end, silent=BOOTING, period_s=0.5):
    """Steps from ``start`` to ``end``; the moves out, with when."""
    out, t = [], start
    while t <= end:
        for x in policy.step(observe(d, t, running, silent)):
            if x.kind == MIGRATE:
                out.append((t, x.node))
                running[x.node] = x.to_scale
        t += period_s
    return out


def test_nothing_moves_out_until_every_connection_was_heard(d):
    running = dict(master_layout(d))
    policy = MigrationPolicy(d)
    assert run(policy, d, running, 0.0, 10.0) == []
    assert any('no move out while the graph comes up: camera_ar, ar_navigation not heard yet'
               in n for n in policy.notes), policy.notes
    # Once the camera delivers, the graph is up: Algorithm 1 moves the largest node out.
    moved = run(policy, d, running, 10.5, 12.0, silent=())
    assert moved and moved[0][0] == 10.5, moved


def test_a_connection_never_heard_holds_the_moves_out_for_bringup_s_at_most(d):
    running = dict(master_layout(d))
    policy = MigrationPolicy(d)
    moved = run(policy, d, running, 0.0, d.decider.bringup_s + 2.0)
    assert moved and moved[0][0] >= d.decider.bringup_s, moved
    assert moved[0][0] < d.decider.bringup_s + 1.0, moved


def test_without_bringup_the_first_move_out_comes_at_once(d):
    """The rule is what holds the moves: with bringup_s 0 the same boot moves at once."""
    running = dict(master_layout(d))
    settings = dataclasses.replace(d.decider, bringup_s=0.0)
    moved = run(MigrationPolicy(d, settings), d, running, 0.0, 2.0)
    assert moved and moved[0][0] <= 1.0, moved
