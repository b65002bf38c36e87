"""Frozen dataclasses describing one deployment: scales, links, nodes, connections, settings."""

from dataclasses import dataclass, field, fields
from functools import cached_property
from types import MappingProxyType
from typing import Any, ClassVar, Dict, FrozenSet, List, Mapping, Optional, Protocol, Tuple, \
    TypeVar

K = TypeVar('K')
V = TypeVar('V')

MASTER = 'master'
REMOTE = 'remote'
ROBOT = 'robot'
SERVER = 'server'
WIRED = 'wired'
WIRELESS = 'wireless'
START_BEFORE_STOP = 'start_before_stop'
STOP_BEFORE_START = 'stop_before_start'
REGRESSION_FORMS = ('linear', 'log', 'poly2', 'poly3', 'quadratic')
INITIAL_LAYOUTS = ('master', 'problem1', 'problem2', 'explicit')
HYSTERESIS_SCOPES = ('scale', 'node')


def frozen_map(mapping: Optional[Mapping[K, V]] = None) -> Mapping[K, V]:
    return MappingProxyType(dict(mapping or {}))


class Dataclass(Protocol):
    """Any dataclass (what ``dataclasses.fields`` and ``replace`` take)."""

    __dataclass_fields__: ClassVar[Dict[str, Any]]


@dataclass(frozen=True)
class Scale:
    """A computer that can run nodes; CPU in percent of one reference core."""

    name: str
    role: str                 # master | remote
    kind: str                 # robot | server
    capacity_cpu: float       # reference-core percent (a 2-core robot of the reference: 200)
    cores: int
    clock_ghz: float
    # The ICAR cost function's alpha_k as the file gives it; None: derived from its power
    # (Deployment.worth).
    gain: Optional[float]
    host: str
    port: int = 0             # its warden's UDP and probe TCP port; 0: derived (scale_port)
    # Used by other deployments too (a fleet's server): its agent starts a copy only under a
    # claim of the host's ledger (agent/ledger.py).
    shared: bool = False
    memory_mb: float = 0.0    # the memory its copies may hold (a shared host's claims); 0: any

    @property
    def is_master(self) -> bool:
        return self.role == MASTER

    @property
    def power(self) -> float:
        """Raw compute power (cores x GHz); the paper sorts remote scales by it."""
        return self.cores * self.clock_ghz


@dataclass(frozen=True)
class Link:
    """A network link between two scales; bandwidth in kbit/s, both directions summed."""

    name: str
    ends: Tuple[str, str]
    bandwidth_kbps: float
    medium: str               # wired | wireless

    def joins(self, a: str, b: str) -> bool:
        return {a, b} == set(self.ends)

    def other(self, scale: str) -> str:
        return self.ends[1] if self.ends[0] == scale else self.ends[0]


@dataclass(frozen=True)
class Launch:
    """How an agent starts a node: a package executable or an explicit command."""

    package: str = ''
    executable: str = ''
    command: Tuple[str, ...] = ()
    arguments: Tuple[str, ...] = ()
    env: Mapping[str, str] = field(default_factory=frozen_map)
    parameters: Mapping[str, object] = field(default_factory=frozen_map)
    ros_name: str = ''        # the node's name in the ROS graph (readiness check)

    @property
    def startable(self) -> bool:
        return bool(self.command) or bool(self.package and self.executable)


@dataclass(frozen=True)
class Settings:
    """Profiling samples of one configurable node: parameter value, CPU and performance."""

    parameter: str
    values: Tuple[float, ...]
    cpu: Tuple[float, ...]
    performance: Tuple[float, ...]
    form: str = 'linear'      # the CPU -> performance regression form
    parameter_form: str = 'linear'   # the parameter -> CPU regression form
    frequency_hz: Tuple[float, ...] = ()  # expected output frequency per sample, when known

    @property
    def configurable(self) -> bool:
        return len(self.cpu) > 1

    @property
    def cpu_min(self) -> float:
        return min(self.cpu)

    @property
    def cpu_max(self) -> float:
        return max(self.cpu)


@dataclass(frozen=True)
class StateSpec:
    """How a node's state goes with it to the copy that takes over (docs/lifecycle.md, state).

    ``topic``: an output whose latest message holds the node's state (Nav2 AMCL: /amcl_pose);
    ``restore``: the input on which a copy takes a message of the same type and continues from
    it (AMCL: /initialpose). The agent remaps ``restore`` per copy, so only the copy that takes
    over hears what it is handed."""

    topic: str
    restore: str
    msg_type: str = ''    # '' = the type of the node's connection on ``topic``, else the graph


@dataclass(frozen=True)
class Node:
    name: str
    launch: Launch
    cpu: float                        # nominal CPU (reference-core percent) on the reference
    performance: float = 0.0          # performance at the nominal setting
    weight: float = 1.0
    residence: Tuple[str, ...] = ()   # scales it may run on; empty = any
    coresidence: Tuple[str, ...] = ()  # nodes that must share its scale
    migratable: Optional[bool] = None  # None = derive; False = never move it
    critical: Optional[bool] = None    # True: pinned to the master without a tolerance-0 link
    managed: bool = True              # False: the agent does not start it (e.g. the decider)
    move_order: str = START_BEFORE_STOP
    lifecycle: bool = False           # a managed (lifecycle) node: driven through its services
    standby: bool = False             # keep an inactive copy on every scale it may run on...
    standby_on: Tuple[str, ...] = ()  # ...or only on these (empty: all of them)
    settings: Optional[Settings] = None
    nice: int = 0                     # niceness added to agent.node_nice for this node alone
    state: Optional[StateSpec] = None  # how its state is handed to the copy that takes over
    memory_mb: float = 0.0            # what a copy holds (a shared host's claims count it)

    @property
    def configurable(self) -> bool:
        return self.settings is not None and self.settings.configurable


@dataclass(frozen=True)
class Connection:
    """A directed topic flow from one node to another, with the ICAR thresholds."""

    name: str
    topic: str
    publisher: str
    subscriber: str
    bandwidth_kbps: float
    freq_min_hz: Optional[float] = None
    freq_opt_hz: Optional[float] = None
    tolerance_s: Optional[float] = None   # Delta; None = not monitored
    msg_type: str = ''                    # e.g. sensor_msgs/msg/LaserScan; '' = from the graph

    @property
    def monitored(self) -> bool:
        """Judged by the Δ rule (runtime/delta.py): both thresholds are set."""
        return self.freq_min_hz is not None and self.tolerance_s is not None

    @property
    def pins_both_ends(self) -> bool:
        """It tolerates no stretch below freq_min (Δ = 0), which no link can promise: both its
        ends are critical, pinned to the master (ICAR 2015)."""
        return self.tolerance_s is not None and self.tolerance_s == 0


def setting(default, help: str, *, low=None, high=None, low_open: bool = False,
            choices: Optional[Tuple[str, ...]] = None, unit: str = '', live: bool = False,
            factory=None):
    """One setting of a deployment file, declared once: its default, what it means, its range
    or choices and unit, and whether the decider takes a change while it runs. Everything else
    derives from it: model/sections.py checks a file and a live change against it, the decider
    declares its ROS parameters (descriptions, ranges) with it, and model/settings_doc.py makes
    the table of docs/configuration.md from it."""
    check = {k: v for k, v in (('low', low), ('high', high), ('choices', choices))
             if v is not None}
    if low_open:
        check['low_open'] = True
    if unit:
        check['unit'] = unit
    meta = {'help': help, 'check': check, 'live': live}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


def checks_of(cls) -> Dict[str, dict]:
    """Field name -> the checks its ``setting`` declares."""
    return {f.name: dict(f.metadata.get('check', {})) for f in fields(cls)}


@dataclass(frozen=True)
class DeciderSettings:
    period_s: float = setting(
        1.0, 'seconds between two turns of the migration loop', low=0, high=3600,
        low_open=True, unit='s', live=True)
    cpu_headroom: float = setting(
        0.9, 'usable fraction of the CPU capacity of a scale', low=0, high=1, low_open=True,
        live=True)
    bandwidth_margin: float = setting(
        0.9, 'usable fraction of the available bandwidth of a link', low=0, high=1,
        low_open=True, live=True)
    observation_max_age_s: float = setting(
        3.0, 'older observations count as missing; a silent link is down', low=0, high=3600,
        low_open=True, unit='s', live=True)
    hysteresis_s: float = setting(
        20.0, "T: a node migrated back is not moved out again for this long (the paper's T)",
        low=0, high=86400, unit='s', live=True)
    hysteresis_scope: str = setting(
        'scale', 'scale: T bars only the scale a node came back from (another remote scale may '
                 "take it at once); node: the paper's rule as written, T bars every move out",
        choices=HYSTERESIS_SCOPES, live=True)
    grace_s: float = setting(
        5.0, 'after a move, the connections of the moved node are not judged', low=0,
        high=3600, unit='s', live=True)
    bringup_s: float = setting(
        30.0, 'a starting decider moves nothing out until every monitored connection whose '
              'nodes run has been heard, or for this long at most (the graph boots)',
        low=0, high=3600, unit='s', live=True)
    agent_timeout_s: float = setting(
        5.0, 'an agent silent this long loses its scale; its nodes move', low=0, high=3600,
        low_open=True, unit='s', live=True)
    migration: bool = setting(
        True, 'false: never move a node out (the no-migration baseline)', live=True)
    rebalance: bool = setting(
        True, 'move a node from a remote scale to a more powerful remote one that can host '
              'it, T after it arrived, when the cost function gains rebalance_min_gain '
              '(beyond the paper: a returning server is used again)', live=True)
    rebalance_min_gain: float = setting(
        25.0, 'the least gain of a rebalancing move: CPU x (alpha there - alpha here), in '
              'reference-core percent x alpha (a node of 50 from alpha 2 to 3.5: 75)',
        low=0, high=1e9, live=True)
    initial_layout: str = setting(
        'master', 'the first layout: every node on the master, the IROS Problem 1 or 2 '
                  'planner, or decider.layout; read once, at start',
        choices=INITIAL_LAYOUTS, live=True)
    layout: Mapping[str, str] = setting(
        None, 'node -> scale, the first layout when initial_layout is explicit',
        factory=frozen_map)
    lease_s: float = setting(
        3.0, 'the decider re-publishes its layout every lease_s / 3; agents follow another '
             'decider at the same or a lower term only after this silence of the one they '
             'follow (a higher term at once)',
        low=0, high=600, low_open=True, unit='s')
    discovery_s: float = setting(
        5.0, 'a starting decider that hears no leading decider of the deployment for this long '
             'leads; one that hears one stands by (it takes over when the leader falls silent)',
        low=0, high=600, low_open=True, unit='s')
    beat_s: float = setting(
        0.05, 'every decider beats on /anyscale/decider this often: the leader that it leads, a '
              'standby that it stands by', low=0, high=10, low_open=True, unit='s')
    takeover_s: float = setting(
        0.4, 'a standby decider takes over after this silence of the leader; a leader that '
             'could not beat for this long less the delivery time of a beat (0.1 s, at most a '
             'third) has stalled: it commands nothing more before it has listened again',
        low=0, high=600, low_open=True, unit='s')


@dataclass(frozen=True)
class SecuritySettings:
    key_file: str = setting(
        '', 'absolute path of the deployment key (anyscale-manager keygen), the same on every '
            'scale, mode 0600: every project message is then signed and receivers drop '
            'unsigned, forged and replayed ones; empty: anyone on the domain can move nodes')
    replay_window_s: float = setting(
        30.0, "signed messages stamped further than this from the receiver's clock are refused "
              "(the scales' clocks must agree within it)", low=0, high=86400,
        low_open=True, unit='s')


MULTICAST, SERVER = 'multicast', 'server'


@dataclass(frozen=True)
class DiscoverySettings:
    # How every process of the deployment finds the others (docs/discovery.md).
    mode: str = setting(
        MULTICAST, "'multicast': DDS's own discovery (ROS's default; many WiFi access points "
                   "drop or throttle multicast); 'server': each scale's warden runs a Fast DDS "
                   'discovery server on its host, every process of the deployment a client of '
                   'all of them (ROS_DISCOVERY_SERVER): nothing multicast, a few kbit/s on a '
                   'link whatever the number of processes', choices=(MULTICAST, SERVER))
    port: int = setting(11811, 'base UDP port of the discovery servers: scale i (from 0, in '
                               'file order) of a deployment in ROS domain D serves on it + 16 D '
                               '+ i (a server ignores DDS domains: robots of a fleet sharing a '
                               'host keep apart by their domains)', low=1,
                        high=65535 - 16 * 233)
    server_command: str = setting(
        '', 'the Fast DDS discovery server executable (empty: fast-discovery-server, else '
            "fastdds's 'discovery' verb, found beside this Python or on PATH)")


@dataclass(frozen=True)
class MonitorSettings:
    scale_rate_hz: float = setting(1.0, 'scale status rate (one reading a turn of the decider '
                                        'at the default period_s)', low=0, high=1000,
                                   low_open=True, unit='Hz')
    heartbeat_rate_hz: float = setting(4.0, "the master's heartbeats to each remote scale",
                                       low=0, high=1000, low_open=True, unit='Hz')
    heartbeat_misses_down: int = setting(3, 'a link is down after this many missed heartbeats '
                                            '(BFD rule, docs/monitoring.md)', low=1, high=1000)
    duplicate_sender_s: float = setting(
        6.0, "two writers of a migratable node's output heard at once for longer than this: an "
             "error (a 'duplicate' event, an error diagnostic, a line in status); a move's "
             'overlap is shorter (docs/monitoring.md, two senders)', low=0, high=3600,
        low_open=True, unit='s')
    probe_window_s: float = setting(2.0, "a probe's rate window", low=0, high=3600,
                                    low_open=True, unit='s')
    probe_publish_rate_hz: float = setting(2.0, 'connection status rate', low=0, high=1000,
                                           low_open=True, unit='Hz')
    bandwidth_probe_interval_s: float = setting(30.0, 'seconds between two routine probes',
                                                low=0, high=86400, low_open=True, unit='s')
    bandwidth_probe_duration_s: float = setting(0.5, 'length of one throughput probe', low=0,
                                                high=60, low_open=True, unit='s')
    bandwidth_probe_port: int = setting(47800, 'base port: scale i (from 0, in file order) '
                                               'uses it + 1 + i unless it sets its own port',
                                        low=1, high=65534)
    congestion_delay_ms: float = setting(
        50.0, 'heartbeat queueing delay (reached by 4 of the 5 beats of the last half second '
              'at 10 Hz) at which a link looks full: never probed while so, and when its '
              'crossing connections deliver below 90 % of their need its figure drops to 0.9 x '
              'that need (docs/monitoring.md); 0 turns it off', low=0, high=60000, unit='ms')


@dataclass(frozen=True)
class AgentSettings:
    sigint_grace_s: float = setting(5.0, 'stopping a node: SIGINT, then SIGTERM after this',
                                    low=0, high=3600, unit='s')
    sigterm_grace_s: float = setting(3.0, '... then SIGKILL after this', low=0, high=3600,
                                     unit='s')
    readiness_timeout_s: float = setting(15.0, 'a started node not in the ROS graph by then '
                                               'is reported not ready; also the longest a '
                                               'start_before_stop handover keeps the old copy',
                                         low=0, high=3600, low_open=True, unit='s')
    lifecycle_timeout_s: float = setting(5.0, 'a lifecycle transition not answered by then: '
                                              'the agent checks with get_state, retries with '
                                              'backoff (3 tries), then restarts the copy',
                                         low=0, high=3600, low_open=True, unit='s')
    restart_backoff_s: float = setting(1.0, 'a first crash (or the first after '
                                            'restart_backoff_max_s of running) restarts at once; '
                                            'a crash loop waits this, doubling', low=0,
                                       high=3600, unit='s')
    restart_backoff_max_s: float = setting(30.0, 'the bound of that wait', low=0, high=86400,
                                           unit='s')
    heartbeat_rate_hz: float = setting(2.0, 'agent state report rate', low=0, high=1000,
                                       low_open=True, unit='Hz')
    node_nice: int = setting(0, 'niceness added to every node the agent starts (not to '
                                'critical ones)', low=0, high=19)
    # A CPU quota stops every normal-priority thread of its group once the group has spent it;
    # a real-time thread runs ahead of them (agent/priority.py).
    critical_priority: int = setting(0, 'real-time (SCHED_RR) priority the critical nodes (in '
                                        'a tolerance-0 connection) run at (needs '
                                        'CAP_SYS_NICE; 0: normal priority)', low=0, high=99)
    # Fast DDS's shared-memory transport stalls the writers of a computer for about 0.35 s,
    # 1-2 s after a participant they write to was SIGKILLed (docs/agent.md, supervision):
    # the nodes an agent starts are the ones that crash and fail over.
    node_dds_transports: str = setting(
        'UDPv4', 'FASTDDS_BUILTIN_TRANSPORTS for every node the agent starts, unless the '
                 "agent's environment or the node's launch env names one ('': Fast DDS's "
                 'default, shared memory and UDPv4); under ROS_AUTOMATIC_DISCOVERY_RANGE='
                 'LOCALHOST rmw_fastrtps keeps shared memory whatever this says',
        choices=('', 'DEFAULT', 'UDPv4', 'UDPv6', 'DEFAULTv6', 'SHM', 'LARGE_DATA',
                 'LARGE_DATAv6'))
    # The warden (agent/warden.py) stops this agent's nodes when the agent is gone this long
    # with no successor (restart_grace_s after it said it restarts in place), SIGKILL after
    # fence_grace_s: the bound within which a dead agent's nodes are gone.
    adopt_grace_s: float = setting(5.0, 'a dead agent with no successor this long: its '
                                        'warden stops its nodes', low=0, high=3600, unit='s')
    restart_grace_s: float = setting(10.0, 'the same after the agent announced a restart in '
                                           'place', low=0, high=3600, unit='s')
    fence_grace_s: float = setting(0.5, 'SIGINT to SIGKILL of a fenced node', low=0, high=60,
                                   unit='s')
    # The warden also answers the link heartbeats: an echo that waits for a core behind the
    # scale's workload reads as a cut link at the watching end.
    warden_priority: int = setting(10, 'real-time (SCHED_RR) priority the warden answers '
                                       'heartbeats at (needs CAP_SYS_NICE; 0: normal '
                                       'priority)', low=0, high=99)
    state_dir: str = setting('', 'the adoption state (empty: ~/.ros/anyscale_manager)')
    log_dir: str = setting('', 'per-node logs (empty: ~/.ros/log/anyscale_manager)')
    # A node's state (nodes.<n>.state) is kept by every agent that may run it and handed to the
    # copy that takes over (docs/lifecycle.md, state).
    state_max_bytes: int = setting(65536, 'a state message larger than this is not kept (a '
                                          'warning once per node); the copy that takes over '
                                          'gets the last one that fitted', low=1,
                                   high=64 * 1024 * 1024, unit='bytes')
    state_stale_s: float = setting(5.0, 'a state older than this when handed over comes with a '
                                        'warning (the serving copy stopped sending it: hung or '
                                        'cut off); it is handed over all the same', low=0,
                                   high=86400, low_open=True, unit='s')


@dataclass(frozen=True)
class Deployment:
    name: str
    source: str
    scales: Tuple[Scale, ...]
    links: Tuple[Link, ...]
    nodes: Tuple[Node, ...]
    connections: Tuple[Connection, ...]
    decider: DeciderSettings = DeciderSettings()
    monitoring: MonitorSettings = MonitorSettings()
    agent: AgentSettings = AgentSettings()
    description: str = ''
    security: SecuritySettings = SecuritySettings()
    discovery: DiscoverySettings = DiscoverySettings()
    # Of a fleet: a claim of a higher priority on a shared scale may preempt a lower one's.
    priority: int = 0

    # --- look-ups (indexes built once: a Deployment never changes) --------------------------
    # cached_property writes straight into the instance dict, which a frozen dataclass allows.
    @cached_property
    def _scales(self) -> Mapping[str, Scale]:
        return frozen_map({s.name: s for s in self.scales})

    @cached_property
    def _nodes(self) -> Mapping[str, Node]:
        return frozen_map({n.name: n for n in self.nodes})

    @cached_property
    def _connections(self) -> Mapping[str, Connection]:
        return frozen_map({c.name: c for c in self.connections})

    @cached_property
    def _links(self) -> Mapping[FrozenSet[str], Link]:
        return frozen_map({frozenset(link.ends): link for link in self.links})

    def scale(self, name: str) -> Scale:
        return _lookup('scale', self._scales, name)

    def scale_port(self, name: str) -> int:
        """The port of ``name``'s warden (UDP heartbeats) and throughput probe server (TCP):
        the scale's own ``port``, else monitoring.bandwidth_probe_port + 1 + its index, so that
        every scale of a deployment may share one machine."""
        scale = self.scale(name)
        if scale.port:
            return scale.port
        return self.monitoring.bandwidth_probe_port + 1 + self.scale_names.index(name)

    def node(self, name: str) -> Node:
        return _lookup('node', self._nodes, name)

    def worth(self, name: str) -> float:
        """A scale's worth, the one rule that placement, the next-best scale, rebalancing, the
        cost function and a shared host's arbitration use: its ``gain`` (the ICAR cost
        function's alpha) where the file gives one, else its power (cores x GHz) over the
        master's, times the master's worth (a robot of 2 x 1.6 GHz is 1, a laptop of
        4 x 2.8 GHz 3.5)."""
        scale = self.scale(name)
        if scale.gain is not None:
            return scale.gain
        master = self.master
        base = master.gain if master.gain is not None else 1.0
        return base * scale.power / master.power if master.power > 0 else base

    def connection(self, name: str) -> Connection:
        return _lookup('connection', self._connections, name)

    @cached_property
    def scale_names(self) -> Tuple[str, ...]:
        return tuple(s.name for s in self.scales)

    @cached_property
    def node_names(self) -> Tuple[str, ...]:
        return tuple(n.name for n in self.nodes)

    @cached_property
    def master(self) -> Scale:
        return next(s for s in self.scales if s.is_master)

    @cached_property
    def remote_scales(self) -> Tuple[Scale, ...]:
        return tuple(s for s in self.scales if not s.is_master)

    def link_between(self, a: str, b: str) -> Optional[Link]:
        return self._links.get(frozenset((a, b))) if a != b else None

    def link_monitor(self, link: Link) -> str:
        """The scale whose agent watches ``link`` (heartbeats, congestion, probes): the master
        for a link that touches it, else the end listed first in scales.names."""
        master = self.master.name
        if master in link.ends:
            return master
        return min(link.ends, key=self.scale_names.index)

    def watched_from(self, scale: str) -> Tuple[str, ...]:
        """The far ends of the links ``scale``'s agent watches: every remote scale from the
        master (declared link or not), and from a remote scale each remote it shares a link
        with and comes before in scales.names."""
        if scale == self.master.name:
            return tuple(s.name for s in self.remote_scales)
        return tuple(link.other(scale) for link in self.remote_links
                     if scale in link.ends and self.link_monitor(link) == scale)

    @cached_property
    def remote_links(self) -> Tuple[Link, ...]:
        """The links between two remote scales (the master's own are not among them)."""
        return tuple(link for link in self.links if self.master.name not in link.ends)

    def connections_of(self, node: str) -> Tuple[Connection, ...]:
        return self._connections_of.get(node, ())

    @cached_property
    def _connections_of(self) -> Mapping[str, Tuple[Connection, ...]]:
        out: Dict[str, List[Connection]] = {}
        for c in self.connections:
            out.setdefault(c.publisher, []).append(c)
            if c.subscriber != c.publisher:
                out.setdefault(c.subscriber, []).append(c)
        return frozen_map({k: tuple(v) for k, v in out.items()})

    # --- derived sets (the ICAR paper's static analysis) ------------------------------------
    def pinning_connections(self, node: str) -> Tuple[Connection, ...]:
        """The node's connections that pin both their ends (``Connection.pins_both_ends``)."""
        return tuple(c for c in self.connections_of(node) if c.pins_both_ends)

    @cached_property
    def critical_nodes(self) -> Tuple[str, ...]:
        """Nodes pinned to the master: declared ``critical: true``, or an end of at least one
        connection that pins both its ends (``Connection.pins_both_ends``)."""
        return tuple(n.name for n in self.nodes
                     if n.critical or self.pinning_connections(n.name))

    @cached_property
    def data_providers(self) -> Tuple[str, ...]:
        """Nodes that publish into the graph but subscribe to nothing (sensor drivers...)."""
        publishers = {c.publisher for c in self.connections}
        subscribers = {c.subscriber for c in self.connections}
        return tuple(n.name for n in self.nodes
                     if n.name in publishers and n.name not in subscribers)

    # --- why: the derived facts in words, for validate and for errors -----------------------
    def why_critical(self, node: str) -> str:
        """What makes ``node`` critical ('' if it is not): its flag, its tolerance-0 links."""
        reasons = []
        if self.node(node).critical:
            reasons.append('critical: true')
        zero = [f'{c.name} to {c.subscriber}' if c.publisher == node
                else f'{c.name} from {c.publisher}'
                for c in self.pinning_connections(node)]
        if zero:
            reasons.append(f'tolerance_s 0 on {_listed(zero)}')
        return '; '.join(reasons)

    def why_data_provider(self, node: str) -> str:
        """What makes ``node`` a data provider ('' if it is not)."""
        if node not in self.data_providers:
            return ''
        out = [c.name for c in self.connections if c.publisher == node]
        return f'subscribes to nothing, publishes {_listed(out)}'

    def why_pinned(self, node: str) -> str:
        """Why ``node`` may run only where allowed_scales says, by itself or through the nodes
        it shares a scale with ('' when nothing restricts it)."""
        own = self.why_own_scales(node)
        if own:
            return own
        mine = set(self.own_scales(node))
        for other in self.coresidence_group(node):
            theirs = self.why_own_scales(other)
            if other != node and theirs and not mine <= set(self.own_scales(other)):
                return f'shares a scale with {other} (coresidence), which {theirs}'
        return ''

    def why_own_scales(self, node: str) -> str:
        """Why ``node`` by itself may not run on every scale ('' when it may)."""
        n = self.node(node)
        master = self.master.name
        if node in self.critical_nodes:
            return f'is critical ({self.why_critical(node)}): pinned to the master {master}'
        if n.residence:
            if set(self.own_scales(node)) >= set(self.scale_names):
                return ''
            return f'has residence {", ".join(self.own_scales(node)) or "on no known scale"}'
        if node in self.data_providers:
            return f'is a data provider ({self.why_data_provider(node)}), kept on the master ' \
                   f'{master} unless given a residence'
        if not n.managed:
            return f'is not managed (agents never start or stop it): stays on the master {master}'
        return ''

    def why_not_migratable(self, node: str) -> str:
        """Why the runtime never moves ``node`` ('' if it may)."""
        n = self.node(node)
        if node in self.migratable_nodes:
            return ''
        if not n.managed:
            return 'not managed: agents never start or stop it'
        if n.migratable is False:
            return 'migratable: false'
        if not n.launch.startable:
            return 'no launch: agents cannot start it'
        allowed = self.allowed_scales(node)
        if not allowed:
            return 'no scale satisfies its residence and coresidence'
        pinned = self.why_pinned(node) or f'may run only on {", ".join(allowed)}'
        master = self.master.name
        if master not in allowed:
            return f'it may not run on the master {master}, as a migratable node must: it {pinned}'
        return f'no second scale to run on: it {pinned}'

    def coresidence_group(self, node: str) -> Tuple[str, ...]:
        """The node and every node it must share a scale with (symmetric, transitive)."""
        groups = self.__dict__.setdefault('_groups', {})
        if node not in groups:
            groups[node] = self._coresidence_group(node)
        return groups[node]

    def _coresidence_group(self, node: str) -> Tuple[str, ...]:
        links = {n.name: set(n.coresidence) for n in self.nodes}
        for n in self.nodes:
            for other in n.coresidence:
                links.setdefault(other, set()).add(n.name)
        group, todo = {node}, [node]
        while todo:
            for other in links.get(todo.pop(), ()):
                if other not in group:
                    group.add(other)
                    todo.append(other)
        return tuple(n for n in self.node_names if n in group)

    def own_scales(self, node: str) -> Tuple[str, ...]:
        """Scales one node may run on by itself: criticality, residence, provider pinning."""
        return _lookup('node', self._own, node)

    @cached_property
    def _own(self) -> Mapping[str, Tuple[str, ...]]:
        critical, providers = set(self.critical_nodes), set(self.data_providers)
        master: Tuple[str, ...] = (self.master.name,)
        out: Dict[str, Tuple[str, ...]] = {}
        for n in self.nodes:
            if n.name in critical:
                out[n.name] = master
            elif n.residence:
                out[n.name] = tuple(s for s in self.scale_names if s in n.residence)
            elif n.name in providers or not n.managed:
                out[n.name] = master
            else:
                out[n.name] = self.scale_names
        return frozen_map(out)

    def allowed_scales(self, node: str) -> Tuple[str, ...]:
        """Scales a node may run on, its coresidence group's constraints included."""
        try:
            return self._allowed[node]
        except KeyError:
            raise KeyError(f'unknown node {node!r}') from None

    @cached_property
    def _allowed(self) -> Mapping[str, Tuple[str, ...]]:
        out = {}
        for n in self.nodes:
            allowed = set(self.scale_names)
            for member in self.coresidence_group(n.name):
                allowed &= set(self.own_scales(member))
            out[n.name] = tuple(s for s in self.scale_names if s in allowed)
        return frozen_map(out)

    def state_msg_type(self, node: str) -> str:
        """The type of ``node``'s state topic as the file gives it ('' = learnt from the graph)."""
        spec = self.node(node).state
        if spec is None:
            return ''
        if spec.msg_type:
            return spec.msg_type
        return next((c.msg_type for c in self.connections
                     if c.publisher == node and c.topic == spec.topic and c.msg_type), '')

    def standby_scales(self, node: str) -> Tuple[str, ...]:
        """Scales that keep an inactive copy of ``node`` while it runs elsewhere."""
        n = self.node(node)
        if not (n.standby and n.lifecycle):
            return ()
        allowed = self.allowed_scales(node)
        return tuple(s for s in allowed if not n.standby_on or s in n.standby_on)

    @cached_property
    def migratable_nodes(self) -> Tuple[str, ...]:
        """Nodes the runtime may move between the master and remote scales."""
        master = self.master.name
        out = []
        for n in self.nodes:
            if n.migratable is False or not n.managed or not n.launch.startable:
                continue
            allowed = self.allowed_scales(n.name)
            if master in allowed and len(allowed) > 1:
                out.append(n.name)
        return tuple(out)


def _lookup(kind: str, index: Mapping[str, V], name: str) -> V:
    try:
        return index[name]
    except KeyError:
        raise KeyError(f'unknown {kind} {name!r}') from None


def _listed(names, limit: int = 3) -> str:
    """'a, b and c'; past ``limit`` items, 'a, b and N more'."""
    names = list(names)
    if len(names) > limit:
        return f'{", ".join(names[:limit - 1])} and {len(names) - limit + 1} more'
    if len(names) > 1:
        return f'{", ".join(names[:-1])} and {names[-1]}'
    return ''.join(names)
