"""Failover: a serving copy that crashed hands over to a standby copy on another scale."""

import math
from typing import List, Optional

from ...model.placement import Verdict
from ...model.types import frozen_map
from ..constraints import evaluate, node_cpu
from ..filters import Candidate, Snapshot, agent_at, can_host
from ..observations import FAILOVER, Decision
from ..scores import by_worth
from .state import Step


def failover(step: Step) -> List[Decision]:
    """A serving copy that crashed hands over to a standby copy on another scale.

    The node's copy on the scale the layout places it stopped against its will (its agent
    reported it exited or restarted, ``CopyObs.crashed_at``) and the node serves nowhere
    else: the first inactive standby copy, on the most powerful scale that can host it now
    (live agent, link up, CPU, bandwidth, residence; the master only needs a live agent),
    is activated there by a new layout;
    the crashed scale's agent restarts its own copy as a standby. With no such copy the
    node is restarted in place by its agent (nothing to decide). The hysteresis T bars
    voluntary moves, not the rescue of a dead copy: a ready standby takes over whatever T
    says, one whose copy has not crashed within T first. A node whose copies crashed on
    every scale it may serve on within T crashes wherever it runs: that is said, with its
    crashes, beside the failover.
    """
    d, s, obs, memory, notes = step.deployment, step.settings, step.obs, step.memory, step.notes
    now, running = step.now, step.running
    out: List[Decision] = []
    snap: Optional[Snapshot] = None
    for node, scale in sorted(memory.desired.items()):
        copies = obs.copies.get(node) or frozen_map()
        here = copies.get(scale)
        if here is None or here.crashed_at is None:
            continue
        if memory.crashed.get((node, scale), -math.inf) >= here.crashed_at:
            continue                                   # this crash was answered
        if running.get(node) not in (None, scale) or node in memory.pending:
            continue
        memory.crashed[(node, scale)] = here.crashed_at
        standby = [x for x, c in copies.items() if x != scale and c.state == 'standby']
        if not standby:
            if d.standby_scales(node):
                notes.append(f'{node} crashed on {scale} ({here.exit_reason}); no standby '
                             f'copy ready elsewhere: restarted in place')
            continue
        if snap is None:
            snap = step.snapshot(evaluate(d, s, obs, step.grace_until, since=memory.started))
        cpu = node_cpu(d, s, obs, node)
        target, refused = None, []
        recent = {x: now - memory.crashed[(node, x)] for x in copies
                  if (node, x) in memory.crashed
                  and now - memory.crashed[(node, x)] < s.hysteresis_s}
        # Copies that have not crashed within T first, then by power (a stable sort).
        for x in sorted(by_worth(d, standby), key=lambda x: x in recent):
            verdict = copy_may_serve(step, snap, node, cpu, x)
            if verdict.failed:
                refused.append(f'{x}: {verdict.reason}')
                continue
            target = x
            break
        if target is None:
            notes.append(f'{node} crashed on {scale} ({here.exit_reason}); restarted in '
                         f'place: no standby copy may take over ({"; ".join(refused)})')
            continue
        out.append(Decision(FAILOVER, node, scale, target,
                            f'{node} crashed on {scale} ({here.exit_reason}); its standby '
                            f'copy on {target} takes over'))
        if target in recent:
            crashes = ', '.join(f'{x} {age:.1f} s ago' for x, age in sorted(recent.items()))
            notes.append(f'{node} crashes wherever it runs (within T = '
                         f'{s.hysteresis_s:g} s: {crashes}): failed over to '
                         f'{target} all the same; each agent restarts its copy with the '
                         'crash-loop backoff (agent.restart_backoff_s)')
    return out


def copy_may_serve(step: Step, snap: Snapshot, node: str, cpu: float, scale: str) -> Verdict:
    """Whether a standby copy on ``scale`` may serve now: it does unless a filter fails
    (``failed``). What cannot be told yet (a link or CPU not observed since the start) does
    not hold a failover back: the copy is there, and the alternative is a cold restart.

    The master takes a node back whatever its CPU reads, as a move back does when a
    constraint breaks (Algorithm 1): it is every node's home, and refusing leaves the node
    to a cold restart in place, silent meanwhile, then sent home anyway once its
    connections have been below freq_min past Δ. (A CPU-bound node's CPU measured on a
    stronger scale is what it got there, not what it needs; the master, run near its quota
    by the decider and its agent, read as full and sent such crashes to in-place restarts:
    ``/amcl_pose`` below 2 Hz for 4.9 s in a crash loop of AMCL on the laptop.) Once it is
    home, the migration rule sends it out again after T like any other."""
    if scale == step.master:
        return agent_at(step.obs, step.settings, scale)
    without = {n: x for n, x in step.running.items() if n != node}
    return can_host(snap, Candidate((node,), scale, cpu, without, urgent=True))
