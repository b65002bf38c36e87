"""What the decider says when an agent goes silent, comes back, or a node has nowhere to go.

Pure (no ROS, time from the observations). A silent agent is not a silent link: each agent
hosts its scale's monitors (the master's hosts the link monitor), so when an agent stops
reporting, what it measured stops with it. The policy draws the consequences (nothing is placed
on a scale whose agent is silent; the master's silence keeps the layout as it is); this class
turns them into notices on change, not every turn, and a one-line summary for /diagnostics.

- ``agent_silent`` (warn): an agent not heard for ``observation_max_age_s``, saying whether the
  link to its scale is up (then it is the agent, not the link), down (the two look alike from
  the master) or not judged;
- ``scale_lost`` (warn): silent past ``agent_timeout_s``: a remote scale's nodes count as not
  running and are placed elsewhere where allowed; the master's are kept;
- ``agent_back`` (info): heard again, with how long it was silent;
- ``unplaceable`` (error): a node that no scale with a live agent and a reachable link may host
  (``MigrationPolicy.unplaceable``), with the reason; ``placeable`` (info) when that ends;
- ``node_exit`` (error): a copy that stopped against its will (a node whose script is missing
  exits at once, and again at each restart), with its exit code and the last line of its log
  as its agent read them: said once, until that copy serves again.
"""

from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Set, Tuple

from ..model.types import DeciderSettings, Deployment
from ..protocol import ERROR, OK, WARN, ProcState
from .constraints import ConstraintReport
from .observations import CopyObs, Observations

AGENT_SILENT = 'agent_silent'
AGENT_BACK = 'agent_back'
SCALE_LOST = 'scale_lost'
UNPLACEABLE = 'unplaceable'
PLACEABLE = 'placeable'
NODE_EXIT = 'node_exit'


@dataclass(frozen=True)
class Notice:
    """One change worth an event: ``scale`` is the scale concerned (for a node: where the
    layout places it)."""

    kind: str
    level: str          # info | warn | error
    scale: str
    node: str
    text: str


class LivenessWatch:
    """Silent agents, lost scales and unplaceable nodes, announced as they start and end."""

    def __init__(self, deployment: Deployment, settings: DeciderSettings):
        self.deployment = deployment
        self.settings = settings
        self.master = deployment.master.name
        self.silent_since: Dict[str, float] = {}    # scale -> when its agent fell silent
        self.lost: Dict[str, float] = {}            # scale -> when it was declared lost
        self.unplaceable: Dict[str, str] = {}       # node -> why
        self.exited: Set[Tuple[str, str]] = set()   # (node, scale) whose exit was said
        self.now = 0.0

    def update(self, obs: Observations, unplaceable: Mapping[str, str],
               report: Optional[ConstraintReport] = None,
               layout: Optional[Mapping[str, str]] = None) -> List[Notice]:
        """The notices of this turn (what changed since the last one)."""
        now = self.now = obs.now
        layout = layout or {}
        out: List[Notice] = []
        timeout = self.settings.agent_timeout_s
        for scale in self.deployment.scale_names:
            lost = scale in obs.lost_scales
            silent_s = obs.silent_agents.get(scale, timeout if lost else None)
            if silent_s is not None and scale not in self.silent_since:
                self.silent_since[scale] = now - silent_s
                out.append(Notice(AGENT_SILENT, 'warn', scale, '',
                                  self._silent_text(scale, silent_s, report)))
            if lost and scale not in self.lost:
                self.lost[scale] = now
                out.append(Notice(SCALE_LOST, 'warn', scale, '', self._lost_text(scale)))
            if silent_s is None and scale in self.silent_since:
                began = self.silent_since.pop(scale)
                self.lost.pop(scale, None)
                text = f'the agent of {scale} reports again after {now - began:.1f} s of silence'
                if scale == self.master:
                    text += ('; its link monitor and probes are judged again once they have '
                             'reported')
                out.append(Notice(AGENT_BACK, 'info', scale, '', text))
        for node, why in unplaceable.items():
            if node not in self.unplaceable:
                where = layout.get(node, '')
                stays = f'; it stays on {where} in the layout' if where else ''
                out.append(Notice(UNPLACEABLE, 'error', where, node,
                                  f'{node} cannot be placed: {why}{stays}'))
        for node in self.unplaceable:
            if node not in unplaceable:
                out.append(Notice(PLACEABLE, 'info', layout.get(node, ''), node,
                                  f'{node} can be placed again'))
        self.unplaceable = dict(unplaceable)
        out += self._exits(obs)
        return out

    def _exits(self, obs: Observations) -> List[Notice]:
        """A copy's exit, said once with what its agent read of it, until it serves again."""
        out: List[Notice] = []
        for node, copies in sorted(obs.copies.items()):
            for scale, c in sorted(copies.items()):
                if c.state == ProcState.RUNNING and c.ready:
                    # Served again: its next exit is news. (A report between two exits of a
                    # crash loop that carries no exit, a copy starting, is not.)
                    self.exited.discard((node, scale))
                    continue
                known = c.exit_code is not None or bool(c.log_tail) \
                    or c.state == ProcState.FAILED
                if c.crashed_at is None or not known or (node, scale) in self.exited:
                    continue
                self.exited.add((node, scale))
                out.append(Notice(NODE_EXIT, 'error', scale, node, exit_text(node, scale, c)))
        return out

    def summary(self) -> Tuple[int, str]:
        """(level, message) for the decider's diagnostics: ERROR while a node cannot be placed,
        WARN while an agent is silent, else (OK, '')."""
        if self.unplaceable:
            return ERROR, 'cannot be placed: ' + '; '.join(
                f'{n} ({why})' for n, why in sorted(self.unplaceable.items()))
        if self.silent_since:
            parts = []
            for scale, began in sorted(self.silent_since.items()):
                what = 'lost' if scale in self.lost else 'silent'
                role = ' (the master: layout kept)' if scale == self.master else ''
                parts.append(f'agent of {scale} {what} for {self.now - began:.1f} s{role}')
            return WARN, '; '.join(parts)
        return OK, ''

    # --- texts ------------------------------------------------------------------------------
    def _silent_text(self, scale: str, silent_s: float,
                     report: Optional[ConstraintReport]) -> str:
        head = f'the agent of {scale}'
        if scale == self.master:
            return (f'{head} (the master scale) has been silent for {silent_s:.1f} s: the link '
                    'monitor and probes it hosts are silent with it, so no link is judged cut '
                    'and no connection it measures is judged; what runs is kept, and nothing '
                    f'is placed on {scale} (no move back to it, none out of it) until it '
                    'reports again')
        tail = (f'nothing is placed on {scale}, and its nodes are placed elsewhere if it stays '
                f'silent past agent_timeout_s ({self.settings.agent_timeout_s:g} s)')
        link = self.deployment.link_between(self.master, scale)
        load = report.links.get(link.name) if report is not None and link is not None else None
        if link is None or load is None:
            return f'{head} has been silent for {silent_s:.1f} s: {tail}'
        if not load.up:
            return (f'{head} has been silent for {silent_s:.1f} s and '
                    f'{load.reason or f"link {link.name} is down"}: a cut link and a dead '
                    f'agent look alike from {self.master}; {tail}')
        if load.observed:
            return (f'{head} has been silent for {silent_s:.1f} s while link {link.name} is '
                    f'up: the agent, not the link; {tail}')
        return f'{head} has been silent for {silent_s:.1f} s (link {link.name} not judged); {tail}'

    def _lost_text(self, scale: str) -> str:
        timeout = self.settings.agent_timeout_s
        if scale == self.master:
            return (f'the agent of {scale} (the master scale) has been silent for more than '
                    f'{timeout:g} s: the nodes it supervised are not supervised (they may still '
                    'run) and count as not running; the layout is kept')
        return (f'scale {scale} lost: its agent has been silent for more than {timeout:g} s; '
                'its nodes count as not running and are placed on scales with a live agent '
                'where allowed')


def exit_text(node: str, scale: str, copy: CopyObs) -> str:
    """'amcl on laptop exited unasked, exit code 2; the last line of its log: ...': one line,
    for an event and for ``status``."""
    reason = copy.exit_reason
    if copy.exit_code is not None:
        text = f'{node} on {scale} exited unasked, exit code {copy.exit_code}'
        said = f'exited with status {copy.exit_code}'     # what the code says already
        if reason.startswith(said + ';'):
            text += f' ({reason[len(said) + 1:].strip()})'  # leftover processes killed
        elif reason and reason != said:
            text += f' ({reason})'
    elif copy.state == ProcState.FAILED:
        text = f'{node} on {scale} cannot be started: {reason or "no reason given"}'
    else:
        text = f'{node} on {scale} exited unasked ({reason or "exit status unknown"})'
    if copy.log_tail:
        text += f'; the last line of its log: {copy.log_tail}'
    elif copy.exit_code is not None:
        text += '; it wrote nothing to its log'
    return text


__all__ = ['LivenessWatch', 'Notice', 'AGENT_SILENT', 'AGENT_BACK', 'SCALE_LOST',
           'UNPLACEABLE', 'PLACEABLE', 'NODE_EXIT', 'exit_text']
