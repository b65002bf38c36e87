"""Which nodes move together, and from where: coresidence groups of migratable nodes settled
where the layout places them."""

from typing import List, Set, Tuple

from ..constraints import node_cpu
from ..scores import by_cpu
from .state import Step

Unit = Tuple[str, ...]


def settled_units(step: Step) -> List[Tuple[Unit, str]]:
    """Each coresidence group of migratable nodes that all run where the layout places them,
    on one scale, with that scale (in deployment order)."""
    d, running, desired = step.deployment, step.running, step.memory.desired
    migratable = set(d.migratable_nodes)
    seen: Set[str] = set()
    units: List[Tuple[Unit, str]] = []
    for node in d.migratable_nodes:
        if node in seen:
            continue
        group = d.coresidence_group(node)
        seen.update(group)
        here = running.get(node)
        if here is not None and all(m in migratable and running.get(m) == here
                                    and desired.get(m) == here for m in group):
            units.append((tuple(group), here))
    return units


def remote_units(step: Step) -> List[Tuple[Unit, str]]:
    """Migratable nodes settled on a remote scale, with their coresidents, and the scale."""
    return [(unit, here) for unit, here in settled_units(step) if here != step.master]


def candidate_units(step: Step) -> List[Tuple[Unit, float]]:
    """Migratable nodes on the master with their coresidents, by CPU, largest first."""
    d, s, obs = step.deployment, step.settings, step.obs
    units = [(unit, sum(node_cpu(d, s, obs, m) for m in unit))
             for unit, here in settled_units(step) if here == step.master]
    return by_cpu(d, units)


def unit_text(unit: Unit) -> str:
    """'amcl', or 'amcl (with map_server)' for a coresidence group."""
    return unit[0] if len(unit) == 1 else f'{unit[0]} (with {", ".join(unit[1:])})'
