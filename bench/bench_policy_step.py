#!/usr/bin/env python3
"""Decider figures: the cost of one step of the migration policy (constraints + Algorithm 1)
and of the decider's whole turn around it.

    python bench/bench_policy_step.py [DEPLOYMENT.yaml ...] [--steps 2000]

Pure core, no ROS: each step builds a fresh observation snapshot (every scale, link and
connection reported fresh at its nominal rate), runs ``MigrationPolicy.step`` and applies its
decisions at once; then the same with ``DeciderTurn.turn`` (the policy plus the events, the
liveness watch, the cost function and the plan check). Prints the mean wall time per step and
the moves made.
"""

import argparse
import os
import time

from anyscale_manager.model.loader import load_deployment
from anyscale_manager.runtime.constraints import link_observation_key
from anyscale_manager.runtime.layout import master_layout
from anyscale_manager.runtime.observations import (ConnectionObs, LinkObs, Observations,
                                                   ScaleObs)
from anyscale_manager.runtime.policy import MigrationPolicy
from anyscale_manager.runtime.turn import DeciderTurn

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULTS = [os.path.join(HERE, '..', 'config', 'icar2015_testbed.yaml'),
            os.path.join(HERE, '..', 'config', 'iros2016', 'instance_10.yaml')]


def snapshot(d, running, now: float) -> Observations:
    return Observations(
        now=now, running=dict(running),
        scales={s: ScaleObs(cpu_total=10.0, stamp=now) for s in d.scale_names},
        links={**{s.name: LinkObs(up=True, stamp=now) for s in d.remote_scales},
               **{link_observation_key(d, link): LinkObs(up=True, stamp=now)
                  for link in d.remote_links}},
        connections={c.name: ConnectionObs(rate_hz=c.freq_opt_hz or c.freq_min_hz or 1.0,
                                           stamp=now) for c in d.connections})


def measure(path: str, steps: int) -> str:
    d = load_deployment(path)
    period = d.decider.period_s
    lines = []
    for whole_turn in (False, True):
        policy = MigrationPolicy(d)
        turn = DeciderTurn(d, d.decider, 0.0, policy)
        running = master_layout(d)
        spent = 0.0
        for i in range(steps):
            now = i * period
            obs = snapshot(d, running, now)
            t0 = time.perf_counter()
            decisions = turn.turn(now, obs).decisions if whole_turn else policy.step(obs)
            spent += time.perf_counter() - t0
            for dec in decisions:
                running[dec.node] = dec.to_scale
        per = f'{1e3 * spent / steps:.3f} ms per {"turn" if whole_turn else "step"} over ' \
            f'{steps} {"turns" if whole_turn else "steps"}, {len(policy.history)} moves'
        lines.append(f'{d.name}: the whole turn: {per}' if whole_turn else
                     f'{d.name}: {len(d.nodes)} nodes, {len(d.connections)} connections, '
                     f'{len(d.migratable_nodes)} migratable: {per}')
    return '\n'.join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('deployments', nargs='*', default=DEFAULTS)
    parser.add_argument('--steps', type=int, default=2000)
    args = parser.parse_args()
    for path in args.deployments:
        print(measure(path, args.steps))


if __name__ == '__main__':
    main()
