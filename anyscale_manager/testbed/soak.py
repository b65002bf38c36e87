"""The chaos soak: the test-bed under a seeded random schedule of faults, judged from outside.

``run(SoakOptions(...))`` starts the test-bed (``harness.Testbed``, namespaces, a shaped link,
CPU quotas) with a deployment key (signed layouts and states), applies the faults that
``chaos.generate`` draws from the seed one after the other, and restarts what it killed as
systemd would (``Restart=always``, ``RestartSec=1``): the decider and the agents. It measures
each fault's reaction time, samples the CPU and memory of the decider and the agents, and at the
end judges what the harness's observer heard (a process no agent started) and what was left
behind: every count of the report must be 0. ``bench/soak.py`` is the command; the rules and
their bounds are in docs/testbed.md (the chaos soak).
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

import psutil
import yaml

from .. import protocol_auth
from ..agent import procs
from ..agent.catalogue import ENV_NODE, ENV_SCALE
from ..agent.reconcile import HEAR_PATIENCE_S
from ..runtime.constraints import required_kbps
from . import chaos, harness, netns
from .known import KNOWN_OPEN
from .record import LIVE_STATES, Record

# Supervised like systemd: two deciders (one leads, the other stands by) and the agents.
DECIDERS = ('decider', 'decider_standby')
SYSTEM = DECIDERS + ('agent_robot', 'agent_laptop')
RESTART_S = 1.0            # systemd's RestartSec: a killed process is started again after this
# Two copies of a node may publish at once during a start_before_stop handover: the losing copy
# goes HEAR_PATIENCE_S after the new one is ready at the latest, then takes its deactivation.
OVERLAP_BOUND_S = HEAR_PATIENCE_S + 1.0
# A cold start of a Python node under the robot's 0.6-core quota, lifecycle activation included
# (about 4 s measured for two at once, docs/testbed.md), with a margin.
COLD_MOVE_S = 6.0
# Two process samples of one node on one scale this far apart: a second copy, not a restart.
DUPLICATE_PROCESS_S = 3.0
# Faults after which nothing has a reason to come home: a move back or a relocation from their
# start to 3 s after their reaction is counted (the laptop agent's death may relocate its nodes
# once it is silent for agent_timeout_s, as documented, and is not among them).
NO_MOVE_BACK = ('kill_agent_robot', 'kill_decider', 'stop_decider', 'hostile')
# A third decider's start is listed apart (``moves_back_noted``), not counted: its protocol
# rule is what the fault checks, and a process joining the domain on the robot made the robot's
# link monitor miss 3 beats (a false cut of 0.04-0.13 s, AMCL brought home by an activation) in
# 2 of 10 starts, 1 of the 3 outside the robot's CPU quota: the false-cut limit of
# docs/testbed.md.
NOTED_MOVE_BACK = ('rival_decider',)
MOVES_BACK = ('migrate_back', 'move_away', 'relocate')
SAMPLE_RESOURCES_S = 5.0
SAMPLE_PROCESSES_S = 1.0


@dataclass
class SoakOptions:
    deployment_path: str
    domain_id: int
    seed: int
    duration_s: float = 600.0
    hysteresis_s: float = 8.0          # the decider's T, as in the e2e tests (20 s in the file)
    kinds: Sequence[str] = chaos.KINDS
    ensure_each: bool = False          # the first faults are one of each kind
    gap_s: Tuple[float, float] = (6.0, 12.0)     # quiet time between two faults (drawn)
    hostile_rate_hz: float = 20.0
    run_dir: str = ''                  # '' = a fresh temporary folder
    keep_run_dir: bool = False         # also kept when a count is not 0
    log: Callable[[str], None] = print
    python: str = sys.executable


class Soak:
    def __init__(self, options: SoakOptions):
        self.o = options
        self.run_dir = options.run_dir or tempfile.mkdtemp(prefix='anyscale-soak-')
        os.makedirs(self.run_dir, exist_ok=True)
        self.key_path = os.path.join(self.run_dir, 'deployment.key')
        if not os.path.exists(self.key_path):
            protocol_auth.write_key(self.key_path)
        self.deployment_path = self._keyed_copy(options.deployment_path)
        self.tb = harness.Testbed(harness.Options(
            self.deployment_path, options.domain_id, mode='netns',
            decider_parameters={'decider.hysteresis_s': str(options.hysteresis_s)},
            link_up_at_start=True, run_dir=os.path.join(self.run_dir, 'bed'),
            keep_run_dir=True, python=options.python))
        self.d = self.tb.deployment
        self.t0 = 0.0
        self.t_end = 0.0
        self.results: List[Dict[str, object]] = []
        self.excuses: List[chaos.Excuse] = []
        self.exits: List[Dict[str, object]] = []
        self.restarts: List[Dict[str, object]] = []
        self.decider_pids: Set[int] = set()
        self.rival_pids: Set[int] = set()
        self.resources = chaos.Resources()
        self.process_samples: List[Tuple[float, Dict[str, int]]] = []
        self.duplicate_processes: List[Dict[str, object]] = []
        self._dup_since: Dict[Tuple[str, str], float] = {}
        self._killed: Dict[str, int] = {}
        self._down: Dict[str, float] = {}
        self._next_resources = 0.0
        self._next_processes = 0.0
        self.missed = 0
        self.rival_misbehaved = 0       # a third decider that published or did not stand by
        self.stale_leader = 0           # a resumed leader published, or was followed again

    # --- set-up ---------------------------------------------------------------------------
    def _keyed_copy(self, path: str) -> str:
        """The deployment with ``security.key_file`` set to this run's key."""
        with open(path) as f:
            data = yaml.safe_load(f)
        params = data['/**']['ros__parameters']
        params['security'] = dict(params.get('security') or {}, key_file=self.key_path)
        out = os.path.join(self.run_dir, 'deployment.yaml')
        with open(out, 'w') as f:
            yaml.safe_dump(data, f, sort_keys=False)
        return out

    def log(self, text: str) -> None:
        self.o.log(text)

    def rel(self, t: float) -> float:
        return round(t - self.t0, 2)

    # --- supervision, like systemd --------------------------------------------------------
    def tick(self) -> None:
        now = time.monotonic()
        for name in SYSTEM:
            proc = self.tb.procs.get(name)
            if proc is None:
                continue
            code = proc.popen.poll()
            if code is None:
                if name in DECIDERS:
                    self.decider_pids.add(proc.popen.pid)
                continue
            proc.expected_exit = True
            if name not in self._down:
                self._down[name] = now
                intended = self._killed.pop(name, None) == proc.popen.pid
                self.exits.append({'t': self.rel(now), 'name': name, 'pid': proc.popen.pid,
                                   'code': code, 'intended': intended})
                if not intended:
                    self.log(f'!! {name} (pid {proc.popen.pid}) exited with {code} unasked; '
                             f'log {proc.log_path}:\n{harness.tail(proc.log_path, 8)}')
            elif now - self._down[name] >= RESTART_S:
                del self._down[name]
                if name in DECIDERS:
                    new = self.tb.start_decider(name)
                    self.decider_pids.add(new.popen.pid)
                else:
                    new = self.tb.start_agent(name.split('_', 1)[1])
                self.restarts.append({'t': self.rel(now), 'name': name, 'pid': new.popen.pid})
        if now >= self._next_resources:
            self._next_resources = now + SAMPLE_RESOURCES_S
            self._sample_resources(now)
        if now >= self._next_processes:
            self._next_processes = now + SAMPLE_PROCESSES_S
            self._sample_processes(now)

    def _sample_resources(self, now: float) -> None:
        for name in SYSTEM:
            proc = self.tb.procs.get(name)
            if proc is None or proc.popen.poll() is not None:
                continue
            try:
                ps = psutil.Process(proc.popen.pid)
                t = ps.cpu_times()
                self.resources.add(now, name, ps.pid, t.user + t.system, ps.memory_info().rss)
            except psutil.Error:
                continue

    def _sample_processes(self, now: float) -> None:
        """Live processes per node and scale, found by the markers every agent puts in its
        nodes' environment (whoever supervises them now): more than one on one scale for
        DUPLICATE_PROCESS_S is a duplicate."""
        counts: Dict[Tuple[str, str], int] = {}
        try:
            children = psutil.Process().children(recursive=True)
        except psutil.Error:
            return
        for child in children:
            try:
                if child.status() == psutil.STATUS_ZOMBIE:
                    continue
                env = child.environ()
            except psutil.Error:
                continue
            node, scale = env.get(ENV_NODE), env.get(ENV_SCALE)
            if node and scale:
                counts[(node, scale)] = counts.get((node, scale), 0) + 1
        per_node: Dict[str, int] = {}
        for (node, _), n in counts.items():
            per_node[node] = per_node.get(node, 0) + n
        self.process_samples.append((now, per_node))
        for key in list(self._dup_since):
            if counts.get(key, 0) <= 1:
                del self._dup_since[key]
        for key, n in counts.items():
            if n > 1:
                since = self._dup_since.setdefault(key, now)
                if now - since >= DUPLICATE_PROCESS_S and not any(
                        x['node'] == key[0] and x['scale'] == key[1] and x['since'] == since
                        for x in self.duplicate_processes):
                    self.duplicate_processes.append({'node': key[0], 'scale': key[1],
                                                     'since': since, 'count': n})
                    self.log(f'!! {n} live processes of {key[0]} on the {key[1]} for '
                             f'{now - since:.1f} s')

    def wait(self, cond: Callable[[Record], bool], timeout_s: float) -> Optional[float]:
        """Supervise until cond(record) holds (the time it did) or the timeout (None)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.tick()
            with self.tb.lock:
                ok = cond(self.tb.record)
            if ok:
                return time.monotonic()
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)

    def sleep(self, seconds: float) -> None:
        self.wait(lambda _r: False, max(0.0, seconds))

    # --- what runs where ------------------------------------------------------------------
    def serving(self, r: Record, scale: str) -> Set[str]:
        return set(r.running_on(scale, ready_only=True))

    def remote_only(self, r: Record) -> List[str]:
        """Nodes serving on the laptop and not on the robot."""
        return sorted(self.serving(r, 'laptop') - self.serving(r, 'robot'))

    def crossing_kbps(self, r: Record) -> float:
        placement = r.placement()
        running = {n: ('robot' if 'robot' in s else s[0]) for n, s in placement.items() if s}
        return sum(required_kbps(self.d, running).values())

    # --- the faults -----------------------------------------------------------------------
    def run_fault(self, f: chaos.Fault) -> Dict[str, object]:
        row: Dict[str, object] = {'index': f.index, 'kind': f.kind, 'what': f.describe(),
                                  'planned_at_s': f.at_s, 'at_s': self.rel(time.monotonic()),
                                  'reaction': '', 'reaction_s': None, 'outcome': '',
                                  'no_move_back': f.kind in NO_MOVE_BACK or (
                                      f.kind == 'kill_node' and f.copy == 'standby'),
                                  'noted_move_back': f.kind in NOTED_MOVE_BACK}
        getattr(self, '_' + f.kind)(f, row)
        row['end_s'] = self.rel(time.monotonic())
        if row['reaction_s'] is not None:
            row['reaction_s'] = round(row['reaction_s'], 3)
        return row

    def _missed(self, row: Dict[str, object], what: str) -> None:
        self.missed += 1
        row['outcome'] = f'MISSED: {what}'
        self.log(f'!! fault {row["index"]} ({row["what"]}): {what}; {self.tb.describe()}')

    def _cut(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        with self.tb.lock:
            remote = self.remote_only(self.tb.record)
        self.tb.cut()
        t_cut = time.monotonic()
        if remote:
            row['reaction'] = f'-> {"+".join(remote)} serving on the robot'
            if self.wait(lambda r: set(remote) <= self.serving(r, 'robot'), 20.0) is None:
                self._missed(row, f'{remote} not serving on the robot 20 s after the cut')
            else:
                with self.tb.lock:
                    t = self.tb.record.serving_since('robot', remote, t_cut)
                row['reaction_s'] = t - t_cut
        else:
            row['reaction'] = 'nothing served from the laptop'
        self.sleep(t_cut + f.hold_s - time.monotonic())
        self.tb.restore()

    def _throttle(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        usable = f.rate_kbps * self.d.decider.bandwidth_margin
        with self.tb.lock:
            need = self.crossing_kbps(self.tb.record)
        self.tb.throttle(f.rate_kbps)
        t = time.monotonic()
        if need > usable:
            row['reaction'] = (f'-> crossing load fits ({need:.0f} kbit/s > usable '
                               f'{usable:.0f})')
            fit = self.wait(lambda r: self.crossing_kbps(r) <= usable, 30.0)
            if fit is None:
                self._missed(row, 'the crossing load still above the usable bandwidth 30 s '
                                  'after the throttle')
            else:
                row['reaction_s'] = fit - t
        else:
            row['reaction'] = f'fits already ({need:.0f} <= {usable:.0f} kbit/s)'
        self.sleep(t + f.hold_s - time.monotonic())
        self.tb.throttle(netns.DEFAULT_RATE_KBPS)

    def _flap(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        with self.tb.lock:
            remote = self.remote_only(self.tb.record)
        t_first = time.monotonic()
        for down, up in f.flaps:
            self.tb.cut()
            self.sleep(down)
            self.tb.restore()
            self.sleep(up)
        with self.tb.lock:
            r = self.tb.record
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

    def _kill_agent(self, scale: str, row: Dict[str, object]) -> None:
        name = f'agent_{scale}'
        with self.tb.lock:
            before = {n: rep.pid for n, rep in self.tb.record.copies(scale).items()}
            serving = {n for n, rep in self.tb.record.running_on(scale, ready_only=True).items()}
        proc = self.tb.procs[name]
        self._killed[name] = proc.popen.pid
        self.tb.kill(name, signal.SIGKILL)
        t_kill = time.monotonic()
        row['reaction'] = '-> a new agent reporting its copies'

        def back(r: Record) -> bool:
            new = self.tb.procs.get(name)
            if new is None or new.started <= t_kill:
                return False
            reports = [st for t, st in r.agent_states.get(scale, []) if t > new.started]
            if not reports:
                return False
            nodes = reports[-1].nodes
            live = all(n in nodes and nodes[n].state in LIVE_STATES for n in before)
            placed = set().union(*(self.serving(r, s) for s in self.d.scale_names))
            return live and serving <= placed
        t = self.wait(back, 40.0)
        if t is None:
            self._missed(row, f'no new {scale} agent reporting {sorted(before)} live 40 s '
                              'after the kill')
            return
        row['reaction_s'] = t - t_kill
        with self.tb.lock:
            now = self.tb.record.agent_states[scale][-1][1].nodes
        adopted = sorted(n for n, pid in before.items() if now[n].pid == pid)
        other = sorted(set(before) - set(adopted))
        row['outcome'] = f'adopted {len(adopted)}/{len(before)}' + (
            f'; new processes for {", ".join(other)}' if other else '')

    def _kill_agent_laptop(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        self._kill_agent('laptop', row)

    def _kill_agent_robot(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        self._kill_agent('robot', row)

    def leader(self) -> Optional[str]:
        """The name of the decider whose layout was heard last."""
        with self.tb.lock:
            last = next((lay for _, lay in reversed(self.tb.record.layouts) if lay.decider), None)
        for name in DECIDERS:
            proc = self.tb.procs.get(name)
            if last is not None and proc is not None and proc.popen.poll() is None \
                    and proc.popen.pid == last.decider.pid:
                return name
        return None

    def _kill_decider(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        name = self.leader() or 'decider'
        proc = self.tb.procs[name]
        killed = proc.popen.pid
        self._killed[name] = killed
        self.tb.kill(name, signal.SIGKILL)
        t_kill = time.monotonic()
        row['what'] = f'SIGKILL the leading decider ({name})'
        row['reaction'] = '-> the other decider publishing'

        def new_ids(r: Record) -> Set[str]:
            return {lay.decider.id for t, lay in r.layouts if t > t_kill and lay.decider
                    and lay.decider.pid in self.decider_pids and lay.decider.pid != killed}
        t_pub = self.wait(lambda r: bool(new_ids(r)), 45.0)
        if t_pub is None:
            self._missed(row, 'no layout from another decider 45 s after the kill')
            return
        row['reaction_s'] = t_pub - t_kill

        def followed(r: Record) -> bool:
            ids = new_ids(r)
            return all(r.agent_state_at(s) is not None and r.agent_state_at(s).decider in ids
                       for s in self.d.scale_names)
        t_follow = self.wait(followed, 20.0)
        with self.tb.lock:
            moves = len(self.tb.record.moves(since=t_kill))
        row['outcome'] = (f'agents following it after {t_follow - t_kill:.2f} s'
                          if t_follow is not None else 'agents NOT following it') + \
            f'; {moves} moves'
        if t_follow is None:
            self._missed(row, 'agents not following the new decider 20 s after it published')

    def _stop_decider(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        name = self.leader() or 'decider'
        stopped = self.tb.procs[name].popen.pid
        with self.tb.lock:
            ids = {lay.decider.id for _, lay in self.tb.record.layouts
                   if lay.decider and lay.decider.pid == stopped}
        os.kill(stopped, signal.SIGSTOP)
        t_stop = time.monotonic()
        row['what'] = f'SIGSTOP the leading decider ({name}) for {f.hold_s:.1f} s'
        row['reaction'] = '-> the other decider publishing'
        try:
            t_pub = self.wait(lambda r: any(
                t > t_stop and lay.decider and lay.decider.pid in self.decider_pids
                and lay.decider.pid != stopped for t, lay in r.layouts), 20.0)
            if t_pub is not None:
                row['reaction_s'] = t_pub - t_stop
            self.sleep(t_stop + f.hold_s - time.monotonic())
        finally:
            os.kill(stopped, signal.SIGCONT)
        t_cont = time.monotonic()
        if t_pub is None:
            self._missed(row, 'no layout from another decider 20 s after the SIGSTOP')
            return
        # Resumed, it must stand by: no layout of its own, no agent following it again.
        self.sleep(2.0)
        with self.tb.lock:
            stale = sum(1 for t, lay in self.tb.record.layouts if t > t_cont and lay.decider
                        and lay.decider.pid == stopped)
            followed = sorted({scale for scale, history in self.tb.record.agent_states.items()
                               for t, st in history if t > t_cont + 1.0 and st.decider in ids})
        row['outcome'] = (f'resumed after {t_cont - t_stop:.1f} s: {stale} layouts of its own; '
                          f'agents following it again: {", ".join(followed) or "none"}')
        if stale or followed:
            self.stale_leader += 1
            self.log(f'!! {name} resumed: {stale} layouts published, followed by '
                     f'{followed or "none"}')

    def _kill_node(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        node = f.node

        def where(r: Record) -> Optional[str]:
            if f.copy == 'standby':
                found = [s for s in self.d.scale_names if node in r.standby_on(s)]
            else:
                found = [s for s in self.d.scale_names if node in self.serving(r, s)]
            return found[0] if len(found) == 1 else None
        if self.wait(lambda r: where(r) is not None, 10.0) is None:
            row['outcome'] = f'skipped: no single {f.copy} copy of {node} within 10 s'
            return
        with self.tb.lock:
            scale = where(self.tb.record)
        try:
            pid = self.tb.kill_node(node, scale, signal.SIGKILL)
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

            def back(r: Record) -> bool:
                return any(node in (reps := r.running_on(s, ready_only=True))
                           and reps[node].pid != pid for s in self.d.scale_names)
        t = self.wait(back, 30.0)
        if t is None:
            self._missed(row, f'{node} not back 30 s after the kill')
        else:
            row['reaction_s'] = t - t_kill
            with self.tb.lock:
                where_now = [s for s in self.d.scale_names
                             if node in self.serving(self.tb.record, s)]
            row['outcome'] = f'serving on {"+".join(where_now) or "-"}'
        if f.copy != 'standby':
            # The killed copy served: what it fed is not judged until it serves again, plus a
            # rate window and the longest Δ.
            mon = self.d.monitoring
            margin = mon.probe_window_s + max(c.tolerance_s or 0.0 for c in self.d.connections)
            conns = [(c.name, c.publisher, c.subscriber) for c in self.d.connections]
            self.excuses.append(chaos.kill_excuse(
                conns, node, t_kill, t if t is not None else t_kill + COLD_MOVE_S,
                margin + 1.0, f'fault {f.index}: {node} killed'))

    def _hostile(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        argv = [self.o.python, '-m', 'anyscale_manager.testbed.hostile',
                '--deployment-file', self.deployment_path, '--duration', str(f.hold_s),
                '--rate-hz', str(self.o.hostile_rate_hz), '--seed', str(f.seed)]
        t = time.monotonic()
        with self.tb.lock:
            gen = {s: (st.decider, st.generation) for s in self.d.scale_names
                   if (st := self.tb.record.agent_state_at(s)) is not None}
        proc = self.tb.start_tool(f'hostile_{f.index}', 'robot', argv)
        done = self.wait(lambda _r: proc.popen.poll() is not None, f.hold_s + 30.0)
        if done is None:
            _stop(proc.popen)
            self._missed(row, 'the hostile publisher did not end')
        row['reaction'] = 'nothing may follow it'
        sent = _last_json(proc.log_path).get('sent', {})
        with self.tb.lock:
            r = self.tb.record
            moves = [(e.kind, e.node) for _, e in r.moves(since=t)]
            after = {s: (st.decider, st.generation) for s in self.d.scale_names
                     if (st := r.agent_state_at(s)) is not None}
        followed = 'unchanged' if after == gen else 'changed'
        row['outcome'] = (f'sent {sum(sent.values())} ({len(sent)} kinds), exit '
                          f'{proc.popen.returncode}; agents {followed}; {len(moves)} moves')
        row['sent'] = sent

    def _rival_decider(self, f: chaos.Fault, row: Dict[str, object]) -> None:
        name = f'decider_rival_{f.index}'
        # Outside the robot's CPU quota: a Python process starting inside it also starved the
        # robot agent's probes past AR's Δ once (1 of 7 starts), a load the restarts of the
        # decider and the agents, in the quota as systemd would start them, already bring.
        proc = self.tb.start_decider(name, quota=False)
        proc.expected_exit = True
        self.rival_pids.add(proc.popen.pid)
        t = time.monotonic()
        limit = self.d.decider.discovery_s + 20.0
        row['reaction'] = '-> a third decider stands by'
        said = 'standing by for decider'
        done = self.wait(lambda _r: said in harness.tail(proc.log_path, 40)
                         or proc.popen.poll() is not None, limit)
        row['reaction_s'] = None if done is None else done - t
        # It stands by a little longer, then is stopped as a person would (SIGINT).
        self.sleep(2.0)
        code = _stop(proc.popen)
        with self.tb.lock:
            published = sum(1 for _, lay in self.tb.record.layouts
                            if lay.decider and lay.decider.pid == proc.popen.pid)
        row['outcome'] = f'{published} layouts published; exit {code}'
        if done is None or published or code != 0:
            self.rival_misbehaved += 1
            self.log(f'!! {name}: {"did not stand by; " if done is None else ""}{published} '
                     f'layouts published, exit {code}:\n{harness.tail(proc.log_path)}')

    # --- the run --------------------------------------------------------------------------
    def run(self) -> Dict[str, object]:
        ok, why = netns.available()
        if not ok:
            raise harness.HarnessError(f'the soak needs the test-bed: {why}')
        nodes = [n.name for n in self.d.nodes if n.managed]
        standby = [n for n in nodes if self.d.standby_scales(n)]
        plain = [n for n in ('odometry', 'ekf', 'navigation') if n in nodes]
        schedule = chaos.generate(self.o.seed, self.o.duration_s, standby, plain,
                                  self.o.kinds, self.o.ensure_each, self.o.gap_s)
        self.log(f'chaos soak: seed {self.o.seed}, {self.o.duration_s:g} s, '
                 f'{len(schedule)} faults; run folder {self.run_dir}')
        started = time.monotonic()
        self.tb.start()
        teardown: Dict[str, object] = {}
        try:
            # The second decider, on the robot like the first: it stands by (and takes over).
            standby = self.tb.start_decider('decider_standby')
            self.decider_pids.add(standby.popen.pid)
            # Judged from when every monitored connection is heard at or above its freq_min at
            # the robot (the boot only waits for every node to run).
            flowing = [c for c in self.d.connections if c.monitored]
            window = self.d.monitoring.probe_window_s
            if self.wait(lambda r: all(r.topic_rate(c.topic, time.monotonic(), window)
                                       >= c.freq_min_hz for c in flowing), 60.0) is None:
                raise harness.HarnessError('the connections did not reach their freq_min '
                                           f'within 60 s of the boot; {self.tb.describe()}')
            self.t0 = time.monotonic()
            self.log(f'test-bed up and flowing in {self.t0 - started:.1f} s (signed layouts, '
                     f'key {self.key_path})')
            for fault in schedule:
                self.sleep(self.t0 + fault.at_s - time.monotonic())
                row = self.run_fault(fault)
                self.results.append(row)
                took = '' if row['reaction_s'] is None else f' in {row["reaction_s"]:.2f} s'
                self.log(f'[{row["at_s"]:7.1f} s] #{fault.index:<2} {row["what"]}: '
                         f'{row["reaction"]}{took} {row["outcome"]}')
            self.sleep(self.t0 + self.o.duration_s - time.monotonic())
            self.t_end = time.monotonic()
            self.wait(lambda r: r.heard_until >= self.t_end + 0.5, 10.0)
            verdict = self.judge()
        finally:
            teardown = self.teardown()
        return self.report(schedule, verdict, teardown)

    def judge(self) -> Dict[str, object]:
        d = self.d
        with self.tb.lock:
            r, laptop = self.tb.record, self.tb.laptop_view
            publishers = {c.topic: c.publisher for c in d.connections}
            dups, overlap = chaos.duplicates(r.arrivals, r.arrival_seqs, publishers, self.t0,
                                             self.t_end, OVERLAP_BOUND_S)
            violations = r.delta_violations(self.t0, self.t_end, 'robot')
            outputs = {c.publisher: c.topic for c in d.connections}
            nodes = [n.name for n in d.nodes if n.managed]
            histories = [r.agent_states.get(s, []) for s in d.scale_names]
            histories.append(laptop.agent_states.get('laptop', []))
            missing = chaos.nowhere(
                nodes, histories, outputs, r.arrivals, self.process_samples, self.t0,
                self.t_end, d.decider.agent_timeout_s, COLD_MOVE_S + d.agent.restart_backoff_s,
                process_nodes=[n for n in nodes if not d.standby_scales(n)])
            real = {(lay.decider.id, lay.generation) for _, lay in r.layouts
                    if lay.decider and lay.decider.pid in self.decider_pids}
            rivals = {lay.decider.id for _, lay in r.layouts
                      if lay.decider and lay.decider.pid in self.rival_pids}
            real_ids = {i for i, _ in real}
            forged, followed_rival = [], []
            for rec in (r, laptop):
                for scale, history in rec.agent_states.items():
                    for t, st in history:
                        if not self.t0 <= t <= self.t_end or st.decider is None:
                            continue        # outside the soak, or following no decider yet
                        if st.decider in rivals:
                            followed_rival.append((self.rel(t), scale, st.decider))
                        elif st.decider not in real_ids or \
                                (st.decider, st.generation) not in real:
                            forged.append((self.rel(t), scale, st.decider, st.generation))
            refused = len(r.refused)
            problems = len(r.problems)
            unneeded, noted = [], []
            for row in self.results:
                if not (row['no_move_back'] or row['noted_move_back']):
                    continue
                a, b = self.t0 + row['at_s'], self.t0 + row['end_s'] + 3.0
                found = [{'fault': row['index'], 'what': row['what'], 'at_s': self.rel(t),
                          'kind': e.kind, 'node': e.node, 'reason': e.reason[:160]}
                         for t, e in r.events if a <= t <= b and e.kind in MOVES_BACK]
                (unneeded if row['no_move_back'] else noted).extend(found)
        counted, forgiven, known = [], [], []
        for v in violations:
            excuse = chaos.excused(v.connection, v.start + v.tolerance_s, self.excuses)
            item = {'connection': v.connection, 'start_s': self.rel(v.start),
                    'below_s': round(v.end - v.start, 2), 'tolerance_s': v.tolerance_s}
            if v.connection in KNOWN_OPEN:
                known.append(dict(item, known_open=KNOWN_OPEN[v.connection]))
            elif excuse is None:
                counted.append(item)
            else:
                forgiven.append(dict(item, excused_by=excuse.why))
        return {
            'duplicates': [{'node': x.node, 'topic': x.topic, 'start_s': self.rel(x.start),
                            'length_s': round(x.length_s, 2)} for x in dups],
            'longest_overlap_s': overlap,
            'delta_violations': counted, 'delta_excused': forgiven, 'delta_known_open': known,
            'nowhere': [{'node': x.node, 'start_s': self.rel(x.start),
                         'length_s': round(x.length_s, 2)} for x in missing],
            'unneeded_moves_back': unneeded, 'moves_back_noted': noted,
            'forged_applied': forged[:20], 'forged_applied_count': len(forged),
            'rival_followed': followed_rival[:20], 'rival_followed_count': len(followed_rival),
            'observer_refused': refused, 'observer_undecodable': problems,
        }

    def teardown(self) -> Dict[str, object]:
        tb = self.tb
        for name, proc in list(tb.procs.items()):
            if name not in SYSTEM and proc.popen.poll() is None:
                _stop(proc.popen)
        tag = tb.network.tag if tb.network is not None else None
        groups = []
        if tb.network is not None:
            for g in tb.network.groups.values():
                groups += [x for x in (g.path, g.acct_path) if x]
        resources = {name: self.resources.window(name, self.t_end - self._edge(), self.t_end)
                     for name in SYSTEM}
        notes = tb.stop()
        left = list(notes)
        if tag:
            left += [f'namespace {ns} left' for ns in netns.list_namespaces()
                     if ns.startswith(tag + '-')]
        left += [f'cgroup {g} left' for g in groups if os.path.exists(g)]
        for p in _project_processes(self.run_dir):
            left.append(f'process {p.pid} ({" ".join(p.cmdline())[:80]}) left; killed')
            try:
                p.kill()
            except psutil.Error:
                pass
        texts = {}
        for root, _, files in os.walk(tb.run_dir):
            for name in files:
                path = os.path.join(root, name)
                try:
                    if os.path.getsize(path) < 64 << 20:
                        with open(path, 'rb') as f:
                            texts[os.path.relpath(path, tb.run_dir)] = f.read().decode(
                                'utf-8', 'replace')
                except OSError:
                    continue
        return {'leftovers': left, 'tracebacks': chaos.tracebacks(texts),
                'resources_end': resources}

    def _edge(self) -> float:
        return min(60.0, max(15.0, self.o.duration_s / 5.0))

    def report(self, schedule: Sequence[chaos.Fault], verdict: Dict[str, object],
               teardown: Dict[str, object]) -> Dict[str, object]:
        unintended = [e for e in self.exits if not e['intended']]
        counts = {
            'duplicate_publishers': len(verdict['duplicates']),
            'duplicate_processes': len(self.duplicate_processes),
            'delta_violations': len(verdict['delta_violations']),
            'nowhere': len(verdict['nowhere']),
            'unneeded_moves_back': len(verdict['unneeded_moves_back']),
            'forged_applied': verdict['forged_applied_count'],
            'rival_followed': verdict['rival_followed_count'],
            'rival_misbehaved': self.rival_misbehaved,
            'stale_leader': self.stale_leader,
            'unexpected_exits': len(unintended),
            'missed_reactions': self.missed,
            'leftovers': len(teardown['leftovers']),
            'tracebacks': len(teardown['tracebacks']),
        }
        edge = self._edge()
        resources = {name: {'start': self.resources.window(name, self.t0, self.t0 + edge),
                            'end': teardown['resources_end'][name],
                            'growth': self.resources.growth(name, 0.5 * self.o.duration_s)}
                     for name in SYSTEM}
        out = {
            'seed': self.o.seed, 'duration_s': round(self.t_end - self.t0, 1),
            'hysteresis_s': self.o.hysteresis_s, 'kinds': list(self.o.kinds),
            'bounds': {'overlap_s': OVERLAP_BOUND_S,
                       'nowhere_s': COLD_MOVE_S + self.d.agent.restart_backoff_s,
                       'restart_s': RESTART_S, 'duplicate_process_s': DUPLICATE_PROCESS_S},
            'counts': counts, 'ok': not any(counts.values()),
            'faults': self.results, 'reactions': chaos.reaction_summary(self.results),
            'schedule': [f.describe() for f in schedule],
            'exits': self.exits, 'restarts': self.restarts,
            'duplicate_processes': self.duplicate_processes,
            'resources': resources, 'resource_window_s': edge,
            **verdict, **teardown, 'run_dir': self.run_dir,
        }
        out.pop('resources_end', None)
        keep = self.o.keep_run_dir or not out['ok']
        if keep:
            with open(os.path.join(self.run_dir, 'report.json'), 'w') as f:
                json.dump(out, f, indent=2, sort_keys=True, default=str)
        else:
            shutil.rmtree(self.run_dir, ignore_errors=True)
            out['run_dir'] = None
        return out


def _stop(popen: subprocess.Popen) -> Optional[int]:
    """End a tool process of ours (SIGINT, then SIGKILL), reap it and return its exit status."""
    return procs.stop_popen(popen, 5.0, session=False)


def _last_json(path: str) -> Dict[str, object]:
    for line in reversed(harness.tail(path, 5).splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    return {}


def _project_processes(run_dir: str) -> List[psutil.Process]:
    """Live processes anywhere on the machine that belong to this run (their ROS log folder
    is in its folder): after the teardown there must be none."""
    out = []
    for p in psutil.process_iter():
        try:
            if p.pid == os.getpid():
                continue
            if p.environ().get('ROS_LOG_DIR', '').startswith(run_dir):
                if p.status() != psutil.STATUS_ZOMBIE:
                    out.append(p)
        except psutil.Error:
            continue
    return out


def run(options: SoakOptions) -> Dict[str, object]:
    return Soak(options).run()


def format_report(report: Dict[str, object]) -> str:
    """The report as text: every fault with its reaction, the reaction times per kind, the
    counts, and the CPU and memory of the decider and the agents."""
    lines = [f'chaos soak: seed {report["seed"]}, {report["duration_s"]:g} s, '
             f'{len(report["faults"])} faults (T = {report["hysteresis_s"]:g} s)', '',
             f'{"#":>3} {"at s":>7}  {"fault":44} {"reaction":>9}  what / outcome']
    for r in report['faults']:
        took = '-' if r['reaction_s'] is None else f'{r["reaction_s"]:.2f} s'
        lines.append(f'{r["index"]:>3} {r["at_s"]:>7.1f}  {r["what"][:44]:44} {took:>9}  '
                     f'{r["reaction"]} {r["outcome"]}'.rstrip())
    lines += ['', f'{"fault kind":20} {"faults":>6} {"timed":>6} {"p50 s":>7} {"p95 s":>7} '
                  f'{"max s":>7}']
    for kind, row in sorted(report['reactions'].items()):
        cells = ['-' if row[k] is None else f'{row[k]:.2f}' for k in ('p50_s', 'p95_s', 'max_s')]
        lines.append(f'{kind:20} {row["faults"]:>6} {row["timed"]:>6} {cells[0]:>7} '
                     f'{cells[1]:>7} {cells[2]:>7}')
    b = report['bounds']
    lines += ['', f'counts (each must be 0; overlap bound {b["overlap_s"]:g} s, nowhere bound '
                  f'{b["nowhere_s"]:g} s):']
    for name, n in report['counts'].items():
        lines.append(f'  {name:22} {n}')
    lines += ['', f'{"process":14} {"CPU % start":>11} {"CPU % end":>10} {"RSS MiB start":>14} '
                  f'{"RSS MiB end":>12} {"RSS growth (same process)":>26}']
    for name, row in report['resources'].items():
        s, e, g = row['start'] or {}, row['end'] or {}, row['growth']
        growth = '-' if not g else f'{g["growth_mib"]:+.2f} MiB over {g["over_s"]:.0f} s'
        lines.append(f'{name:14} {s.get("cpu_percent", "-"):>11} {e.get("cpu_percent", "-"):>10} '
                     f'{s.get("rss_mib", "-"):>14} {e.get("rss_mib", "-"):>12} {growth:>26}')
    for key in ('duplicates', 'delta_violations', 'nowhere', 'unneeded_moves_back',
                'forged_applied', 'rival_followed', 'leftovers', 'tracebacks',
                'duplicate_processes', 'moves_back_noted'):
        if report.get(key):
            lines += ['', f'{key}:'] + [f'  {json.dumps(x, default=str)[:300]}'
                                        for x in report[key]]
    unintended = [e for e in report['exits'] if not e['intended']]
    if unintended:
        lines += ['', 'unexpected exits:'] + [f'  {x}' for x in unintended]
    if report.get('delta_excused'):
        lines += ['', f'Δ spans excused (a serving copy killed): {len(report["delta_excused"])}']
    if report.get('delta_known_open'):
        lines += ['', 'KNOWN OPEN DEFECTS (testbed/known.py), not counted above:'] + [
            f'  {x["connection"]} below freq_min {x["below_s"]} s at {x["start_s"]} s: '
            f'{x["known_open"]}' for x in report['delta_known_open']]
    lines.append('')
    lines.append('PASS: every count is 0' if report['ok'] else 'FAIL: see the counts above')
    return '\n'.join(lines)


__all__ = ['COLD_MOVE_S', 'OVERLAP_BOUND_S', 'RESTART_S', 'Soak', 'SoakOptions',
           'format_report', 'run']
