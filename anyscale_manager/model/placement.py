"""Placement verdicts, and the filters the deployment alone decides: residence and coresidence.

Placement follows the Kubernetes scheduler framework: filters (hard constraints) judge one node,
or one unit of nodes that move together, on one scale over a frozen snapshot, each returning a
``Verdict``: a code saying which check it is, whether it passes, and a reason; scores then rank
the scales that pass. A reason is said of the node being placed, mostly without naming it: the
caller does (``amcl -> laptop: not allowed there``).

The filters here need nothing but the deployment, so the planners (planning/feasibility.py),
the check of a first layout (runtime/layout.py) and the migration policy (runtime/filters.py)
judge residence and coresidence by the same functions. The filters that read observations are
in runtime/filters.py.
"""

from dataclasses import dataclass
from enum import Enum
from typing import Iterable, Mapping, Optional, Sequence, Tuple

from .types import Deployment


class Code(Enum):
    """Which check a verdict comes from (its ``value`` is what logs and tests read)."""

    OK = 'ok'                                   # every check passed
    RESIDENCE = 'residence'                     # the node may not run there
    CORESIDENCE = 'coresidence'                 # a node it must share a scale with is elsewhere
    AGENT_SILENT = 'agent_silent'               # the scale's agent is silent or lost
    NO_LINK = 'no_link'                         # no link from the master reaches the scale
    LINK_DOWN = 'link_down'                     # a link it needs is down or silent
    LINK_NOT_OBSERVED = 'link_not_observed'     # its link not observed since the start (wait)
    CPU_NOT_OBSERVED = 'cpu_not_observed'       # its CPU not measured yet or since the last
    #                                             node moved there started (wait)
    CPU_STALE = 'cpu_stale'                     # its CPU reports stopped
    CPU = 'cpu'                                 # used + the unit's CPU > usable
    BANDWIDTH = 'bandwidth'                     # a link it loads would need more than usable
    HYSTERESIS = 'hysteresis'                   # it came back from there within T
    HANDOVER = 'handover'                       # the link from the scale it leaves is down
    SHARE_NOT_HEARD = 'share_not_heard'         # a shared host's claims not reported yet (wait)
    SHARED = 'shared'                           # a shared host lacks room beside others' claims


@dataclass(frozen=True)
class Verdict:
    """One filter's answer, or the first failing one of a chain.

    ``ok``: True passes, False fails, None cannot be told yet (what it needs has not been
    observed): not a no, so a caller that must choose on a full view waits.
    """

    code: Code
    reason: str = ''
    ok: Optional[bool] = True

    @property
    def passed(self) -> bool:
        return self.ok is True

    @property
    def failed(self) -> bool:
        return self.ok is False

    @property
    def waiting(self) -> bool:
        return self.ok is None


PASS = Verdict(Code.OK)


def passes(reason: str = '') -> Verdict:
    return Verdict(Code.OK, reason, True)


def fails(code: Code, reason: str) -> Verdict:
    return Verdict(code, reason, False)


def waits(code: Code, reason: str) -> Verdict:
    return Verdict(code, reason, None)


def first_failing(verdicts: Iterable[Verdict]) -> Verdict:
    """The first verdict that does not pass (later ones are not asked for: pass a generator),
    else a pass whose reason joins those of the passes ('; ')."""
    said = []
    for v in verdicts:
        if not v.passed:
            return v
        if v.reason:
            said.append(v.reason)
    return passes('; '.join(said))


# --- residence ----------------------------------------------------------------------------------

def residence(deployment: Deployment, node: str, scale: str) -> Verdict:
    """``node`` by itself may run on ``scale``: criticality, its residence, the pinning of
    data providers and unmanaged nodes to the master (``Deployment.own_scales``). The reason
    says which of them holds it and where it may run."""
    d = deployment
    own = d.own_scales(node)
    if scale in own:
        return PASS
    where = ', '.join(own) or 'no scale'
    if node in d.critical_nodes:
        why = f'is critical ({d.why_critical(node)}) and must run on {where}'
    elif d.node(node).residence:
        why = f'may run only on {where} (residence)'
    elif not d.node(node).managed:
        why = f'is not managed by an agent and stays on {where}'
    else:
        why = f'is a data provider and stays on {where}'
    return fails(Code.RESIDENCE, why)


def allowed(deployment: Deployment, node: str, scale: str) -> Verdict:
    """``node`` and every node it must share a scale with may run on ``scale``: ``residence``
    of each member of its coresidence group (``Deployment.allowed_scales``, computed once)."""
    if scale in deployment.allowed_scales(node):
        return PASS
    return fails(Code.RESIDENCE, 'not allowed there')


# --- coresidence --------------------------------------------------------------------------------

def apart(deployment: Deployment, node: str, scale: str, placed: Mapping[str, str],
          among: Optional[Sequence[str]] = None) -> Tuple[str, ...]:
    """The nodes ``node`` must share a scale with (its coresidence group, or only ``among``)
    that ``placed`` puts somewhere other than ``scale``; unplaced ones are not counted."""
    group = deployment.coresidence_group(node) if among is None else among
    return tuple(m for m in group
                 if m != node and m in placed and placed[m] != scale)


def coresidence(deployment: Deployment, node: str, scale: str,
                placed: Mapping[str, str]) -> Verdict:
    """``node`` on ``scale`` beside every node it must share a scale with, where ``placed``
    has them."""
    away = apart(deployment, node, scale, placed)
    if not away:
        return PASS
    return fails(Code.CORESIDENCE, 'must share a scale with '
                 + ', '.join(f'{m} (on {placed[m]})' for m in away))


__all__ = ['Code', 'PASS', 'Verdict', 'allowed', 'apart', 'coresidence', 'fails',
           'first_failing', 'passes', 'residence', 'waits']
