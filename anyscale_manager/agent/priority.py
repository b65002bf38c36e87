"""Critical nodes at real-time priority (``agent.critical_priority``).

A critical node is in a tolerance-0 connection: its output may never be below its minimum. On a
scale whose CPU is full, a node at normal priority waits for a core behind the others however
low their niceness: a CPU quota (a systemd ``CPUQuota``, a cgroup's ``cpu.max``) stops every
normal-priority thread of the group once the group has spent its share, and the heavy nodes
spend it. Real-time round robin (``SCHED_RR``) runs the node ahead of every normal-priority
thread as soon as it wakes, and a quota does not stop it. ``chrt -r`` sets the policy and execs
the node (same pid; every thread it starts inherits the policy), as ``nice -n`` does for
``agent.node_nice``.

Setting a real-time policy needs CAP_SYS_NICE (or an ``RLIMIT_RTPRIO``) and, where the kernel
schedules real-time threads by cgroup, a real-time budget in the node's group. ``Launch`` tries
it once with a process of no consequence and says what it found: without it the critical nodes
run at normal priority, each as before.
"""

import subprocess
from typing import List, Optional, Tuple

CHRT = 'chrt'


def try_realtime(priority: int, chrt: str = CHRT) -> Tuple[bool, str]:
    """Whether a process started here may run at real-time round robin ``priority``: ``chrt``
    runs ``true`` at it. (ok, what the refusal said)."""
    try:
        out = subprocess.run([chrt, '-r', str(priority), 'true'], stdin=subprocess.DEVNULL,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             timeout=10.0)
    except (OSError, subprocess.TimeoutExpired) as e:
        return False, f'{chrt}: {getattr(e, "strerror", None) or e}'
    if out.returncode != 0:
        return False, (out.stdout.strip().splitlines() or [f'exit {out.returncode}'])[-1]
    return True, ''


class Launch:
    """The command prefix of a critical node, decided at the first critical start."""

    def __init__(self, priority: int, chrt: str = CHRT):
        self.priority = priority
        self.chrt = chrt
        self._prefix: Optional[List[str]] = None

    def critical_prefix(self) -> Tuple[List[str], str]:
        """(prefix, what to say once: '' after the first call or when there is nothing to
        say). The prefix is empty with ``critical_priority`` 0 or when the kernel refuses."""
        if self.priority <= 0:
            return [], ''
        if self._prefix is not None:
            return self._prefix, ''
        ok, why = try_realtime(self.priority, self.chrt)
        if ok:
            self._prefix = [self.chrt, '-r', str(self.priority)]
            return self._prefix, (f'critical nodes run at real-time priority {self.priority} '
                                  '(SCHED_RR)')
        self._prefix = []
        return self._prefix, (
            f'critical nodes run at normal priority: real-time priority {self.priority} '
            f'refused ({why}); on a full CPU they can then wait behind the other nodes. '
            'Grant CAP_SYS_NICE to the agent (systemd: AmbientCapabilities=CAP_SYS_NICE) or '
            'set agent.critical_priority to 0')
