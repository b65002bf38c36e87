"""Link coverage along the path: where each remote scale's link is up, and its goodput there."""

from dataclasses import dataclass
from typing import Dict, Sequence, Tuple

import numpy as np

from .model import SHARED, PathModel


@dataclass(frozen=True)
class LinkSchedule:
    """A link's coverage along one lap: outages as [start_m, end_m) and the goodput elsewhere."""

    length_m: float
    outages: Tuple[Tuple[float, float], ...]
    peak_kbps: float
    ramp_m: float = 0.0

    def up(self, s_m: float) -> bool:
        return not any(a <= s_m < b for a, b in self.outages)

    def available_kbps(self, s_m: float) -> float:
        """Goodput at ``s_m``: 0 in a hole, ramping up to the peak away from a hole's edges."""
        nearest = float('inf')
        for a, b in self.outages:
            if a <= s_m < b:
                return 0.0
            nearest = min(nearest, abs(s_m - a), abs(s_m - b))
        if self.ramp_m <= 0 or nearest >= self.ramp_m:
            return self.peak_kbps
        return self.peak_kbps * nearest / self.ramp_m

    @property
    def availability(self) -> float:
        """Share of the lap where the link is up."""
        down = sum(b - a for a, b in self.outages)
        return 1.0 - down / self.length_m

    def next_change_m(self, s_m: float) -> float:
        """The next position after ``s_m`` where the link goes up or down (inf: none)."""
        edges = [e for a, b in self.outages for e in (a, b) if e > s_m]
        return min(edges) if edges else float('inf')


def always_up(path: PathModel, peak_kbps: float) -> LinkSchedule:
    return LinkSchedule(path.length_m, (), peak_kbps, path.edge_ramp_m)


def draw_schedule(rng: np.random.Generator, path: PathModel, peak_kbps: float) -> LinkSchedule:
    """A lap with availability ~ U(low, high) and a uniform number of holes at random places.

    The down share is cut into the holes and the up share into the gaps around them by uniform
    random breaks (a flat Dirichlet), so holes and gaps are exchangeable and any position along
    the lap is equally likely to be covered.
    """
    availability = rng.uniform(path.availability_low, path.availability_high)
    holes = int(rng.integers(path.outages_min, path.outages_max + 1))
    down_m = (1.0 - availability) * path.length_m
    if holes == 0 or down_m <= 0:
        return always_up(path, peak_kbps)
    hole_m = rng.dirichlet(np.ones(holes)) * down_m
    gap_m = rng.dirichlet(np.ones(holes + 1)) * (path.length_m - down_m)
    outages = []
    s = 0.0
    for i in range(holes):
        s += gap_m[i]
        outages.append((float(s), float(s + hole_m[i])))
        s += hole_m[i]
    return LinkSchedule(path.length_m, tuple(outages), peak_kbps, path.edge_ramp_m)


def draw_schedules(rng: np.random.Generator, path: PathModel, remote_scales: Sequence[str],
                   peak_kbps: Dict[str, float]) -> Dict[str, LinkSchedule]:
    """One schedule per remote scale: independent draws, or one pattern shared by all links."""
    if path.links == SHARED and remote_scales:
        first = draw_schedule(rng, path, 1.0)
        return {s: LinkSchedule(first.length_m, first.outages, peak_kbps[s], first.ramp_m)
                for s in remote_scales}
    return {s: draw_schedule(rng, path, peak_kbps[s]) for s in remote_scales}


def best_case_schedules(path: PathModel, remote_scales: Sequence[str],
                        peak_kbps: Dict[str, float]) -> Dict[str, LinkSchedule]:
    """Every link always up at its peak goodput (the paper's best case)."""
    return {s: always_up(path, peak_kbps[s]) for s in remote_scales}
