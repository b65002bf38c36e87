"""The nodes of a lost scale go where a live agent can run them."""

from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from ..filters import Candidate, Snapshot, cpu_headroom, reachable
from ..observations import RELOCATE, Decision
from ..scores import by_worth
from .next_best import next_best
from .state import Step


def relocate_lost(step: Step, snap: Snapshot, already: Sequence[Decision]) -> List[Decision]:
    """Nodes placed on a lost remote scale go where a live agent can run them (the master
    first); the master's own nodes stay (its agent is silent: the layout is kept). A node no
    scale may take is reported in ``step.unplaceable`` with the reason."""
    d, obs = step.deployment, step.obs
    lost = set(obs.lost_scales) & set(d.scale_names)
    if not lost:
        return []
    out: List[Decision] = []
    moved = {x.node for x in already}
    extra_cpu: Dict[str, float] = {}
    placed = dict(step.running)
    for x in already:
        placed[x.node] = x.to_scale
    for scale in sorted((lost & set(obs.fencing)) - {step.master}):
        step.notes.append(f'the nodes of {scale} stay placed there: its agent is silent but '
                          'its warden says they may still run (the agent restarts, or is gone '
                          'and they are not stopped yet): never two copies serving')
    for node, scale in list(step.memory.desired.items()):
        if scale not in lost or scale == step.master or node in moved \
                or scale in obs.fencing:
            continue
        target, why_not = relocation_target(step, snap, placed, node, scale, extra_cpu)
        if target is None:
            step.unplaceable[node] = why_not
            continue
        placed[node] = target
        extra_cpu[target] = extra_cpu.get(target, 0.0) + d.node(node).cpu
        out.append(Decision(RELOCATE, node, scale, target,
                            f'{lost_reason(step, snap, scale)}; {node} placed on {target}'))
    return out


def lost_reason(step: Step, snap: Snapshot, scale: str) -> str:
    """Why ``scale`` is lost, telling a silent agent behind a live link from a cut link."""
    silent = step.obs.silent_agents.get(scale)
    text = (f'scale {scale} lost: its agent has been silent'
            + ('' if silent is None else f' for {silent:.1f} s')
            + f' (> agent_timeout_s {step.settings.agent_timeout_s:g} s)')
    link = step.deployment.link_between(step.master, scale)
    if link is None:
        return text
    load = snap.report.links.get(link.name)
    if load is None:
        return text
    if not load.up:
        return (f'{text}, and {load.reason or f"link {link.name} down"}: a cut link and a '
                f'dead agent look alike from {step.master}')
    if load.observed:
        return (f'{text} while link {link.name} is up: the agent, not the link, is gone, '
                f'and its nodes may be gone with it')
    return text


def relocation_target(step: Step, snap: Snapshot, placed: Mapping[str, str], node: str,
                      lost: str, extra_cpu: Mapping[str, float]) -> Tuple[Optional[str], str]:
    """(scale, '') where a node of a lost scale goes, or (None, why no scale may host it):
    the next-best scale (``next_best``), else the master, else the most powerful reachable
    scale with CPU to spare (a node the master may not run)."""
    d, master = step.deployment, step.master
    allowed = d.allowed_scales(node)
    usable, refused = [], []
    for scale in allowed:
        verdict = reachable(snap, scale)
        if verdict.passed:
            usable.append(scale)
        else:
            refused.append(verdict.reason)          # each reason names its scale
    if not usable:
        return None, (f'allowed scales {", ".join(allowed)} have no live agent or are '
                      f'unreachable ({"; ".join(refused)})')
    target, _ = next_best(step, snap, placed, node, lost, extra_cpu)
    if target != master:
        return target, ''
    if master in usable:
        return master, ''
    cpu = d.node(node).cpu
    for scale in by_worth(d, usable):
        room = cpu_headroom(snap, Candidate((node,), scale, cpu, placed,
                                            extra_cpu.get(scale, 0.0), urgent=True))
        if room.passed:
            return scale, ''
    return by_worth(d, usable)[0], ''
