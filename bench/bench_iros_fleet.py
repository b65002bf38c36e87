"""The IROS 2016 case study live as a fleet: the plan's per-node CPU and performance beside what
a live run measures (the paper's validation: 2.5 % average deviation of performance).

    flock /tmp/asm-live.lock python bench/bench_iros_fleet.py [--instance FILE]
        [--duration-s 60] [--cpu-factor 0.15] [--json OUT.json]

The instance is split into one deployment per robot and planned over the fleet (``plan
--split-iros``); each planned robot file is made runnable (testbed/iros_live.py: workload
stand-ins whose CPU is the planned CPU, one reference core = ``--cpu-factor`` of a core here).
Robots and the server run in network namespaces (testbed/fleet_netns.FleetNetwork: robot_a,
robot_b, server, CPU quotas, a shaped link per robot), each robot in its own ROS domain with its
decider, its robot's agent and its agent of the shared server (one claims ledger).

Measured over ``--duration-s`` once every node's output is heard: each node's process CPU
(psutil, percent of a core here, divided by the factor back into percent of a reference core)
and its output rate as heard on its robot. A stand-in has no accuracy of its own, so a node's
measured performance is, as in the paper (eq. 10), its planned performance times its delivered
share of its planned output rate; deviation = |measured - predicted| / predicted. The pacers
(sensors that pace the nodes, no work) are listed apart: a pacer's CPU is what a workload
process publishing at that rate costs here doing nothing, so each node's CPU is also given net
of the pacer of its rate on its scale ("idle", "net"). The plan's CPU figures are the nodes'
work; a live process costs its work plus that. Every node off by more than 10 % (performance
or CPU) is named with the reason; the shared server's claims are read from its ledger (by
deployment, against its capacity) and any refusal from the agents' and deciders' output.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional, Tuple

import psutil
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from anyscale_manager.protocol import TOPIC_LAYOUT  # noqa: E402
from anyscale_manager.testbed import ports  # noqa: E402
from anyscale_manager.testbed.fleet import BIN, HOME, SERVER, Fleet, other_domain  # noqa: E402
from anyscale_manager.testbed.fleet_netns import SERVER_SCALE, FleetNetwork  # noqa: E402
from anyscale_manager.testbed.iros_live import (  # noqa: E402
    DEFAULT_CPU_FACTOR, LiveDeployment, live_deployment, machine_percent, reference_percent)

MSG_TYPE = 'std_msgs/msg/UInt8MultiArray'
NAMESPACES = ('robot_a', 'robot_b')
OFF_PCT = 10.0


def plan(instance: str, out_dir: str) -> List[str]:
    """The planned robot files of ``instance``, robot 1 first."""
    subprocess.run([os.path.join(BIN, 'anyscale-manager'), 'plan', '--split-iros', instance,
                    '--write-dir', out_dir], check=True, stdout=subprocess.DEVNULL)
    return sorted(os.path.join(out_dir, f) for f in os.listdir(out_dir)
                  if f.endswith('.planned.yaml'))


def run_settings(params: dict, run_dir: str, robot: str, port: int) -> None:
    """What a run on this machine needs besides the deployment: where the agents keep state
    (one directory for every agent: the server's claims ledger is shared), short timeouts, and
    a hysteresis longer than the run so that the measured layout is the planner's."""
    params['decider'].update({'period_s': 0.25, 'grace_s': 1.0, 'agent_timeout_s': 3.0,
                              'observation_max_age_s': 3.0, 'hysteresis_s': 3600.0})
    params['monitoring'] = {'heartbeat_rate_hz': 4.0, 'heartbeat_misses_down': 12,
                            'scale_rate_hz': 4.0, 'bandwidth_probe_interval_s': 86400.0,
                            'bandwidth_probe_port': port}
    params['agent'] = {'sigint_grace_s': 1.0, 'sigterm_grace_s': 1.0,
                       'readiness_timeout_s': 10.0, 'restart_backoff_s': 0.2,
                       'restart_backoff_max_s': 2.0, 'heartbeat_rate_hz': 4.0,
                       'state_dir': os.path.join(run_dir, 'host_state'),
                       'log_dir': os.path.join(run_dir, robot)}


class Heard:
    """Arrivals per topic from an observer's JSON lines."""

    def __init__(self):
        self.arrivals: Dict[str, List[float]] = {}
        self.ready = False
        self.lock = threading.Lock()

    def read(self, stream) -> None:
        for raw in iter(stream.readline, b''):
            try:
                obj = json.loads(raw)
            except ValueError:
                continue
            if not isinstance(obj, dict):
                continue
            with self.lock:
                if obj.get('ready'):
                    self.ready = True
                for topic, times in (obj.get('arrivals') or {}).items():
                    self.arrivals.setdefault(topic, []).extend(times)

    def count(self, topic: str, start: float, end: float) -> int:
        with self.lock:
            return sum(1 for t in self.arrivals.get(topic, []) if start <= t < end)

    def topics(self) -> List[str]:
        with self.lock:
            return [t for t, a in self.arrivals.items() if a]


def node_processes(run_dir: str) -> Dict[Tuple[str, str], psutil.Process]:
    """(ROS domain, node name) -> its workload process, for this run's processes only (their
    ROS log directory is under ``run_dir``)."""
    found: Dict[Tuple[str, str], psutil.Process] = {}
    for proc in psutil.process_iter(['cmdline']):
        cmd = proc.info['cmdline'] or []
        if not cmd or not os.path.basename(cmd[1] if len(cmd) > 1 and 'python' in cmd[0]
                                           else cmd[0]) == 'workload' or '--name' not in cmd:
            continue
        try:
            env = proc.environ()
            if proc.status() == psutil.STATUS_ZOMBIE:
                continue
        except psutil.Error:
            continue
        if not env.get('ROS_LOG_DIR', '').startswith(run_dir):
            continue
        found[(env.get('ROS_DOMAIN_ID', ''), cmd[cmd.index('--name') + 1])] = proc
    return found


def cpu_s(proc: psutil.Process) -> Optional[float]:
    try:
        t = proc.cpu_times()
        return t.user + t.system
    except psutil.Error:
        return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--instance', default=os.path.join(os.path.dirname(HERE), 'config',
                                                       'iros2016', 'instance_5.yaml'))
    ap.add_argument('--duration-s', type=float, default=60.0)
    ap.add_argument('--settle-s', type=float, default=10.0,
                    help='after every output is heard, before measuring')
    ap.add_argument('--cpu-factor', type=float, default=DEFAULT_CPU_FACTOR,
                    help='one reference core as a fraction of one core of this machine')
    ap.add_argument('--robot-cores', type=float, default=0.6)
    ap.add_argument('--server-cores', type=float, default=1.2)
    ap.add_argument('--json', default='')
    a = ap.parse_args()
    run_dir = tempfile.mkdtemp(prefix='iros_fleet_')
    planned_files = plan(a.instance, os.path.join(run_dir, 'plan'))
    if len(planned_files) != len(NAMESPACES):
        print(f'{a.instance}: {len(planned_files)} robots; this bench runs '
              f'{len(NAMESPACES)}', file=sys.stderr)
        return 2
    network = FleetNetwork(NAMESPACES, run_dir, robot_cores=a.robot_cores,
                           server_cores=a.server_cores)
    procs: List[subprocess.Popen] = []
    logs = []
    heard: Dict[str, Heard] = {}
    domains: Dict[str, int] = {}
    lives: Dict[str, LiveDeployment] = {}
    claims_seen: List[Dict[str, float]] = []
    ledger = Fleet(run_dir, {})
    first = 20 + os.getpid() % 80
    port_base = ports.port_base()
    result: dict = {}
    try:
        network.setup()
        addresses = network.addresses
        for i, (ns, path) in enumerate(zip(NAMESPACES, planned_files)):
            with open(path) as f:
                planned = yaml.safe_load(f)
            params = planned['/**']['ros__parameters']
            robot_scale = next(s for s in params['scales']['names']
                               if params['scales'][s].get('role') == 'master')
            server_scale = next(s for s in params['scales']['names']
                                if params['scales'][s].get('shared'))
            live = live_deployment(planned, a.cpu_factor,
                                   {robot_scale: addresses[ns],
                                    server_scale: addresses[SERVER_SCALE]},
                                   os.path.join(BIN, 'workload'))
            run_settings(live.params, run_dir, ns, port_base + 7 * i)
            lives[ns] = live
            domain = first if i == 0 else other_domain(first)
            domains[ns] = domain
            file = os.path.join(run_dir, f'{ns}.yaml')
            with open(file, 'w') as f:
                yaml.safe_dump({'/**': {'ros__parameters': live.params}}, f)
            # The observer first (outside the quota), then the agents and the decider.
            err = open(os.path.join(run_dir, f'{ns}_observer.err'), 'ab')
            logs.append(err)
            argv = [sys.executable, '-m', 'anyscale_manager.testbed.observer',
                    '--project', TOPIC_LAYOUT]
            for n in live.nodes:
                argv += ['--topic', f'{n.output_topic}:{MSG_TYPE}']
            obs = network.control.popen(ns, argv, network.env(ns, ns, domain), False,
                                        stdout=subprocess.PIPE, stderr=err)
            procs.append(obs)
            heard[ns] = Heard()
            threading.Thread(target=heard[ns].read, args=(obs.stdout,), daemon=True).start()
            for role, args in ((SERVER, ['agent', '-p', f'scale:={server_scale}']),
                               (HOME, ['agent', '-p', f'scale:={robot_scale}']),
                               ('decider', ['decider'])):
                log = open(os.path.join(run_dir, f'{ns}_{role}.out'), 'ab')
                logs.append(log)
                cmd = [os.path.join(BIN, args[0]), '--ros-args', '--params-file', file,
                       *args[1:]]
                procs.append(network.popen(ns, role, cmd, domain, log))
        # Settle: every node's output heard on its robot.
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline:
            missing = [f'{ns}:{n.name}' for ns, live in lives.items() for n in live.nodes
                       if n.output_topic not in heard[ns].topics()]
            if not missing:
                break
            dead = [p.args for p in procs if p.poll() is not None]
            if dead:
                raise RuntimeError(f'exited: {dead}')
            time.sleep(1.0)
        else:
            raise RuntimeError(f'never heard: {", ".join(missing)} (run dir {run_dir})')
        time.sleep(a.settle_s)
        found = node_processes(run_dir)
        wanted = {(str(domains[ns]), n.name) for ns, live in lives.items() for n in live.nodes}
        if not wanted <= set(found):
            raise RuntimeError(f'no process for {sorted(wanted - set(found))}')
        start = time.monotonic()
        before = {k: cpu_s(found[k]) for k in wanted}
        while time.monotonic() < start + a.duration_s:
            claims_seen.append(ledger.claims_by_robot())
            time.sleep(2.0)
        end = time.monotonic()
        after = {k: cpu_s(found[k]) for k in wanted}
        wall = end - start
        refused = []
        for ns in NAMESPACES:
            for role in (SERVER, HOME, 'decider'):
                with open(os.path.join(run_dir, f'{ns}_{role}.out'), errors='replace') as f:
                    refused += [f'{ns} {role}: {line.strip()}' for line in f
                                if 'refused' in line]
        result = report(lives, domains, heard, before, after, start, end, wall, claims_seen,
                        refused, a)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(2)
        for p in reversed(procs):
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        ledger.close()
        notes = network.teardown()
        for log in logs:
            log.close()
        if notes:
            print('cleaned up:', '; '.join(notes), file=sys.stderr)
    if a.json:
        with open(a.json, 'w') as f:
            json.dump(result, f, indent=2)
    return 0


def report(lives, domains, heard, before, after, start, end, wall, claims_seen, refused,
           a) -> dict:
    rows = []
    pacers: Dict[Tuple[str, str, float], dict] = {}
    nodes = []
    for ns, live in lives.items():
        for n in live.nodes:
            key = (str(domains[ns]), n.name)
            used = None if before[key] is None or after[key] is None else \
                (after[key] - before[key]) / wall * 100.0
            rate = heard[ns].count(n.output_topic, start, end) / wall
            row = {'robot': live.name, 'node': n.name, 'scale': n.scale, 'setting': n.setting,
                   'rate_hz': n.rate_hz, 'rate_measured_hz': round(rate, 3),
                   'cpu_predicted': n.cpu,
                   'cpu_machine_pct': None if used is None else round(used, 3),
                   'cpu_measured': None if used is None else
                   round(reference_percent(used, live.cpu_factor), 2)}
            if n.pacer:
                pacers[(live.name, n.scale, n.rate_hz)] = row
            else:
                command = live.params['nodes'][n.name]['launch']['command']
                nodes.append((n, row, command.count('--sub') - 1))
    for n, row, inputs in nodes:
        perf = n.performance * min(row['rate_measured_hz'] / n.rate_hz, 1.0)
        dev = abs(perf - n.performance) / n.performance * 100.0 if n.performance else 0.0
        # The idle cost of a ROS process publishing at this rate: the pacer of this rate on
        # this scale, which does no work.
        floor = pacers[(row['robot'], n.scale, n.rate_hz)]['cpu_measured']
        cpu = row['cpu_measured']
        net = None if cpu is None or floor is None else cpu - floor
        row.update(inputs=inputs, performance_predicted=n.performance,
                   performance_measured=round(perf, 3), deviation_pct=round(dev, 2),
                   cpu_deviation_pct=None if cpu is None else
                   round((cpu - n.cpu) / n.cpu * 100.0, 1),
                   cpu_floor=floor, cpu_net=None if net is None else round(net, 2),
                   cpu_net_deviation_pct=None if net is None else
                   round((net - n.cpu) / n.cpu * 100.0, 1))
        rows.append(row)
    off = []
    for r in rows:
        reasons = []
        if r['deviation_pct'] > OFF_PCT:
            reasons.append(f"performance {r['deviation_pct']:.1f} % off: delivered "
                           f"{r['rate_measured_hz']:.2f} of {r['rate_hz']:g} Hz")
        if r['cpu_deviation_pct'] is not None and abs(r['cpu_deviation_pct']) > OFF_PCT:
            here = machine_percent(r['cpu_predicted'], a.cpu_factor)
            floor_here = machine_percent(r['cpu_floor'], a.cpu_factor)
            if r['cpu_predicted'] < r['cpu_floor']:
                why = (f"planned {r['cpu_predicted']:g} ({here:.2f} % of a core here) is below "
                       f"what a ROS process costs idle at {r['rate_hz']:g} Hz "
                       f"({r['cpu_floor']:.1f}, {floor_here:.2f} % of a core)")
            elif abs(r['cpu_net_deviation_pct']) <= OFF_PCT:
                why = (f"the idle cost of the process ({r['cpu_floor']:.1f}) on top of its "
                       f"work; net of it {r['cpu_net']:.1f} ({r['cpu_net_deviation_pct']:+.0f} %)")
            elif r['cpu_net'] > r['cpu_predicted']:
                why = (f"net of its idle cost ({r['cpu_floor']:.1f}) still {r['cpu_net']:.1f} "
                       f"({r['cpu_net_deviation_pct']:+.0f} %): its {r['inputs']} input "
                       'subscription(s) beyond the pacer, each message a callback, which the '
                       'pacer does not have')
            else:
                why = 'less work than planned: fewer outputs than its rate'
            reasons.append(f"CPU {r['cpu_deviation_pct']:+.0f} %: {why}")
        if reasons:
            off.append({'robot': r['robot'], 'node': r['node'], 'why': '; '.join(reasons)})
    average = statistics.mean(r['deviation_pct'] for r in rows)
    cpu_devs = [abs(r['cpu_deviation_pct']) for r in rows if r['cpu_deviation_pct'] is not None]
    net_devs = [abs(r['cpu_net_deviation_pct']) for r in rows
                if r['cpu_net_deviation_pct'] is not None and r['cpu_predicted'] >= 40]
    capacity = float(next(iter(lives.values())).params['scales']['c3']['capacity_cpu'])
    peak: Dict[str, float] = {}
    for c in claims_seen:
        for k, v in c.items():
            peak[k] = max(peak.get(k, 0.0), v)
    last = claims_seen[-1] if claims_seen else {}
    over = sum(1 for c in claims_seen if sum(c.values()) > capacity + 1e-9)
    print(f'IROS fleet live: {len(rows)} nodes of {len(lives)} robots, {wall:.0f} s measured, '
          f'one reference core = {a.cpu_factor:g} of a core here (CPU below in percent of a '
          'reference core)')
    print(f"{'robot':<28} {'node':<14} {'scale':<5} {'setting':<26} {'Hz':>3} {'heard':>6} "
          f"{'CPU plan':>8} {'meas':>6} {'idle':>5} {'net':>6} {'perf plan':>9} "
          f"{'perf meas':>9} {'dev %':>5}")
    for r in rows:
        print(f"{r['robot']:<28} {r['node']:<14} {r['scale']:<5} {r['setting']:<26} "
              f"{r['rate_hz']:>3g} {r['rate_measured_hz']:>6.2f} {r['cpu_predicted']:>8g} "
              f"{_num(r['cpu_measured']):>6} {_num(r['cpu_floor']):>5} {_num(r['cpu_net']):>6} "
              f"{r['performance_predicted']:>9.2f} {r['performance_measured']:>9.2f} "
              f"{r['deviation_pct']:>5.2f}")
    print('(idle: the pacer of its rate on its scale, a workload process that does no work; '
          'net: measured less idle)')
    print(f'average performance deviation: {average:.2f} % (the paper: 2.5 %); CPU: mean '
          f'|deviation| {statistics.mean(cpu_devs):.1f} % of the process, net of its idle '
          f'cost {statistics.mean(net_devs) if net_devs else float("nan"):.1f} % over the '
          'nodes planned at 40 or more')
    print(f'nodes off by more than {OFF_PCT:g} %: {len(off)}')
    for o in off:
        print(f"  {o['robot']} {o['node']}: {o['why']}")
    print(f'shared server c3 (capacity {capacity:g}): claims at the end '
          + ', '.join(f'{k} {v:g}' for k, v in sorted(last.items()))
          + f' (together {sum(last.values()):g}); samples above capacity: {over} of '
          f'{len(claims_seen)}')
    print(f'claims refused: {len(refused)}' + ''.join(f'\n  {x}' for x in refused[:10]))
    return {'instance': a.instance, 'cpu_factor': a.cpu_factor, 'duration_s': round(wall, 1),
            'nodes': rows, 'pacers': list(pacers.values()),
            'average_performance_deviation_pct': round(average, 3),
            'mean_abs_cpu_deviation_pct': round(statistics.mean(cpu_devs), 2),
            'mean_abs_cpu_net_deviation_pct_planned_40_up':
                round(statistics.mean(net_devs), 2) if net_devs else None,
            'off': off, 'server_capacity': capacity, 'claims_end': last, 'claims_peak': peak,
            'samples_above_capacity': over, 'samples': len(claims_seen),
            'refused': refused}


def _num(x: Optional[float]) -> str:
    return '-' if x is None else f'{x:.1f}'


if __name__ == '__main__':
    sys.exit(main())
