"""The chaos soak: the test-bed under a seeded random schedule of faults, judged from outside.

``run(SoakOptions(...))`` starts the test-bed (``harness.Testbed``, namespaces, a shaped link,
CPU quotas) with a deployment key (signed layouts and states), applies the faults that
``chaos.generate`` draws from the seed one after the other, and restarts what it killed as
systemd would (``Restart=always``, ``RestartSec=1``): the decider and the agents. It measures
each fault's reaction time, samples the CPU and memory of the decider and the agents, and at the
end judges what the harness's observer heard (a process no agent started) and what was left
behind: every count of the report must be 0. ``bench/soak.py`` is the command; the rules and
their bounds are in docs/testbed.md (the chaos soak).

The runner is this module: supervision, the schedule, the teardown. Each fault kind's handler
is in ``faults`` (``faults.REGISTRY``), the samples in ``samples``, the judging in ``verdict``
and the report in ``soak_report``.
"""

import json
import os
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import psutil
import yaml

from .. import protocol_auth
from ..agent import procs
from ..runtime.delta import rate_below
from . import chaos, faults, harness, netns, soak_report, verdict
from .record import Record
from .samples import DUPLICATE_PROCESS_S, SAMPLE_PROCESSES_S, SAMPLE_RESOURCES_S, Samples
from .soak_report import format_report
from .verdict import COLD_MOVE_S, OVERLAP_BOUND_S, Tally

# Supervised like systemd: two deciders (one leads, the other stands by) and the agents.
DECIDERS = ('decider', 'decider_standby')
SYSTEM = DECIDERS + ('agent_robot', 'agent_laptop')
RESTART_S = 1.0            # systemd's RestartSec: a killed process is started again after this


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
        self.tally = Tally()
        self.samples = Samples(self.log)
        self._killed: Dict[str, int] = {}
        self._restart_after: Dict[str, float] = {}      # name -> its restart delay this once
        self._down: Dict[str, float] = {}
        self._next_resources = 0.0
        self._next_processes = 0.0

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
        tally = self.tally
        for name in SYSTEM:
            proc = self.tb.procs.get(name)
            if proc is None:
                continue
            code = proc.popen.poll()
            if code is None:
                if name in DECIDERS:
                    tally.decider_pids.add(proc.popen.pid)
                continue
            proc.expected_exit = True
            if name not in self._down:
                self._down[name] = now
                intended = self._killed.pop(name, None) == proc.popen.pid
                tally.exits.append({'t': self.rel(now), 'name': name, 'pid': proc.popen.pid,
                                    'code': code, 'intended': intended})
                if not intended:
                    self.log(f'!! {name} (pid {proc.popen.pid}) exited with {code} unasked; '
                             f'log {proc.log_path}:\n{harness.tail(proc.log_path, 8)}')
            elif now - self._down[name] >= self._restart_after.get(name, RESTART_S):
                del self._down[name]
                self._restart_after.pop(name, None)
                if name in DECIDERS:
                    new = self.tb.start_decider(name)
                    tally.decider_pids.add(new.popen.pid)
                else:
                    new = self.tb.start_agent(name.split('_', 1)[1])
                tally.restarts.append({'t': self.rel(now), 'name': name, 'pid': new.popen.pid})
        if now >= self._next_resources:
            self._next_resources = now + SAMPLE_RESOURCES_S
            self.samples.add_resources(now, self._live_system())
        if now >= self._next_processes:
            self._next_processes = now + SAMPLE_PROCESSES_S
            self.samples.add_processes(now)

    def _live_system(self) -> Dict[str, int]:
        """name -> pid of each supervised process that runs."""
        out = {}
        for name in SYSTEM:
            proc = self.tb.procs.get(name)
            if proc is not None and proc.popen.poll() is None:
                out[name] = proc.popen.pid
        return out

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

    # --- what the fault handlers call -----------------------------------------------------
    def kill(self, name: str, restart_after_s: float = RESTART_S) -> int:
        """SIGKILL one supervised process (its exit is then counted as intended) and wait for
        it; return its pid. It is restarted after ``restart_after_s``."""
        pid = self.tb.procs[name].popen.pid
        self._killed[name] = pid
        self._restart_after[name] = restart_after_s
        self.tb.kill(name, signal.SIGKILL)
        return pid

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

    def miss(self, row: Dict[str, object], what: str) -> None:
        """A reaction not seen within its fault's limit: counted, and said with the state."""
        self.tally.missed += 1
        row['outcome'] = f'MISSED: {what}'
        self.log(f'!! fault {row["index"]} ({row["what"]}): {what}; {self.tb.describe()}')

    # --- the run --------------------------------------------------------------------------
    def run_fault(self, f: chaos.Fault) -> Dict[str, object]:
        row: Dict[str, object] = {'index': f.index, 'kind': f.kind, 'what': f.describe(),
                                  'planned_at_s': f.at_s, 'at_s': self.rel(time.monotonic()),
                                  'reaction': '', 'reaction_s': None, 'outcome': '',
                                  'no_move_back': verdict.no_move_back(f),
                                  'noted_move_back': verdict.noted_move_back(f)}
        faults.REGISTRY[f.kind](self, f, row)
        row['end_s'] = self.rel(time.monotonic())
        if row['reaction_s'] is not None:
            row['reaction_s'] = round(row['reaction_s'], 3)
        return row

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
            self.tally.decider_pids.add(standby.popen.pid)
            # Judged from when every monitored connection is heard at or above its freq_min at
            # the robot (the boot only waits for every node to run).
            flowing = [c for c in self.d.connections if c.monitored]
            window = self.d.monitoring.probe_window_s

            def at_freq_min(r: Record) -> bool:
                return not any(rate_below(c.freq_min_hz,
                                          r.topic_rate(c.topic, time.monotonic(), window))
                               for c in flowing)
            if self.wait(at_freq_min, 60.0) is None:
                raise harness.HarnessError('the connections did not reach their freq_min '
                                           f'within 60 s of the boot; {self.tb.describe()}')
            self.t0 = time.monotonic()
            self.log(f'test-bed up and flowing in {self.t0 - started:.1f} s (signed layouts, '
                     f'key {self.key_path})')
            for fault in schedule:
                self.sleep(self.t0 + fault.at_s - time.monotonic())
                row = self.run_fault(fault)
                self.tally.results.append(row)
                took = '' if row['reaction_s'] is None else f' in {row["reaction_s"]:.2f} s'
                self.log(f'[{row["at_s"]:7.1f} s] #{fault.index:<2} {row["what"]}: '
                         f'{row["reaction"]}{took} {row["outcome"]}')
            self.sleep(self.t0 + self.o.duration_s - time.monotonic())
            self.t_end = time.monotonic()
            self.wait(lambda r: r.judged_until() >= self.t_end, 10.0)
            found = self.judge()
        finally:
            teardown = self.teardown()
        return self.report(schedule, found, teardown)

    def judge(self) -> Dict[str, object]:
        with self.tb.lock:
            return verdict.judge(self.d, self.tb.record, self.tb.laptop_view, self.tally,
                                 self.samples.processes, self.t0, self.t_end)

    def teardown(self) -> Dict[str, object]:
        tb = self.tb
        for name, proc in list(tb.procs.items()):
            if name not in SYSTEM and proc.popen.poll() is None:
                procs.stop_popen(proc.popen, faults.TOOL_SIGINT_GRACE_S, session=False)
        tag = tb.network.tag if tb.network is not None else None
        groups = []
        if tb.network is not None:
            for g in tb.network.groups.values():
                groups += [x for x in (g.path, g.acct_path) if x]
        edge = soak_report.resource_window_s(self.o.duration_s)
        resources = {name: self.samples.resources.window(name, self.t_end - edge, self.t_end)
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
        return {'leftovers': left, 'tracebacks': chaos.tracebacks(_log_texts(tb.run_dir)),
                'resources_end': resources}

    def report(self, schedule: Sequence[chaos.Fault], found: Dict[str, object],
               teardown: Dict[str, object]) -> Dict[str, object]:
        """The report (soak_report.build), written to the run folder when it is kept; the
        folder is removed otherwise."""
        bounds = {'overlap_s': OVERLAP_BOUND_S,
                  'nowhere_s': COLD_MOVE_S + self.d.agent.restart_backoff_s,
                  'restart_s': RESTART_S, 'duplicate_process_s': DUPLICATE_PROCESS_S}
        out = soak_report.build(
            seed=self.o.seed, planned_s=self.o.duration_s, hysteresis_s=self.o.hysteresis_s,
            kinds=self.o.kinds, bounds=bounds, t0=self.t0, t_end=self.t_end,
            schedule=schedule, system=SYSTEM, tally=self.tally, samples=self.samples,
            verdict=found, teardown=teardown, run_dir=self.run_dir)
        keep = self.o.keep_run_dir or not out['ok']
        if keep:
            with open(os.path.join(self.run_dir, 'report.json'), 'w') as f:
                json.dump(out, f, indent=2, sort_keys=True, default=str)
        else:
            shutil.rmtree(self.run_dir, ignore_errors=True)
            out['run_dir'] = None
        return out


def _log_texts(run_dir: str) -> Dict[str, str]:
    """Every file of the test-bed's run folder under 64 MiB, as text, by its relative path."""
    texts = {}
    for root, _, files in os.walk(run_dir):
        for name in files:
            path = os.path.join(root, name)
            try:
                if os.path.getsize(path) < 64 << 20:
                    with open(path, 'rb') as f:
                        texts[os.path.relpath(path, run_dir)] = f.read().decode(
                            'utf-8', 'replace')
            except OSError:
                continue
    return texts


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


__all__ = ['COLD_MOVE_S', 'OVERLAP_BOUND_S', 'RESTART_S', 'Soak', 'SoakOptions',
           'format_report', 'run']
