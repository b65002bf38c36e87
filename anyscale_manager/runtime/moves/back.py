"""Algorithm 1's violation branch: the nodes that cause a violation leave the scale they are
on, for the next-best scale or the master."""

import math
from typing import Dict, List, Mapping, Sequence, Tuple

from ..constraints import CPU, FREQUENCY, LINK_DOWN, ConstraintReport, node_cpu, required_kbps
from ..filters import Snapshot
from ..observations import MIGRATE_BACK, MOVE_AWAY, Decision
from ..upstream import UpstreamWatch
from .next_best import next_best
from .state import Step


def migrate_back(step: Step, snap: Snapshot, upstream: UpstreamWatch,
                 already: Sequence[Decision]) -> Tuple[List[Decision], bool]:
    """Algorithm 1's violation branch. Returns the moves and whether any was called for.

    While the master's agent is silent a move back is called for but not made (nothing
    could start the node there): the layout is kept, and the notes say why."""
    d, s, obs, memory, master = step.deployment, step.settings, step.obs, step.memory, step.master
    running, report, notes = step.running, snap.report, step.notes
    taken = {x.node for x in already}
    out: List[Decision] = []
    actionable = False
    migrated = [n for n, _ in memory.migrated]
    # Where every node will be once the moves asked for (earlier, and in this step) are
    # made: what the next-best scale is judged against.
    placed = dict(running)
    for n, (where, _) in memory.pending.items():
        if n in placed:
            placed[n] = where
    for x in already:
        placed[x.node] = x.to_scale
    sent: Dict[str, float] = {}                     # scale -> CPU sent there this step

    def beyond(node: str, far: Sequence[str]) -> bool:
        # Placed beyond a link: where it is sent, else where it runs. A node already sent
        # to this side of the link is not, though its old copy beyond it is reported
        # running until the new one serves (a turn a moment later would send it again).
        return (memory.desired.get(node) or running.get(node)) in far

    def back(node: str, reason: str) -> None:
        if node in taken or node not in migrated:
            return
        taken.add(node)
        # Every managed node has a desired scale; what runs is the fallback.
        leaving = memory.desired.get(node) or running.get(node, '')
        target, why = next_best(step, snap, placed, node, leaving, sent)
        placed[node] = target         # one held for the master counts as back too
        if target == master:
            if step.hold_for_master(node):
                return
            out.append(Decision(MIGRATE_BACK, node, leaving, master, reason + (
                f'; no other scale may take it ({why})' if why else '')))
        else:
            out.append(Decision(MOVE_AWAY, node, leaving, target,
                                f'{reason}; {node} to {target}, the next-best scale: {why}'))
        sent[target] = sent.get(target, 0.0) + node_cpu(d, s, obs, node)

    # A link down (or silent) brings back at once everything placed beyond it, running
    # or still starting there: waiting for the connections' Δ would be too late.
    for link_name, load in report.links.items():
        if load.up or master not in load.ends:
            continue        # a link between two remote scales: the do-while below
        far = [e for e in load.ends if e != master]
        placed_beyond = [n for n in migrated if beyond(n, far)]
        if placed_beyond:
            actionable = True
            reason = load.reason or f'link {link_name} down'
            quiet = [e for e in far if e in obs.silent_agents]
            if quiet:
                reason += (f' and the agent of {", ".join(quiet)} is silent too: a cut link '
                           f'and a dead agent look alike from {master}')
            for n in placed_beyond:
                back(n, reason)
    for v in report.of_kind(LINK_DOWN, FREQUENCY):
        if v.kind == LINK_DOWN and master not in report.links[v.subject].ends:
            continue        # only the connections crossing it move: the do-while below
        explained = upstream.explains(obs, running, v.subject) if v.kind == FREQUENCY else ''
        if explained:
            notes.append(f'{v.subject} below freq_min, explained upstream: {explained}; '
                         'nothing moved for it')
            continue
        culprits = [n for n in v.nodes if n in migrated]
        if v.kind == LINK_DOWN:
            far = [e for e in report.links[v.subject].ends if e != master]
            culprits = [n for n in culprits if beyond(n, far)]
        actionable = actionable or bool(culprits)
        for n in culprits:
            back(n, v.reason)
    for v in report.of_kind(CPU):
        culprits = [n for n in reversed(migrated) if n in v.nodes]
        if not culprits:
            continue
        actionable = True
        # One node at a time, and not before the CPU freed by the last one leaving this
        # scale can show in its measurement (the grace period).
        left = [n for n, (where, _) in memory.pending.items() if running.get(n) == v.subject
                and where != v.subject]
        recent = [n for n, t in memory.last_move.items() if n not in migrated
                  and obs.now - t < s.grace_s]
        # Nor within the grace period of a node's arrival there: a process starting (a
        # Python node: about a core for a second) is not the load it will be.
        settling = [n for n in culprits
                    if obs.now - memory.last_move.get(n, -math.inf) < s.grace_s]
        if not left and not recent and not settling \
                and not any(n in taken for n in culprits):
            back(culprits[0], v.reason + f'; {culprits[0]} was the last moved there')
    # do ... while required_BW > network_BW: pick, among the migrated nodes crossing an
    # overloaded link, the one whose return frees the most bandwidth on it (ties: the most
    # recently migrated), until every link fits. Moves already asked for count as done.
    # A link between two remote scales that is down carries nothing: what crosses it
    # moves, one node at a time, to where nothing does (the rest stays where it is).
    # An overloaded link that no move can relieve (what crosses it is pinned there, or
    # already moving) does not hold back the others.
    for _ in range(len(migrated) + 1):
        pick = None
        for link_name, required, usable in overloaded_links(step, report, placed):
            best, best_gain = None, 0.0
            for n in reversed(migrated):
                if n in taken or placed.get(n, master) == master:
                    continue
                where, _ = next_best(step, snap, placed, n, placed[n], sent)
                trial = dict(placed, **{n: where})
                gain = required - required_kbps(d, trial)[link_name]
                if gain > best_gain:
                    best, best_gain = n, gain
            if best is not None:
                pick = (link_name, required, usable, best, best_gain)
                break
        if pick is None:
            break
        link_name, required, usable, best, best_gain = pick
        actionable = True
        load = report.links[link_name]
        if not load.up:
            back(best, f'{load.reason}: {required:.0f} kbit/s cross it; {best} frees '
                       f'{best_gain:.0f} kbit/s')
        else:
            back(best, f'link {link_name}: required {required:.0f} kbit/s > usable '
                       f'{usable:.0f} kbit/s{load.cap_note}; {best} frees '
                       f'{best_gain:.0f} kbit/s')
    return out, actionable


def overloaded_links(step: Step, report: ConstraintReport,
                     running: Mapping[str, str]) -> List[Tuple[str, float, float]]:
    """(link, required, usable) of each link that ``running`` loads beyond its usable
    bandwidth: a link from the master that is down is not watched (what is beyond it comes
    back as a whole); one between two remote scales that is down has usable 0."""
    required = required_kbps(step.deployment, running)
    out = []
    for name, load in report.links.items():
        watched = load.up or step.master not in load.ends     # down: usable 0
        if watched and required[name] > load.usable_kbps:
            out.append((name, required[name], load.usable_kbps))
    return out
