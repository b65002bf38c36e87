"""The test-bed harness: the whole system on one machine, started and torn down as one thing.

``Testbed`` builds the network (``netns.Network``: a namespace per scale of the deployment, a
shaped link per link of the file, CPU quotas in the file's power ratio), starts the decider and
one agent per scale exactly as a person would (``--ros-args --params-file DEPLOYMENT -p
scale:=...``, with per-run state and log folders), and an observer node in each scale's
namespace whose output fills that scale's ``Record`` (``views``; ``record`` is the master's).
The master's observer hears every connection's topic; another scale's hears the project's
topics (so its agent's reports are known while its link to the master is cut) and, with three
scales or more, the topics of the connections whose publisher may run there (a topic whose
publisher is pinned elsewhere is not pulled across a link for the observer's sake). Each link
is cut, restored and throttled from here, agents and the decider can be killed and started
again, one managed node's process can be signalled, and ``stop()`` (also from ``__exit__`` and
on errors) stops everything gracefully, then kills whatever is left, removes the namespaces and
cgroups, and says what it had to clean.

The test-bed runs two scales (the ICAR robot and laptop) or more (``config/
three_scales_testbed.yaml``: robot, laptop and server), the master named ``robot``. Without the
rights to build namespaces it runs two scales on loopback and emulates the link: a cut freezes
(SIGSTOP) the laptop agent and every process it started, a restore thaws them; a throttle cannot
be emulated there and is refused with the reason; three scales need namespaces. The mode is
chosen once, at the start: its ``links.LinkControl`` cuts, restores and throttles the links and
starts every process where its scale is.
"""

import ctypes
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import psutil

from .. import config_files, protocol, protocol_auth
from ..agent import shm
from ..agent.catalogue import ENV_NODE, ENV_SCALE
from ..model.loader import load_deployment
from ..model.types import SERVER, Deployment
from ..nodes.workload import POSE_TYPE, REFERENCE_CORE
from . import links, netns
from .errors import HarnessError
from .links import LOOPBACK, NETNS
from .record import Record

PR_SET_CHILD_SUBREAPER = 36


def _become_subreaper() -> bool:
    """Orphans of our children (nodes of a killed agent) re-parent to us, so we can reap them."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


@dataclass
class Proc:
    name: str
    scale: str
    argv: List[str]
    popen: subprocess.Popen
    log_path: str
    started: float


@dataclass
class Options:
    deployment_path: str
    domain_id: int
    mode: str = 'auto'                       # auto | netns | loopback
    # the link's rate with two scales; with more, each link starts at its nominal bandwidth
    rate_kbps: float = netns.DEFAULT_RATE_KBPS
    reference_core: float = REFERENCE_CORE   # one robot core, in cores of this machine
    cpu_quota: bool = True
    run_dir: str = ''                        # '' = a fresh temporary folder, removed at stop
    keep_run_dir: bool = False
    decider_parameters: Mapping[str, str] = field(default_factory=dict)
    link_up_at_start: bool = True            # False: boot with the link cut (all on the robot)
    python: str = sys.executable
    # 'server': the deployment's discovery.mode server, on links that carry no multicast
    # (namespaces only); 'multicast': the file's own (its neighbours static peers).
    discovery: str = 'multicast'
    # True: the master scale runs the agent and the decider as one process (`master`).
    master_process: bool = False


class Testbed:
    def __init__(self, options: Options):
        self.options = options
        self.deployment: Deployment = load_deployment(options.deployment_path)
        d = self.deployment
        if d.discovery.mode == SERVER and options.discovery != SERVER:
            # A file that says server: every process of the test-bed a client (the observers).
            self.options = options = replace(options, discovery=SERVER)
        names = d.scale_names
        if d.master.name != 'robot' or len(names) < 2 or \
                (len(names) == 2 and 'laptop' not in names):
            raise HarnessError(f'{options.deployment_path}: the test-bed needs the master scale '
                               f'robot and the laptop, or three scales or more, got '
                               f'{", ".join(names)}')
        joined = {frozenset(link.ends) for link in d.links}
        alone = [s for s in names if not any(s in pair for pair in joined)]
        if alone:
            raise HarnessError(f'{options.deployment_path}: scale {alone[0]} has no link')
        if options.mode not in links.MODES:
            raise HarnessError(f'unknown mode {options.mode!r}')
        if len(names) > 2 and options.mode == LOOPBACK:
            raise HarnessError('three scales or more need network namespaces: loopback can '
                               'emulate one link only')
        self.mode = options.mode
        self.mode_reason = ''
        # What cuts, restores and throttles the links and starts the processes: the mode's,
        # built at the start; nothing built before it and after the stop.
        self.link_control: links.LinkControl = links.LinkControl()
        self.procs: Dict[str, Proc] = {}
        # What each scale's observer heard; the master's is ``record``. Another scale's own
        # agent reports are there while its link to the master is cut.
        self.views: Dict[str, Record] = {s: Record(d) for s in names}
        self.record = self.views[d.master.name]
        if d.security.key_file:
            # The observers' records check signatures as the agents do: a forged or replayed
            # layout or state is not taken for what the system did.
            try:
                key = protocol_auth.load_key(d.security.key_file)
            except protocol_auth.KeyFileError as e:
                raise HarnessError(str(e)) from None
            for view in self.views.values():
                view.key = key
        self.lock = threading.Lock()
        self.t0 = time.monotonic()
        self._observers: List[Proc] = []
        self._readers: List[threading.Thread] = []
        if len(d.links) == 1:
            self._links = {d.links[0].name: (True, float(options.rate_kbps))}
        else:
            self._links = {link.name: (True, float(link.bandwidth_kbps)) for link in d.links}
        self._own_run_dir = not options.run_dir
        self.run_dir = options.run_dir or tempfile.mkdtemp(prefix='anyscale-testbed-')
        self.cleanup_notes: List[str] = []
        self.cpu_cores = {s.name: s.capacity_cpu / 100.0 * options.reference_core
                          for s in self.deployment.scales}

    @property
    def network(self) -> Optional[netns.Network]:
        """The namespaces, links and cgroups while the test-bed runs in namespaces, else None."""
        return self.link_control.network

    @property
    def laptop_view(self) -> Record:
        """The laptop observer's record (the two-scale test-bed's remote scale)."""
        return self.views['laptop']

    @property
    def remote_scales(self) -> List[str]:
        return [s for s in self.deployment.scale_names if s != self.deployment.master.name]

    # --- life cycle ---------------------------------------------------------------------------
    def start(self, ready_timeout_s: float = 90.0) -> 'Testbed':
        # The agents clear these before each node they start; the harness before its own.
        self.cleanup_notes += shm.remove_broken_port_files()
        try:
            self._start(ready_timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def _start(self, ready_timeout_s: float) -> None:
        _become_subreaper()
        self.mode, self.mode_reason = links.choose(self.mode)
        os.makedirs(os.path.join(self.run_dir, 'logs'), exist_ok=True)
        d = self.deployment
        control: links.LinkControl
        if self.mode == NETNS:
            control = links.NamespaceLinks(
                d.scale_names,
                [(link.name, link.ends[0], link.ends[1], self._links[link.name][1])
                 for link in d.links],
                self.cpu_cores if self.options.cpu_quota else {},
                multicast=self.options.discovery != SERVER)
        elif self.options.discovery == SERVER:
            raise HarnessError('discovery through servers runs in network namespaces only '
                               f'(here: {self.mode_reason})')
        else:
            control = links.LoopbackLinks(d.scale_names, self._laptop_agent_pid)
        control.setup()
        self.link_control = control
        self.t0 = time.monotonic()
        for link, (up, rate) in self._links.items():
            self.record.link_set(self.t0, up, rate, link)
        boot_cut = not self.options.link_up_at_start
        if boot_cut and not control.cuts_processes:
            for link in self.master_links():
                self.cut(link)
        master = self.deployment.master.name
        self._start_observer(master, self.record, self._topics(master))
        if control.observer_per_scale:
            many = len(self.deployment.scale_names) > 2
            for scale in self.remote_scales:
                # With two scales the laptop's observer hears the agents' reports only (as
                # before three scales existed: its CPU stays out of the measured figures).
                self._start_observer(scale, self.views[scale],
                                     self._topics(scale) if many else [],
                                     project=None if many else [protocol.TOPIC_AGENT_STATE])
        for scale in self.deployment.scale_names:
            self.start_agent(scale)
        if boot_cut and control.cuts_processes:
            self.cut()
        robot_group = control.cpu_group('robot')
        if robot_group is not None:
            # Boot: ten Python nodes starting at once would keep an Atom-sized robot saturated
            # for many seconds and starve the monitors. The agents read their quota when they
            # start; once they have, the robot gets the whole machine until every node runs,
            # then its quota back. Nothing is measured before that.
            self.wait_for(lambda r: 'robot' in r.scale_status, 30.0,
                          "the robot agent's scale monitor")
            _lift_quota(robot_group)
            self.mark('boot: robot CPU quota lifted while the nodes start')
        if not self.options.master_process:
            self.start_decider()
        managed = [n.name for n in self.deployment.nodes if n.managed]
        self.wait_for(lambda r: all(r.where(n) for n in managed), ready_timeout_s,
                      'every managed node running')
        if robot_group is not None:
            robot_group.set_cores(self.cpu_cores['robot'])
            self.mark(f'robot CPU quota {self.cpu_cores["robot"]:.2f} cores')

    def _topics(self, scale: str) -> List[str]:
        """The connection topics an observer on ``scale`` hears (``TOPIC:TYPE``): every one on
        the master; elsewhere those whose publisher may run there."""
        d = self.deployment
        return sorted({f'{c.topic}:{c.msg_type}' if c.msg_type else c.topic
                       for c in d.connections
                       if scale == d.master.name or scale in d.allowed_scales(c.publisher)})

    def pose_topics(self) -> List[str]:
        """The state topics that carry a pose (the AMCL stand-in's /amcl_pose): the observer
        writes their poses, for the judge of a carried state (testbed/poses.py)."""
        d = self.deployment
        return sorted({n.state.topic for n in d.nodes if n.state is not None
                       and d.state_msg_type(n.name) == POSE_TYPE})

    def set_pose_topics(self) -> List[str]:
        """The restore topics of those nodes, on which a user may set a pose (RViz's initial
        pose, the test-bed's user): the judge takes the jump to it for one asked for."""
        d = self.deployment
        return sorted({n.state.restore for n in d.nodes if n.state is not None
                       and d.state_msg_type(n.name) == POSE_TYPE})

    def master_links(self) -> List[str]:
        """The links that touch the master scale."""
        master = self.deployment.master.name
        return [link.name for link in self.deployment.links if master in link.ends]

    def stop(self) -> List[str]:
        """Stop everything; return what had to be force-cleaned (empty on a clean stop)."""
        notes: List[str] = []
        self.link_control.release()
        robot_group = self.link_control.cpu_group('robot')
        if robot_group is not None:
            # Ten Python nodes shutting down at once under the robot's quota take many seconds;
            # nothing is measured any more, so the teardown gets the whole machine (as the boot).
            try:
                _lift_quota(robot_group)
            except OSError as e:
                notes.append(f'could not lift the robot CPU quota for the teardown: {e}')
        # Every decider (a standby's too), then the agents.
        system = [n for n in self.procs if n.startswith('decider')]
        system += [f'agent_{s}' for s in self.remote_scales]
        system += [f'agent_{self.deployment.master.name}']
        for name in system:
            proc = self.procs.get(name)
            if proc and proc.popen.poll() is None:
                _signal_group(proc.popen.pid, signal.SIGINT)
        settings = self.deployment.agent
        grace = settings.sigint_grace_s + settings.sigterm_grace_s + 8.0
        for name in system:
            proc = self.procs.get(name)
            if proc is None:
                continue
            try:
                proc.popen.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                # What it is doing, in its log, before it is killed (the decider and every
                # workload node write their threads' stacks on SIGUSR1).
                said = ''
                if name.startswith('decider'):
                    netns.send_signal(proc.popen.pid, signal.SIGUSR1)
                    try:
                        proc.popen.wait(timeout=1.0)
                    except subprocess.TimeoutExpired:
                        said = f" (its threads' stacks: the end of {proc.log_path})"
                notes.append(f'{name} did not stop within {grace:.0f} s after SIGINT; '
                             f'killed{said}')
                _signal_group(proc.popen.pid, signal.SIGKILL)
                proc.popen.wait()
        for observer in self._observers:
            _signal_group(observer.popen.pid, signal.SIGINT)
        for observer in self._observers:
            try:
                observer.popen.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                _signal_group(observer.popen.pid, signal.SIGKILL)
                observer.popen.wait()
        for reader in self._readers:
            reader.join(timeout=5.0)
        leftovers = self._descendants()
        if leftovers:
            notes.append('processes left behind and killed: ' + ', '.join(
                f'{p.pid} ({_cmdline(p)})' for p in leftovers))
            for p in leftovers:
                netns.send_signal(p.pid, signal.SIGKILL)
            psutil.wait_procs(leftovers, timeout=5.0)
        notes.extend(self.link_control.teardown())
        self.link_control = links.LinkControl()
        _reap(exclude={p.popen.pid for p in self.procs.values()})
        if self._own_run_dir and not self.options.keep_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        self.cleanup_notes.extend(notes)
        return notes

    def __enter__(self) -> 'Testbed':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- processes ----------------------------------------------------------------------------
    def _env(self, scale: str) -> Dict[str, str]:
        env = child_env(self.options.domain_id, os.path.join(self.run_dir, 'ros_log'),
                        self.link_control.discovery_peers(scale))
        if self.options.discovery == SERVER:
            # Every process a client of the scales' servers (as the agents and the decider
            # make themselves): no static peers, nothing multicast.
            from ..agent.discovery import client_setup
            env.pop('ROS_STATIC_PEERS', None)
            env.update(client_setup(['x'] + self._deployment_args(), env)[0])
        return env

    def _deployment_args(self) -> List[str]:
        args = ['--ros-args', '--params-file', self.options.deployment_path]
        args += self.link_control.ros_parameters()
        if self.options.discovery == SERVER:
            args += ['-p', f'discovery.mode:={SERVER}']
        args += ['-p', f'agent.state_dir:={os.path.join(self.run_dir, "state")}',
                 '-p', f'agent.log_dir:={os.path.join(self.run_dir, "nodes")}']
        return args

    def _spawn(self, name: str, scale: str, argv: Sequence[str], quota: bool = True,
               stdout=None) -> Proc:
        log_path = os.path.join(self.run_dir, 'logs', f'{name}.log')
        log = open(log_path, 'ab')
        env = self._env(scale)
        try:
            popen = self.link_control.popen(scale, argv, env, quota, stdout=stdout or log,
                                            stderr=log)
        finally:
            log.close()
        proc = Proc(name, scale, list(argv), popen, log_path, time.monotonic())
        self.procs[name] = proc
        return proc

    def _start_observer(self, scale: str, record: Record, topics: Sequence[str],
                        project: Optional[Sequence[str]] = None) -> None:
        """An observer on ``scale`` (outside its quota) whose lines fill ``record``: the
        arrivals of ``topics`` (``TOPIC[:TYPE]``) and the project topics (all, or only
        ``project``)."""
        argv = [self.options.python, '-m', 'anyscale_manager.testbed.observer']
        if os.geteuid() == 0 and shutil.which('chrt'):
            # Round-robin real-time priority (its threads inherit it): the instrument that
            # judges must not itself be the process that waits for a core, when two emulated
            # computers, their monitors and the tests share this machine's cores.
            argv = ['chrt', '--rr', '10'] + argv
        for topic in topics:
            argv += ['--topic', topic]
        for topic in project or ():
            argv += ['--project', topic]
        if project is None:
            for topic in self.pose_topics():
                argv += ['--pose', topic]
            for topic in self.set_pose_topics():
                argv += ['--set-pose', topic]
        record.topics = frozenset(topic.partition(':')[0] for topic in topics)
        name = f'observer_{scale}'
        observer = self._spawn(name, scale, argv, quota=False, stdout=subprocess.PIPE)
        self.procs.pop(name)
        self._observers.append(observer)
        stream = observer.popen.stdout

        def read() -> None:
            for raw in iter(stream.readline, b''):
                with self.lock:
                    record.ingest_line(raw.decode('utf-8', 'replace'))
        reader = threading.Thread(target=read, name=f'{name}-reader', daemon=True)
        reader.start()
        self._readers.append(reader)
        self.wait_for(lambda _r: record.observer_ready is not None, 30.0,
                      f'the observer on the {scale} to start')

    def start_agent(self, scale: str) -> Proc:
        joint = self.options.master_process and scale == self.deployment.master.name
        argv = [self.options.python, '-m',
                f'anyscale_manager.nodes.{"master" if joint else "agent"}']
        argv += self._deployment_args() + ['-p', f'scale:={scale}']
        if joint:
            argv += self._decider_args()
        proc = self._spawn(f'agent_{scale}', scale, argv)
        self.mark(f'agent {scale} started (pid {proc.popen.pid})')
        return proc

    def start_decider(self, name: str = 'decider', quota: bool = True) -> Proc:
        """The decider; under another ``name``, a second one (started by mistake);
        ``quota=False``: outside the robot's CPU quota."""
        argv = [self.options.python, '-m', 'anyscale_manager.nodes.decider']
        argv += self._deployment_args() + self._decider_args()
        proc = self._spawn(name, 'robot', argv, quota=quota)
        self.mark(f'{name} started (pid {proc.popen.pid})')
        return proc

    def _decider_args(self) -> List[str]:
        return [arg for param, value in sorted(self.options.decider_parameters.items())
                for arg in ('-p', f'{param}:={value}')]

    def start_tool(self, name: str, scale: str, argv: Sequence[str],
                   quota: bool = False) -> Proc:
        """A process that is not part of the system (a hostile publisher, say) in ``scale``'s
        namespace, with a test-bed ROS environment and a log in the run's logs folder. The
        caller ends it: one still running at ``stop()`` is a leftover."""
        proc = self._spawn(name, scale, argv, quota=quota)
        self.mark(f'{name} started on the {scale} (pid {proc.popen.pid})')
        return proc

    def kill(self, name: str, sig: int = signal.SIGKILL, timeout_s: float = 10.0) -> int:
        """Signal one of our processes (decider, agent_robot, agent_laptop) and wait for it."""
        proc = self.procs.get(name)
        if proc is None or proc.popen.poll() is not None:
            raise HarnessError(f'{name} is not running')
        # Only the process itself: an agent's nodes are in their own sessions and live on.
        netns.send_signal(proc.popen.pid, sig)
        self.mark(f'{name} sent {signal.Signals(sig).name}')
        try:
            return proc.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise HarnessError(f'{name} (pid {proc.popen.pid}) still runs {timeout_s:g} s '
                               f'after {signal.Signals(sig).name}') from None

    def restart_agent(self, scale: str, sig: int = signal.SIGKILL) -> Proc:
        """Kill one scale's agent (its nodes live on: each is in its own session) and start a
        new one at once, which adopts them; return the new agent's process."""
        self.kill(f'agent_{scale}', sig)
        return self.start_agent(scale)

    def node_pids(self, node: str, scale: str) -> List[int]:
        """Live processes that an agent of ``scale`` started for ``node`` (found by the
        environment every agent gives its nodes), whoever supervises them now: two are a
        duplicate."""
        out = []
        for p in self._descendants():
            try:
                env = p.environ()
            except psutil.Error:
                continue
            if env.get(ENV_NODE) == node and env.get(ENV_SCALE) == scale:
                out.append(p.pid)
        return sorted(out)

    def kill_node(self, node: str, scale: str, sig: int = signal.SIGKILL,
                  timeout_s: float = 10.0) -> int:
        """Signal the process of ``node`` on ``scale`` (the pid its agent last reported, checked
        against the process's environment) and, for a fatal signal, wait until it is gone;
        return the pid."""
        with self.lock:
            report = self.views[scale].copies(scale).get(node)
        if report is None:
            raise HarnessError(f'the {scale} agent reports no live process of {node}')
        pid = report.pid
        if pid not in self.node_pids(node, scale):
            raise HarnessError(f'pid {pid}, reported for {node} on {scale}, is not a process '
                               f'that agent started for it (live: {self.node_pids(node, scale)})')
        netns.send_signal(pid, sig)
        self.mark(f'{node} on {scale} (pid {pid}, {report.state}) sent '
                  f'{signal.Signals(sig).name}')
        if sig in (signal.SIGKILL, signal.SIGTERM, signal.SIGINT):
            deadline = time.monotonic() + timeout_s
            while _live(pid):
                if time.monotonic() > deadline:
                    raise HarnessError(f'{node} (pid {pid}) still runs {timeout_s:g} s after '
                                       f'{signal.Signals(sig).name}')
                time.sleep(0.05)
        return pid

    def running(self, name: str) -> bool:
        proc = self.procs.get(name)
        return proc is not None and proc.popen.poll() is None

    def _descendants(self) -> List[psutil.Process]:
        """Live descendants (orphans of killed agents included: we are their subreaper)."""
        ours = {p.popen.pid for p in self.procs.values()}
        ours |= {o.popen.pid for o in self._observers}
        _reap(exclude=ours)
        live = []
        try:
            children = psutil.Process().children(recursive=True)
        except psutil.Error:
            return []
        for child in children:
            try:
                if child.status() != psutil.STATUS_ZOMBIE:
                    live.append(child)
            except psutil.Error:
                continue
        return live

    # --- the links ----------------------------------------------------------------------------
    def _link_name(self, link: Optional[str]) -> str:
        if link is None:
            if len(self._links) != 1:
                raise HarnessError(f'name the link: this test-bed has {", ".join(self._links)}')
            return next(iter(self._links))
        if link not in self._links:
            raise HarnessError(f'unknown link {link!r}; this test-bed has '
                               f'{", ".join(self._links)}')
        return link

    def _link_set(self, link: str, up: bool, rate_kbps: float, text: str) -> None:
        now = time.monotonic()
        self._links[link] = (up, float(rate_kbps))
        with self.lock:
            for view in self.views.values():
                view.link_set(now, up, rate_kbps, link)
        self.mark(text)

    def cut(self, link: Optional[str] = None) -> None:
        """Cut a link (the only one, or the one named): every packet dropped both ways."""
        self._cut_or_restore(link, False)

    def restore(self, link: Optional[str] = None) -> None:
        self._cut_or_restore(link, True)

    def _cut_or_restore(self, link: Optional[str], up: bool) -> None:
        link = self._link_name(link)
        (self.link_control.restore if up else self.link_control.cut)(link)
        what = 'restored' if up else 'cut'
        self._link_set(link, up, self._links[link][1],
                       f'link {link} {what}' if len(self._links) > 1 else f'link {what}')

    def throttle(self, rate_kbps: float, link: Optional[str] = None) -> None:
        link = self._link_name(link)
        self.link_control.throttle(rate_kbps, link)
        named = f'link {link}' if len(self._links) > 1 else 'link'
        self._link_set(link, self._links[link][0], rate_kbps,
                       f'{named} shaped to {rate_kbps:g} kbit/s')

    def apply(self, step) -> None:
        """One step of a link schedule (``schedule.Step``: cut, restore or throttle, of the
        only link or the one it names). A step this test-bed cannot take (a throttle on
        loopback) is marked skipped in the record."""
        link = step.link or None
        try:
            if step.action == 'cut':
                self.cut(link)
            elif step.action == 'restore':
                self.restore(link)
            else:
                self.throttle(step.rate_kbps, link)
        except HarnessError as e:
            self.mark(f'{step} skipped: {e}')

    @property
    def link(self) -> Tuple[bool, float]:
        """(up, rate kbit/s) of the only link."""
        return self._links[self._link_name(None)]

    def link_state(self, link: str) -> Tuple[bool, float]:
        return self._links[self._link_name(link)]

    def _laptop_agent_pid(self) -> Optional[int]:
        """The laptop agent's pid while it runs (on loopback a cut freezes its processes)."""
        proc = self.procs.get('agent_laptop')
        if proc is None or proc.popen.poll() is not None:
            return None
        return proc.popen.pid

    # --- observing ----------------------------------------------------------------------------
    def mark(self, text: str) -> None:
        with self.lock:
            self.record.mark(time.monotonic(), text)

    def now(self) -> float:
        return time.monotonic()

    def wait_heard(self, end: float, timeout_s: float = 10.0) -> None:
        """Wait until every observer's arrivals are complete up to ``end`` (its lines have
        come HEARD_LAG_S past it), so that a Δ judgement up to ``end`` judges the whole span."""
        for scale, view in self.views.items():
            if not view.topics:
                continue        # no observer there, or one of project topics only: no Δ
            self.wait_for(lambda _r, v=view: v.judged_until() >= end, timeout_s,
                          f"the {scale} observer's lines past {end:.2f}")

    def wait_for(self, predicate: Callable[[Record], bool], timeout_s: float,
                 what: str) -> float:
        """Poll predicate(record) until true; return the monotonic time it became true."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self.lock:
                if predicate(self.record):
                    return time.monotonic()
            for name, proc in list(self.procs.items()):
                code = proc.popen.poll()
                if code is not None and name in ('agent_robot', 'decider') \
                        and not getattr(proc, 'expected_exit', False):
                    raise HarnessError(f'{name} exited with {code} while waiting for {what}; '
                                       f'log {proc.log_path}:\n{tail(proc.log_path)}')
            if time.monotonic() > deadline:
                decider = self.procs.get('decider')
                raise HarnessError(f'timed out after {timeout_s:g} s waiting for {what}; '
                                   f'{self.describe()}' + (
                                       '' if decider is None else
                                       f'; decider log {decider.log_path}:\n'
                                       f'{tail(decider.log_path)}'))
            time.sleep(0.1)

    def sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(min(0.1, max(0.0, end - time.monotonic())))

    def describe(self) -> str:
        with self.lock:
            r = self.record
            placement = r.placement()
            layout = r.layout_at()
            return (f'placement {dict(sorted(placement.items()))}; layout '
                    f'{layout.generation if layout else None} '
                    f'{dict(sorted(layout.assignments.items())) if layout else {}}; '
                    f'last events {[(e.kind, e.node, e.reason[:80]) for _, e in r.events[-4:]]}; '
                    f'last notes {[e.reason for _, e in r.events if e.kind == "note"][-4:]}')

    def cpu_seconds(self) -> Dict[str, float]:
        """CPU seconds used so far by the decider, each agent (without its nodes), each scale."""
        out: Dict[str, float] = {}
        for name, proc in self.procs.items():
            try:
                leader = _python_leader(proc.popen.pid)
                t = leader.cpu_times()
                out[name] = t.user + t.system
            except psutil.Error:
                continue
        for scale in self.deployment.scale_names:
            used = self.link_control.cpu_usage_s(scale)
            if used is not None:
                out[f'scale_{scale}'] = used
        return out


def child_env(domain_id: int, log_dir: str, peer: Optional[str] = None) -> Dict[str, str]:
    """The environment of a ROS process of the test-bed: this run's domain, discovery on
    loopback, or (``peer``: the other namespace's address) on the namespace pair only, and the
    packaged discovery profile (config/fastdds_discovery.xml)."""
    keep = ('PATH', 'HOME', 'LANG', 'LC_ALL', 'PYTHONPATH', 'AMENT_PREFIX_PATH',
            'LD_LIBRARY_PATH', 'RMW_IMPLEMENTATION', 'VIRTUAL_ENV')
    env = {k: v for k, v in os.environ.items() if k in keep}
    env['PYTHONUNBUFFERED'] = '1'
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_LOG_DIR'] = log_dir
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    if peer is not None:
        # DDS stays on the namespace pair: multicast and the peer's address, UDP only (shared
        # memory would reach across namespaces and bypass the link).
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'
        env['ROS_STATIC_PEERS'] = peer
        env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    else:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    # The discovery profile a deployment is advised to use (a caller's own profile wins).
    return config_files.with_discovery_profile(
        {**env, **{v: os.environ[v] for v in config_files.PROFILE_VARS if os.environ.get(v)}})


def _lift_quota(group) -> None:
    """Let a scale's cgroup use the whole machine (boot and teardown, when nothing is judged)."""
    group.set_cores(float(psutil.cpu_count() or 1))


def _python_leader(pid: int) -> psutil.Process:
    """The process doing the work: our wrappers (sh, ip netns exec) exec into it, same pid."""
    return psutil.Process(pid)


def _cmdline(p: psutil.Process) -> str:
    try:
        return ' '.join(p.cmdline())[:100]
    except psutil.Error:
        return '?'


def _live(pid: int) -> bool:
    """A process that exists and has not exited (a zombie waiting for its parent has)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        netns.send_signal(pid, sig)


def _reap(exclude=frozenset()) -> None:
    """Collect exit statuses of orphans that re-parented to us (we are their subreaper); our
    own Popen children (``exclude``) are left to their Popen objects."""
    try:
        children = psutil.Process().children()
    except psutil.Error:
        return
    for child in children:
        if child.pid in exclude:
            continue
        try:
            if child.status() == psutil.STATUS_ZOMBIE:
                os.waitpid(child.pid, os.WNOHANG)
        except (psutil.Error, ChildProcessError):
            continue


def tail(path: str, lines: int = 15) -> str:
    try:
        with open(path, 'rb') as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 4000))
            text = f.read().decode('utf-8', 'replace')
    except OSError:
        return '(no log)'
    return '\n'.join(text.splitlines()[-lines:])


__all__ = ['HarnessError', 'LOOPBACK', 'NETNS', 'Options', 'Proc', 'Testbed', 'child_env', 'tail']
