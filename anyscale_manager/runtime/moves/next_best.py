"""The next-best scale (beyond the paper, which has one remote scale in mind): where a node that
must leave a scale goes."""

from typing import Mapping, Optional, Tuple

from ..constraints import node_cpu
from ..filters import Candidate, Snapshot, can_host, handover, hysteresis
from ..scores import by_worth
from .state import Step


def next_best(step: Step, snap: Snapshot, placed: Mapping[str, str], node: str,
              leaving: Optional[str], sent: Mapping[str, float]) -> Tuple[str, str]:
    """(scale, why) for a node that must leave ``leaving``: the remote scale worth most
    (Deployment.worth), worth more than the master, that can host it now (live agent, its
    links up and observed, CPU and bandwidth, counting what this step already sent there; not
    a scale it left within T, nor one the link from ``leaving`` to which is down), else the
    master (Algorithm 1's migrate-back). With hysteresis scope 'node' (the paper's rule as
    written) always the master."""
    d, s, master = step.deployment, step.settings, step.master
    if s.hysteresis_scope == 'node':
        return master, ''
    others = [x for x in d.allowed_scales(node)
              if x not in (leaving, master) and d.worth(x) > d.worth(master)]
    if not others:
        return master, ''
    cpu = node_cpu(d, s, step.obs, node)
    without = {n: x for n, x in placed.items() if n != node}
    refused = []
    for scale in by_worth(d, others):
        held = hysteresis(step.memory.last_back, s.hysteresis_s, (node,), scale, step.now)
        if not held.passed:
            refused.append(held.reason)
            continue
        cut = handover(snap, leaving, scale)
        if not cut.passed:
            refused.append(f'{scale}: {cut.reason}')
            continue
        verdict = can_host(snap, Candidate((node,), scale, cpu, without, sent.get(scale, 0.0),
                                           urgent=True))
        if verdict.passed:
            return scale, verdict.reason
        refused.append(f'{scale}: {verdict.reason}')
    return master, '; '.join(refused)
