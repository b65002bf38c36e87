"""Algorithm 1's else branch: at most one node (or coresidence group) moves out of the master."""

from typing import List

from ..filters import Candidate, Snapshot, can_host, hysteresis
from ..observations import MIGRATE, Decision
from ..scores import by_worth
from .rebalance import rebalance
from .state import Step
from .units import candidate_units, unit_text


def migrate_out(step: Step, snap: Snapshot) -> List[Decision]:
    """The migratable nodes on the master by CPU, largest first, each to the remote scale
    worth most (Deployment.worth; by default the most powerful) that can host it now and that
    T does not hold it back from; the first that fits moves. Nothing moves while the master's
    agent is silent, a move is pending, or the master's CPU has not been reported yet (within
    the start-up allowance), and a scale that cannot be told yet holds the whole move out.
    Nor while the graph comes up: a monitored connection whose nodes run and that was never
    heard, within ``bringup_s`` of the start. When none moves: ``rebalance``."""
    d, s, now, master, notes = step.deployment, step.settings, step.now, step.master, step.notes
    if not s.migration:
        return []
    why = step.agent_silent(master)
    if why:
        notes.append(f'no move out: {why}, nothing could stop the copy left on {master}')
        return []
    if step.memory.pending:
        notes.append('waiting for ' + ', '.join(
            f'{n} to run on {x}' for n, (x, _) in sorted(step.memory.pending.items())))
        return []
    if master not in step.obs.scales and snap.since_start <= s.observation_max_age_s:
        # The nodes are ranked by their measured CPU: give the master's scale monitor the
        # same start-up allowance as every other observation (after it, nominal CPU).
        notes.append(f'waiting for a first CPU report from {master} (nodes are ranked '
                     f'by measured CPU)')
        return []
    unheard = step.unheard()
    if unheard and snap.since_start < s.bringup_s:
        # The graph boots: a node moved now would be judged on inputs that never came (its
        # output 0 Hz past Δ once its grace ends) and sent back.
        notes.append(f'no move out while the graph comes up: {", ".join(unheard)} not heard '
                     f'yet ({snap.since_start:.0f} of bringup_s {s.bringup_s:g} s)')
        return []
    last_back = step.memory.last_back
    remotes = by_worth(d, [x.name for x in d.remote_scales])
    for unit, cpu in candidate_units(step):
        if s.hysteresis_scope == 'node':
            held = hysteresis(last_back, s.hysteresis_s, unit, None, now)
            if not held.passed:
                notes.append(held.reason)
                continue
        for scale in remotes:
            held = hysteresis(last_back, s.hysteresis_s, unit, scale, now)
            if not held.passed:
                notes.append(held.reason)
                continue
            verdict = can_host(snap, Candidate(unit, scale, cpu, step.running))
            if verdict.waiting:
                # Not a no: not known yet. Picking another scale or node now would be a
                # choice made on a partial view, so the move out waits for the observation.
                notes.append(f'{unit[0]} -> {scale}: waiting: {verdict.reason}')
                return []
            if verdict.failed:
                notes.append(f'{unit[0]} -> {scale}: {verdict.reason}')
                continue
            reason = (f'{unit_text(unit)}: CPU {cpu:.0f}, the most CPU-intensive '
                      f'migratable node that fits, to {scale} (worth {d.worth(scale):g}): '
                      f'{verdict.reason}')
            return [Decision(MIGRATE, n, master, scale, reason) for n in unit]
    return rebalance(step, snap)
