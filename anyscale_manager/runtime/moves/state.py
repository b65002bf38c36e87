"""What the moves share: the policy's memory between turns, and one step's inputs and notes."""

import math
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Set, Tuple

from ...model.types import DeciderSettings, Deployment, frozen_map
from ..constraints import ConstraintReport
from ..filters import Snapshot, agent_at
from ..observations import Decision, Observations, is_fresh


@dataclass
class Memory:
    """Algorithm 1's state: the migrated list, migrate-back and move times, pending moves."""

    desired: Dict[str, str] = field(default_factory=dict)
    migrated: List[Tuple[str, str]] = field(default_factory=list)   # (node, scale), in order
    # (node, scale it came back from) -> time of its last migrate-back (or relocation)
    last_back: Dict[Tuple[str, str], float] = field(default_factory=dict)
    last_move: Dict[str, float] = field(default_factory=dict)       # node -> its last move
    pending: Dict[str, Tuple[str, float]] = field(default_factory=dict)  # node -> (scale, when)
    # scale -> (when the last move there settled, the node that moved)
    arrived: Dict[str, Tuple[float, str]] = field(default_factory=dict)
    # (node, scale) -> when its copy there crashed and was failed over: one failover per
    # crash, and no failover back to that scale within the hysteresis T.
    crashed: Dict[Tuple[str, str], float] = field(default_factory=dict)
    history: List[Tuple[float, Decision]] = field(default_factory=list)
    last_move_out: float = -math.inf
    started: Optional[float] = None
    # Monitored connections heard delivering (a fresh reading above 0 Hz) since the start.
    heard: Set[str] = field(default_factory=set)

    def in_migrated(self, node: str) -> bool:
        return any(n == node for n, _ in self.migrated)

    def grace_until(self, grace_s: float) -> Mapping[str, float]:
        """node -> the end of the grace period after its last move."""
        return frozen_map({n: t + grace_s for n, t in self.last_move.items()})


@dataclass
class Step:
    """One step: the deployment and settings, the observations, what runs (known nodes on known
    scales), the memory the moves read and change, and what they say: notes (why nothing, or
    nothing more, moved) and unplaceable nodes (node -> why no scale with a live agent may host
    it)."""

    deployment: Deployment
    settings: DeciderSettings
    obs: Observations
    running: Dict[str, str]
    memory: Memory
    notes: List[str] = field(default_factory=list)
    unplaceable: Dict[str, str] = field(default_factory=dict)

    @property
    def master(self) -> str:
        return self.deployment.master.name

    @property
    def now(self) -> float:
        return self.obs.now

    @property
    def grace_until(self) -> Mapping[str, float]:
        return self.memory.grace_until(self.settings.grace_s)

    def snapshot(self, report: ConstraintReport) -> Snapshot:
        """The filters' frozen view of this step, judged by ``report``."""
        return Snapshot(self.deployment, self.settings, self.obs, report, self.memory.started,
                        frozen_map(self.memory.arrived))

    def agent_silent(self, scale: str) -> str:
        """Why the agent of ``scale`` cannot take a node now ('' when it can)."""
        return agent_at(self.obs, self.settings, scale).reason

    def hear(self) -> None:
        """Note the monitored connections this step's readings show delivering."""
        for c in self.deployment.connections:
            reading = self.obs.connections.get(c.name)
            if c.monitored and reading is not None and reading.rate_hz > 0.0 \
                    and is_fresh(reading.stamp, self.now, self.settings):
                self.memory.heard.add(c.name)

    def unheard(self) -> List[str]:
        """The monitored connections whose publisher and subscriber both run, not heard
        delivering yet since the start (a graph still booting)."""
        return [c.name for c in self.deployment.connections
                if c.monitored and c.name not in self.memory.heard
                and c.publisher in self.running and c.subscriber in self.running]

    def hold_for_master(self, node: str) -> bool:
        """Whether a move of ``node`` back to the master waits because the master's agent is
        silent (it could not start the node there): the layout is kept, and said why."""
        why = self.agent_silent(self.master)
        if why:
            self.notes.append(f'{node} is not brought back to {self.master}: {why}, nothing '
                              f'can start it there; the layout is kept')
        return bool(why)
