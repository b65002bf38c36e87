"""Moves asked for and not yet running: settled when they run, undone when the agents do not
apply them in time."""

from typing import List

from ...model.capacity import claim_lease_s
from ...model.types import DeciderSettings, Deployment
from ..observations import MIGRATE_BACK, Decision
from .state import Step


def pending_timeout_s(deployment: Deployment, settings: DeciderSettings) -> float:
    """How long the agents get to apply a move before it is undone."""
    return deployment.agent.readiness_timeout_s + settings.agent_timeout_s


def _preemption_s(step: Step, node: str, scale: str) -> float:
    """The longer a move may take while a shared host has asked lower-priority claims to make
    room for it: their robots take their nodes home first, and a dead one's claim ends with its
    lease (model/capacity.py claim_lease_s)."""
    share = step.obs.shares.get(scale)
    if share is None or node not in share.waiting:
        return 0.0
    return claim_lease_s(step.deployment)


def settle_pending(step: Step) -> List[Decision]:
    """A pending node running where it was sent is settled (the scale's next CPU reading can
    include its load). One still not there past ``pending_timeout_s`` is undone: a move out
    comes back to the master (unless the master's agent is silent: then it waits), any other
    is dropped with a note."""
    memory, running, now, master = step.memory, step.running, step.now, step.master
    timeout = pending_timeout_s(step.deployment, step.settings)
    out = []
    for node, (scale, asked) in list(memory.pending.items()):
        if running.get(node) == scale:
            del memory.pending[node]
            # From now on a CPU reading of that scale can include the node's load.
            memory.arrived[scale] = (now, node)
        elif now - asked > timeout + _preemption_s(step, node, scale):
            if scale != master and memory.in_migrated(node) and step.hold_for_master(node):
                continue
            del memory.pending[node]
            where = running.get(node, 'nowhere')
            if scale != master and memory.in_migrated(node):
                out.append(Decision(
                    MIGRATE_BACK, node, scale, master,
                    f'{node} still not running on {scale} {now - asked:.1f} s after the '
                    f'move (runs {where}); undoing it'))
            else:
                step.notes.append(f'{node} not yet running on {scale} {now - asked:.1f} s '
                                  f'after it was asked (runs {where})')
    return out
