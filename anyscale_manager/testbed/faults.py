"""The chaos soak's faults: one handler per kind of ``chaos.KINDS``, found in ``REGISTRY``.

A handler ``handler(soak, fault, row)`` applies one fault of the schedule to the running
test-bed, waits for the system's reaction within the fault's limit (supervising meanwhile,
through ``soak.wait`` and ``soak.sleep``), undoes the fault, and fills the fault's ``row``:
``reaction`` (what the system must do), ``reaction_s`` (how long it took, None when there was
nothing to react to) and ``outcome``. A reaction not seen in time is ``soak.miss``ed. The rules
and their limits: docs/testbed.md (the chaos soak).
"""

import json
import os
import signal
import time
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Set

from ..agent import procs
from ..model.types import Deployment
from ..runtime.constraints import required_kbps
from . import chaos, harness, netns
from .record import LIVE_STATES, Record
from .verdict import COLD_MOVE_S, resumed_layouts

if TYPE_CHECKING:
    from .soak import Soak

Row = Dict[str, object]
# A tool process of the soak (a hostile publisher, a third decider) gets this long after its
# SIGINT, then SIGKILL.
TOOL_SIGINT_GRACE_S = 5.0
# A lost agent's nodes are gone within adopt_grace_s + fence_grace_s (docs/agent.md, fencing);
# this much more is allowed for the warden's own period and this machine's load.
FENCE_SLACK_S = 1.5
# After an agent's restart in place, a move, a restart or a link report it caused shows within
# this long (a link is judged down within its heartbeats' timeout; the decider turns at once).
HUP_SETTLE_S = 2.0


# --- what runs where ----------------------------------------------------------------------------

def serving(r: Record, scale: str) -> Set[str]:
    return set(r.running_on(scale, ready_only=True))


def remote_only(r: Record) -> List[str]:
    """Nodes serving on the laptop and not on the robot."""
    return sorted(serving(r, 'laptop') - serving(r, 'robot'))


def crossing_kbps(d: Deployment, r: Record) -> float:
    placement = r.placement()
    running = {n: ('robot' if 'robot' in s else s[0]) for n, s in placement.items() if s}
    return sum(required_kbps(d, running).values())


# --- the link -----------------------------------------------------------------------------------

def cut(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb = soak.tb
    with tb.lock:
        remote = remote_only(tb.record)
    tb.cut()
    t_cut = time.monotonic()
    if remote:
        row['reaction'] = f'-> {"+".join(remote)} serving on the robot'
        if soak.wait(lambda r: set(remote) <= serving(r, 'robot'), 20.0) is None:
            soak.miss(row, f'{remote} not serving on the robot 20 s after the cut')
        else:
            with tb.lock:
                t = tb.record.serving_since('robot', remote, t_cut)
            row['reaction_s'] = t - t_cut
    else:
        row['reaction'] = 'nothing served from the laptop'
    soak.sleep(t_cut + f.hold_s - time.monotonic())
    tb.restore()


def throttle(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, d = soak.tb, soak.d
    usable = f.rate_kbps * d.decider.bandwidth_margin
    with tb.lock:
        need = crossing_kbps(d, tb.record)
    tb.throttle(f.rate_kbps)
    t = time.monotonic()
    if need > usable:
        row['reaction'] = f'-> crossing load fits ({need:.0f} kbit/s > usable {usable:.0f})'
        fit = soak.wait(lambda r: crossing_kbps(d, r) <= usable, 30.0)
        if fit is None:
            soak.miss(row, 'the crossing load still above the usable bandwidth 30 s after the '
                           'throttle')
        else:
            row['reaction_s'] = fit - t
    else:
        row['reaction'] = f'fits already ({need:.0f} <= {usable:.0f} kbit/s)'
    soak.sleep(t + f.hold_s - time.monotonic())
    tb.throttle(netns.DEFAULT_RATE_KBPS)


def flap(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb = soak.tb
    with tb.lock:
        remote = remote_only(tb.record)
    t_first = time.monotonic()
    for down, up in f.flaps:
        tb.cut()
        soak.sleep(down)
        tb.restore()
        soak.sleep(up)
    with tb.lock:
        r = tb.record
        moves = len(r.moves(since=t_first))
        back = r.serving_since('robot', remote, t_first) if remote else None
    if remote:
        row['reaction'] = f'-> {"+".join(remote)} serving on the robot'
        if back is not None:
            row['reaction_s'] = back - t_first
        else:
            row['reaction'] = f'{"+".join(remote)} kept on the laptop (no cut seen)'
    else:
        row['reaction'] = 'nothing served from the laptop'
    row['outcome'] = f'{moves} moves'


# --- the agents ---------------------------------------------------------------------------------

def _kill_agent(soak: 'Soak', scale: str, row: Row) -> None:
    tb, d = soak.tb, soak.d
    name = f'agent_{scale}'
    with tb.lock:
        before = {n: rep.pid for n, rep in tb.record.copies(scale).items()}
        serving_before = set(tb.record.running_on(scale, ready_only=True))
    soak.kill(name)
    t_kill = time.monotonic()
    row['reaction'] = '-> a new agent reporting its copies'

    def back(r: Record) -> bool:
        new = tb.procs.get(name)
        if new is None or new.started <= t_kill:
            return False
        reports = [st for t, st in r.agent_states.get(scale, []) if t > new.started]
        if not reports:
            return False
        nodes = reports[-1].nodes
        live = all(n in nodes and nodes[n].state in LIVE_STATES for n in before)
        placed = set().union(*(serving(r, s) for s in d.scale_names))
        return live and serving_before <= placed
    t = soak.wait(back, 40.0)
    if t is None:
        soak.miss(row, f'no new {scale} agent reporting {sorted(before)} live 40 s after the '
                       'kill')
        return
    row['reaction_s'] = t - t_kill
    with tb.lock:
        now = tb.record.agent_states[scale][-1][1].nodes
    adopted = sorted(n for n, pid in before.items() if now[n].pid == pid)
    other = sorted(set(before) - set(adopted))
    row['outcome'] = f'adopted {len(adopted)}/{len(before)}' + (
        f'; new processes for {", ".join(other)}' if other else '')


def lose_agent_laptop(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    """The laptop's agent SIGKILLed with no successor for ``f.hold_s``: its nodes must stop
    by themselves within the fencing bound (adopt_grace_s + fence_grace_s, with slack for this
    machine), what it served must serve on the robot, and two copies never serve at once
    (judged on what the observer heard). The agent that comes back starts fresh copies."""
    tb, d = soak.tb, soak.d
    name = 'agent_laptop'
    with tb.lock:
        copies = sorted(tb.record.copies('laptop'))
        remote = remote_only(tb.record)
    soak.kill(name, restart_after_s=f.hold_s)
    t_kill = time.monotonic()
    bound = d.agent.adopt_grace_s + d.agent.fence_grace_s + FENCE_SLACK_S
    row['reaction'] = (f'-> {"+".join(remote)} serving on the robot; ' if remote else '-> ') + \
        f'its copies of {", ".join(copies) or "nothing"} gone within {bound:g} s'
    if remote:
        t = soak.wait(lambda r: set(remote) <= serving(r, 'robot'), bound + 20.0)
        if t is None:
            soak.miss(row, f'{remote} not serving on the robot {bound + 20.0:g} s after the '
                           'laptop agent was lost')
        else:
            with tb.lock:
                t = tb.record.serving_since('robot', remote, t_kill) or t
            row['reaction_s'] = t - t_kill
    gone = soak.wait(lambda _r: not any(tb.node_pids(n, 'laptop') for n in copies),
                     bound + 10.0)
    if gone is None or gone - t_kill > bound:
        soak.tally.unfenced += 1
        left = {n: tb.node_pids(n, 'laptop') for n in copies}
        soak.log(f'!! fault {f.index}: the nodes of the lost laptop agent still ran '
                 f'{bound:g} s after it died: {left}')
    fenced = 'not gone' if gone is None else f'gone after {gone - t_kill:.2f} s'
    soak.sleep(t_kill + f.hold_s - time.monotonic())

    def fresh(r: Record) -> bool:
        new = tb.procs.get(name)
        if new is None or new.started <= t_kill:
            return False
        reports = [st for t, st in r.agent_states.get('laptop', []) if t > new.started]
        return bool(reports) and all(n in reports[-1].nodes and reports[-1].nodes[n].state
                                     in LIVE_STATES for n in copies)
    t_new = soak.wait(fresh, 40.0)
    row['outcome'] = f'its copies {fenced}; ' + (
        'a new agent with fresh copies' if t_new is not None else 'NO new agent reporting')
    if t_new is None:
        soak.miss(row, f'no new laptop agent reporting {copies} live 40 s after its restart')


def _hup_agent(soak: 'Soak', scale: str, row: Row) -> None:
    """SIGHUP: the agent restarts in place (same process, new instance) and adopts its
    nodes; nothing may move, restart or be reported cut."""
    tb = soak.tb
    name = f'agent_{scale}'
    with tb.lock:
        last = tb.record.agent_state_at(scale)
        instance = last.instance if last is not None else None
        pids = {n: rep.pid for n, rep in tb.record.copies(scale).items()}
    pid = tb.procs[name].popen.pid
    os.kill(pid, signal.SIGHUP)
    t_hup = time.monotonic()
    tb.mark(f'{name} sent SIGHUP')
    row['reaction'] = '-> the same agent back in place, nothing moved or restarted'

    def back(r: Record) -> bool:
        history = r.agent_states.get(scale, [])
        return bool(history) and history[-1][0] > t_hup and history[-1][1].instance != instance
    t = soak.wait(back, 30.0)
    if t is None:
        soak.miss(row, f'the {scale} agent not back 30 s after its SIGHUP')
        return
    row['reaction_s'] = t - t_hup
    soak.sleep(HUP_SETTLE_S)         # what the restart would cause shows within this
    with tb.lock:
        r = tb.record
        now = {n: rep.pid for n, rep in r.copies(scale).items()}
        moves = [(e.kind, e.node) for _, e in r.moves(since=t_hup)]
        downs = sum(1 for t_s, st in r.link_status if t_s >= t_hup and not st.up)
    restarted = sorted(n for n, p in pids.items() if now.get(n) != p)
    same = tb.procs[name].popen.pid == pid and tb.procs[name].popen.poll() is None
    row['outcome'] = (f'{"same process" if same else "a NEW process"}; moves {len(moves)}, '
                      f'nodes restarted {len(restarted)}, link down reports {downs}')
    if restarted or moves or downs or not same:
        soak.tally.restart_harm += 1
        soak.log(f'!! {name} restarted in place: moves {moves}, restarted {restarted}, link '
                 f'down reports {downs}, same process {same}')


def hup_agent_laptop(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    _hup_agent(soak, 'laptop', row)


def hup_agent_robot(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    _hup_agent(soak, 'robot', row)


def kill_agent_laptop(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    _kill_agent(soak, 'laptop', row)


def kill_agent_robot(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    _kill_agent(soak, 'robot', row)


# --- the deciders -------------------------------------------------------------------------------

def kill_decider(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, d, tally = soak.tb, soak.d, soak.tally
    name = soak.leader() or 'decider'
    killed = soak.kill(name)
    t_kill = time.monotonic()
    row['what'] = f'SIGKILL the leading decider ({name})'
    row['reaction'] = '-> the other decider publishing'

    def new_ids(r: Record) -> Set[str]:
        return {lay.decider.id for t, lay in r.layouts if t > t_kill and lay.decider
                and lay.decider.pid in tally.decider_pids and lay.decider.pid != killed}
    t_pub = soak.wait(lambda r: bool(new_ids(r)), 45.0)
    if t_pub is None:
        soak.miss(row, 'no layout from another decider 45 s after the kill')
        return
    row['reaction_s'] = t_pub - t_kill

    def followed(r: Record) -> bool:
        ids = new_ids(r)
        return all(r.agent_state_at(s) is not None and r.agent_state_at(s).decider in ids
                   for s in d.scale_names)
    t_follow = soak.wait(followed, 20.0)
    with tb.lock:
        moves = len(tb.record.moves(since=t_kill))
    row['outcome'] = (f'agents following it after {t_follow - t_kill:.2f} s'
                      if t_follow is not None else 'agents NOT following it') + \
        f'; {moves} moves'
    if t_follow is None:
        soak.miss(row, 'agents not following the new decider 20 s after it published')


def stop_decider(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, tally = soak.tb, soak.tally
    name = soak.leader() or 'decider'
    stopped = tb.procs[name].popen.pid
    with tb.lock:
        ids = {lay.decider.id for _, lay in tb.record.layouts
               if lay.decider and lay.decider.pid == stopped}
    os.kill(stopped, signal.SIGSTOP)
    t_stop = time.monotonic()
    row['what'] = f'SIGSTOP the leading decider ({name}) for {f.hold_s:.1f} s'
    row['reaction'] = '-> the other decider publishing'
    try:
        t_pub = soak.wait(lambda r: any(
            t > t_stop and lay.decider and lay.decider.pid in tally.decider_pids
            and lay.decider.pid != stopped for t, lay in r.layouts), 20.0)
        if t_pub is not None:
            row['reaction_s'] = t_pub - t_stop
        soak.sleep(t_stop + f.hold_s - time.monotonic())
    finally:
        wall_cont = time.time()
        os.kill(stopped, signal.SIGCONT)
    t_cont = time.monotonic()
    if t_pub is None:
        soak.miss(row, 'no layout from another decider 20 s after the SIGSTOP')
        return
    # Resumed, it must stand by: no layout composed after the resume, no agent following it
    # again. Its last layout before the stop may arrive late (a retransmission): listed.
    soak.sleep(2.0)
    with tb.lock:
        stale, late = resumed_layouts(tb.record.layouts, stopped, t_cont, wall_cont)
        followed = sorted({scale for scale, history in tb.record.agent_states.items()
                           for t, st in history if t > t_cont + 1.0 and st.decider in ids})
    row['outcome'] = (f'resumed after {t_cont - t_stop:.1f} s: {stale} layouts of its own'
                      + (f' ({late} from before the stop heard late)' if late else '')
                      + f'; agents following it again: {", ".join(followed) or "none"}')
    if stale or followed:
        tally.stale_leader += 1
        soak.log(f'!! {name} resumed: {stale} layouts composed, followed by '
                 f'{followed or "none"}')


def rival_decider(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, tally = soak.tb, soak.tally
    name = f'decider_rival_{f.index}'
    # Outside the robot's CPU quota: a Python process starting inside it also starved the
    # robot agent's probes past AR's Δ once (1 of 7 starts), a load the restarts of the
    # decider and the agents, in the quota as systemd would start them, already bring.
    proc = tb.start_decider(name, quota=False)
    proc.expected_exit = True
    tally.rival_pids.add(proc.popen.pid)
    t = time.monotonic()
    limit = soak.d.decider.discovery_s + 20.0
    row['reaction'] = '-> a third decider stands by'
    said = 'standing by for decider'
    done = soak.wait(lambda _r: said in harness.tail(proc.log_path, 40)
                     or proc.popen.poll() is not None, limit)
    row['reaction_s'] = None if done is None else done - t
    # It stands by a little longer, then is stopped as a person would (SIGINT).
    soak.sleep(2.0)
    code = procs.stop_popen(proc.popen, TOOL_SIGINT_GRACE_S, session=False)
    with tb.lock:
        published = sum(1 for _, lay in tb.record.layouts
                        if lay.decider and lay.decider.pid == proc.popen.pid)
    row['outcome'] = f'{published} layouts published; exit {code}'
    if done is None or published or code != 0:
        tally.rival_misbehaved += 1
        soak.log(f'!! {name}: {"did not stand by; " if done is None else ""}{published} '
                 f'layouts published, exit {code}:\n{harness.tail(proc.log_path)}')


# --- the nodes and the protocol -----------------------------------------------------------------

def kill_node(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, d = soak.tb, soak.d
    node = f.node

    def where(r: Record) -> Optional[str]:
        if f.copy != 'standby':
            return _serving_on_one(d, r, node)
        found = [s for s in d.scale_names if node in r.standby_on(s)]
        return found[0] if len(found) == 1 else None
    if soak.wait(lambda r: where(r) is not None, 10.0) is None:
        row['outcome'] = f'skipped: no single {f.copy} copy of {node} within 10 s'
        return
    with tb.lock:
        scale = where(tb.record)
        standby_elsewhere = _standby_elsewhere(d, tb.record, node, scale)
    try:
        pid = tb.kill_node(node, scale, signal.SIGKILL)
    except harness.HarnessError as e:
        row['outcome'] = f'skipped: {e}'
        return
    t_kill = time.monotonic()
    row['what'] = f'{row["what"]} on the {scale}'
    if f.copy == 'standby':
        row['reaction'] = '-> a new standby copy'

        def back(r: Record) -> bool:
            rep = r.copies(scale).get(node)
            return rep is not None and rep.pid != pid and rep.state == 'standby'
    else:
        row['reaction'] = '-> serving again'
        back = _served_again(d, node, pid)
    t = soak.wait(back, 30.0)
    if t is None:
        soak.miss(row, f'{node} not back 30 s after the kill')
    else:
        row['reaction_s'] = t - t_kill
        with tb.lock:
            where_now = [s for s in d.scale_names if node in serving(tb.record, s)]
        row['outcome'] = f'serving on {"+".join(where_now) or "-"}'
    if f.copy != 'standby' and not standby_elsewhere:
        _excuse_cold_restart(soak, f, node, t_kill, t)


def _serving_on_one(d: Deployment, r: Record, node: str) -> Optional[str]:
    """The one scale that serves ``node``, or None when none or several do."""
    found = [s for s in d.scale_names if node in serving(r, s)]
    return found[0] if len(found) == 1 else None


def _served_again(d: Deployment, node: str, pid: int) -> Callable[[Record], bool]:
    """``node`` served somewhere by another process than ``pid`` (the one killed)."""
    def back(r: Record) -> bool:
        return any(node in (reps := r.running_on(s, ready_only=True))
                   and reps[node].pid != pid for s in d.scale_names)
    return back


def _standby_elsewhere(d: Deployment, r: Record, node: str, scale: str) -> bool:
    """A standby copy of ``node`` on another scale: its serving copy's crash is then a
    failover, judged like any other fault (no Δ excused)."""
    return any(node in r.standby_on(s) for s in d.scale_names if s != scale)


def _excuse_cold_restart(soak: 'Soak', f: chaos.Fault, node: str, t_kill: float,
                         t_back: Optional[float]) -> None:
    """A serving copy with no standby anywhere was killed: it can only start again cold,
    so what it fed is not judged until it serves again, plus a rate window and the longest
    Δ."""
    d = soak.d
    margin = d.monitoring.probe_window_s + max(c.tolerance_s or 0.0 for c in d.connections)
    conns = [(c.name, c.publisher, c.subscriber) for c in d.connections]
    soak.tally.excuses.append(chaos.kill_excuse(
        conns, node, t_kill, t_back if t_back is not None else t_kill + COLD_MOVE_S,
        margin + 1.0, f'fault {f.index}: {node} killed (no standby copy)'))


def crash_loop(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    """The serving copy of one node SIGKILLed CRASH_LOOP_KILLS times, each time once it
    serves again: it must serve again after every crash (a standby copy taking over where
    one exists, else a restart in place), and never be served nowhere past the bound."""
    tb, d = soak.tb, soak.d
    node = f.node
    row['reaction'] = f'-> {node} serving again after each crash'
    times: List[float] = []
    places: List[str] = []
    for k in range(chaos.CRASH_LOOP_KILLS):
        if soak.wait(lambda r: _serving_on_one(d, r, node) is not None, 30.0) is None:
            soak.miss(row, f'{node} not serving on exactly one scale before crash {k + 1}')
            return
        with tb.lock:
            scale = _serving_on_one(d, tb.record, node)
            standby_elsewhere = _standby_elsewhere(d, tb.record, node, scale)
        try:
            pid = tb.kill_node(node, scale, signal.SIGKILL)
        except harness.HarnessError as e:
            soak.miss(row, f'crash {k + 1} of {node} on the {scale}: {e}')
            return
        t_kill = time.monotonic()
        t = soak.wait(_served_again(d, node, pid), 30.0)
        if not standby_elsewhere:
            _excuse_cold_restart(soak, f, node, t_kill, t)
        if t is None:
            soak.miss(row, f'{node} not serving 30 s after crash {k + 1}')
            return
        times.append(t - t_kill)
        with tb.lock:
            places.append('+'.join(s for s in d.scale_names if node in serving(tb.record, s)))
    row['reaction_s'] = max(times)
    row['outcome'] = 'serving again after ' + ', '.join(
        f'{x:.2f} s on {where}' for x, where in zip(times, places))


def hostile(soak: 'Soak', f: chaos.Fault, row: Row) -> None:
    tb, d = soak.tb, soak.d
    argv = [soak.o.python, '-m', 'anyscale_manager.testbed.hostile',
            '--deployment-file', soak.deployment_path, '--duration', str(f.hold_s),
            '--rate-hz', str(soak.o.hostile_rate_hz), '--seed', str(f.seed)]
    t = time.monotonic()
    with tb.lock:
        gen = {s: (st.decider, st.generation) for s in d.scale_names
               if (st := tb.record.agent_state_at(s)) is not None}
    proc = tb.start_tool(f'hostile_{f.index}', 'robot', argv)
    done = soak.wait(lambda _r: proc.popen.poll() is not None, f.hold_s + 30.0)
    if done is None:
        procs.stop_popen(proc.popen, TOOL_SIGINT_GRACE_S, session=False)
        soak.miss(row, 'the hostile publisher did not end')
    row['reaction'] = 'nothing may follow it'
    sent = _last_json(proc.log_path).get('sent', {})
    with tb.lock:
        r = tb.record
        moves = [(e.kind, e.node) for _, e in r.moves(since=t)]
        after = {s: (st.decider, st.generation) for s in d.scale_names
                 if (st := r.agent_state_at(s)) is not None}
    followed = 'unchanged' if after == gen else 'changed'
    row['outcome'] = (f'sent {sum(sent.values())} ({len(sent)} kinds), exit '
                      f'{proc.popen.returncode}; agents {followed}; {len(moves)} moves')
    row['sent'] = sent


def _last_json(path: str) -> Dict[str, object]:
    """The last JSON object among the last lines of a log (a tool's summary)."""
    for line in reversed(harness.tail(path, 5).splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    return {}


REGISTRY: Dict[str, Callable[['Soak', chaos.Fault, Row], None]] = {
    'cut': cut,
    'throttle': throttle,
    'flap': flap,
    'kill_agent_laptop': kill_agent_laptop,
    'kill_agent_robot': kill_agent_robot,
    'kill_decider': kill_decider,
    'stop_decider': stop_decider,
    'kill_node': kill_node,
    'hostile': hostile,
    'rival_decider': rival_decider,
    'lose_agent_laptop': lose_agent_laptop,
    'hup_agent_laptop': hup_agent_laptop,
    'hup_agent_robot': hup_agent_robot,
    'crash_loop': crash_loop,
}


__all__ = ['REGISTRY', 'TOOL_SIGINT_GRACE_S', 'crossing_kbps', 'remote_only', 'serving']
