"""The ICAR 2015 cost function: Perf_map (Eq. 1) and its integral over a run (Eq. 2)."""

import math
from typing import Mapping, Optional, Tuple

from ..model.types import Deployment


def perf_map(deployment: Deployment, running: Mapping[str, str],
             cpu_by_node: Optional[Mapping[str, float]] = None) -> float:
    """Eq. 1: the sum over running nodes of CPU usage times the gain alpha of its scale.

    CPU is the measured usage when ``cpu_by_node`` has the node, else its nominal ``cpu``
    (reference-core percent). Names the deployment does not know are ignored.
    """
    gains = {s.name: deployment.worth(s.name) for s in deployment.scales}
    nominal = {n.name: n.cpu for n in deployment.nodes}
    total = 0.0
    for node, scale in running.items():
        if node not in nominal or scale not in gains:
            continue
        cpu = nominal[node]
        if cpu_by_node is not None and node in cpu_by_node:
            measured = float(cpu_by_node[node])
            if math.isfinite(measured) and measured >= 0:
                cpu = measured
        total += cpu * gains[scale]
    return total


class CostIntegrator:
    """Eq. 2 over time: each mapping's Perf_map times the time it was held, summed.

    ``update(now, running)`` closes the interval since the previous update with the Perf_map
    that held during it (a left Riemann sum: a mapping counts from when it was observed), then
    returns the current Perf_map and the integral so far. Time never runs backwards here: an
    earlier ``now`` adds nothing.
    """

    def __init__(self, deployment: Deployment):
        self.deployment = deployment
        self.integral = 0.0
        self.current = 0.0
        self.started: Optional[float] = None
        self.last: Optional[float] = None

    @property
    def elapsed_s(self) -> float:
        if self.started is None or self.last is None:
            return 0.0
        return self.last - self.started

    @property
    def mean(self) -> float:
        """The time-averaged Perf_map so far (the current one before any time has passed)."""
        elapsed = self.elapsed_s
        return self.integral / elapsed if elapsed > 0 else self.current

    def update(self, now: float, running: Mapping[str, str],
               cpu_by_node: Optional[Mapping[str, float]] = None) -> Tuple[float, float]:
        if self.started is None or self.last is None:
            self.started = self.last = now
        elif now > self.last:
            self.integral += self.current * (now - self.last)
            self.last = now
        self.current = perf_map(self.deployment, running, cpu_by_node)
        return self.current, self.integral
