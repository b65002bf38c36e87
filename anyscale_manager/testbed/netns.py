"""Network namespaces joined by shaped veth links, and CPU quota cgroups, for one run.

``Network`` builds a test-bed's plumbing on one Linux machine: a namespace per scale (by default
the ICAR test-bed's "robot" and "laptop"), a veth pair per link (by default one, the WiFi), each
scale with one address on all its links and a host route to each neighbour (so DDS discovery and
data between two scales stay on their own link), loopback up and a multicast route, a token
bucket (tbf) on both ends of each link at its rate, and a CPU quota cgroup per scale. Each link
can be cut (both ends' root qdisc replaced by ``blackhole``: every packet is dropped while the
interfaces stay up, as when a robot drives out of WiFi coverage; multicast loop-back inside a
namespace is untouched, so nodes on one scale keep discovering each other), restored and
throttled at any time, on its own.

Every name carries the creating process's pid and a per-process counter (``asm-<pid>-<n>-robot``),
so concurrent runs never collide, and ``remove_stale()`` removes what a killed run left behind.
``teardown()`` kills every process still inside the namespaces or cgroups, deletes the
namespaces (the veth pair goes with them) and removes the cgroups; it runs from ``__exit__``, so
an exception inside ``with Network(...)`` leaves nothing behind either.

Needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN), iproute2 (``ip``, ``tc``), util-linux's
``nsenter`` and either cgroup v1's
cpu controller (``cpu.cfs_quota_us``) or cgroup v2 (``cpu.max``). ``available()`` says plainly
which of these is missing.
"""

import itertools
import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

SCALES = ('robot', 'laptop')
NAME_PREFIX = 'asm'
DEFAULT_RATE_KBPS = 54000.0
DEFAULT_SUBNET = '10.77.0.'        # .1 = the first scale (robot), .2 the second, ...
CFS_PERIOD_US = 10000      # a short period: a throttled scale stalls for ms, not 100 ms
# Real-time budget of the scales' groups per rt period (1 s), where the kernel schedules
# real-time threads by group (cgroup v1 cpu.rt_runtime_us): for the warden answering heartbeats
# and the critical nodes (agent.critical_priority; the ICAR robot's five use about 15 % of one
# core together). A group that spends its budget has every real-time thread stopped for the
# rest of the second, which a real robot's computer does not do: the scales share 90 % of each
# core (the machine's root keeps 95 %), at most 45 % each.
RT_RUNTIME_TOTAL_US = 900000
RT_RUNTIME_MAX_US = 450000
NETNS_RUN_DIR = '/var/run/netns'
_NAME_RE = re.compile(r'^%s-(\d+)-(\d+)-(\w+)$' % NAME_PREFIX)
_counter = itertools.count(1)


class TestbedError(RuntimeError):
    """A step of building or driving the test-bed failed; the message names the command."""


def _run(argv: Sequence[str], check: bool = True, timeout: float = 10.0) -> str:
    try:
        out = subprocess.run(list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise TestbedError(f'{" ".join(argv)}: {e}') from None
    if check and out.returncode != 0:
        raise TestbedError(f'{" ".join(argv)}: exit {out.returncode}: '
                           f'{(out.stderr or out.stdout).strip()}')
    return out.stdout


# --- capability checks ----------------------------------------------------------------------

def _mounts() -> List[Tuple[str, str, str]]:
    try:
        with open('/proc/mounts') as f:
            return [tuple(line.split()[1:4]) for line in f if len(line.split()) >= 4]
    except OSError:
        return []


def cgroup_mode() -> Tuple[Optional[str], str]:
    """('v1', cpu mount) or ('v2', root) when a cpu quota can be set, else (None, reason)."""
    for mount, fstype, options in _mounts():
        if fstype == 'cgroup' and 'cpu' in options.split(','):
            if os.path.exists(os.path.join(mount, 'cpu.cfs_quota_us')):
                return 'v1', mount
    for mount, fstype, _ in _mounts():
        if fstype == 'cgroup2':
            try:
                with open(os.path.join(mount, 'cgroup.controllers')) as f:
                    if 'cpu' in f.read().split():
                        return 'v2', mount
            except OSError:
                continue
    return None, 'no cgroup cpu controller (neither v1 cpu.cfs_quota_us nor v2 cpu.max)'


def _cpuacct_mount() -> Optional[str]:
    for mount, fstype, options in _mounts():
        if fstype == 'cgroup' and 'cpuacct' in options.split(','):
            return mount
    return None


def available() -> Tuple[bool, str]:
    """Whether this process can build the test-bed, and if not, plainly why."""
    if os.geteuid() != 0:
        return False, 'not running as root: network namespaces and cgroups need root'
    for tool, package in (('ip', 'iproute2'), ('tc', 'iproute2'), ('nsenter', 'util-linux')):
        if shutil.which(tool) is None:
            return False, f'the {tool!r} command ({package}) is not installed'
    probe = f'{NAME_PREFIX}-{os.getpid()}-probe'
    try:
        _run(['ip', 'netns', 'add', probe])
    except TestbedError as e:
        return False, f'cannot create a network namespace ({e})'
    try:
        _run(['ip', '-n', probe, 'link', 'add', 'p0', 'type', 'veth', 'peer', 'name', 'p1'])
        _run(['tc', '-n', probe, 'qdisc', 'add', 'dev', 'p0', 'root', 'tbf', 'rate',
              '1mbit', 'burst', '4kb', 'latency', '50ms'])
        _run(['tc', '-n', probe, 'qdisc', 'replace', 'dev', 'p0', 'root', 'blackhole'])
    except TestbedError as e:
        return False, f'cannot shape a veth link with tbf/blackhole ({e})'
    finally:
        _run(['ip', 'netns', 'del', probe], check=False)
    mode, where = cgroup_mode()
    if mode is None:
        return False, where
    return True, f'network namespaces, tbf and cgroup {mode} CPU quotas available'


# --- CPU quota cgroups ----------------------------------------------------------------------

class CpuGroup:
    """One cgroup with a CPU quota (in machine cores), v1 or v2, plus CPU accounting."""

    def __init__(self, name: str, rt_runtime_us: int = 50000):
        mode, root = cgroup_mode()
        if mode is None:
            raise TestbedError(root)
        self.name = name
        self.mode = mode
        self.path = os.path.join(root, name)
        self.acct_path: Optional[str] = None
        self.cores: Optional[float] = None
        if mode == 'v2':
            # The root is exempt from "no internal processes"; enable cpu for its children.
            control = os.path.join(root, 'cgroup.subtree_control')
            try:
                with open(control) as f:
                    enabled = f.read().split()
                if 'cpu' not in enabled:
                    with open(control, 'w') as f:
                        f.write('+cpu')
            except OSError as e:
                raise TestbedError(f'{control}: cannot enable the cpu controller ({e})') from None
        try:
            os.makedirs(self.path, exist_ok=False)
        except OSError as e:
            raise TestbedError(f'{self.path}: {e}') from None
        if mode == 'v1' and os.path.exists(os.path.join(self.path, 'cpu.rt_runtime_us')):
            # With real-time group scheduling a new group may run no real-time thread at all;
            # give it a budget (``rt_runtime_us`` per second), so that an agent's warden
            # can answer the heartbeats at the priority it asks for (agent.warden_priority), and
            # the critical nodes run at theirs (agent.critical_priority).
            try:
                self._write('cpu.rt_runtime_us', str(rt_runtime_us))
            except TestbedError:
                pass
        if mode == 'v1':
            acct = _cpuacct_mount()
            if acct and not os.path.samefile(acct, root):
                path = os.path.join(acct, name)
                try:
                    os.makedirs(path, exist_ok=False)
                    self.acct_path = path
                except OSError:
                    self.acct_path = None

    def _write(self, filename: str, value: str, base: Optional[str] = None) -> None:
        path = os.path.join(base or self.path, filename)
        try:
            with open(path, 'w') as f:
                f.write(value)
        except OSError as e:
            raise TestbedError(f'{path}: cannot write {value!r} ({e})') from None

    def set_cores(self, cores: Optional[float]) -> None:
        """Cap the group at ``cores`` machine cores (None = no cap)."""
        if cores is not None and not cores > 0:
            raise ValueError(f'CPU quota must be > 0 cores, got {cores!r}')
        quota = -1 if cores is None else max(1000, int(round(cores * CFS_PERIOD_US)))
        if self.mode == 'v1':
            self._write('cpu.cfs_period_us', str(CFS_PERIOD_US))
            self._write('cpu.cfs_quota_us', str(quota))
        else:
            self._write('cpu.max', f'{"max" if quota < 0 else quota} {CFS_PERIOD_US}')
        self.cores = cores

    def set_weight(self, factor: float) -> None:
        """The group's CPU weight against its siblings (every other process of this machine
        and the other scales' groups), ``factor`` times the default: cgroup v1 ``cpu.shares``
        (default 1024), v2 ``cpu.weight`` (default 100)."""
        if not factor > 0:
            raise ValueError(f'CPU weight factor must be > 0, got {factor!r}')
        if self.mode == 'v1':
            self._write('cpu.shares', str(max(2, min(262144, round(1024 * factor)))))
        else:
            self._write('cpu.weight', str(max(1, min(10000, round(100 * factor)))))

    @property
    def procs_files(self) -> Tuple[str, ...]:
        files = [os.path.join(self.path, 'cgroup.procs')]
        if self.acct_path:
            files.append(os.path.join(self.acct_path, 'cgroup.procs'))
        return tuple(files)

    def add(self, pid: int) -> None:
        for path in self.procs_files:
            self._write(os.path.basename(path), str(pid), os.path.dirname(path))

    def pids(self) -> List[int]:
        pids = set()
        for path in self.procs_files:
            try:
                with open(path) as f:
                    pids.update(int(x) for x in f.read().split())
            except (OSError, ValueError):
                continue
        return sorted(pids)

    def usage_s(self) -> Optional[float]:
        """CPU time used by the group's processes so far, in seconds (None if not accounted)."""
        try:
            if self.mode == 'v2':
                with open(os.path.join(self.path, 'cpu.stat')) as f:
                    for line in f:
                        key, _, value = line.partition(' ')
                        if key == 'usage_usec':
                            return int(value) / 1e6
                return None
            if self.acct_path:
                with open(os.path.join(self.acct_path, 'cpuacct.usage')) as f:
                    return int(f.read()) / 1e9
        except (OSError, ValueError):
            return None
        return None

    def remove(self, timeout_s: float = 5.0) -> None:
        """Kill what is left in the group and remove it."""
        for path in (self.path, self.acct_path):
            if path:
                _remove_cgroup_dir(path, timeout_s)


def _remove_cgroup_dir(path: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while os.path.isdir(path):
        pids = []
        try:
            with open(os.path.join(path, 'cgroup.procs')) as f:
                pids = [int(x) for x in f.read().split()]
        except (OSError, ValueError):
            pass
        for pid in pids:
            send_signal(pid, signal.SIGKILL)
        try:
            os.rmdir(path)
            return
        except OSError as e:
            if time.monotonic() > deadline:
                raise TestbedError(f'{path}: cannot remove cgroup ({e}); pids {pids}') from None
            time.sleep(0.05)


def send_signal(pid: int, sig: int) -> None:
    """Signal a process that may have exited meanwhile (or is not ours to signal)."""
    try:
        os.kill(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


# --- the namespaces and the links ------------------------------------------------------------

@dataclass(frozen=True)
class LinkState:
    up: bool
    rate_kbps: float


@dataclass(frozen=True)
class Wire:
    """One link of the test-bed: a veth pair between two scales' namespaces."""

    name: str
    ends: Tuple[str, str]
    rate_kbps: float


def tbf_arguments(rate_kbps: float) -> List[str]:
    """tbf parameters for a rate: a 10 ms bucket (at least two full frames), 100 ms of queue
    (a WiFi driver's queue is of that order)."""
    if not rate_kbps > 0:
        raise ValueError(f'link rate must be > 0 kbit/s, got {rate_kbps!r}')
    burst = max(3200, int(rate_kbps * 1000 / 8 * 0.010))
    return ['tbf', 'rate', f'{int(round(rate_kbps))}kbit', 'burst', str(burst),
            'latency', '100ms']


def _interface(link: str, scale: str, index: int) -> str:
    """A link end's interface name (the kernel allows 15 characters)."""
    name = f'{link}-{scale}'
    return name if len(name) <= 15 else f'l{index}-{scale}'[:15]


class Network:
    """One namespace per scale, a shaped veth link per pair of scales the caller names, and
    per-scale CPU quotas.

    Each scale has one address (``addresses``: 10.77.0.1 for the first scale, .2 for the
    second, ...), set on every interface of its namespace, with a host route to each neighbour
    over the link that joins them; nothing is forwarded, so a packet between two scales crosses
    only their own link, and a scale reached over two links (the server, from the robot and from
    the laptop) has one address for both, as a host name does. By default: the ICAR test-bed's
    robot and laptop joined by one WiFi link (``wifi``) at ``rate_kbps``.
    """

    def __init__(self, rate_kbps: float = DEFAULT_RATE_KBPS,
                 cpu_cores: Optional[Mapping[str, Optional[float]]] = None,
                 subnet: str = DEFAULT_SUBNET, tag: Optional[str] = None,
                 scales: Sequence[str] = SCALES,
                 links: Optional[Sequence[Tuple[str, str, str, float]]] = None,
                 multicast: bool = True):
        """``links``: (name, end, end, rate kbit/s) each; default one link ``wifi`` joining
        the first two scales at ``rate_kbps``. ``multicast`` False: the devices' multicast flag
        off and no multicast route. That does not stop a socket that names its interface (DDS's
        do: the kernel then takes a group for on-link and sends; this kernel has no tc action
        to drop it): a test counts what crosses (test/fixtures/multicast_count.py)."""
        self.multicast = multicast
        self.tag = tag or f'{NAME_PREFIX}-{os.getpid()}-{next(_counter)}'
        self.scales = tuple(scales)
        if len(set(self.scales)) != len(self.scales) or len(self.scales) < 2 \
                or len(self.scales) > 250:
            raise ValueError(f'scales must be 2 to 250 distinct names, got {self.scales}')
        if links is None:
            links = [('wifi', self.scales[0], self.scales[1], rate_kbps)]
        self.wires: Dict[str, Wire] = {}
        for name, a, b, rate in links:
            if a not in self.scales or b not in self.scales or a == b:
                raise ValueError(f'link {name!r}: ends {a!r}, {b!r} must be two of '
                                 f'{", ".join(self.scales)}')
            if name in self.wires or any({a, b} == set(w.ends) for w in self.wires.values()):
                raise ValueError(f'link {name!r}: a second link of that name or pair')
            tbf_arguments(rate)      # validate before building anything
            self.wires[name] = Wire(name, (a, b), float(rate))
        self.namespaces = {s: f'{self.tag}-{s}' for s in self.scales}
        self.addresses = {s: f'{subnet}{i + 1}' for i, s in enumerate(self.scales)}
        self.interfaces = {(w.name, s): _interface(w.name, s, i)
                           for i, w in enumerate(self.wires.values()) for s in w.ends}
        self.cpu_cores = dict(cpu_cores or {})
        self.groups: Dict[str, CpuGroup] = {}
        self._state = {name: LinkState(True, w.rate_kbps) for name, w in self.wires.items()}
        self._built = False
        self._generation: Dict[Tuple[str, str], int] = {}     # the last root qdisc handle

    # -- life cycle --
    def setup(self) -> 'Network':
        if self._built:
            return self
        self._built = True            # from here on, teardown() has something to undo
        try:
            for ns in self.namespaces.values():
                _run(['ip', 'netns', 'add', ns])
                _run(['ip', '-n', ns, 'link', 'set', 'lo', 'up'])
            multicast_set = set()
            for wire in self.wires.values():
                a, b = wire.ends
                _run(['ip', 'link', 'add', self.interfaces[(wire.name, a)], 'netns',
                      self.namespaces[a], 'type', 'veth', 'peer', 'name',
                      self.interfaces[(wire.name, b)], 'netns', self.namespaces[b]])
                for scale, other in ((a, b), (b, a)):
                    ns, dev = self.namespaces[scale], self.interfaces[(wire.name, scale)]
                    mine = self.addresses[scale]
                    _run(['ip', '-n', ns, 'addr', 'add', mine + '/32', 'dev', dev])
                    _run(['ip', '-n', ns, 'link', 'set', dev, 'multicast',
                          'on' if self.multicast else 'off', 'up'])
                    _run(['ip', '-n', ns, 'route', 'add', self.addresses[other] + '/32',
                          'dev', dev, 'src', mine])
                    if scale not in multicast_set and self.multicast:
                        # DDS discovery multicast leaves by one link (a route per prefix);
                        # the neighbours over the others are static unicast peers
                        # (``peers``), and multicast loops back inside the namespace.
                        _run(['ip', '-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev])
                        multicast_set.add(scale)
                    self._shape(wire.name, scale)
            rt_runtime_us = min(RT_RUNTIME_MAX_US,
                                RT_RUNTIME_TOTAL_US // max(1, len(self.cpu_cores)))
            for scale, cores in self.cpu_cores.items():
                if scale not in self.scales:
                    raise ValueError(f'unknown scale {scale!r} for a CPU quota')
                group = CpuGroup(f'{self.tag}-{scale}', rt_runtime_us)
                self.groups[scale] = group
                group.set_cores(cores)
        except BaseException:
            self.teardown()
            raise
        return self

    def teardown(self) -> List[str]:
        """Kill every process left in the namespaces and cgroups, remove them; return problems."""
        problems: List[str] = []
        if not self._built:
            return problems
        for sig in (signal.SIGTERM, signal.SIGKILL):
            pids = self.leftover_pids()
            for pid in pids:
                send_signal(pid, sig)
            deadline = time.monotonic() + (1.0 if sig == signal.SIGTERM else 3.0)
            while pids and time.monotonic() < deadline:
                pids = [p for p in self.leftover_pids() if _alive(p)]
                time.sleep(0.05)
        for ns in self.namespaces.values():
            if ns in list_namespaces():
                try:
                    _run(['ip', 'netns', 'del', ns])
                except TestbedError as e:
                    problems.append(str(e))
        for group in self.groups.values():
            try:
                group.remove()
            except TestbedError as e:
                problems.append(str(e))
        self.groups = {}
        self._built = False
        return problems

    def __enter__(self) -> 'Network':
        return self.setup()

    def __exit__(self, *exc) -> None:
        self.teardown()

    def leftover_pids(self) -> List[int]:
        pids = set()
        for ns in self.namespaces.values():
            if ns in list_namespaces():
                out = _run(['ip', 'netns', 'pids', ns], check=False)
                pids.update(int(x) for x in out.split() if x.isdigit())
        for group in self.groups.values():
            pids.update(group.pids())
        pids.discard(os.getpid())
        return sorted(pids)

    def peers(self, scale: str) -> List[str]:
        """The addresses of the scales one link away from ``scale`` (its DDS static peers)."""
        return [self.addresses[other] for w in self.wires.values() if scale in w.ends
                for other in w.ends if other != scale]

    # -- the links --
    def _wire(self, link: Optional[str]) -> Wire:
        if link is None:
            if len(self.wires) != 1:
                raise ValueError(f'name a link: this network has {", ".join(self.wires)}')
            return next(iter(self.wires.values()))
        if link not in self.wires:
            raise ValueError(f'unknown link {link!r}; this network has '
                             f'{", ".join(self.wires)}')
        return self.wires[link]

    def _shape(self, link: str, scale: str) -> None:
        ns, dev = self.namespaces[scale], self.interfaces[(link, scale)]
        state = self._state[link]
        qdisc = tbf_arguments(state.rate_kbps) if state.up else ['blackhole']
        # Every change grafts a new root qdisc (its handle alternates 1:/2:). Replacing a tbf
        # with a tbf of the same handle only changes it in place, and a veth whose tbf is
        # changed with packets queued can stall for good (a throttle left 5-12 packets stuck,
        # and the link silent, in about 1 change of 12); a grafted qdisc starts clean and
        # drops what the old one held, as a WiFi rate change loses its queue.
        key = (link, scale)
        self._generation[key] = self._generation.get(key, 0) % 2 + 1
        handle = f'{self._generation[key]}:'
        _run(['tc', '-n', ns, 'qdisc', 'replace', 'dev', dev, 'root', 'handle', handle] + qdisc)

    def _set(self, wire: Wire, up: bool, rate_kbps: float) -> None:
        before = self._state[wire.name]
        self._state[wire.name] = LinkState(up, float(rate_kbps))
        if before.up or up:          # a throttle of a cut link applies on restore
            for scale in wire.ends:
                self._shape(wire.name, scale)

    def cut(self, link: Optional[str] = None) -> None:
        """Drop every packet on the link, both ways (interfaces stay up)."""
        wire = self._wire(link)
        self._set(wire, False, self._state[wire.name].rate_kbps)

    def restore(self, link: Optional[str] = None) -> None:
        wire = self._wire(link)
        self._set(wire, True, self._state[wire.name].rate_kbps)

    def throttle(self, rate_kbps: float, link: Optional[str] = None) -> None:
        """Shape both directions to ``rate_kbps`` (applies at once if up, else on restore)."""
        tbf_arguments(rate_kbps)
        wire = self._wire(link)
        self._set(wire, self._state[wire.name].up, rate_kbps)

    @property
    def link(self) -> LinkState:
        """The state of the only link (a network of several links: ``link_state(name)``)."""
        return self._state[self._wire(None).name]

    def link_state(self, link: str) -> LinkState:
        return self._state[self._wire(link).name]

    def qdisc(self, scale: str, link: Optional[str] = None) -> str:
        """The kernel's view of one end's root qdisc (for checks and the status table)."""
        wire = self._wire(link)
        return _run(['tc', '-n', self.namespaces[scale], 'qdisc', 'show', 'dev',
                     self.interfaces[(wire.name, scale)]]).strip()

    # -- processes --
    def command(self, scale: str, argv: Sequence[str], cpu_quota: bool = True) -> List[str]:
        """argv wrapped to run in ``scale``'s namespace (and its cgroup, joined before exec)."""
        if scale not in self.scales:
            raise ValueError(f'unknown scale {scale!r}; expected one of '
                             f'{", ".join(self.scales)}')
        # nsenter switches only the network namespace; ``ip netns exec`` would also remount
        # /sys, hiding /sys/fs/cgroup from the scale monitor inside.
        nsenter = shutil.which('nsenter') or '/usr/bin/nsenter'
        inner = [nsenter, f'--net={NETNS_RUN_DIR}/{self.namespaces[scale]}', '--'] + list(argv)
        group = self.groups.get(scale) if cpu_quota else None
        if group is None:
            return inner
        files = group.procs_files
        script = ('n=$1; shift; while [ "$n" -gt 0 ]; do echo $$ > "$1" || exit 125; '
                  'shift; n=$((n-1)); done; exec "$@"')
        return ['/bin/sh', '-c', script, 'sh', str(len(files))] + list(files) + inner

    def popen(self, scale: str, argv: Sequence[str], env: Mapping[str, str],
              cpu_quota: bool = True, **kwargs) -> subprocess.Popen:
        """Start argv inside ``scale``'s namespace and cgroup with exactly ``env``."""
        kwargs.setdefault('start_new_session', True)
        return subprocess.Popen(self.command(scale, argv, cpu_quota), env=dict(env), **kwargs)

    def run(self, scale: str, argv: Sequence[str], timeout: float = 10.0) -> str:
        """Run a short command inside ``scale``'s namespace (no quota) and return its output."""
        return _run(self.command(scale, argv, cpu_quota=False), timeout=timeout)

    def cpu_usage_s(self, scale: str) -> Optional[float]:
        group = self.groups.get(scale)
        return group.usage_s() if group else None


# --- leftovers --------------------------------------------------------------------------------

def list_namespaces() -> List[str]:
    out = _run(['ip', 'netns', 'list'], check=False)
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def remove_stale() -> List[str]:
    """Remove namespaces and cgroups left by test-bed runs whose process is gone."""
    removed = []
    for ns in list_namespaces():
        m = _NAME_RE.match(ns)
        if m and not _alive(int(m.group(1))):
            for pid in _run(['ip', 'netns', 'pids', ns], check=False).split():
                send_signal(int(pid), signal.SIGKILL)
            _run(['ip', 'netns', 'del', ns], check=False)
            removed.append(ns)
    mode, root = cgroup_mode()
    roots = [root] if mode else []
    acct = _cpuacct_mount() if mode == 'v1' else None
    if acct:
        roots.append(acct)
    for base in roots:
        try:
            names = os.listdir(base)
        except OSError:
            continue
        for name in names:
            m = _NAME_RE.match(name)
            path = os.path.join(base, name)
            if m and os.path.isdir(path) and not _alive(int(m.group(1))):
                try:
                    _remove_cgroup_dir(path, 2.0)
                    removed.append(path)
                except TestbedError:
                    pass
    return removed


__all__ = ['CpuGroup', 'LinkState', 'Network', 'SCALES', 'TestbedError', 'Wire', 'available',
           'cgroup_mode', 'list_namespaces', 'remove_stale', 'tbf_arguments']
