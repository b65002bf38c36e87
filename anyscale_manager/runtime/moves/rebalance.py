"""Rebalancing (beyond the paper): a node on a remote scale moves to a more powerful one when
the cost function gains enough."""

import math
from typing import List

from ..constraints import node_cpu
from ..filters import Candidate, Snapshot, can_host, handover, hysteresis
from ..observations import REBALANCE, Decision
from ..scores import by_worth, rebalance_gain
from .state import Step
from .units import remote_units, unit_text


def rebalance(step: Step, snap: Snapshot) -> List[Decision]:
    """A node (or coresidence group) on a remote scale moves to a more powerful remote scale
    that can host it, when the cost function gains at least ``rebalance_min_gain`` (CPU x
    (alpha there - alpha here)), not before T has passed since it last moved, nor to a scale
    it left within T. One move per turn: the largest gain; each move only raises the cost
    function, so nothing ping-pongs without a violation in between (and a violation's move
    back holds the scale for T)."""
    s, d, now, memory = step.settings, step.deployment, step.now, step.memory
    if not s.rebalance:
        return []
    remotes = by_worth(d, [x.name for x in d.remote_scales])
    best = held = None
    for unit, here in remote_units(step):
        since = max(memory.last_move.get(n, -math.inf) for n in unit)
        if now - since < s.hysteresis_s:
            continue
        cpu = sum(node_cpu(d, s, step.obs, n) for n in unit)
        without = {n: x for n, x in step.running.items() if n not in unit}
        for scale in remotes:
            gain = rebalance_gain(d, cpu, here, scale)
            if scale == here or gain < s.rebalance_min_gain or gain <= 0:
                continue
            verdict = hysteresis(memory.last_back, s.hysteresis_s, unit, scale, now)
            if verdict.passed:
                verdict = handover(snap, here, scale)
            if verdict.passed:
                verdict = can_host(snap, Candidate(unit, scale, cpu, without))
            if not verdict.passed:
                if held is None or gain > held[0]:
                    held = (gain, unit, here, scale, verdict)
                continue
            if best is None or gain > best[0]:
                best = (gain, unit, here, scale, cpu, verdict.reason)
            break                  # the most powerful scale that fits, for this unit
    if best is None:
        if held is not None:
            # Said by the check's name, not its figures: the note is an event once per text.
            _, unit, here, scale, verdict = held
            step.notes.append(f'{unit_text(unit)} stays on {here}: moving it to {scale} would '
                              f'gain at least rebalance_min_gain, held by the '
                              f'{verdict.code.value} check')
        return []
    gain, unit, here, scale, cpu, why = best
    reason = (f'{unit_text(unit)}: CPU {cpu:.0f} on {here} (worth '
              f'{d.worth(here):g}) to {scale} (worth {d.worth(scale):g}): the cost '
              f'function gains {gain:.0f} >= rebalance_min_gain {s.rebalance_min_gain:g}; '
              f'{why}')
    return [Decision(REBALANCE, n, here, scale, reason) for n in unit]
