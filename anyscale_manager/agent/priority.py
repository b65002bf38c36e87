"""Critical nodes at real-time priority (``agent.critical_priority``).

A critical node is in a tolerance-0 connection: its output may never be below its minimum. On a
scale whose CPU is full, a node at normal priority waits for a core behind the others however
low their niceness: a CPU quota (a systemd ``CPUQuota``, a cgroup's ``cpu.max``) stops every
normal-priority thread of the group once the group has spent its share, and the heavy nodes
spend it. Real-time round robin (``SCHED_RR``) runs the node ahead of every normal-priority
thread as soon as it wakes, and a quota does not stop it.

The node starts at normal priority and is raised ``SETTLE_S`` after it is ready (seen in the
ROS graph): its start-up (the interpreter, the middleware, the discovery of its peers, which
goes on after it is seen) is the heaviest work it does, and at real-time priority it would take
the scale's cores from everything else and spend the real-time budget of a group where the
kernel keeps one (cgroup v1 ``cpu.rt_runtime_us``), stopping every critical node of the group
for the rest of the second (0.42 s on the test-bed's robot, a critical node raised as soon as
seen in a crash loop). Every thread of the node is raised; a thread it starts later inherits
the policy of the thread that starts it.

Raising needs CAP_SYS_NICE (or an ``RLIMIT_RTPRIO``) and, where the kernel schedules real-time
threads by cgroup, a real-time budget in the node's group. Refused once, it is said once and
not tried again: the critical nodes then run at normal priority, as before.
"""

import os
from typing import Optional

SETTLE_S = 2.0


def advice(setting: str) -> str:
    """What to do where real-time priority is refused (the agent's ``setting`` asked for it)."""
    return ('Grant CAP_SYS_NICE to the agent (systemd: AmbientCapabilities=CAP_SYS_NICE) or '
            f'set agent.{setting} to 0')


def set_realtime(tid: int, priority: int) -> Optional[str]:
    """Thread (or process) ``tid`` (0: the caller) to real-time round robin ``priority``.
    None when done or the thread is gone, else why not."""
    try:
        os.sched_setscheduler(tid, os.SCHED_RR, os.sched_param(priority))
    except ProcessLookupError:
        return None                             # that thread has ended
    except OSError as e:
        return e.strerror or str(e)
    return None


def raise_threads(pid: int, priority: int, rounds: int = 5) -> Optional[str]:
    """Every thread of ``pid`` to real-time round robin ``priority``, until no new thread
    appears. None when done (or the process is gone: nothing left to raise), else why not."""
    done = set()
    for _ in range(rounds):
        try:
            tids = {int(t) for t in os.listdir(f'/proc/{pid}/task')}
        except OSError:
            return None
        fresh = tids - done
        if not fresh:
            return None
        for tid in sorted(fresh):
            why = set_realtime(tid, priority)
            if why is not None:
                return why
        done |= fresh
    return None


class Realtime:
    """Raises the critical nodes as they become ready; says the outcome once."""

    def __init__(self, priority: int):
        self.priority = priority
        self.refused = False
        self._said = False

    def raise_node(self, name: str, pid: int) -> str:
        """Raise ``pid``; what to say ('' when nothing is new)."""
        if self.priority <= 0 or self.refused:
            return ''
        why = raise_threads(pid, self.priority)
        if why is not None:
            self.refused = True
            return (f'critical nodes run at normal priority: real-time priority '
                    f'{self.priority} refused for {name} ({why}); on a full CPU they can then '
                    f'wait behind the other nodes. {advice("critical_priority")}')
        if self._said:
            return ''
        self._said = True
        return (f'critical nodes run at real-time priority {self.priority} (SCHED_RR) once '
                f'ready: {name} is the first')
