"""A shared scale's answers (scales.<s>.shared, agent/ledger.py): a move there that its host
refuses for want of room is undone at once, and a node asked to leave by a claim of a higher
priority goes home, so that the capacity can be handed over. Both are ``yield`` decisions: no
hysteresis holds the node back from that host afterwards (room decides, through the decider's
shared_room filter)."""

from typing import List

from ..observations import YIELD, Decision
from .state import Step


def shared_answers(step: Step) -> List[Decision]:
    """Undo the pending moves a shared host refused (the copy they were leaving still serves:
    the node goes back there); bring home the nodes a shared host asks to leave."""
    memory, running, master = step.memory, step.running, step.master
    out: List[Decision] = []
    for node, (scale, _asked) in list(memory.pending.items()):
        share = step.obs.shares.get(scale)
        why = None if share is None else share.refused.get(node)
        if why is None:
            continue
        del memory.pending[node]
        home = running.get(node, master)
        if home == scale:
            home = master
        out.append(Decision(YIELD, node, scale, home,
                            f'{scale} has no room for {node}: {why}'))
    moving = {d.node for d in out} | set(memory.pending)
    for scale, share in sorted(step.obs.shares.items()):
        for node, by in sorted(share.asked.items()):
            if running.get(node) != scale or node in moving or scale == master:
                continue
            out.append(Decision(YIELD, node, scale, master,
                                f'{by} of a higher priority asks {scale} for the room '
                                f'{node} holds there'))
    return out
