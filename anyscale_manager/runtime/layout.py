"""The first layout: everything on the master, a planner's answer, or an explicit map.

Then adoption: a decider that starts while nodes already run keeps them where they are when that
is allowed, instead of restarting them where the plan would put them.
"""

from dataclasses import replace
from typing import TYPE_CHECKING, Dict, List, Mapping, Optional, Tuple

from ..model.placement import allowed, apart
from ..model.types import DeciderSettings, Deployment

if TYPE_CHECKING:
    from ..planning import Placement

PROBLEMS = {'problem1': 1, 'problem2': 2}


class LayoutError(ValueError):
    """A first layout that cannot be built; the message says why."""


def default_scale(deployment: Deployment, node: str) -> str:
    """Where a node goes when nothing else says: the master when allowed, else its first scale."""
    allowed = deployment.allowed_scales(node)
    master = deployment.master.name
    if master in allowed or not allowed:
        return master
    return allowed[0]


def managed_nodes(deployment: Deployment) -> Tuple[str, ...]:
    return tuple(n.name for n in deployment.nodes if n.managed)


def master_layout(deployment: Deployment) -> Dict[str, str]:
    """The paper's default: every managed node on the master (or its only allowed scale)."""
    return {n: default_scale(deployment, n) for n in managed_nodes(deployment)}


def planned_layout(deployment: Deployment, problem: int,
                   settings: Optional[DeciderSettings] = None
                   ) -> Tuple[Dict[str, str], Dict[str, 'Placement']]:
    """Problem 1 or 2 of the IROS 2016 paper, from the planning package: layout, placements.

    The planner fills each scale only to the CPU the decider lets nodes use there, by the
    decider's ``settings`` (default: the deployment's): a first layout the CPU rule would judge
    over capacity at once would be moved as soon as it started.
    """
    if settings is not None and settings != deployment.decider:
        deployment = replace(deployment, decider=settings)
    # Imported when a planner is asked for: the planners and numpy then load, a decider that
    # starts from the master layout does without them.
    try:
        from ..planning import solve
    except ImportError as e:
        raise LayoutError(f'initial_layout problem{problem}: the planner is not available '
                          f'in this install ({e})') from None
    try:
        plan = solve(deployment, problem=problem)
    except (ValueError, KeyError, RuntimeError) as e:
        raise LayoutError(f'initial_layout problem{problem}: the planner failed: {e}') from None
    if not plan.feasible:
        why = '; '.join(plan.violations) or 'no reason'
        raise LayoutError(f'initial_layout problem{problem}: no feasible plan ({why})')
    out = master_layout(deployment)
    for node, placement in plan.layout.items():
        if node in out:
            out[node] = placement.scale
    return out, dict(plan.layout)


def initial_layout(deployment: Deployment,
                   settings: Optional[DeciderSettings] = None) -> Dict[str, str]:
    """The layout the decider starts from, per ``decider.initial_layout``; validated."""
    return initial_plan(deployment, settings)[0]


def initial_plan(deployment: Deployment, settings: Optional[DeciderSettings] = None
                 ) -> Tuple[Dict[str, str], Optional[Dict[str, 'Placement']]]:
    """The first layout and, when a planner made it, its placements (for the plan check)."""
    settings = settings or deployment.decider
    mode = settings.initial_layout
    placements = None
    if mode == 'master':
        layout = master_layout(deployment)
    elif mode in PROBLEMS:
        layout, placements = planned_layout(deployment, PROBLEMS[mode], settings)
    elif mode == 'explicit':
        if not settings.layout:
            raise LayoutError('initial_layout explicit: decider.layout is empty')
        layout = master_layout(deployment)
        for node, scale in settings.layout.items():
            if node not in layout:
                raise LayoutError(f'decider.layout.{node}: not a managed node of deployment '
                                  f'{deployment.name!r}')
            layout[node] = scale
    else:
        raise LayoutError(f'decider.initial_layout: unknown mode {mode!r}')
    problems = check_layout(deployment, layout)
    if problems:
        raise LayoutError(f'initial_layout {mode}: ' + '; '.join(problems))
    return layout, placements


def check_layout(deployment: Deployment, layout: Mapping[str, str]) -> List[str]:
    """Every way ``layout`` breaks residence, criticality or coresidence; empty when valid."""
    problems = []
    for node, scale in layout.items():
        if node not in deployment.node_names:
            problems.append(f'unknown node {node!r}')
            continue
        if scale not in deployment.scale_names:
            problems.append(f'{node}: unknown scale {scale!r}')
            continue
        if not allowed(deployment, node, scale).passed:
            problems.append(f'{node} may not run on {scale} (allowed: '
                            f'{", ".join(deployment.allowed_scales(node))})')
        for other in apart(deployment, node, scale, layout):
            problems.append(f'{node} and {other} must share a scale '
                            f'({scale} vs {layout[other]})')
    return problems


def adopt(deployment: Deployment, planned: Mapping[str, str],
          running: Mapping[str, str]) -> Tuple[Dict[str, str], Tuple[str, ...]]:
    """The first layout to publish: what already runs, where allowed; the plan elsewhere.

    Returns the layout and one note per node whose place differs from the plan (adopted) or
    that runs where it may not (moved to the plan).
    """
    layout = dict(planned)
    notes = []
    done = set()
    for node in list(layout):
        if node in done:
            continue
        group = [m for m in deployment.coresidence_group(node) if m in layout]
        done.update(group)
        wheres = {running[m] for m in group if m in running}
        if not wheres or all(running.get(m, layout[m]) == layout[m] for m in group):
            continue
        where = next(iter(wheres))
        if len(wheres) == 1 and allowed(deployment, node, where).passed:
            for m in group:
                if layout[m] != where:
                    notes.append(f'adopted {m} where it runs ({where}; planned {layout[m]})')
                    layout[m] = where
            continue
        for m in group:
            if m in running and running[m] != layout[m]:
                notes.append(f'{m} runs on {running[m]}, where it may not stay; '
                             f'placed on {layout[m]}')
    return layout, tuple(notes)
