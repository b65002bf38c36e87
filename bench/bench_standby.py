"""What a standby copy costs: an inactive lifecycle workload beside an active one, and how soon
an activated copy serves.

    .venv/bin/python bench/bench_standby.py --domain-id N [--seconds 20] [--rounds 20]
        [--workloads amcl,ar] [--deployment config/icar2015_testbed.yaml] [--json]

For each workload, its arguments are those of its entry in the deployment, with --lifecycle.
The nodes publishing its inputs run as in the test-bed (plain workloads at the test-bed's rates:
laser and map_server for amcl, camera for ar). Two copies of the workload run side by side, their
lifecycle services remapped for the scales robot and laptop as the agent does; both are
configured and robot's copy is activated.

- Cost: CPU in % of one core (utime + stime from /proc/<pid>/stat over --seconds) and resident
  memory (VmRSS from /proc/<pid>/status) of each copy, while the active one works.
- Activation: robot's copy is deactivated, then laptop's copy is activated and deactivated
  --rounds times through a ChangeState client kept for the whole run: the time from the
  activate request to its answer, and to the first output received here. The copy creates its
  subscriptions on activate, so that time includes their discovery by the input's publisher
  and the wait for the next input.

DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in the given domain.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from anyscale_manager.agent.procs import stop_popen

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
SCALES = ('robot', 'laptop')
CONFIGURE, ACTIVATE, DEACTIVATE = 1, 3, 4
CLK_TCK = os.sysconf('SC_CLK_TCK')


# --- /proc --------------------------------------------------------------------------------------

def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (its own threads, not its children)."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK     # utime, stime


def rss_bytes(pid: int) -> int:
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) * 1024
    return 0


def percentile(values, q):
    return statistics.quantiles(values, n=100, method='inclusive')[q - 1]


# --- processes ----------------------------------------------------------------------------------

def start_workload(args, env, ros_args=()):
    return subprocess.Popen([sys.executable, '-m', 'anyscale_manager.nodes.workload', *args,
                             '--ros-args', *ros_args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT, start_new_session=True)


def scale_remaps(scale):
    """The remaps the agent gives one scale's copy of a lifecycle node."""
    from anyscale_manager.agent.catalogue import LIFECYCLE_SERVICES, LIFECYCLE_TOPICS
    out = []
    for name in LIFECYCLE_SERVICES + LIFECYCLE_TOPICS:
        out += ['-r', f'~/{name}:=~/{scale}/{name}']
    return out


def stop(proc, timeout_s=10.0):
    """SIGINT, then SIGKILL past the deadline; the exit status."""
    return stop_popen(proc, timeout_s)


def plan(deployment, name):
    """The workload's arguments (with --lifecycle), its spec, and the arguments of the
    test-bed nodes that publish its inputs."""
    from anyscale_manager.nodes.workload import parse_spec
    node = deployment.node(name)
    args = list(node.launch.arguments)
    if '--lifecycle' not in args:
        args.append('--lifecycle')
    spec = parse_spec(args)
    feeders = []
    for other in deployment.nodes:
        if other.name == name or other.launch.executable != 'workload':
            continue
        other_args = [a for a in other.launch.arguments if a != '--lifecycle']
        if {e.topic for e in parse_spec(other_args).outputs} & {e.topic for e in spec.inputs}:
            feeders.append((other.name, other_args))
    return args, spec, feeders


# --- the harness node ---------------------------------------------------------------------------

class Harness:
    """One rclpy node: kept lifecycle clients per copy, arrival times of outputs."""

    def __init__(self):
        import rclpy
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState, GetState
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from anyscale_manager.nodes.workload import subscriber_qos
        self._rclpy, self._Transition = rclpy, Transition
        self._ChangeState, self._GetState = ChangeState, GetState
        self._qos = subscriber_qos()
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node(f'bench_standby_{os.getpid()}', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.arrivals = {}
        self._clients = {}

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.ctx)

    def listen(self, topic, type_name):
        from anyscale_manager.nodes.workload_messages import message_class
        self.arrivals[topic] = []
        self.node.create_subscription(message_class(type_name), topic,
                                      lambda _raw: self.arrivals[topic].append(time.monotonic()),
                                      self._qos, raw=True)

    def spin_until(self, condition, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=0.005)
        return True

    def _client(self, services, srv_type, name):
        key = (services, name)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(srv_type, f'{services}/{name}')
        return self._clients[key]

    def _call(self, client, request, timeout_s):
        """Answer, or None after a lost one: rmw_fastrtps drops an answer to a client whose
        response reader the server has not matched yet (asked again by the callers)."""
        if not self.spin_until(client.service_is_ready, timeout_s):
            raise RuntimeError(f'{client.srv_name}: no such service')
        future = client.call_async(request)
        if self.spin_until(future.done, min(2.0, timeout_s)):
            return future.result()
        client.remove_pending_request(future)
        return None

    def state(self, services, timeout_s=20.0):
        client = self._client(services, self._GetState, 'get_state')
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            response = self._call(client, self._GetState.Request(), deadline - time.monotonic())
            if response is not None:
                return response.current_state.label
        raise RuntimeError(f'{services}/get_state: no answer in {timeout_s:g} s')

    def change(self, services, transition_id, timeout_s=20.0):
        """(success, time of the answer); warm the client with get_state first."""
        client = self._client(services, self._ChangeState, 'change_state')
        request = self._ChangeState.Request(transition=self._Transition(id=transition_id))
        response = self._call(client, request, timeout_s)
        if response is None:
            raise RuntimeError(f'{services}/change_state: transition {transition_id} '
                               'not answered')
        return response.success, time.monotonic()


# --- one workload -------------------------------------------------------------------------------

def measure(harness, deployment, name, env, seconds, rounds, log):
    args, spec, feeders = plan(deployment, name)
    output = spec.outputs[0].topic
    driving = spec.driver
    harness.listen(output, spec.outputs[0].msg_type)
    arrivals = harness.arrivals[output]
    log(f'{name}: {" ".join(args)}')
    log(f'{name}: inputs from {", ".join(n for n, _ in feeders) or "nobody"}')
    procs = [start_workload(a, env) for _, a in feeders]
    copies = {scale: start_workload(args, env, scale_remaps(scale)) for scale in SCALES}
    services = {scale: f'/{spec.name}/{scale}' for scale in SCALES}
    result = {'workload': name, 'arguments': args,
              'work_ms_per_output': spec.cpu_s_per_output * 1000.0}
    try:
        for scale in SCALES:
            harness.state(services[scale])          # up, and the client's path matched
            ok, _ = harness.change(services[scale], CONFIGURE)
            if not ok:
                raise RuntimeError(f'{name} on {scale}: configure refused')
        ok, _ = harness.change(services['robot'], ACTIVATE)
        if not ok or not harness.spin_until(lambda: len(arrivals) >= 3, 60.0):
            raise RuntimeError(f'{name}: the active copy never published')

        harness.spin_until(lambda: False, 2.0)      # past the start-up
        pids = {scale: copies[scale].pid for scale in SCALES}
        cpu0 = {s: cpu_seconds(p) for s, p in pids.items()}
        t0, n0 = time.monotonic(), len(arrivals)
        log(f'{name}: measuring CPU for {seconds:g} s')
        harness.spin_until(lambda: False, seconds)
        wall = time.monotonic() - t0
        result['output_hz'] = (len(arrivals) - n0) / wall
        for scale, state in (('robot', 'active'), ('laptop', 'inactive')):
            pid = pids[scale]
            result[state] = {'cpu_percent': 100.0 * (cpu_seconds(pid) - cpu0[scale]) / wall,
                             'rss_mib': rss_bytes(pid) / 2 ** 20}

        ok, _ = harness.change(services['robot'], DEACTIVATE)
        laptop = services['laptop']
        answered, first = [], []
        for i in range(rounds):
            # Wait until no copy subscribes, then a little longer, off the input's phase.
            if not harness.spin_until(lambda: harness.node.count_subscribers(driving) == 0,
                                      10.0):
                raise RuntimeError(f'{name}: an input subscription outlived deactivate')
            harness.spin_until(lambda: False, 0.2 + 0.37 * (i % 3))
            before = len(arrivals)
            t_request = time.monotonic()
            ok, t_answer = harness.change(laptop, ACTIVATE)
            if not ok:
                raise RuntimeError(f'{name}: activate refused')
            if not harness.spin_until(lambda: len(arrivals) > before, 10.0):
                raise RuntimeError(f'{name}: nothing published within 10 s of activate')
            answered.append(t_answer - t_request)
            first.append(arrivals[before] - t_request)
            ok, _ = harness.change(laptop, DEACTIVATE)
        result['activate_answer_ms'] = [round(v * 1000, 2) for v in answered]
        result['activate_first_output_ms'] = [round(v * 1000, 2) for v in first]
    finally:
        codes = {scale: stop(p) for scale, p in copies.items()}
        for p in procs:
            stop(p)
    result['exit_codes'] = codes
    return result


def table(results, seconds):
    lines = [f'Standby cost (CPU over {seconds:g} s, % of one core of this machine; '
             'RSS resident memory)', '',
             '| workload | output Hz | active CPU % | active RSS MiB | inactive CPU % '
             '| inactive RSS MiB |', '| --- | ---: | ---: | ---: | ---: | ---: |']
    for r in results:
        lines.append(f'| {r["workload"]} | {r["output_hz"]:.1f} '
                     f'| {r["active"]["cpu_percent"]:.1f} | {r["active"]["rss_mib"]:.0f} '
                     f'| {r["inactive"]["cpu_percent"]:.2f} | {r["inactive"]["rss_mib"]:.0f} |')
    lines += ['', 'Activation of the inactive copy (ms from the activate request, kept client;'
              ' the first output includes the CPU work of one output)', '',
              '| workload | n | work per output | answer p50 | answer p95 | first output p50 '
              '| first output p95 |', '| --- | ---: | ---: | ---: | ---: | ---: | ---: |']
    for r in results:
        a, f = r['activate_answer_ms'], r['activate_first_output_ms']
        lines.append(f'| {r["workload"]} | {len(a)} | {r["work_ms_per_output"]:.1f} '
                     f'| {statistics.median(a):.1f} '
                     f'| {percentile(a, 95):.1f} | {statistics.median(f):.1f} '
                     f'| {percentile(f, 95):.1f} |')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--domain-id', type=int, required=True, help='ROS_DOMAIN_ID (0-232)')
    ap.add_argument('--seconds', type=float, default=20.0, help='CPU window per workload')
    ap.add_argument('--rounds', type=int, default=20, help='activations per workload')
    ap.add_argument('--workloads', default='amcl,ar', help='deployment entries to measure')
    ap.add_argument('--deployment',
                    default=os.path.join(REPO, 'config', 'icar2015_testbed.yaml'))
    ap.add_argument('--json', action='store_true', help='print the results as JSON instead')
    args = ap.parse_args()
    if not 0 <= args.domain_id <= 232:
        ap.error(f'--domain-id: must be between 0 and 232, got {args.domain_id}')
    if args.seconds <= 0 or args.rounds < 2:
        ap.error('--seconds must be > 0 and --rounds at least 2')
    os.environ.update(ROS_DOMAIN_ID=str(args.domain_id),
                      ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    env = dict(os.environ, PYTHONUNBUFFERED='1')

    from anyscale_manager.model.loader import DeploymentError, load_deployment
    try:
        deployment = load_deployment(args.deployment)
        names = [n for n in args.workloads.split(',') if n]
        for name in names:
            deployment.node(name)
    except DeploymentError as e:
        ap.error(str(e))
    except KeyError as e:
        ap.error(e.args[0])

    def log(text):
        print(text, file=sys.stderr, flush=True)

    harness = Harness()
    try:
        results = [measure(harness, deployment, name, env, args.seconds, args.rounds, log)
                   for name in names]
    finally:
        harness.close()
    if args.json:
        print(json.dumps(results, indent=1))
    else:
        print(table(results, args.seconds))
        for r in results:
            if set(r['exit_codes'].values()) != {0}:
                print(f'{r["workload"]}: exit codes after SIGINT {r["exit_codes"]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
