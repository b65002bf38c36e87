"""Files the package ships in share/anyscale_manager/config (config/ of the source tree when it
runs from there), and the Fast DDS discovery profile every process of a deployment should use."""

import os
from typing import Dict, List, MutableMapping, Optional

DISCOVERY_PROFILE = 'fastdds_discovery.xml'
# Jazzy's Fast DDS (2.x) reads this variable; Fast DDS 3 reads FASTDDS_DEFAULT_PROFILES_FILE.
PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def candidates(name: str) -> List[str]:
    """Where ``name`` may be: the installed share directory first, then the source tree."""
    out = []
    try:
        from ament_index_python.packages import get_package_share_directory
        out.append(os.path.join(get_package_share_directory('anyscale_manager'), 'config', name))
    except Exception:   # not installed with colcon, or ament_index missing: the source tree
        pass
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out.append(os.path.join(here, 'config', name))
    return out


def find(name: str) -> Optional[str]:
    """The first existing file of ``candidates(name)``, or None."""
    return next((p for p in candidates(name) if os.path.isfile(p)), None)


def with_discovery_profile(env: MutableMapping[str, str]) -> Dict[str, str]:
    """``env`` with the packaged discovery profile named, unless it already names a profile
    (a user's own profile wins; it then needs its own leaseAnnouncement, see docs/agent.md)."""
    out = dict(env)
    if any(out.get(v) for v in PROFILE_VARS):
        return out
    path = find(DISCOVERY_PROFILE)
    if path is not None:
        out[PROFILE_VARS[0]] = path
    return out
