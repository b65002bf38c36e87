"""Exact small knapsacks on a CPU grid: best settings on one scale, best fill of one scale.

Both work on a grid of ``quantum`` CPU units. Option steps that are not on the grid are rounded
up, and the room rounded down, so a result always fits; on the IROS instances every share is an
integer and the grid is exact.
"""

import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .instance import Instance

MAX_GRID = 200_000


def _grid(room: float, quantum: float) -> Tuple[int, float]:
    q = quantum
    if room / q + 1 > MAX_GRID:
        q = room / (MAX_GRID - 1)
    return int(math.floor(room / q + 1e-9)) + 1, q


def _units(x: float, q: float) -> int:
    return max(0, int(math.ceil(x / q - 1e-9)))


def best_settings(inst: Instance, nodes: Sequence[int], room: float
                  ) -> Optional[Tuple[float, Dict[int, int]]]:
    """The settings of ``nodes`` (configurable, on one scale) that maximise their weighted
    performance within ``room`` CPU (the scale's capacity less its fixed nodes).

    A multiple-choice knapsack solved by dynamic programming over the CPU grid; returns
    (value, node -> option) or None when even the smallest settings do not fit.
    """
    base = sum(inst.options[n][0].cpu for n in nodes)
    spare = room - base
    if spare < -1e-6:
        return None
    if not nodes:
        return 0.0, {}
    size, q = _grid(max(spare, 0.0), inst.quantum)
    dp = np.zeros(size)
    picks: List[np.ndarray] = []
    weights: List[List[int]] = []
    for n in nodes:
        opts = inst.options[n]
        new = np.full(size, -np.inf)
        arg = np.zeros(size, dtype=np.int32)
        w_n = []
        for k, o in enumerate(opts):
            w = _units(o.cpu - opts[0].cpu, q)
            w_n.append(w)
            if w >= size:
                break
            cand = dp[:size - w] + inst.value(n, k)
            seg = new[w:]
            better = cand > seg
            seg[better] = cand[better]
            arg[w:][better] = k
        dp = new
        picks.append(arg)
        weights.append(w_n)
    c = size - 1
    value = float(dp[c])
    out: Dict[int, int] = {}
    for i in range(len(nodes) - 1, -1, -1):
        k = int(picks[i][c])
        out[nodes[i]] = k
        c -= weights[i][k]
    return value, out


def best_fill(sizes: Sequence[float], room: float, quantum: float) -> List[int]:
    """Indices of a subset of ``sizes`` with the largest total not above ``room``
    (subset sum by dynamic programming on the grid)."""
    if room <= 0 or not sizes:
        return []
    size, q = _grid(room, quantum)
    w = [_units(s, q) for s in sizes]
    reach = np.zeros(size, dtype=bool)
    reach[0] = True
    history = []
    for wi in w:
        history.append(reach.copy())
        if wi < size:
            reach[wi:] |= history[-1][:size - wi]
    best = int(np.flatnonzero(reach)[-1])
    chosen = []
    for i in range(len(w) - 1, -1, -1):
        if history[i][best]:
            continue        # reachable without item i
        chosen.append(i)
        best -= w[i]
    return sorted(chosen)
