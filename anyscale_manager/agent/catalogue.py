"""What one scale's agent may start: argv and environment per node, built from the deployment.

The catalogue is the only source of commands: a layout names nodes, never commands, so the agent
starts nothing that is not in here. Every entry is resolved once, when the agent starts; an entry
that cannot be resolved carries its problem and is reported as failed instead of started.
"""

import os
import shutil
import sys
from dataclasses import dataclass, field
from typing import Callable, Dict, Mapping, Optional, Tuple

from ..model import types as t

# Variables a child inherits from the agent; everything else comes from launch.env.
# _ROS_WHEELS_BOOTSTRAP_COMPLETE: set by the pip-installed ROS wheels once LD_LIBRARY_PATH is
# right (it is passed on too); without it every Python child re-executes itself (~40 ms).
BASE_ENV_NAMES = ('PATH', 'HOME', 'LANG', 'LC_ALL', 'PYTHONPATH', 'AMENT_PREFIX_PATH',
                  'LD_LIBRARY_PATH', 'USER', 'LOGNAME', 'TZ', '_ROS_WHEELS_BOOTSTRAP_COMPLETE')
BASE_ENV_PREFIXES = ('ROS_', 'RMW_', 'RCUTILS_', 'FASTRTPS_', 'FASTDDS_', 'CYCLONEDDS_')
# The agent is a discovery servers' super client (it learns message types from the graph);
# its nodes are plain clients.
NOT_INHERITED = ('ROS_SUPER_CLIENT',)
DDS_TRANSPORTS = 'FASTDDS_BUILTIN_TRANSPORTS'
ENV_NODE = 'ANYSCALE_AGENT_NODE'          # marks a child: which catalogue entry it is
ENV_SCALE = 'ANYSCALE_AGENT_SCALE'        # and which scale's agent started it
ENV_INSTANCE = 'ANYSCALE_AGENT_INSTANCE'  # a per-start token, checked when adopting
# A lifecycle node's services and transition topic, under its own name (``~/...``). Copies of
# one node on several scales share that name, so one request to ``/amcl/change_state`` would
# reach them all: each copy gets them remapped to ``~/<scale>/...`` when it starts.
LIFECYCLE_SERVICES = ('change_state', 'get_state', 'get_available_states',
                      'get_available_transitions', 'get_transition_graph')
LIFECYCLE_TOPICS = ('transition_event',)


@dataclass(frozen=True)
class Entry:
    """One startable node: a complete argv and an explicit environment."""

    name: str
    argv: Tuple[str, ...]
    env: Mapping[str, str] = field(default_factory=t.frozen_map)
    ros_name: str = ''
    move_order: str = t.START_BEFORE_STOP
    problem: str = ''           # why it cannot be started ('' = it can)
    lifecycle: bool = False
    services: str = ''          # a lifecycle copy's service namespace: '/amcl/robot'
    nice: int = 0               # the node's own niceness, added to agent.node_nice
    critical: bool = False      # pinned by a tolerance-0 connection: not niced by node_nice
    # A node with ``state:``: where it publishes its state, and the prefix of each started
    # process's own restore input (its ``restore`` topic remapped under it per start,
    # ``copy_restore_topic``: only that process hears what it is handed).
    state_topic: str = ''
    restore_topic: str = ''
    restore_input: str = ''     # the node's own restore topic, as others publish to it

    @property
    def startable(self) -> bool:
        return not self.problem and bool(self.argv)


def base_environment(environ: Mapping[str, str]) -> Dict[str, str]:
    """The minimal inherited environment: paths, locale and the ROS middleware settings."""
    out = {k: v for k, v in environ.items()
           if (k in BASE_ENV_NAMES or k.startswith(BASE_ENV_PREFIXES))
           and k not in NOT_INHERITED}
    # Children write to log files: unbuffered Python output keeps them readable after a crash.
    out.setdefault('PYTHONUNBUFFERED', '1')
    return out


def _ament_prefix(package: str) -> Optional[str]:
    try:
        from ament_index_python.packages import get_package_prefix
    except ImportError:
        return None
    try:
        return get_package_prefix(package)
    except (LookupError, OSError, ValueError):
        # PackageNotFoundError is a KeyError; an unset AMENT_PREFIX_PATH is an EnvironmentError.
        return None


def _is_executable(path: str) -> bool:
    return os.path.isfile(path) and os.access(path, os.X_OK)


def resolve_executable(package: str, executable: str, search_path: str,
                       ament_prefix: Callable[[str], Optional[str]] = _ament_prefix
                       ) -> Tuple[str, str]:
    """Find a package's executable: (path, '') or ('', problem).

    Order: <prefix>/lib/<package>/<executable> from the ament index; the executable next to the
    running interpreter (a virtual environment's editable install has no ament index entry);
    then PATH.
    """
    tried = []
    prefix = ament_prefix(package)
    if prefix:
        candidate = os.path.join(prefix, 'lib', package, executable)
        if _is_executable(candidate):
            return candidate, ''
        tried.append(candidate)
    else:
        tried.append(f'ament index (package {package!r} not found)')
    beside = os.path.join(os.path.dirname(sys.executable), executable)
    if _is_executable(beside):
        return beside, ''
    tried.append(beside)
    found = shutil.which(executable, path=search_path)
    if found:
        return found, ''
    tried.append('PATH')
    return '', f'executable {executable!r} of package {package!r} not found (tried ' \
               f'{", ".join(tried)})'


def format_parameter(value: object) -> str:
    """A value as rcl's YAML parser reads it back with the same type."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(format_parameter(v) for v in value) + ']'
    text = str(value)
    # Quote every string so '5', 'true' or 'null' stay strings.
    return "'" + text.replace("'", "''") + "'"


def build_argv(node: t.Node, search_path: str,
               ament_prefix: Callable[[str], Optional[str]] = _ament_prefix,
               scale: str = '') -> Tuple[Tuple[str, ...], str]:
    """The full argv of a node's launch, or ((), problem); a lifecycle node's services are
    remapped under ``scale``."""
    launch = node.launch
    if launch.command:
        head = list(launch.command)
        if os.sep not in head[0]:
            found = shutil.which(head[0], path=search_path)
            if not found:
                return (), f'command {head[0]!r} not found on PATH'
            head[0] = found
    elif launch.package and launch.executable:
        path, problem = resolve_executable(launch.package, launch.executable, search_path,
                                           ament_prefix)
        if problem:
            return (), problem
        head = [path]
    else:
        return (), 'no command and no package/executable to start'
    argv = head + list(launch.arguments) + ['--ros-args', '-r',
                                            f'__node:={ros_base_name(node)}']
    full = ros_full_name(node)
    if full.startswith('/') and full.count('/') > 1:
        argv += ['-r', f'__ns:={full.rsplit("/", 1)[0]}']
    for key in sorted(launch.parameters):
        argv += ['-p', f'{key}:={format_parameter(launch.parameters[key])}']
    if node.lifecycle and scale:
        for name in LIFECYCLE_SERVICES + LIFECYCLE_TOPICS:
            argv += ['-r', f'~/{name}:=~/{scale}/{name}']
    return tuple(argv), ''


def restore_topic(node: t.Node, scale: str) -> str:
    """The prefix of the restore topics of ``scale``'s copies of a node with ``state:``:
    '/ns/amcl/robot/restore' (beside its lifecycle services)."""
    return lifecycle_services(node, scale) + '/restore'


def copy_restore_topic(entry: Entry, instance: str) -> str:
    """The restore topic of one started process of ``entry`` (``instance``: its per-start
    token): a process of its own, so that a copy killed a moment ago, whose reader DDS still
    counts until its lease ends, never holds up the hand-over to the copy that follows it."""
    return f'{entry.restore_topic}/i{instance[:16]}'


def restore_remap(entry: Entry, instance: str) -> Tuple[str, ...]:
    """The ROS arguments that give one started process its own restore topic ('' entries: none)."""
    if not entry.restore_topic:
        return ()
    return ('-r', f'{entry.restore_input}:={copy_restore_topic(entry, instance)}')


def lifecycle_services(node: t.Node, scale: str) -> str:
    """Where ``scale``'s copy of a lifecycle node serves its lifecycle: '/ns/amcl/robot'."""
    full = ros_full_name(node)
    return ('' if full.startswith('/') else '/') + f'{full}/{scale}'


def ros_base_name(node: t.Node) -> str:
    """The node's name without namespace: what __node remaps."""
    name = node.launch.ros_name or node.name
    return name.rstrip('/').rsplit('/', 1)[-1]


def ros_full_name(node: t.Node) -> str:
    """The name the readiness check looks for: '/ns/name' or 'name'."""
    return node.launch.ros_name or node.name


def build_catalogue(deployment: t.Deployment, scale: str,
                    environ: Optional[Mapping[str, str]] = None,
                    ament_prefix: Callable[[str], Optional[str]] = _ament_prefix,
                    ) -> Dict[str, Entry]:
    """Every managed, startable node that may run on ``scale``, in deployment order."""
    if scale not in deployment.scale_names:
        raise ValueError(f'{deployment.source}: unknown scale {scale!r} (scales: '
                         f'{", ".join(deployment.scale_names)})')
    environ = os.environ if environ is None else environ
    base = base_environment(environ)
    out = {}
    critical = set(deployment.critical_nodes)
    for node in deployment.nodes:
        if not node.managed or not node.launch.startable:
            continue
        if scale not in deployment.allowed_scales(node.name):
            continue
        env = dict(base)
        if deployment.agent.node_dds_transports:
            env.setdefault(DDS_TRANSPORTS, deployment.agent.node_dds_transports)
        env.update({str(k): str(v) for k, v in node.launch.env.items()})
        env[ENV_NODE] = node.name
        env[ENV_SCALE] = scale
        argv, problem = build_argv(node, env.get('PATH', os.defpath), ament_prefix, scale)
        out[node.name] = Entry(name=node.name, argv=argv, env=t.frozen_map(env),
                               ros_name=ros_full_name(node), move_order=node.move_order,
                               problem=problem, lifecycle=node.lifecycle,
                               services=lifecycle_services(node, scale) if node.lifecycle
                               else '', nice=node.nice, critical=node.name in critical,
                               state_topic=node.state.topic if node.state else '',
                               restore_topic=restore_topic(node, scale) if node.state else '',
                               restore_input=node.state.restore if node.state else '')
    return out
