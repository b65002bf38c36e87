"""The placement scores: how the migration policy ranks the scales and units the filters pass.

Pure functions of the deployment (and the CPU a unit uses): the scale worth most first,
the most CPU-intensive unit first, and the gain of the cost function (ICAR 2015 Eq. 1) that a
rebalance must reach.
"""

from typing import List, Sequence, Tuple

from ..model.types import Deployment


def by_worth(deployment: Deployment, names: Sequence[str]) -> List[str]:
    """``names`` from the scale worth most (Deployment.worth: its gain, else its power), then
    the most powerful, then in deployment order."""
    order = {s.name: i for i, s in enumerate(deployment.scales)}
    return sorted(names, key=lambda n: (-deployment.worth(n), -deployment.scale(n).power,
                                        order[n]))


def by_cpu(deployment: Deployment, units: Sequence[Tuple[Tuple[str, ...], float]]
           ) -> List[Tuple[Tuple[str, ...], float]]:
    """(unit, CPU) pairs from the most CPU-intensive (ties: deployment order of the first
    node): Algorithm 1 moves the largest first."""
    order = {n: i for i, n in enumerate(deployment.node_names)}
    return sorted(units, key=lambda u: (-u[1], order[u[0][0]]))


def rebalance_gain(deployment: Deployment, cpu: float, here: str, there: str) -> float:
    """What the cost function gains when a unit of ``cpu`` moves from ``here`` to ``there``:
    CPU x (worth there - worth here)."""
    return cpu * (deployment.worth(there) - deployment.worth(here))


__all__ = ['by_cpu', 'by_worth', 'rebalance_gain']
