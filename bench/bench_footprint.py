"""The manager's own footprint: CPU and memory of the decider, each agent and each warden on an
idle 3-node graph, beside a bare rclpy node.

    .venv/bin/python bench/bench_footprint.py [--window 60] [--settle 20] [--domain-id N]
        [--rate-hz 2] [--standby-decider] [--baseline-hz 1] [--out FILE] [--keep DIR]
        [--profile DIR] [--source DIR] [--against DIR] [--master] [--against-master]

Two scales of this machine, home (the master, a robot) and away, each run an agent (which
starts its warden), and a decider runs on home; all real processes, DDS on loopback
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the given domain, every one with the packaged
discovery profile as run.sh gives it. The graph: sensor (home) -> worker (migratable) -> pinned
(home), the package's workload node at --rate-hz, with both connections probed. The settings
are the package's defaults but for the bandwidth probe, run once at the start only: over
loopback it measures memory copies at gigabytes a second, which no robot's link carries.
With --standby-decider a second decider stands by beside the first. With --master the
home agent and the decider run as the package's `master` process (one rclpy context and DDS
participant, one executor spinning both nodes: nodes/master.py); --against-master runs the
tree of --against that way too.

Beside them the bench starts a bare rclpy node with one timer at --baseline-hz, spun by
rclpy.spin: what any ROS 2 Python process costs here.

Once every node runs, the bench waits --settle s, then measures over --window s, from /proc
(psutil): each process's CPU (user + system, its own threads; the nodes an agent starts are
measured apart) in % of one core, split by thread (the main thread, which spins the executor
and runs every callback; the other Python threads; Fast DDS's dds.* threads), and its memory
(RSS, and PSS and USS: shared libraries counted once across processes). The monitors run as
callbacks on the agent's main thread and cannot be told apart by thread: with --profile DIR
(py-spy installed in the venv; it samples from outside without stopping the process) each
manager process is also sampled over the window, and the main thread's CPU is shared out over
what its samples were doing (the agent's turn, each monitor, the executor itself).

--source DIR runs the manager (and the nodes) from another source tree of the package, a
checkout of an earlier commit (git worktree add DIR COMMIT); --against DIR runs a second
deployment from DIR in the next domain at the same time, both measured over the same window:
the way to compare two versions, since the same code reads up to twice as much CPU on this
machine when it is idle as when it is loaded (the bare rclpy node read 0.35 % and 0.65 %).
Prints a table per scale; --out FILE writes the figures as JSON (the other run under
'against'). The bench itself joins no ROS domain: it reads the agents' state files and /proc
only.
"""

import argparse
import collections
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Dict, List

import psutil
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
BIN = os.path.dirname(sys.executable)
SCALES = ('home', 'away')
MIB = 1024.0 * 1024.0

BASELINE = r'''
import sys
import rclpy
from rclpy.executors import ExternalShutdownException
rclpy.init()
node = rclpy.create_node('bench_footprint_baseline')
node.create_timer(1.0 / float(sys.argv[1]), lambda: None)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''

# What a profiled sample of a main thread was doing: the innermost frame whose file (and
# function, where one is given) matches; the node's module as a whole only when none does.
COMPONENTS = (
    ('scale monitor', 'monitors/scale.py', ''),
    ('link monitor', 'monitors/link.py', ''),
    ('probes', 'monitors/probes.py', ''),
    ('state relay', 'nodes/state_relay.py', ''),
    ('lifecycle clients', 'nodes/lifecycle_client.py', ''),
    ('agent tick', 'nodes/agent.py', '_tick'),
    ('agent inputs', 'nodes/agent.py', 'take'),
    ('agent report', 'nodes/agent.py', '_publish_state'),
    ('decider beat', 'nodes/decider_beat.py', ''),
    ('decider turn', 'nodes/decider.py', '_tick'),
    ('decider intake', 'nodes/decider.py', '_intake'),
    ('decider renew', 'nodes/decider.py', '_renew'),
    ('decider', 'nodes/decider.py', ''),
    ('agent', 'nodes/agent.py', ''),
)
GENERIC = ('decider', 'agent')


def deployment(folder: str, topic: str, rate_hz: float, port: int) -> str:
    def workload(name, *args):
        return {'command': [os.path.join(BIN, 'workload'), '--name', name, *args,
                            '--rate-hz', str(rate_hz)]}
    conn = {'msg_type': 'std_msgs/msg/UInt8MultiArray', 'bandwidth_kbps': 1.0,
            'freq_min_hz': rate_hz / 2, 'tolerance_s': 2.0}
    cores = psutil.cpu_count(logical=True) or 1
    params = {
        'deployment': {'name': f'bench_footprint_{os.getpid()}'},
        'scales': {'names': list(SCALES),
                   'home': {'role': 'master', 'kind': 'robot', 'capacity_cpu': 200.0,
                            'cores': cores, 'clock_ghz': 1.6},
                   'away': {'role': 'remote', 'kind': 'server', 'capacity_cpu': 700.0,
                            'cores': cores, 'clock_ghz': 2.8, 'gain': 3.5}},
        'links': {'names': ['net'], 'net': {'ends': list(SCALES), 'bandwidth_kbps': 54000.0}},
        'nodes': {'names': ['sensor', 'worker', 'pinned'],
                  'sensor': {'launch': workload('sensor', '--pub', topic + '/s'), 'cpu': 1.0,
                             'residence': ['home']},
                  'worker': {'launch': workload('worker', '--sub', topic + '/s', '--pub',
                                                topic + '/w'), 'cpu': 1.0},
                  'pinned': {'launch': workload('pinned', '--sub', topic + '/w', '--pub',
                                                topic + '/p'), 'cpu': 1.0,
                             'residence': ['home']}},
        'connections': {'names': ['sensor_worker', 'worker_pinned'],
                        'sensor_worker': dict(conn, topic=topic + '/s', publisher='sensor',
                                              subscriber='worker'),
                        'worker_pinned': dict(conn, topic=topic + '/w', publisher='worker',
                                              subscriber='pinned')},
        'monitoring': {'bandwidth_probe_interval_s': 86400.0,
                       'bandwidth_probe_port': port},
        'agent': {'state_dir': os.path.join(folder, 'state'),
                  'log_dir': os.path.join(folder, 'log')},
    }
    path = os.path.join(folder, 'deployment.yaml')
    with open(path, 'w') as f:
        yaml.safe_dump({'/**': {'ros__parameters': params}}, f)
    return path


# --- /proc ----------------------------------------------------------------------------------

def thread_kind(pid: int, tid: int) -> str:
    if tid == pid:
        return 'main'
    try:
        with open(f'/proc/{pid}/task/{tid}/comm') as f:
            comm = f.read().strip()
    except OSError:
        return 'other'
    return 'dds' if comm.startswith('dds.') else 'python'


def cpu_snapshot(proc: psutil.Process) -> Dict[str, float]:
    """CPU seconds of the process (its own threads), in total and by kind of thread."""
    out: Dict[str, float] = collections.defaultdict(float)
    times = proc.cpu_times()
    out['total'] = times.user + times.system
    for t in proc.threads():
        out[thread_kind(proc.pid, t.id)] += t.user_time + t.system_time
    return dict(out)


def memory(proc: psutil.Process) -> Dict[str, float]:
    full = proc.memory_full_info()
    return {'rss_mib': full.rss / MIB, 'pss_mib': getattr(full, 'pss', 0.0) / MIB,
            'uss_mib': full.uss / MIB}


# --- py-spy ---------------------------------------------------------------------------------

FRAME = re.compile(r'^(?P<func>.*) \((?P<file>[^()]*?)(?::\d+)?\)$')


def attribute(raw_path: str, pid: int) -> Dict[str, float]:
    """Share of the main thread's samples by component (COMPONENTS), from py-spy's raw output
    (one collapsed stack and its count a line, the thread first: 'thread (TID): NAME')."""
    counts: Dict[str, int] = collections.Counter()
    try:
        with open(raw_path) as f:
            lines = f.read().splitlines()
    except OSError:
        return {}
    for line in lines:
        stack, _, count = line.rpartition(' ')
        if not stack or not count.isdigit():
            continue
        frames = stack.split(';')
        if not frames[0].startswith(f'thread ({pid})'):     # the main thread's id is the pid
            continue
        name = 'executor and rclpy'
        generic = None
        for frame in reversed(frames[1:]):          # the innermost component frame names it
            m = FRAME.match(frame)
            if m is None:
                continue
            found = next((label for label, path, func in COMPONENTS
                          if m.group('file').endswith(path) and
                          (not func or m.group('func').split('.')[-1] == func)), None)
            if found and found not in GENERIC:
                name = found
                break
            if found and generic is None:
                generic = found
        else:
            name = generic or name
        counts[name] += int(count)
    total = sum(counts.values())
    return {k: v / total for k, v in counts.most_common()} if total else {}


# --- the run --------------------------------------------------------------------------------

def state_files(folder: str) -> Dict[str, dict]:
    out = {}
    state = os.path.join(folder, 'state')
    for scale in SCALES:
        for name in os.listdir(state) if os.path.isdir(state) else ():
            if name.endswith(f'_{scale}.json'):
                try:
                    with open(os.path.join(state, name)) as f:
                        out[scale] = json.load(f)
                except (OSError, ValueError):
                    pass
    return out


def placement(folder: str) -> Dict[str, List[str]]:
    """scale -> the nodes whose process lives there (from the agents' state files)."""
    out = {}
    for scale, data in state_files(folder).items():
        out[scale] = sorted(n for n, rec in (data.get('nodes') or {}).items()
                            if psutil.pid_exists(rec.get('pid', 0)))
    return out


def wait_for(cond, timeout_s: float, what: str):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = cond()
        if value:
            return value
        time.sleep(0.25)
    raise RuntimeError(f'timed out after {timeout_s:g} s waiting for {what}')


def commit(source: str) -> str:
    """The commit of the source tree, marked when its package has uncommitted changes."""
    def git(*words):
        return subprocess.run(['git', '-C', source, *words], capture_output=True,
                              text=True).stdout.strip()
    changed = git('status', '--porcelain', '--', 'anyscale_manager')
    return git('rev-parse', '--short', 'HEAD') + (' with uncommitted changes' if changed else '')


def busy_others() -> List[str]:
    """Heavy runs of others on this machine (end-to-end tests, benches, the demo)."""
    mine = {os.getpid(), os.getppid()}
    out = []
    for proc in psutil.process_iter(['pid', 'cmdline']):
        cmd = ' '.join(proc.info['cmdline'] or [])
        if proc.info['pid'] not in mine and re.search(r'test_e2e|bench_|demo', cmd) \
                and 'bench_footprint' not in cmd:
            out.append(f'{proc.info["pid"]} {cmd[:100]}')
    return out


class Run:
    """One deployment of the graph from one source tree, in one domain: its processes, started,
    measured and stopped."""

    def __init__(self, args, label: str, source: str, domain: int, folder: str):
        from anyscale_manager import config_files
        self.args, self.label, self.source, self.domain = args, label, source, domain
        self.master = args.master and label == 'this' \
            or args.against_master and label == 'against'
        self.folder = folder
        os.makedirs(folder, exist_ok=True)
        self.env = config_files.with_discovery_profile(dict(
            os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            PYTHONUNBUFFERED='1'))
        if source != REPO:
            # Ahead of the editable install's finder: the agent's children (the warden, the
            # workload nodes) inherit it.
            self.env['PYTHONPATH'] = os.pathsep.join(
                filter(None, [source, self.env.get('PYTHONPATH')]))
        # Ports of its own: the wardens of both runs listen on this machine.
        from anyscale_manager.testbed import ports
        self.path = deployment(folder, f'/bench_footprint_{os.getpid()}_{domain}', args.rate_hz,
                               ports.port_base(10 * domain))
        self.procs: Dict[str, subprocess.Popen] = {}
        self.measured: Dict[str, psutil.Process] = {}
        self.roles: Dict[str, tuple] = {}

    def _start(self, name: str, argv: List[str]) -> None:
        log = open(os.path.join(self.folder, f'{name}.out'), 'w')
        # In the run's folder: ``python -m`` puts the working directory first on the path.
        self.procs[name] = subprocess.Popen(argv, env=self.env, stdout=log,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            start_new_session=True, cwd=self.folder)

    def start(self) -> None:
        args, ros = self.args, ['--ros-args', '--params-file', self.path]
        self._start('baseline', [sys.executable, '-c', BASELINE, str(args.baseline_hz)])
        agent = [sys.executable, '-m', 'anyscale_manager.nodes.agent']
        decider = [sys.executable, '-m', 'anyscale_manager.nodes.decider']
        for scale in SCALES:
            if self.master and scale == 'home':
                self._start('agent_home', [sys.executable, '-m', 'anyscale_manager.nodes.master',
                                           *ros, '-p', f'scale:={scale}'])
            else:
                self._start(f'agent_{scale}', [*agent, *ros, '-p', f'scale:={scale}'])
        if not self.master:
            self._start('decider', [*decider, *ros])
        if args.standby_decider:
            time.sleep(2.0)          # it starts after the leader, and stands by
            self._start('decider_standby', [*decider, *ros])

    def ready(self) -> bool:
        return sum(len(v) for v in placement(self.folder).values()) >= 3

    def find(self) -> None:
        """Who is measured: the manager's processes, the wardens and nodes (the agents'
        children), and the baseline."""
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f'{self.label}: {name} exited with {proc.returncode} (log '
                                   f'in {self.folder})')
            self.measured[name] = psutil.Process(proc.pid)
        for scale in SCALES:
            for child in self.measured[f'agent_{scale}'].children():
                cmd = ' '.join(child.cmdline())
                if 'anyscale_manager.agent.warden' in cmd:
                    self.measured[f'warden_{scale}'] = child
                else:
                    node = re.search(r'--name (\S+)', cmd)
                    self.measured[f'node_{node.group(1) if node else child.pid}@{scale}'] = child
        for name in self.measured:
            if name.startswith(('agent_', 'warden_')):
                self.roles[name] = (name.split('_', 1)[1], name.split('_', 1)[0])
            elif name.startswith('decider'):
                self.roles[name] = ('home', name)
            elif name.startswith('node_'):
                self.roles[name] = (name.split('@')[1], name.split('@')[0])
            else:
                self.roles[name] = ('-', name)

    def snapshot(self) -> Dict[str, Dict[str, float]]:
        return {n: cpu_snapshot(p) for n, p in self.measured.items()}

    def result(self, before, after, elapsed, rss_max, shares, placed_before) -> dict:
        rows = {}
        for n, proc in self.measured.items():
            cpu = {k: 100.0 * (after[n].get(k, 0.0) - before[n].get(k, 0.0)) / elapsed
                   for k in ('total', 'main', 'python', 'dds')}
            rows[n] = dict(scale=self.roles[n][0], role=self.roles[n][1], pid=proc.pid,
                           cpu_percent=cpu['total'], main_thread=cpu['main'],
                           python_threads=cpu['python'], dds_threads=cpu['dds'],
                           rss_max_mib=rss_max[n], **memory(proc))
            if n in shares:
                rows[n]['main_thread_by_component'] = {
                    k: v * cpu['main'] for k, v in shares[n].items()}
        home = [n for n in rows if n.startswith(('agent_home', 'decider', 'warden_home'))]
        every = [n for n in rows if n.startswith(('agent_', 'decider', 'warden_'))]
        return {
            'label': self.label, 'source': self.source, 'commit': commit(self.source),
            'domain_id': self.domain, 'master': self.master,
            'standby_decider': self.args.standby_decider, 'placed': placed_before,
            'moved_during_window': placed_before != placement(self.folder), 'processes': rows,
            'home_manager_cpu_percent': sum(rows[n]['cpu_percent'] for n in home),
            'manager_rss_mib': sum(rows[n]['rss_mib'] for n in every),
            'manager_pss_mib': sum(rows[n]['pss_mib'] for n in every),
        }

    def stop(self) -> None:
        """The agents stop their nodes and their wardens leave; the deciders and the baseline
        stop on SIGINT. Past the deadline, each process started here is killed by its pid."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 20.0
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5.0)
        for data in state_files(self.folder).values():
            for rec in (data.get('nodes') or {}).values():
                pid = rec.get('pid', 0)
                if pid and psutil.pid_exists(pid):
                    os.kill(pid, signal.SIGKILL)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--window', type=float, default=60.0, help='seconds measured')
    ap.add_argument('--settle', type=float, default=20.0,
                    help='seconds after every node runs before the window')
    ap.add_argument('--domain-id', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', '150')))
    ap.add_argument('--rate-hz', type=float, default=2.0, help="the workload nodes' rate")
    ap.add_argument('--standby-decider', action='store_true',
                    help='a second decider on home, standing by')
    ap.add_argument('--baseline-hz', type=float, default=1.0,
                    help="the bare rclpy node's timer")
    ap.add_argument('--out', metavar='FILE', help='write the figures as JSON')
    ap.add_argument('--keep', metavar='DIR', help='write the deployment and logs into DIR')
    ap.add_argument('--profile', metavar='DIR',
                    help='sample each manager process with py-spy over the window into DIR')
    ap.add_argument('--source', metavar='DIR',
                    help='run the package from this source tree (default: the installed one)')
    ap.add_argument('--against', metavar='DIR',
                    help='also run the deployment from this source tree (an earlier commit), '
                         'in the next domain, measured in the same window')
    ap.add_argument('--master', action='store_true',
                    help='the home agent and the decider as one `master` process (not the run '
                         'of --against)')
    ap.add_argument('--against-master', action='store_true',
                    help='the run of --against as one `master` process too (its tree must have '
                         'nodes/master.py)')
    args = ap.parse_args()
    if args.window <= 0 or args.settle < 0:
        ap.error('--window must be positive and --settle not negative')
    if args.profile and shutil.which('py-spy', path=BIN + os.pathsep + os.environ.get(
            'PATH', '')) is None:
        ap.error('--profile needs py-spy (.venv/bin/pip install py-spy)')
    trees = [('this', os.path.abspath(args.source or REPO))]
    if args.against:
        trees.insert(0, ('against', os.path.abspath(args.against)))
    for _, tree in trees:
        if not os.path.isdir(os.path.join(tree, 'anyscale_manager')):
            ap.error(f'{tree}: no anyscale_manager package there')
    others = busy_others()
    if others:
        print('note: heavy runs of others on this machine:\n  ' + '\n  '.join(others),
              flush=True)
    sys.path.insert(0, REPO)
    top = args.keep or tempfile.mkdtemp(prefix='bench_footprint_')
    runs = [Run(args, label, tree, args.domain_id + k, os.path.join(top, label))
            for k, (label, tree) in enumerate(reversed(trees))]
    try:
        for run in runs:
            run.start()
        wait_for(lambda: all(run.ready() for run in runs), 120.0, 'the three nodes running')
        print(f'nodes at {args.rate_hz:g} Hz; running: '
              + '; '.join(f'{run.label} (domain {run.domain}) {placement(run.folder)}'
                          for run in runs) + f'; settling {args.settle:g} s', flush=True)
        time.sleep(args.settle)
        for run in runs:
            run.find()
        placed = [placement(run.folder) for run in runs]
        spies = {}
        if args.profile:
            os.makedirs(args.profile, exist_ok=True)
            for name, proc in runs[0].measured.items():
                if name.startswith(('agent_', 'decider')):
                    out = os.path.join(args.profile, f'{name}.txt')
                    spies[name] = (subprocess.Popen(
                        [os.path.join(BIN, 'py-spy'), 'record', '--nonblocking', '--threads',
                         '--full-filenames', '--rate', '200', '--format', 'raw', '--duration',
                         str(int(args.window)), '--output', out, '--pid', str(proc.pid)],
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL), out)
        load_before = os.getloadavg()
        t0 = time.monotonic()
        before = [run.snapshot() for run in runs]
        rss_max: List[Dict[str, float]] = [collections.defaultdict(float) for _ in runs]
        while time.monotonic() - t0 < args.window:
            time.sleep(min(5.0, max(0.0, args.window - (time.monotonic() - t0))))
            for run, peak in zip(runs, rss_max):
                for n, proc in run.measured.items():
                    try:
                        peak[n] = max(peak[n], proc.memory_info().rss / MIB)
                    except psutil.Error:
                        pass
        after = [run.snapshot() for run in runs]
        elapsed = time.monotonic() - t0
        load_after = os.getloadavg()
        shares = {}
        for name, (spy, out) in spies.items():
            try:
                spy.wait(30.0)
            except subprocess.TimeoutExpired:
                spy.kill()
            shares[name] = attribute(out, runs[0].measured[name].pid)
        results = [run.result(b, a, elapsed, peak, shares if k == 0 else {}, where)
                   for k, (run, b, a, peak, where)
                   in enumerate(zip(runs, before, after, rss_max, placed))]
        common = {'command': ' '.join(sys.argv), 'date': time.strftime('%Y-%m-%d %H:%M:%S'),
                  'window_s': elapsed, 'settle_s': args.settle, 'rate_hz': args.rate_hz,
                  'cpus': psutil.cpu_count(logical=True), 'load_before': load_before,
                  'load_after': load_after, 'others_busy': others}
        for r in reversed(results):
            r.update(common)
            report(r)
        result = dict(results[0], against=results[1] if len(results) > 1 else None)
        if args.out:
            with open(args.out, 'w') as f:
                json.dump(result, f, indent=1, sort_keys=True)
            print(f'written: {args.out}')
    finally:
        for run in runs:
            run.stop()
        if not args.keep:
            time.sleep(1.0)        # the wardens see the state folder go, and leave
            shutil.rmtree(top, ignore_errors=True)
    return 0


def report(r: dict) -> None:
    rows = r['processes']
    print(f'\n{r["label"]}: {r["source"]}, {r["date"]} at {r["commit"]}: {r["window_s"]:.0f} s '
          f'window after '
          f'{r["settle_s"]:g} s, {r["cpus"]} CPUs, load {r["load_before"][0]:.1f} -> '
          f'{r["load_after"][0]:.1f}; nodes: {r["placed"]}'
          + (' (a node moved during the window)' if r['moved_during_window'] else ''))
    head = (f'{"process":<22} {"CPU %":>6} {"main":>6} {"py thr":>6} {"dds":>6} '
            f'{"RSS MiB":>8} {"PSS":>6} {"USS":>6}')
    for scale in (*SCALES, '-'):
        names = [n for n in rows if rows[n]['scale'] == scale]
        if not names:
            continue
        print(f'\n{"scale " + scale if scale != "-" else "reference"}')
        print(head)
        for n in sorted(names, key=lambda k: (rows[k]['role'].startswith('node'), k)):
            x = rows[n]
            print(f'{n:<22} {x["cpu_percent"]:6.2f} {x["main_thread"]:6.2f} '
                  f'{x["python_threads"]:6.2f} {x["dds_threads"]:6.2f} {x["rss_mib"]:8.1f} '
                  f'{x["pss_mib"]:6.1f} {x["uss_mib"]:6.1f}')
            for k, v in (x.get('main_thread_by_component') or {}).items():
                print(f'    {k:<30} {v:6.2f}')
    if r['master']:
        print('\nagent_home is the `master` process: the home agent and the decider')
    print(f'\nthe manager on home (agent + decider(s) + warden): '
          f'{r["home_manager_cpu_percent"]:.2f} % of one core; every manager process: '
          f'RSS {r["manager_rss_mib"]:.0f} MiB, PSS {r["manager_pss_mib"]:.0f} MiB')
    print("monitors: callbacks on the agent's main thread, not separable by thread "
          '(--profile shares that thread out)')


if __name__ == '__main__':
    sys.exit(main())
