"""Files the package ships in share/anyscale_manager/config (config/ of the source tree when it
runs from there), and the Fast DDS discovery profile every process of a deployment should use."""

import os
from typing import Dict, List, MutableMapping, Optional

DISCOVERY_PROFILE = 'fastdds_discovery.xml'
# The profile under discovery.mode server (docs/discovery.md), in place of the one above.
SERVER_PROFILE = 'fastdds_discovery_server.xml'
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


def is_packaged(path: str) -> bool:
    """Whether ``path`` is one of the package's own discovery profiles."""
    ours = {os.path.realpath(p) for name in (DISCOVERY_PROFILE, SERVER_PROFILE)
            for p in candidates(name)}
    return os.path.realpath(path) in ours


def with_server_profile(env: MutableMapping[str, str]) -> Dict[str, str]:
    """The variables that name the packaged profile for discovery servers' clients
    (``SERVER_PROFILE``) in ``env``: where it names no profile or a packaged one (empty: a
    user's own profile, kept)."""
    named = [env.get(v) for v in PROFILE_VARS if env.get(v)]
    if any(not is_packaged(p) for p in named):
        return {}
    path = find(SERVER_PROFILE)
    if path is None:
        return {}
    return {v: path for v in PROFILE_VARS if env.get(v)} or {PROFILE_VARS[0]: path}
