"""What a fleet run measures (sim/fleet.py): per robot, per server, the ledger's decisions, and
the figures drawn from them, alone and over several runs.

- utilisation of a server: the CPU claimed on it over its capacity, time-averaged over the run;
- over-commit: the seconds during which a server's claims, or the CPU of the copies running on
  it (from the robots' worlds, whatever the ledger says), exceeded its capacity;
- refused: claim decisions answered 'does not fit'; waiting: answered 'waits for lower claims
  to leave'; preemptions: asks to leave (a robot's node on a server asked to go by a claim of
  a higher priority), each counted once;
- Δ violations: stretches of a monitored connection below its freq_min that outlast its Δ,
  as the world counts them (sim/world.py);
- fairness: Jain's index over the robots' time with a node serving on a shared server,
  (sum x)^2 / (n sum x^2): 1 when every robot had the same time, 1/n when one had it all;
- saved: the path time saved against no migration, from the distance the robot drove in the
  run (1 - v_min / v_mean, as the single-robot improvement);
- a claim decision's cost: the wall time of one ``Ledger.claim`` transaction.
"""

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Dict, Sequence, Tuple

import numpy as np

if TYPE_CHECKING:
    from .fleet import FleetSpec


def jain(values: Sequence[float]) -> float:
    """Jain's fairness index of ``values`` (1.0 when all are 0: nobody had more)."""
    x = np.asarray(values, dtype=float)
    squares = float(np.sum(x * x))
    if x.size == 0 or squares == 0:
        return 1.0
    return float(np.sum(x)) ** 2 / (x.size * squares)


def percentile_ms(seconds: Sequence[float], q: float) -> float:
    return float(np.percentile(seconds, q)) * 1000.0 if len(seconds) else 0.0


@dataclass(frozen=True)
class RobotResult:
    name: str
    priority: int
    driven_m: float
    improvement_pct: float      # path time saved against no migration
    server_time_s: float        # with a node serving on a shared server
    delta_violations: int
    migrations: int
    perf_map_mean: float


@dataclass(frozen=True)
class ServerResult:
    name: str
    capacity_cpu: float
    utilisation: float          # claimed CPU over capacity, time-averaged
    peak_claimed_cpu: float
    peak_running_cpu: float
    overcommit_s: float


@dataclass(frozen=True)
class FleetRun:
    spec: 'FleetSpec'
    run: int                            # its index: with the seed, each robot's coverage
    duration_s: float                   # simulated
    robots: Tuple[RobotResult, ...]
    servers: Tuple[ServerResult, ...]
    granted: int                        # claim decisions of the servers' ledgers, by answer
    refused: int
    waiting: int                        # refused for now: lower claims were asked to leave
    asks: Tuple[Tuple[float, str, str, str], ...]   # (t, server, 'robot/node' asked, by whom)
    claim_s: Tuple[float, ...]  # every claim decision's wall time
    wall_s: float

    @property
    def claims(self) -> int:
        return self.granted + self.refused + self.waiting

    @property
    def preemptions(self) -> int:
        return len(self.asks)

    @property
    def fairness(self) -> float:
        return jain([r.server_time_s for r in self.robots])

    @property
    def utilisation(self) -> float:
        """Over the servers."""
        return float(np.mean([s.utilisation for s in self.servers]))

    @property
    def overcommit_s(self) -> float:
        return sum(s.overcommit_s for s in self.servers)

    @property
    def delta_violations(self) -> int:
        return sum(r.delta_violations for r in self.robots)

    @property
    def improvement_pct(self) -> float:
        """Over the robots."""
        return float(np.mean([r.improvement_pct for r in self.robots]))

    def figures(self) -> Dict[str, Any]:
        """The run's outcome: every figure but the wall times (the same for the same seed)."""
        return {
            'run': self.run, 'duration_s': self.duration_s,
            'robots': [asdict(r) for r in self.robots],
            'servers': [asdict(s) for s in self.servers],
            'claims': self.claims, 'granted': self.granted, 'refused': self.refused,
            'waiting': self.waiting, 'preemptions': self.preemptions,
            'asks': [list(a) for a in self.asks],
            'fairness': self.fairness, 'utilisation': self.utilisation,
            'overcommit_s': self.overcommit_s, 'delta_violations': self.delta_violations,
            'improvement_pct': self.improvement_pct,
        }

    def to_dict(self) -> Dict[str, Any]:
        out = self.figures()
        out.update(claim_p50_ms=percentile_ms(self.claim_s, 50),
                   claim_p95_ms=percentile_ms(self.claim_s, 95), wall_s=self.wall_s)
        return out


@dataclass(frozen=True)
class FleetSummary:
    """One fleet's runs, averaged (the claim decisions' cost over every decision of them)."""

    runs: int
    utilisation: float
    overcommit_s: float
    claims: float               # per run
    refused: float
    waiting: float
    preemptions: float
    delta_violations: float
    fairness: float
    improvement_pct: float
    claim_p50_ms: float
    claim_p95_ms: float
    wall_s: float               # in all

    @classmethod
    def of(cls, runs: Sequence[FleetRun]) -> 'FleetSummary':
        if not runs:
            raise ValueError('no runs to summarise')

        def mean(figure: str) -> float:
            return float(np.mean([getattr(r, figure) for r in runs]))

        seconds = [s for r in runs for s in r.claim_s]
        return cls(runs=len(runs), utilisation=mean('utilisation'),
                   overcommit_s=mean('overcommit_s'), claims=mean('claims'),
                   refused=mean('refused'), waiting=mean('waiting'),
                   preemptions=mean('preemptions'), delta_violations=mean('delta_violations'),
                   fairness=mean('fairness'), improvement_pct=mean('improvement_pct'),
                   claim_p50_ms=percentile_ms(seconds, 50),
                   claim_p95_ms=percentile_ms(seconds, 95),
                   wall_s=sum(r.wall_s for r in runs))
