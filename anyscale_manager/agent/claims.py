"""The agent of a shared scale starts or activates a copy only under a claim of the host's
ledger (agent/ledger.py); what it may not start is held back, said and reported.

``HostClaims.gate`` takes the processes the agent's turn wants and its lifecycle goals, and
returns them with what the ledger refuses taken out: a copy not started yet is not started, a
standby copy whose activation does not fit stays inactive. A live copy keeps running whatever
the ledger says (its claim was granted when it started; nothing running is lost). A copy that is
gone releases its claim. Its deployment's claims are renewed every quarter of a lease.
"""

import math
from typing import Callable, Dict, List, Optional, Set, Tuple

from ..model.types import Deployment
from ..protocol import HostShare, LifecycleState, ShareClaim
from . import lifecycle as lc
from .ledger import Claim, HostFigure, Ledger, LedgerError, Share

LogLine = Tuple[str, str]


class HostClaims:
    """One agent's claims on its shared host."""

    def __init__(self, ledger: Ledger, deployment: Deployment, scale: str):
        self.ledger = ledger
        self.deployment = deployment
        self.scale = scale
        self.held: Dict[str, Claim] = {}         # node -> the claim granted to its copy here
        self.refused: Dict[str, str] = {}        # node -> why it may not start or serve here
        self.waiting: Dict[str, str] = {}        # node -> the preemption it waits for
        self.figure: Optional[HostFigure] = None
        self.share: Optional[Share] = None
        self._renewed = -math.inf
        self._said: Dict[str, str] = {}
        self._report: Optional[HostShare] = None
        self.report_changed = False             # by the last gate: the agent publishes anew

    def begin(self, now: float) -> List[LogLine]:
        """Join the host; a copy this agent adopts keeps the claim it had, and the waits of
        an agent before it go (``Ledger.forget_waits``)."""
        scale = self.deployment.scale(self.scale)
        self.figure = self.ledger.join(scale.capacity_cpu, scale.memory_mb,
                                       self.deployment.priority, now)
        self.ledger.forget_waits(now)
        self.held = self.ledger.own(now)
        self._renewed = now
        self.share = self.ledger.share(now)
        self._report = self._build_report()
        logs = [('info', f'shared scale: claims in {self.ledger.path}; host capacity '
                         f'{self.figure.capacity_cpu:g} CPU'
                         + (f', {self.figure.memory_mb:g} MiB' if self.figure.memory_mb else '')
                         + (f'; adopted claims: {", ".join(sorted(self.held))}'
                            if self.held else ''))]
        if self.figure.disagreement:
            logs.append(('warn', f'scales.{self.scale}: {self.figure.disagreement}'))
        return logs

    def claim_for(self, name: str, active: bool) -> Claim:
        node = self.deployment.node(name)
        return Claim(self.deployment.name, name, node.cpu if active else 0.0, node.memory_mb,
                     self.deployment.priority, active)

    def gate(self, now: float, want: Set[str], goals: Dict[str, Optional[LifecycleState]],
             live: Callable[[str], bool],
             serving: Callable[[str], bool] = lambda name: False) -> List[LogLine]:
        """Take out of ``want`` and ``goals`` (in place) what the host's claims do not allow;
        release the claims of copies gone. ``live(name)``: its process runs here;
        ``serving(name)``: its copy may still be active (a copy being deactivated keeps its
        active claim until it is inactive, so that its room is not handed on while it serves)."""
        logs: List[LogLine] = []
        try:
            for name in sorted(set(want) | set(self.held) | set(self.waiting)):
                self._gate_one(name, now, want, goals, live, serving, logs)
            if now - self._renewed >= self.ledger.lease_s / 4:
                self.ledger.renew(now)
                self._renewed = now
            self.share = self.ledger.share(now)     # a read: no lock
        except LedgerError as e:
            # Nothing new starts without a claim; what runs keeps running.
            for name in list(want):
                if not live(name) and name not in self.held:
                    want.discard(name)
                    self.refused[name] = f'the claims ledger fails: {e}'
            logs.append(('error', str(e)))
        report = self._build_report()
        self.report_changed = report != self._report
        self._report = report
        return logs

    def _gate_one(self, name: str, now: float, want: Set[str],
                  goals: Dict[str, Optional[LifecycleState]], live: Callable[[str], bool],
                  serving: Callable[[str], bool], logs: List[LogLine]) -> None:
        if name not in want:
            self.refused.pop(name, None)
            self._withdraw(name, now)
            if name in self.held and not live(name):
                self.ledger.release(name, now)
                del self.held[name]
                logs.append(('info', f'{name}: its copy is gone; its claim released'))
            return
        goal = goals.get(name, lc.ACTIVE)
        # A copy kept as it is (goal None: before the first layout) claims as it may serve:
        # one adopted in an unknown state, or active, holds its room; a standby copy just
        # started here does not (it would ask others to leave before any layout placed it).
        wanted = self.claim_for(name, goal == lc.ACTIVE or (goal is None and serving(name)))
        held = self.held.get(name)
        if held == wanted or (held is not None and held.active and not wanted.active
                              and serving(name)):
            self._withdraw(name, now)
            return
        answer = self.ledger.claim(wanted, now)
        if answer.granted:
            self.held[name] = wanted
            self.refused.pop(name, None)
            self.waiting.pop(name, None)
            self._say(name, 'info', f'{name}: {answer.reason}', logs)
            return
        (self.waiting if answer.waiting else self.refused)[name] = answer.reason
        (self.refused if answer.waiting else self.waiting).pop(name, None)
        self._say(name, 'warn', f'{name}: not started or activated here: {answer.reason}', logs)
        if name in self.held:                  # its standby copy stays as it is
            goals[name] = lc.INACTIVE
        elif live(name):
            # A copy running with no claim (the ledger lost it): it keeps running, unclaimed.
            return
        else:
            want.discard(name)
            if name in goals:
                goals[name] = lc.FINALIZED

    def _withdraw(self, name: str, now: float) -> None:
        """No longer wait for room for ``name``: the reservation that waiting held goes."""
        if name in self.waiting:
            self.ledger.withdraw(name, now)
            del self.waiting[name]

    def report(self) -> Optional[HostShare]:
        """The host as this agent sees it, for its report (None before it joined), as of the
        last gate."""
        return self._report

    def _build_report(self) -> Optional[HostShare]:
        share = self.share
        if share is None:
            return None
        return HostShare(
            capacity_cpu=share.capacity_cpu, memory_mb=share.memory_mb,
            # What others wait for is theirs too, for this deployment's decider.
            claims={f'{c.deployment}/{c.node}': ShareClaim(c.cpu, c.memory_mb, c.priority,
                                                           c.active)
                    for c in share.others + share.reserved},
            refused=dict(self.refused), waiting=dict(self.waiting), asked=dict(share.asked))

    def _say(self, name: str, level: str, text: str, logs: List[LogLine]) -> None:
        if self._said.get(name) != text:
            self._said[name] = text
            logs.append((level, text))
