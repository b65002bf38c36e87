"""The placement filters the observations decide, over one turn's frozen snapshot.

Each filter judges a ``Candidate`` (a node, or a coresidence group moving as one, for one scale)
by a ``Snapshot`` (the deployment, the settings, the observations and the constraint report
built from them) and returns a ``Verdict`` (model/placement.py): a code, whether it passes
(True), fails (False) or cannot be told yet (None: what it needs has not been observed), and a
reason. ``can_host`` runs them in order and returns the first that does not pass: a live agent
there, allowed there (residence, the coresidence group's included), a link from the master up
and observed, the scale's CPU measured, CPU headroom, bandwidth on every link whose load grows.
A pass says the CPU and bandwidth it found. The migration policy ranks the scales that pass
(runtime/scores.py) and takes the first.
"""

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Optional, Tuple

from ..model import placement
from ..model.capacity import usable_cpu
from ..model.placement import PASS, Code, Verdict, fails, first_failing, passes, waits
from ..model.types import DeciderSettings, Deployment, Link, frozen_map
from .constraints import ConstraintReport, LinkLoad, is_fresh, required_kbps, scale_cpu
from .observations import Observations


@dataclass(frozen=True)
class Snapshot:
    """What the filters judge by, frozen for one turn. ``started``: when the policy started
    watching (what is never observed is missing only ``observation_max_age_s`` after it);
    ``arrived``: scale -> (when the last move there settled, the node that moved)."""

    deployment: Deployment
    settings: DeciderSettings
    obs: Observations
    report: ConstraintReport
    started: Optional[float] = None
    arrived: Mapping[str, Tuple[float, str]] = field(default_factory=frozen_map)

    @property
    def master(self) -> str:
        return self.deployment.master.name

    @property
    def since_start(self) -> float:
        """Time since the policy started watching (0 before it)."""
        return 0.0 if self.started is None else self.obs.now - self.started

    def master_link(self, scale: str) -> Tuple[Optional[Link], Optional[LinkLoad]]:
        """The link from the master to ``scale`` and its load in the report (None: none)."""
        link = self.deployment.link_between(self.master, scale)
        return link, None if link is None else self.report.links[link.name]


@dataclass(frozen=True)
class Candidate:
    """``unit`` (its nodes, the first named in notes) on ``scale``: its CPU, where every node
    runs meanwhile (``running``, the unit's own nodes left out or not), and the CPU this turn
    already sent to ``scale``. ``urgent``: the unit must leave where it is (a link down, a
    lost scale, a Δ): it may not count on room a preemption would make on a shared scale, which
    takes the lower robots' moves home first."""

    unit: Tuple[str, ...]
    scale: str
    cpu: float
    running: Mapping[str, str]
    sent_cpu: float = 0.0
    urgent: bool = False


Filter = Callable[[Snapshot, Candidate], Verdict]


def agent_at(obs: Observations, settings: DeciderSettings, scale: str) -> Verdict:
    """The agent of ``scale`` can take a node now: it is neither lost nor silent."""
    if scale in obs.lost_scales:
        return fails(Code.AGENT_SILENT, f'the agent of {scale} is lost (silent > '
                                        f'{settings.agent_timeout_s:g} s)')
    if scale in obs.silent_agents:
        return fails(Code.AGENT_SILENT, f'the agent of {scale} is silent')
    return PASS


def live_agent(snap: Snapshot, cand: Candidate) -> Verdict:
    return agent_at(snap.obs, snap.settings, cand.scale)


def residence(snap: Snapshot, cand: Candidate) -> Verdict:
    """Every node of the unit, with its coresidence group, may run there."""
    for node in cand.unit:
        verdict = placement.allowed(snap.deployment, node, cand.scale)
        if not verdict.passed:
            return verdict
    return PASS


def link_up(snap: Snapshot, cand: Candidate) -> Verdict:
    """A link from the master reaches the scale and is up (observed or not)."""
    link, load = snap.master_link(cand.scale)
    if link is None or load is None:
        return fails(Code.NO_LINK, f'no link from {snap.master}')
    return PASS if load.up else fails(Code.LINK_DOWN, load.reason)


def link_observed(snap: Snapshot, cand: Candidate) -> Verdict:
    """The link from the master has been observed since the start (else: wait for it)."""
    link, load = snap.master_link(cand.scale)
    if link is None or load is None or load.observed:
        return PASS
    return waits(Code.LINK_NOT_OBSERVED, f'link {link.name} not observed yet')


def cpu_observed(snap: Snapshot, cand: Candidate) -> Verdict:
    """The scale's CPU measurement can be trusted to host one more node.

    Passes on a fresh report received after the last node moved there started running (so it
    includes that node's load). Waits with no report yet within ``observation_max_age_s`` of
    the start, or none since the last node started there. Fails when its reports stopped.
    """
    obs, scale = snap.obs, cand.scale
    so = obs.scales.get(scale)
    max_age = snap.settings.observation_max_age_s
    if so is None or not is_fresh(so.stamp, obs.now, snap.settings):
        if so is None and snap.since_start <= max_age:
            return waits(Code.CPU_NOT_OBSERVED, f'no CPU report from {scale} yet')
        last = 'never' if so is None else f'{obs.now - so.stamp:.1f} s ago'
        return fails(Code.CPU_STALE, f'no fresh CPU report from {scale} (last {last}, max age '
                                     f'{max_age:g} s)')
    arrived = snap.arrived.get(scale)
    if arrived is not None and so.stamp <= arrived[0]:
        return waits(Code.CPU_NOT_OBSERVED, f'CPU of {scale} not measured since {arrived[1]} '
                                            f'started there ({obs.now - arrived[0]:.1f} s ago)')
    return PASS


def cpu_headroom(snap: Snapshot, cand: Candidate) -> Verdict:
    """What the scale uses (measured, else nominal), what this turn sent there and the unit's
    CPU fit in its usable CPU (capacity x headroom)."""
    d, s = snap.deployment, snap.settings
    if d.scale(cand.scale).shared:
        return PASS           # judged by its claims (shared_room): others' load is not its
    used, _ = scale_cpu(d, s, snap.obs, cand.scale)
    used += cand.sent_cpu
    usable = usable_cpu(d.scale(cand.scale).capacity_cpu, s)
    if used + cand.cpu > usable:
        return fails(Code.CPU, f'CPU {used:.0f} + {cand.cpu:.0f} > usable {usable:.0f}')
    return passes(f'CPU {used:.0f} + {cand.cpu:.0f} <= {usable:.0f}')


def shared_room(snap: Snapshot, cand: Candidate) -> Verdict:
    """A shared scale (``scales.<s>.shared``) has room for the unit beside every other
    deployment's claim on its host that this one may not preempt (one of its priority or
    higher; an urgent unit: every claim), as its agent reports them (agent/ledger.py): CPU
    within the host's usable CPU, memory within the host's memory. This deployment's own nodes
    there count by their nominal CPU, as their claims do."""
    d, obs = snap.deployment, snap.obs
    if not d.scale(cand.scale).shared:
        return PASS
    share = obs.shares.get(cand.scale)
    if share is None:
        return waits(Code.SHARE_NOT_HEARD, f'no word yet from the agent of {cand.scale} on '
                                           "its host's claims")
    mine = [n for n, s in cand.running.items() if s == cand.scale and n not in cand.unit]
    own = sum(d.node(n).cpu for n in mine) + cand.sent_cpu
    # Its claim will be its nominal CPU, whatever it was measured at here.
    cpu = max(cand.cpu, sum(d.node(n).cpu for n in cand.unit))
    floor = d.priority if not cand.urgent else -math.inf
    keep = [c for c in share.claims.values() if c.priority >= floor]
    held = sum(c.cpu for c in keep if c.active)
    free = usable_cpu(share.capacity_cpu, snap.settings) - held
    holders = ', '.join(sorted(k for k, c in share.claims.items()
                               if c.priority >= floor)) or 'nobody'
    if own + cpu > free:
        return fails(Code.SHARED, f'shared {cand.scale}: CPU {own:.0f} + {cpu:.0f} > '
                                  f'{free:.0f} left by {holders}')
    if share.memory_mb > 0:
        unit_mb = sum(d.node(n).memory_mb for n in cand.unit)
        own_mb = sum(d.node(n).memory_mb for n, c in obs.copies.items()
                     if cand.scale in c and n not in cand.unit)
        left_mb = share.memory_mb - sum(c.memory_mb for c in keep)
        if own_mb + unit_mb > left_mb:
            return fails(Code.SHARED, f'shared {cand.scale}: memory {own_mb:.0f} + '
                                      f'{unit_mb:.0f} MiB > {left_mb:.0f} left by {holders}')
    return passes(f'shared {cand.scale}: CPU {own:.0f} + {cpu:.0f} <= {free:.0f}')


def bandwidth(snap: Snapshot, cand: Candidate) -> Verdict:
    """Every link whose load grows with the unit there is up and carries it within its usable
    bandwidth (available x margin); the pass names each such link's load."""
    d = snap.deployment
    trial = dict(cand.running, **{n: cand.scale for n in cand.unit})
    before, after = required_kbps(d, cand.running), required_kbps(d, trial)
    detail = []
    for name, need in after.items():
        if need <= before[name]:
            continue
        load = snap.report.links[name]
        if not load.up:
            return fails(Code.LINK_DOWN, f'link {name} down')
        if need > load.usable_kbps:
            return fails(Code.BANDWIDTH, f'link {name} would need {need:.0f} kbit/s > usable '
                                         f'{load.usable_kbps:.0f}{load.cap_note}')
        detail.append(f'link {name} {need:.0f}/{load.usable_kbps:.0f} kbit/s{load.cap_note}')
    return passes('; '.join(detail))


# In this order: a later filter may read what an earlier one vouched for (the link it found
# up), and a wait (None) is given before a no that a later filter would find.
FILTERS: Tuple[Filter, ...] = (live_agent, residence, link_up, link_observed, cpu_observed,
                               cpu_headroom, shared_room, bandwidth)


def can_host(snap: Snapshot, cand: Candidate) -> Verdict:
    """The first of ``FILTERS`` that does not pass, else a pass with what CPU and bandwidth
    it found ('CPU 40 + 30 <= 90; link wifi 900/4000 kbit/s')."""
    return first_failing(f(snap, cand) for f in FILTERS)


def reachable(snap: Snapshot, scale: str) -> Verdict:
    """A node can be placed on ``scale`` now, whatever its CPU: a live agent, and (a remote
    scale) a link from the master that is up. The reason names the scale."""
    verdict = agent_at(snap.obs, snap.settings, scale)
    if not verdict.passed or scale == snap.master:
        return verdict
    link, load = snap.master_link(scale)
    if link is None or load is None:
        return fails(Code.NO_LINK, f'no link from {snap.master} to {scale}')
    return PASS if load.up else fails(Code.LINK_DOWN, load.reason)


def handover(snap: Snapshot, leaving: Optional[str], scale: str) -> Verdict:
    """A node may move from ``leaving`` straight to ``scale``: the link between them, if any,
    is up. The copy that stops and the one that starts hear each other's reports over it;
    across a cut, the handover would wait out its timeouts."""
    link = snap.deployment.link_between(leaving, scale) if leaving is not None else None
    if link is None or snap.report.links[link.name].up:
        return PASS
    return fails(Code.HANDOVER, f'{snap.report.links[link.name].reason} (the handover from '
                                f'{leaving} needs it)')


def hysteresis(last_back: Mapping[Tuple[str, str], float], hysteresis_s: float,
               unit: Tuple[str, ...], scale: Optional[str], now: float) -> Verdict:
    """The hysteresis T does not hold ``unit`` back from ``scale`` (any scale if None).

    Scope 'node' (the paper's literal rule) asks with None: a node migrated back is not moved
    out again within T. Scope 'scale' (the default) asks with the scale: a node is not moved
    back to the scale it came back from within T, but may go to another remote scale, whose
    link did not fail it. ``last_back``: (node, scale it came back from) -> when.
    """
    latest = None
    for (n, came_from), when in last_back.items():
        if n in unit and (scale is None or came_from == scale) and now - when < hysteresis_s:
            if latest is None or when > latest[0]:
                latest = (when, n, came_from)
    if latest is None:
        return PASS
    when, n, came_from = latest
    target = '' if scale is None else f' -> {scale}'
    return fails(Code.HYSTERESIS, f'{unit[0]}{target}: {n} migrated back from {came_from} '
                                  f'{now - when:.1f} s ago, within T = {hysteresis_s:g} s')


__all__ = ['FILTERS', 'Candidate', 'Filter', 'Snapshot', 'agent_at', 'bandwidth', 'can_host',
           'cpu_headroom', 'cpu_observed', 'handover', 'hysteresis', 'link_observed', 'link_up',
           'live_agent', 'reachable', 'residence', 'shared_room']
