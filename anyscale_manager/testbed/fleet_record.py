"""What a fleet run showed, sample by sample: where each robot's worker ran, each robot's link,
the server's claims by robot, what each robot's users heard, and the run's own actions.

Pure: fed samples, observer lines (testbed/observer.py) and marks, each stamped with the one
monotonic clock every namespace of the machine shares; it answers the tests' questions and
gives a demo its timeline. No rclpy, no processes here (testbed/fleet_netns.py takes the
samples).
"""

import json
import math
import threading
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from .fleet import ACTIVE_WINDOW_S, HOME, SERVER
from .record import HEARD_LAG_S


# How long lifecycle copies must be seen serving above the capacity to count (over_capacity): the
# serving judge's reach back (twice its window) and a sample's lateness.
OVER_SPAN_S = 2 * ACTIVE_WINDOW_S + 0.1


@dataclass(frozen=True)
class FleetSample:
    """The fleet at time ``t``."""

    t: float
    # robot -> role ('home', 'away') -> the live worker processes its agent there supervises
    workers: Mapping[str, Mapping[str, int]]
    links_up: Mapping[str, bool]          # robot -> its link to the server is up
    claims_cpu: Mapping[str, float]       # robot -> the CPU of its active claims on the server
    # robot -> the migratable nodes whose copy serves on the server, and the CPU its file
    # declares for them (the ICAR graph: where workers counts copies of two nodes)
    on_server_nodes: Mapping[str, Tuple[str, ...]] = field(default_factory=dict)
    server_cpu: Mapping[str, float] = field(default_factory=dict)

    @property
    def on_server(self) -> int:
        """Worker processes on the server, of every robot."""
        return sum(w.get(SERVER, 0) for w in self.workers.values())

    @property
    def claimed_cpu(self) -> float:
        return sum(self.claims_cpu.values())

    @property
    def serving_cpu(self) -> float:
        """The CPU declared for every copy serving on the server, of every robot."""
        return sum(self.server_cpu.values())

    def all_away(self, robot: str, nodes) -> bool:
        """Every one of ``nodes`` (robot's migratable nodes) serves on the server."""
        return self.on_server_nodes.get(robot) == tuple(sorted(nodes))

    def none_away(self, robot: str) -> bool:
        """None of ``robot``'s copies serves on the server (the robot has started)."""
        return robot in self.on_server_nodes and not self.on_server_nodes[robot]

    def where(self, robot: str) -> str:
        """Where robot's worker runs: 'home', 'away', 'both' or 'none'."""
        w = self.workers.get(robot, {})
        at = [role for role in (HOME, SERVER) if w.get(role, 0)]
        return at[0] if len(at) == 1 else ('both' if at else 'none')


def over_capacity(samples: Sequence[FleetSample], capacity_cpu: float,
                  lifecycle: bool) -> List[FleetSample]:
    """The samples in which the server is over ``capacity_cpu``: its claims above it, or the CPU
    its serving copies declare above it (``lifecycle``: in every sample for OVER_SPAN_S up to
    that one). A lifecycle copy is judged serving from its CPU since the newest sample of it at
    least ACTIVE_WINDOW_S old (fleet.Activity), up to twice that window back when the samples
    come every 0.2 s, so a copy deactivated within it still counts beside the one its robot's
    claim let activate after it (two samples 0.2 s apart, each over, were that alone). A plain
    copy serves while its process lives: one sample over is over."""
    out = []
    since: Optional[float] = None       # the start of the stretch of samples serving over
    for s in samples:
        serving = s.serving_cpu > capacity_cpu + 1e-9
        since = (s.t if since is None else since) if serving else None
        counted = serving and (not lifecycle or s.t - since >= OVER_SPAN_S - 1e-9)
        if counted or s.claimed_cpu > capacity_cpu + 1e-9:
            out.append(s)
    return out


@dataclass(frozen=True)
class HandOver:
    """After a holder's link was cut at ``cut``: when its worker was home, its server copy gone
    (``fenced``) and its claim released, and when the other robot's worker started on the
    server and served there (its home copy let go)."""

    cut: float
    home: float
    fenced: float
    released: float
    started: float
    serving: float

    @property
    def freed(self) -> float:
        """The room handed on: the cut-off copy gone and its claim released."""
        return max(self.fenced, self.released)


class FleetRecord:
    """Samples, marks and each robot's heard arrivals of one run (observer lines may arrive
    from reader threads: every access holds the record's lock)."""

    def __init__(self, t0: float):
        self.t0 = t0
        self.samples: List[FleetSample] = []
        self.marks: List[Tuple[float, str]] = []
        self._arrivals: Dict[str, List[float]] = {}
        self._by_topic: Dict[str, Dict[str, List[float]]] = {}
        self._heard_until: Dict[str, float] = {}
        self._ready: Dict[str, float] = {}
        self._lock = threading.Lock()

    # --- feeding ----------------------------------------------------------------------------
    def add(self, sample: FleetSample) -> None:
        with self._lock:
            self.samples.append(sample)

    def mark(self, t: float, text: str) -> None:
        with self._lock:
            self.marks.append((t, text))

    def ingest_line(self, robot: str, line: str) -> None:
        """One line of the observer in ``robot``'s namespace: its arrivals on every topic it
        hears are that robot's (the worker graph: its worker's output only)."""
        try:
            obj = json.loads(line)
        except ValueError:
            return
        if not isinstance(obj, dict) or not isinstance(obj.get('t'), (int, float)):
            return
        with self._lock:
            self._heard_until[robot] = max(self._heard_until.get(robot, -math.inf), obj['t'])
            if obj.get('ready'):
                self._ready.setdefault(robot, obj['t'])
            arrivals = obj.get('arrivals')
            for topic, times in (arrivals.items() if isinstance(arrivals, dict) else ()):
                if not isinstance(times, list):
                    continue
                got = [float(t) for t in times if isinstance(t, (int, float))]
                self._arrivals.setdefault(robot, []).extend(got)
                self._by_topic.setdefault(robot, {}).setdefault(str(topic), []).extend(got)

    # --- questions --------------------------------------------------------------------------
    def ready(self, robot: str) -> bool:
        """The observer in ``robot``'s namespace runs."""
        with self._lock:
            return robot in self._ready

    def heard(self, robot: str, topic: Optional[str] = None) -> List[float]:
        """When ``robot``'s users heard ``topic`` (None: any topic its observer hears, the
        worker graph's worker output), in order."""
        with self._lock:
            if topic is None:
                return sorted(self._arrivals.get(robot, []))
            return sorted(self._by_topic.get(robot, {}).get(topic, []))

    def judged_until(self, robot: str) -> float:
        """Up to when ``robot``'s heard arrivals are complete (the observer's flush lag)."""
        with self._lock:
            return self._heard_until.get(robot, -math.inf) - HEARD_LAG_S

    def between(self, start: float = -math.inf, end: float = math.inf) -> List[FleetSample]:
        with self._lock:
            return [s for s in self.samples if start <= s.t <= end]

    def most_on_server(self, start: float = -math.inf, end: float = math.inf) -> int:
        return max((s.on_server for s in self.between(start, end)), default=0)

    def most_claimed(self, start: float = -math.inf, end: float = math.inf) -> float:
        return max((s.claimed_cpu for s in self.between(start, end)), default=0.0)

    def first(self, holds: Callable[[FleetSample], bool], since: float = -math.inf
              ) -> Optional[float]:
        """The time of the first sample from ``since`` on in which ``holds``."""
        return next((s.t for s in self.between(since) if holds(s)), None)

    def hand_over(self, holder: str, other: str, cut: float) -> HandOver:
        """The hand-over of the server from ``holder``, whose link was cut at ``cut``, to
        ``other``, read from the samples (each step must have been sampled)."""
        def first(holds: Callable[[FleetSample], bool]) -> float:
            t = self.first(holds, since=cut)
            if t is None:
                raise ValueError(f'the hand-over from {holder} to {other}: a step not sampled')
            return t
        return HandOver(cut, first(lambda s: s.workers[holder][HOME] >= 1),
                        first(lambda s: s.workers[holder][SERVER] == 0),
                        first(lambda s: not s.claims_cpu.get(holder)),
                        first(lambda s: s.workers[other][SERVER] >= 1),
                        first(lambda s: s.where(other) == SERVER))

    def timeline(self, robots: Sequence[str], every_s: float = 1.0) -> List[str]:
        """One row per ``every_s`` (and one per mark): seconds from the start, then per robot
        where its worker runs, its link and its claim on the server; for a demo's figure or a
        failed test's message."""
        with self._lock:
            samples, marks = list(self.samples), list(self.marks)
        rows = [(t, 1, f'{t - self.t0:7.2f}  -- {text}') for t, text in marks]
        next_t = -math.inf
        for sample in samples:
            if sample.t < next_t:
                continue
            next_t = sample.t + every_s
            rows.append((sample.t, 0, f'{sample.t - self.t0:7.2f}  ' + '  '.join(
                f'{r}: {sample.where(r):4} link {"up" if sample.links_up.get(r) else "CUT":3} '
                f'claim {sample.claims_cpu.get(r, 0.0):3.0f}'
                + (f' away {",".join(sample.on_server_nodes[r]) or "-"}'
                   if r in sample.on_server_nodes else '') for r in robots)))
        return [text for _, _, text in sorted(rows)]


__all__ = ['FleetRecord', 'FleetSample', 'HandOver', 'over_capacity']
