"""The simulated robot: its path, its speed model and the rate model of its nodes.

Pure functions and frozen values; the world (``world.py``) holds the state that changes.

Speed model (a generalisation of the ICAR 2015 test-bed, where the youBot drives at 0.4 m/s only
while AMCL runs on the laptop and at 0.2 m/s otherwise):

* a node's output rate is ``min(rate_opt, rate_base * gain_k / gain_master * cpu_share_k)``:
  on the master it reaches its base rate (the connection's freq_min: the robot "satisfies only
  the minimum values"), on a scale with a larger gain alpha_k it runs proportionally faster, up
  to its optimal rate (freq_opt);
* some nodes govern the robot's speed (``speed_weight`` > 0, the weights sum to 1): each one's
  quality ``q = (rate - base) / (opt - base)`` clamped to [0, 1], as received on the master;
  ``v = v_min + (v_max - v_min) * sum(w * q)``;
* when a speed-governing node's output does not reach the master at its minimum rate (its
  scale is cut off, or it is starting after a move), the robot falls back to ``v_min`` (dead
  reckoning on odometry) for the output connection's tolerance Delta, and stops beyond it.
"""

from dataclasses import dataclass, field
from typing import Dict, Mapping, Optional, Tuple

from ..model.types import Deployment, frozen_map
from ..runtime.delta import past_delta

INDEPENDENT = 'independent'
SHARED = 'shared'
LINK_MODES = (INDEPENDENT, SHARED)


@dataclass(frozen=True)
class PathModel:
    """The path, the robot's speeds and the radio environment along the path."""

    length_m: float = 115.0               # the test-bed's square path
    speed_min_mps: float = 0.2            # every speed-governing node at its base rate
    speed_max_mps: float = 0.4            # every speed-governing node at its optimal rate
    availability_low: float = 0.45        # share of the path where a link is up: U(low, high)
    availability_high: float = 0.65
    outages_min: int = 1                  # coverage holes per lap and link: uniform integer
    outages_max: int = 3
    throughput_fraction: float = 0.45     # WiFi goodput / nominal (802.11g: ~24 of 54 Mbit/s)
    edge_ramp_m: float = 5.0              # goodput ramps from 0 at a hole's edge to its peak
    migration_delay_s: float = 2.0        # a moved node's new instance needs this to start
    # A lifecycle node with standby moving to a scale that keeps an inactive copy of it is
    # activated there, not started (bench/bench_standby.py measures activation -> first output).
    standby_resume_s: float = 0.05
    links: str = INDEPENDENT              # independent: one coverage pattern per remote scale

    def __post_init__(self):
        checks = (
            (self.length_m > 0, 'length_m must be > 0'),
            (0 < self.speed_min_mps <= self.speed_max_mps,
             'speeds must satisfy 0 < speed_min_mps <= speed_max_mps'),
            (0 <= self.availability_low <= self.availability_high <= 1,
             'availability must satisfy 0 <= low <= high <= 1'),
            (0 <= self.outages_min <= self.outages_max, 'outages must satisfy 0 <= min <= max'),
            (0 < self.throughput_fraction <= 1, 'throughput_fraction must be in (0, 1]'),
            (self.edge_ramp_m >= 0, 'edge_ramp_m must be >= 0'),
            (self.migration_delay_s >= 0, 'migration_delay_s must be >= 0'),
            (self.standby_resume_s >= 0, 'standby_resume_s must be >= 0'),
            (self.links in LINK_MODES, f'links must be one of {", ".join(LINK_MODES)}'),
        )
        for ok, message in checks:
            if not ok:
                raise ValueError(f'PathModel: {message}')


@dataclass(frozen=True)
class NodeProfile:
    """What the simulator needs to know about one node beyond the deployment."""

    rate_base_hz: float          # output rate on the master (0 for nodes that publish once)
    rate_opt_hz: float           # the rate it cannot exceed
    speed_weight: float = 0.0    # share of the robot's speed it governs
    tolerance_s: float = 0.0     # Delta of its output connection (for the speed model)


@dataclass(frozen=True)
class SimSystem:
    """One simulated system: a deployment plus the profiles the world needs."""

    label: str
    n: int                       # processing nodes (data providers not counted)
    m: int                       # migratable nodes
    k: int                       # scales
    deployment: Deployment
    profiles: Mapping[str, NodeProfile] = field(default_factory=frozen_map)

    @property
    def speed_nodes(self) -> Tuple[str, ...]:
        return tuple(n for n, p in self.profiles.items() if p.speed_weight > 0)


def profiles_from_deployment(deployment: Deployment,
                             speed_weights: Mapping[str, float]) -> Dict[str, NodeProfile]:
    """Base and optimal rates from each node's monitored output connections."""
    unknown = set(speed_weights) - set(deployment.node_names)
    if unknown:
        raise ValueError(f'speed weights name unknown nodes: {", ".join(sorted(unknown))}')
    total = sum(speed_weights.values())
    if speed_weights and abs(total - 1.0) > 1e-9:
        raise ValueError(f'speed weights must sum to 1, got {total:g}')
    providers = set(deployment.data_providers)
    out = {}
    for node in deployment.nodes:
        outs = [c for c in deployment.connections if c.publisher == node.name and c.monitored]
        mins = [float(c.freq_min_hz or 0.0) for c in outs]
        opts = [c.freq_opt_hz if c.freq_opt_hz is not None else m for c, m in zip(outs, mins)]
        tolerances = [float(c.tolerance_s or 0.0) for c in outs]
        opt = max(opts) if opts else 0.0
        # A sensor driver publishes at its hardware rate; processing nodes only reach their
        # minimum on the master.
        base = opt if node.name in providers else (max(mins) if mins else 0.0)
        weight = float(speed_weights.get(node.name, 0.0))
        if weight > 0 and not mins:
            raise ValueError(f'speed node {node.name!r} has no monitored output connection')
        out[node.name] = NodeProfile(rate_base_hz=base, rate_opt_hz=max(opt, base),
                                     speed_weight=weight,
                                     tolerance_s=min(tolerances) if tolerances else 0.0)
    return out


def node_rate(profile: NodeProfile, gain_ratio: float, cpu_share: float = 1.0) -> float:
    """Output rate of a node on a scale whose gain is ``gain_ratio`` times the master's."""
    return min(profile.rate_opt_hz, profile.rate_base_hz * gain_ratio * cpu_share)


def quality(profile: NodeProfile, rate_hz: float) -> float:
    """How far between its base and optimal rate a node runs, in [0, 1]."""
    span = profile.rate_opt_hz - profile.rate_base_hz
    if span <= 0:
        return 1.0 if rate_hz >= profile.rate_opt_hz else 0.0
    return min(1.0, max(0.0, (rate_hz - profile.rate_base_hz) / span))


def robot_speed(path: PathModel, profiles: Mapping[str, NodeProfile],
                delivered_hz: Mapping[str, float],
                starved_for_s: Optional[Mapping[str, float]] = None) -> float:
    """The speed the robot can drive at, from the speed nodes' rates received on the master.

    ``starved_for_s[n]`` is how long node n's output has been below its base rate (absent or
    negative: not starved).
    """
    starved_for_s = starved_for_s or {}
    score = 0.0
    fallback = False
    for name, p in profiles.items():
        if p.speed_weight <= 0:
            continue
        starved = starved_for_s.get(name, -1.0)
        if starved >= 0:
            if past_delta(starved, p.tolerance_s):
                return 0.0
            fallback = True
            continue
        score += p.speed_weight * quality(p, delivered_hz.get(name, 0.0))
    if fallback:
        return path.speed_min_mps
    return path.speed_min_mps + (path.speed_max_mps - path.speed_min_mps) * min(1.0, score)
