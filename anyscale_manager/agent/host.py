"""The identity of the machine an agent runs on, which it reports in every AgentState: scales
whose agents report one identity share a machine (single-machine mode, runtime/hosts.py)."""

import socket
from typing import Tuple

from ..runtime.hosts import identity_from

BOOT_ID = '/proc/sys/kernel/random/boot_id'
MACHINE_ID = '/etc/machine-id'


def _first_line(path: str) -> str:
    try:
        with open(path) as f:
            return f.readline().strip()
    except OSError:
        return ''


def this_host(boot_id_path: str = BOOT_ID, machine_id_path: str = MACHINE_ID
              ) -> Tuple[str, str]:
    """(host id, host name) of this machine: the kernel's boot id, else the machine id, else
    the host name (runtime/hosts.identity_from)."""
    name = socket.gethostname()[:256]
    return identity_from(_first_line(boot_id_path), _first_line(machine_id_path), name), name
