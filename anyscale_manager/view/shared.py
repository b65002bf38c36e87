"""The status view's lines of a shared scale (scales.<s>.shared): its host's capacity, the
claims on it by deployment, and this deployment's nodes it refuses or asks to leave, as the
scale's agent last reported them (agent/claims.py)."""

from typing import Dict, List, Mapping, Tuple

from .. import protocol as p


def share_lines(agents: Mapping[str, Tuple[p.AgentState, float]],
                scale_names: Tuple[str, ...], deployment: str) -> List[str]:
    """One block per shared scale heard: 'SHARED <scale>' and a line per deployment."""
    out: List[str] = []
    for scale in scale_names:
        report = agents.get(scale)
        share = report[0].share if report is not None else None
        if share is None:
            continue
        memory = f', {share.memory_mb:g} MiB' if share.memory_mb else ''
        out.append(f'SHARED {scale}: host capacity {share.capacity_cpu:g} CPU{memory}')
        mine = {n: r for n, r in report[0].nodes.items()}
        by_deployment: Dict[str, List[str]] = {}
        for key, c in sorted(share.claims.items()):
            who, _, node = key.partition('/')
            what = f'{c.cpu:g} CPU' if c.active else 'standby'
            by_deployment.setdefault(who, []).append(
                f'{node} {what}' + (f' {c.memory_mb:g} MiB' if c.memory_mb else '')
                + f' (priority {c.priority})')
        own = [f'{n} {r.state}' for n, r in sorted(mine.items())
               if r.state in p.LIVE_STATES or r.state == p.ProcState.STANDBY]
        rows = [(deployment + ' (this one)', own or ['nothing'])]
        rows += sorted(by_deployment.items())
        for who, items in rows:
            out.append(f'  {who:<24} {", ".join(items)}')
        for node, why in sorted(share.refused.items()):
            out.append(f'  refused here: {node}: {why}')
        for node, why in sorted(share.waiting.items()):
            out.append(f'  waiting here: {node}: {why}')
        for node, by in sorted(share.asked.items()):
            out.append(f'  asked to leave: {node}, by {by}')
    return out
