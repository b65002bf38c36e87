"""How the test-bed acts on its links and where its processes run: one class per network mode.

``NamespaceLinks`` builds a namespace per scale, a shaped veth pair per link and CPU quota
cgroups (``netns.Network``): each link is cut, restored and throttled alone, each process starts
inside its scale's namespace (and cgroup), discovery stays on the namespace pairs.
``LoopbackLinks`` runs two scales on this machine's loopback and emulates their one link: a cut
freezes (SIGSTOP) the laptop agent and every process it started, a restore thaws them; a
throttle cannot be emulated and is refused with the reason, and there are no CPU quotas.
``LinkControl`` itself is the test-bed with nothing built, before it starts and after it stops.

The harness picks the mode once when it starts (``choose``) and from then on calls the control
it built, never the mode: both classes answer the same calls.
"""

import os
import signal
import socket
import subprocess
from typing import Callable, List, Mapping, Optional, Sequence, Tuple

import psutil

from . import netns
from .errors import HarnessError

NETNS, LOOPBACK = 'netns', 'loopback'
MODES = ('auto', NETNS, LOOPBACK)


def choose(mode: str, available: Callable[[], Tuple[bool, str]] = netns.available
           ) -> Tuple[str, str]:
    """The mode a test-bed asked to run in ``mode`` (auto, netns or loopback) runs in, and
    why: auto takes namespaces where ``available()`` says they can be built, else loopback;
    netns without them is an error."""
    if mode not in MODES:
        raise HarnessError(f'unknown mode {mode!r}')
    if mode == LOOPBACK:
        return LOOPBACK, 'loopback asked for: the link is emulated'
    ok, why = available()
    if ok:
        return NETNS, why
    if mode == NETNS:
        raise HarnessError(f'network namespaces not available: {why}')
    return LOOPBACK, (f'no network namespaces ({why}): running on loopback with the link '
                      "emulated (a cut freezes the laptop's processes; no bandwidth shaping, "
                      'no CPU quotas)')


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class LinkControl:
    """The links of a test-bed with nothing built: nothing to cut, restore or throttle, nowhere
    to start a process. Each mode's class answers the same calls."""

    mode = ''
    network: Optional[netns.Network] = None
    # An observer on every scale: each scale is a network of its own, so what an observer
    # hears while its scale's link is cut is what that scale hears.
    observer_per_scale = False
    # A cut acts on the processes behind the link, not on a network: a boot with the link cut
    # cuts once they run.
    cuts_processes = False

    def setup(self) -> None:
        """Build what the mode needs; on an error, leave nothing built."""

    def cut(self, link: str) -> None:
        """Drop everything on ``link``, both ways."""

    def restore(self, link: str) -> None:
        """Undo a cut of ``link``."""

    def throttle(self, rate_kbps: float, link: str) -> None:
        """Shape ``link`` to ``rate_kbps`` both ways."""
        raise HarnessError('cannot throttle: the test-bed is not running')

    def popen(self, scale: str, argv: Sequence[str], env: Mapping[str, str], quota: bool,
              stdout, stderr) -> subprocess.Popen:
        """Start ``argv`` on ``scale`` (``quota``: inside its CPU quota) in a session of its
        own, with exactly ``env``."""
        raise HarnessError('the test-bed is not running: nowhere to start a process')

    def discovery_peers(self, scale: str) -> Optional[str]:
        """The DDS static peers of a process on ``scale`` (``ROS_STATIC_PEERS``), or None for
        discovery on loopback."""
        return None

    def ros_parameters(self) -> List[str]:
        """The ``-p NAME:=VALUE`` arguments that tell the decider and the agents where each
        scale is."""
        return []

    def cpu_group(self, scale: str) -> Optional[netns.CpuGroup]:
        """The CPU quota cgroup of ``scale``, None without quotas."""
        return None

    def cpu_usage_s(self, scale: str) -> Optional[float]:
        """CPU seconds used so far by every process in ``scale``'s cgroup, None without one."""
        return None

    def release(self) -> None:
        """Before the stop: let every process behind a cut link run again, so it can take its
        SIGINT."""

    def teardown(self) -> List[str]:
        """Remove what ``setup`` built; return what had to be force-cleaned."""
        return []


class NamespaceLinks(LinkControl):
    """A namespace per scale, a shaped veth link per link of the deployment, CPU quotas."""

    mode = NETNS
    observer_per_scale = True

    def __init__(self, scales: Sequence[str], links: Sequence[Tuple[str, str, str, float]],
                 cpu_cores: Mapping[str, float], multicast: bool = True):
        """``links``: (name, end, end, rate kbit/s) each; ``cpu_cores``: the quota of each
        scale, in cores of this machine (empty: no quotas); ``multicast`` False: the links
        carry none."""
        self._multicast = multicast
        self._scales = tuple(scales)
        self._links = list(links)
        self._cpu_cores = dict(cpu_cores)

    def setup(self) -> None:
        netns.remove_stale()
        # Network.setup tears down what it built when a step fails.
        self.network = netns.Network(cpu_cores=self._cpu_cores, scales=self._scales,
                                     links=self._links, multicast=self._multicast).setup()

    def cut(self, link: str) -> None:
        self.network.cut(link)

    def restore(self, link: str) -> None:
        self.network.restore(link)

    def throttle(self, rate_kbps: float, link: str) -> None:
        self.network.throttle(rate_kbps, link)

    def popen(self, scale: str, argv: Sequence[str], env: Mapping[str, str], quota: bool,
              stdout, stderr) -> subprocess.Popen:
        return self.network.popen(scale, argv, env, cpu_quota=quota, stdout=stdout,
                                  stderr=stderr)

    def discovery_peers(self, scale: str) -> Optional[str]:
        return ';'.join(self.network.peers(scale))

    def ros_parameters(self) -> List[str]:
        args: List[str] = []
        for scale, ip in self.network.addresses.items():
            args += ['-p', f'scales.{scale}.host:={ip}']
        return args

    def cpu_group(self, scale: str) -> Optional[netns.CpuGroup]:
        return self.network.groups.get(scale)

    def cpu_usage_s(self, scale: str) -> Optional[float]:
        return self.network.cpu_usage_s(scale)

    def teardown(self) -> List[str]:
        notes = []
        stray = self.network.leftover_pids()
        if stray:
            notes.append(f'processes left in the namespaces/cgroups: {stray}')
        notes.extend(self.network.teardown())
        return notes


class LoopbackLinks(LinkControl):
    """Two scales on loopback, their one link emulated by freezing the laptop's processes."""

    mode = LOOPBACK
    cuts_processes = True

    def __init__(self, scales: Sequence[str], laptop_agent: Callable[[], Optional[int]]):
        """``laptop_agent()``: the pid of the laptop's agent while it runs, else None."""
        self._scales = tuple(scales)
        self._laptop_agent = laptop_agent
        self._frozen: List[int] = []
        self.probe_port = 0

    def setup(self) -> None:
        # The bandwidth probes of every scale listen on this one machine: a free base port.
        self.probe_port = free_tcp_port()

    def _laptop_pids(self) -> List[int]:
        pid = self._laptop_agent()
        if pid is None:
            return []
        try:
            root = psutil.Process(pid)
            return [root.pid] + [c.pid for c in root.children(recursive=True)]
        except psutil.Error:
            return []

    def cut(self, link: str) -> None:
        pids = self._laptop_pids()
        _signal_each(pids, signal.SIGSTOP)
        self._frozen = pids

    def restore(self, link: str) -> None:
        self.release()

    def throttle(self, rate_kbps: float, link: str) -> None:
        raise HarnessError('cannot throttle on loopback: bandwidth shaping needs network '
                           'namespaces (root)')

    def popen(self, scale: str, argv: Sequence[str], env: Mapping[str, str], quota: bool,
              stdout, stderr) -> subprocess.Popen:
        return subprocess.Popen(list(argv), env=env, stdout=stdout, stderr=stderr,
                                start_new_session=True)

    def ros_parameters(self) -> List[str]:
        args: List[str] = []
        for scale in self._scales:
            args += ['-p', f'scales.{scale}.host:=127.0.0.1']
        return args + ['-p', f'monitoring.bandwidth_probe_port:={self.probe_port}']

    def release(self) -> None:
        _signal_each(self._frozen, signal.SIGCONT)
        self._frozen = []


def _signal_each(pids: Sequence[int], sig: int) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


__all__ = ['LOOPBACK', 'LinkControl', 'LoopbackLinks', 'MODES', 'NETNS', 'NamespaceLinks',
           'choose', 'free_tcp_port']
