"""Fast DDS shared-memory port files that a killed process left empty, found and removed.

Fast DDS (the default ROS 2 Jazzy middleware) gives each participant on a computer a
shared-memory port: a file ``/dev/shm/fastrtps_port<N>``, created and then sized. A process
killed between the two (SIGKILL while it starts: an agent's last resort, an OOM kill, a crash)
leaves the file empty, and every later participant that picks port N spins inside
``rclpy.init()`` for good, deaf to SIGINT and SIGTERM (seen here: a node that never came up,
and every node after it). A port file is sized in microseconds, so one that is still empty
seconds after it was made is broken, whoever made it; removing it lets the next participant
create it again. Files of other kinds (segments, ``_el``/``_sl`` locks, semaphores) are left
alone. Pure file-system code, no ROS.
"""

import os
import re
import time
from typing import Callable, List, Optional

SHM_DIR = '/dev/shm'
PORT_FILE = re.compile(r'fastrtps_port\d+')
# Far above the time from creating a port file to sizing it, even for a process that a CPU
# quota holds back for a whole period (100 ms).
MIN_AGE_S = 5.0


def broken_port_files(directory: str = SHM_DIR, now: Optional[float] = None,
                      min_age_s: float = MIN_AGE_S) -> List[str]:
    """Paths of the empty Fast DDS port files in ``directory`` older than ``min_age_s``."""
    now = time.time() if now is None else now
    try:
        names = os.listdir(directory)
    except OSError:
        return []
    found = []
    for name in sorted(names):
        if not PORT_FILE.fullmatch(name):
            continue
        path = os.path.join(directory, name)
        try:
            st = os.stat(path)
        except OSError:
            continue
        if st.st_size == 0 and now - st.st_mtime >= min_age_s:
            found.append(path)
    return found


def remove_broken_port_files(directory: str = SHM_DIR, now: Optional[float] = None,
                             min_age_s: float = MIN_AGE_S,
                             say: Optional[Callable[[str], None]] = None) -> List[str]:
    """Remove what ``broken_port_files`` finds; return the paths removed (``say`` each)."""
    removed = []
    for path in broken_port_files(directory, now, min_age_s):
        try:
            if os.stat(path).st_size != 0:      # sized meanwhile: not broken after all
                continue
            os.unlink(path)
        except OSError:
            continue
        removed.append(path)
        if say is not None:
            say(f'removed {path}: an empty Fast DDS shared-memory port file (its creator was '
                'killed while starting); a participant that picked its port would hang')
    return removed
