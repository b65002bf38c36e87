"""The ICAR 2015 system constraints, evaluated over one observation snapshot.

Three kinds (the paper's Sec. III-B.4): every monitored connection's frequency against its
freq_min with its tolerance Δ; every scale's CPU against its capacity (times a headroom); every
link's required bandwidth (the connections the running layout makes cross it) against what it
has available (times a margin). Judged on what actually runs (``Observations.running``).

A link's available bandwidth is the link monitor's measurement capped at the link's nominal
``bandwidth_kbps`` (``capped_kbps``): an active probe between two scales of one machine runs
over loopback and measures memory copies (23 456 370 kbit/s against a nominal 54 000 was
seen), which no decision should rest on. A reason built on a capped figure says so
(``LinkLoad.cap_note``).

Freshness: an observation older than ``observation_max_age_s`` counts as missing. A missing link
report is a down link; a missing connection reading is a rate of 0 Hz; a missing scale report
falls back to the nominal CPU of the nodes running there. Something never observed is missing
once ``observation_max_age_s`` has passed since ``since`` (the time the caller started watching);
with no ``since`` it is missing at once.

Each violation names the nodes whose migration back to the master would address it
(``Violation.nodes``): the policy picks among them.
"""

import math
from dataclasses import dataclass, field
from typing import Dict, FrozenSet, Iterable, List, Mapping, Optional, Tuple

from ..model.capacity import usable_cpu
from ..model.types import Connection, DeciderSettings, Deployment, Link, frozen_map
from ..model.violation import Violation
from .delta import ConnectionVerdict, below_start, time_below
from .observations import Observations, is_fresh

FREQUENCY = 'frequency'
CPU = 'cpu'
BANDWIDTH = 'bandwidth'
LINK_DOWN = 'link_down'
STALE = 'stale'
KINDS = (FREQUENCY, CPU, BANDWIDTH, LINK_DOWN, STALE)

_EMPTY: Mapping[str, float] = frozen_map()


@dataclass(frozen=True)
class LinkLoad:
    """Required against available bandwidth on one link, kbit/s."""

    link: str
    ends: Tuple[str, str]
    up: bool
    observed: bool                 # a fresh observation backs ``up`` and ``available_kbps``
    nominal_kbps: float
    available_kbps: float          # measured capped at nominal, else nominal; 0 when down
    usable_kbps: float             # available x bandwidth_margin
    required_kbps: float
    connections: Tuple[str, ...]   # the connections crossing it
    reason: str = ''               # why it counts as down, when it does
    measured_kbps: Optional[float] = None   # the monitor's figure behind available, uncapped

    @property
    def ok(self) -> bool:
        if self.required_kbps <= 0:
            return True
        return self.up and self.required_kbps <= self.usable_kbps

    @property
    def capped(self) -> bool:
        """The measurement was above the nominal: available is the nominal."""
        return self.measured_kbps is not None and self.measured_kbps > self.nominal_kbps

    @property
    def cap_note(self) -> str:
        """' (measured X kbit/s, capped at the nominal Y)' when capped, else ''."""
        if not self.capped:
            return ''
        return (f' (measured {self.measured_kbps:.0f} kbit/s, above the nominal: capped at '
                f'{self.nominal_kbps:.0f})')


@dataclass(frozen=True)
class ScaleLoad:
    """CPU used against the usable capacity of one scale (reference-core percent)."""

    scale: str
    cpu_used: float
    measured: bool                 # False: the nominal CPU of the nodes running there
    capacity_cpu: float
    usable_cpu: float              # capacity x cpu_headroom

    @property
    def ok(self) -> bool:
        return self.cpu_used <= self.usable_cpu


@dataclass(frozen=True)
class ConnectionCheck:
    """One monitored connection's frequency constraint: the Δ rule's verdict on it, and
    whether that verdict counts now."""

    connection: str
    rate_hz: Optional[float]       # None: no fresh reading (counted as 0 Hz)
    verdict: ConnectionVerdict     # its continuous time below freq_min against Δ
    judged: bool                   # False in a grace period or unjudged_connections

    @property
    def below_for_s(self) -> float:
        return self.verdict.below_for_s

    @property
    def violated(self) -> bool:
        return self.judged and self.verdict.past_delta


@dataclass(frozen=True)
class ConstraintReport:
    """Everything ``evaluate`` found at ``now``; frozen."""

    now: float
    violations: Tuple[Violation, ...]
    links: Mapping[str, LinkLoad] = field(default_factory=frozen_map)
    scales: Mapping[str, ScaleLoad] = field(default_factory=frozen_map)
    connections: Mapping[str, ConnectionCheck] = field(default_factory=frozen_map)

    def of_kind(self, *kinds: str) -> Tuple[Violation, ...]:
        return tuple(v for v in self.violations if v.kind in kinds)

    @property
    def ok(self) -> bool:
        return not self.violations

    @property
    def bandwidth_ok(self) -> bool:
        return not self.of_kind(BANDWIDTH, LINK_DOWN)

    @property
    def frequency_ok(self) -> bool:
        return not self.of_kind(FREQUENCY)

    @property
    def cpu_ok(self) -> bool:
        return not self.of_kind(CPU)


# --- helpers shared with the policy ------------------------------------------------------------

def link_observation_key(deployment: Deployment, link: Link) -> str:
    """The key of ``Observations.links`` for a link: its remote end when it touches the master,
    else 'A-B', the scale that watches it then the other (scale names hold no '-')."""
    master = deployment.master.name
    if master in link.ends:
        return link.other(master)
    monitor = deployment.link_monitor(link)
    return f'{monitor}-{link.other(monitor)}'


def link_text(deployment: Deployment, link: Link) -> str:
    """'link wifi to laptop' for a link from the master, 'link backhaul between laptop and
    server' for one between two remote scales."""
    master = deployment.master.name
    if master in link.ends:
        return f'link {link.name} to {link.other(master)}'
    return f'link {link.name} between {link.ends[0]} and {link.ends[1]}'


def crossing(deployment: Deployment, running: Mapping[str, str]
             ) -> Tuple[Dict[str, List[Connection]], List[Tuple[Connection, str, str]]]:
    """Connections each link carries under ``running``, and connections with no link at all."""
    on_link: Dict[str, List[Connection]] = {link.name: [] for link in deployment.links}
    unlinked: List[Tuple[Connection, str, str]] = []
    for c in deployment.connections:
        a, b = running.get(c.publisher), running.get(c.subscriber)
        if a is None or b is None or a == b:
            continue
        link = deployment.link_between(a, b)
        if link is None:
            unlinked.append((c, a, b))
        else:
            on_link[link.name].append(c)
    return on_link, unlinked


def capped_kbps(measured_kbps: float, nominal_kbps: float) -> float:
    """What a link is taken to have: its measurement, never above its nominal (loopback)."""
    return max(0.0, min(measured_kbps, nominal_kbps))


def measured_kbps(deployment: Deployment, obs: Observations, link: Link) -> Optional[float]:
    """The link monitor's last bandwidth figure for a link, uncapped (None: none)."""
    lo = obs.links.get(link_observation_key(deployment, link))
    return None if lo is None else lo.available_kbps


def required_kbps(deployment: Deployment, running: Mapping[str, str]) -> Dict[str, float]:
    """Bandwidth each link must carry under ``running`` (kbit/s, both directions summed)."""
    on_link, _ = crossing(deployment, running)
    return {name: sum(c.bandwidth_kbps for c in conns) for name, conns in on_link.items()}


def link_capacity(deployment: Deployment, settings: DeciderSettings, obs: Observations,
                  link: Link, since: Optional[float] = None) -> Tuple[bool, bool, float, str]:
    """(up, observed, available_kbps, why_down) for one link, from the latest observation.

    Available is the measurement capped at the nominal (``capped_kbps``), the nominal while
    nothing was measured. Every link is watched by the agent of one of its ends
    (``Deployment.link_monitor``).
    """
    key = link_observation_key(deployment, link)
    what = link_text(deployment, link)
    lo = obs.links.get(key)
    max_age = settings.observation_max_age_s
    if key in obs.unjudged_links:
        # No fresh report because the monitor's host is silent or just started: neither a
        # cut (nothing comes back for it) nor a link to move out over (not observed).
        last = lo.available_kbps if lo is not None and lo.available_kbps is not None \
            else link.bandwidth_kbps
        return True, False, capped_kbps(last, link.bandwidth_kbps), ''
    if lo is None:
        silent = math.inf if since is None else obs.now - since
        if silent > max_age:
            why = 'never reported' if since is None else f'no report for {silent:.1f} s'
            return False, False, 0.0, f'{what} silent ({why}, max age {max_age:g} s)'
        return True, False, link.bandwidth_kbps, ''
    age = obs.now - lo.stamp
    if age > max_age:
        return False, False, 0.0, f'{what} silent for {age:.1f} s (max age {max_age:g} s)'
    if not lo.up:
        return False, True, 0.0, f'{what} reported down'
    available = link.bandwidth_kbps if lo.available_kbps is None else lo.available_kbps
    return True, True, capped_kbps(available, link.bandwidth_kbps), ''


def node_cpu(deployment: Deployment, settings: DeciderSettings, obs: Observations,
             node: str) -> float:
    """A node's CPU: measured on the scale it runs on when fresh, else its nominal CPU."""
    scale = obs.running.get(node)
    so = obs.scales.get(scale) if scale is not None else None
    if so is not None and is_fresh(so.stamp, obs.now, settings) and node in so.cpu_by_node:
        return float(so.cpu_by_node[node])
    return deployment.node(node).cpu


def scale_cpu(deployment: Deployment, settings: DeciderSettings, obs: Observations,
              scale: str, running: Optional[Mapping[str, str]] = None) -> Tuple[float, bool]:
    """(CPU used on a scale, measured?): the fresh report, else the nominal sum of its nodes."""
    so = obs.scales.get(scale)
    if so is not None and is_fresh(so.stamp, obs.now, settings):
        return float(so.cpu_total), True
    running = obs.running if running is None else running
    known = set(deployment.node_names)
    return sum(deployment.node(n).cpu for n, s in running.items()
               if s == scale and n in known), False


def _off_master(deployment: Deployment, running: Mapping[str, str],
                names: Iterable[str]) -> Tuple[str, ...]:
    master = deployment.master.name
    out = []
    for n in names:
        s = running.get(n)
        if s is not None and s != master and n not in out:
            out.append(n)
    return tuple(out)


# --- evaluation ----------------------------------------------------------------------------------

def evaluate(deployment: Deployment, settings: DeciderSettings, obs: Observations,
             grace_until: Mapping[str, float] = _EMPTY, *,
             below_for: Optional[Mapping[str, float]] = None,
             since: Optional[float] = None,
             lost_scales: FrozenSet[str] = frozenset()) -> ConstraintReport:
    """Check the three constraint kinds on what actually runs; return a frozen report.

    ``grace_until``: node -> time until which its connections are not judged (after a move).
    ``below_for``: connection -> time below freq_min from a ``DeltaTracker``; without it, the
    same rule on this one snapshot (runtime/delta.py's ``below_start``).
    ``since``: when the caller started watching, so that something never observed is missing
    only after ``observation_max_age_s`` (None: missing at once).
    """
    now = obs.now
    known = set(deployment.node_names)
    running = {n: s for n, s in obs.running.items()
               if n in known and s in deployment.scale_names}
    violations: List[Violation] = []
    lost = frozenset(lost_scales) | frozenset(obs.lost_scales)

    # (i) frequencies
    checks: Dict[str, ConnectionCheck] = {}
    for c in deployment.connections:
        if not c.monitored:
            continue
        reading = obs.connections.get(c.name)
        fresh = reading is not None and is_fresh(reading.stamp, now, settings)
        if below_for is not None:
            below = float(below_for.get(c.name, 0.0))
        else:
            below = time_below(below_start(reading, now, settings,
                                           -math.inf if since is None else since), now)
        in_grace = any(grace_until.get(n, -math.inf) > now for n in (c.publisher, c.subscriber))
        both_run = c.publisher in running and c.subscriber in running
        # A connection measured by a silent (or just restarted) agent's probe: no verdict.
        measured = c.name not in obs.unjudged_connections
        rate_hz = reading.rate_hz if reading is not None and fresh else None
        check = ConnectionCheck(connection=c.name, rate_hz=rate_hz,
                                verdict=ConnectionVerdict.judge(below, c.tolerance_s),
                                judged=both_run and not in_grace and measured)
        checks[c.name] = check
        if check.violated:
            rate = f'{check.rate_hz:.2f} Hz' if fresh else 'no fresh reading (0 Hz)'
            violations.append(Violation(
                FREQUENCY, c.name,
                f'connection {c.name} below freq_min {c.freq_min_hz:g} Hz for {below:.1f} s '
                f'> tolerance {c.tolerance_s:g} s ({rate})',
                _off_master(deployment, running, (c.publisher, c.subscriber))))
        elif reading is not None and not fresh and check.judged:
            violations.append(Violation(
                STALE, c.name,
                f'connection {c.name}: last reading {now - reading.stamp:.1f} s old '
                f'(max age {settings.observation_max_age_s:g} s), counted as 0 Hz'))

    # (ii) CPU
    scales: Dict[str, ScaleLoad] = {}
    master = deployment.master.name
    for s in deployment.scales:
        used, measured = scale_cpu(deployment, settings, obs, s.name, running)
        load = ScaleLoad(scale=s.name, cpu_used=used, measured=measured,
                         capacity_cpu=s.capacity_cpu,
                         usable_cpu=usable_cpu(s.capacity_cpu, settings))
        scales[s.name] = load
        hosted = tuple(n for n, where in running.items() if where == s.name)
        so = obs.scales.get(s.name)
        if so is not None and not measured and hosted and s.name not in lost:
            violations.append(Violation(
                STALE, s.name,
                f'scale {s.name}: CPU report {now - so.stamp:.1f} s old (max age '
                f'{settings.observation_max_age_s:g} s); using nominal CPU {used:.0f}'))
        if not load.ok:
            culprits = () if s.name == master else \
                tuple(n for n in deployment.migratable_nodes if n in hosted)
            violations.append(Violation(
                CPU, s.name,
                f'scale {s.name} CPU {used:.0f} > usable {load.usable_cpu:.0f} '
                f'({s.capacity_cpu:g} x headroom {settings.cpu_headroom:g})'
                + ('' if measured else ' (nominal estimate)'), culprits))

    # (iii) bandwidth and link state
    on_link, unlinked = crossing(deployment, running)
    links: Dict[str, LinkLoad] = {}
    for link in deployment.links:
        up, observed, available, why = link_capacity(deployment, settings, obs, link, since)
        conns = on_link[link.name]
        required = sum(c.bandwidth_kbps for c in conns)
        link_load = LinkLoad(link=link.name, ends=link.ends, up=up, observed=observed,
                             nominal_kbps=link.bandwidth_kbps, available_kbps=available,
                             usable_kbps=available * settings.bandwidth_margin,
                             required_kbps=required, connections=tuple(c.name for c in conns),
                             reason=why,
                             measured_kbps=measured_kbps(deployment, obs, link) if up else None)
        links[link.name] = link_load
        # Beyond a link from the master: everything on its remote end (cut off, it stops its
        # own copies). A link between two remote scales cuts off nothing: only the
        # connections that cross it.
        far = [e for e in link.ends if e != master] if master in link.ends else []
        hosted_far = tuple(n for n, where in running.items() if where in far)
        if not up and (required > 0 or hosted_far):
            names = {c.publisher for c in conns} | {c.subscriber for c in conns}
            violations.append(Violation(
                LINK_DOWN, link.name, why,
                _off_master(deployment, running, list(names) + list(hosted_far))))
        elif up and required > link_load.usable_kbps:
            ends = [n for c in conns for n in (c.publisher, c.subscriber)]
            violations.append(Violation(
                BANDWIDTH, link.name,
                f'link {link.name}: required {required:.0f} kbit/s > usable '
                f'{link_load.usable_kbps:.0f} kbit/s ({available:.0f} available x margin '
                f'{settings.bandwidth_margin:g}){link_load.cap_note}',
                _off_master(deployment, running, ends)))
    for c, a, b in unlinked:
        violations.append(Violation(
            BANDWIDTH, c.name, f'connection {c.name} joins {a} and {b}, which share no link',
            _off_master(deployment, running, (c.publisher, c.subscriber))))

    return ConstraintReport(now=now, violations=tuple(violations), links=frozen_map(links),
                            scales=frozen_map(scales), connections=frozen_map(checks))
