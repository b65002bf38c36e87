"""The project's own topics: names, QoS roles and JSON payloads, with strict decoding.

Every project topic carries a std_msgs/msg/String whose ``data`` is one JSON object, so the
package needs no generated interfaces and any tool (``ros2 topic echo``) can read it. Decoding
never trusts the sender: wrong types, missing fields, non-finite or huge numbers, oversized or
deeply nested payloads and unknown kinds raise ProtocolError with a message naming the topic and
the field. Stamps are the sender's wall clock and only informative; freshness is judged by the
receiver's own clock.
"""

import json
import math
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any, Dict, Mapping, Optional, Type, TypeVar

PREFIX = '/anyscale'
TOPIC_LAYOUT = PREFIX + '/layout'                  # decider -> agents, latched
TOPIC_AGENT_STATE = PREFIX + '/agent_state'        # agents -> decider, latched per agent
TOPIC_SCALE_STATUS = PREFIX + '/scale_status'      # scale monitor (in each agent)
TOPIC_LINK_STATUS = PREFIX + '/link_status'        # link monitors (each link's watching agent)
# A link monitor that starts publishes no LinkStatus until its first echo, for at most this
# long: before the remote has discovered it, silence says nothing of the link.
LINK_MONITOR_START_S = 3.0
TOPIC_CONNECTION_STATUS = PREFIX + '/connection_status'  # probes (in each agent)
TOPIC_EVENTS = PREFIX + '/events'                  # decider decisions with reasons
TOPIC_OBJECTIVE = PREFIX + '/objective'            # decider cost function
TOPIC_PLAN_CHECK = PREFIX + '/plan_check'          # decider plan-against-reality report
TOPIC_DECIDER = PREFIX + '/decider'                # deciders' beats: leader and standbys
TOPIC_DIAGNOSTICS = '/diagnostics'

MAX_PAYLOAD_BYTES = 1 << 20
# The deepest message (AgentState.nodes.<node>.<field>) nests 3 levels: anything much deeper is
# hostile, and is refused before any code walks it recursively.
MAX_DEPTH = 8
# Readings, stamps and settings are far below this; a bound keeps sums and products of readings
# finite (a CPU of 1e308 summed twice is infinite, and so would be the objective published).
MAX_MAGNITUDE = 1e12
# Generations, sequences: the largest integer a JSON reader with doubles still keeps exact.
MAX_GENERATION = 2 ** 53
# A decider adds one generation per decision: a larger jump from the followed decider is not
# one of its layouts (a forged or corrupted number would otherwise lock its real ones out).
MAX_GENERATION_STEP = 1_000_000

# Diagnostic levels as plain ints (DiagnosticStatus.level is bytes in Python).
OK, WARN, ERROR, STALE = 0, 1, 2, 3


class ProtocolError(ValueError):
    """A message that does not match its topic's schema."""


class _Vocabulary(StrEnum):
    """A closed set of words read from the wire: a member is its word (it compares equal to
    it and serialises as it), and a word outside the set is refused with the set named."""

    @classmethod
    def parse(cls, word: Any, where: str = ''):
        try:
            return cls(word)
        except ValueError:
            raise ProtocolError(f'{where or cls.__name__}: expected one of '
                                f'{", ".join(cls)}, got {word!r:.40}') from None


class ProcState(_Vocabulary):
    """A node's state in an agent's report: the supervisor's process states (agent/supervisor.py),
    STANDBY for a live lifecycle copy kept inactive (agent/lifecycle.py), and CRASHED, a word of
    the wire that readers count as down though the supervisor reports a crash as BACKOFF."""

    STARTING = 'starting'
    RUNNING = 'running'
    STOPPING = 'stopping'
    STOPPED = 'stopped'
    CRASHED = 'crashed'
    BACKOFF = 'backoff'
    FAILED = 'failed'
    STANDBY = 'standby'


class LifecycleState(_Vocabulary):
    """A managed node's state as its get_state service labels it: the four primary states, the
    transition states it passes through, and UNKNOWN (not read yet)."""

    UNKNOWN = 'unknown'
    UNCONFIGURED = 'unconfigured'
    INACTIVE = 'inactive'
    ACTIVE = 'active'
    FINALIZED = 'finalized'
    CONFIGURING = 'configuring'
    CLEANINGUP = 'cleaningup'
    SHUTTINGDOWN = 'shuttingdown'
    ACTIVATING = 'activating'
    DEACTIVATING = 'deactivating'
    ERRORPROCESSING = 'errorprocessing'


NODE_STATES = tuple(ProcState)
# A copy that runs, or is on its way to running, its node's work (not stopping, not standby).
LIVE_STATES = (ProcState.STARTING, ProcState.RUNNING)
# ScaleStatus.cpu_source (runtime/cpu.py): what a scale's cpu_total measures.
CPU_SOURCES = ('cgroup', 'machine', 'processes')

T = TypeVar('T', bound='Message')


def _check(value: Any, kind: Any, where: str) -> Any:
    """Validate one JSON value against a small type language; return it normalised."""
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise ProtocolError(f'{where}: expected a finite number, got {value!r:.60}')
        if abs(value) > MAX_MAGNITUDE:
            raise ProtocolError(f'{where}: {value:.3g} is beyond the bound '
                                f'{MAX_MAGNITUDE:g}')
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProtocolError(f'{where}: expected an integer, got {value!r:.60}')
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise ProtocolError(f'{where}: expected true or false, got {value!r:.60}')
        return value
    if kind is str:
        if not isinstance(value, str):
            raise ProtocolError(f'{where}: expected a string, got {value!r:.60}')
        return value
    if isinstance(kind, type) and issubclass(kind, _Vocabulary):
        if not isinstance(value, str):
            raise ProtocolError(f'{where}: expected a string, got {value!r:.60}')
        return kind.parse(value, where)
    if isinstance(kind, tuple) and kind[0] == 'optional':
        return None if value is None else _check(value, kind[1], where)
    if isinstance(kind, tuple) and kind[0] == 'map':
        if not isinstance(value, dict):
            raise ProtocolError(f'{where}: expected a map, got {value!r:.60}')
        return {str(k): _check(v, kind[1], f'{where}.{_printable(k)}')
                for k, v in value.items()}
    if isinstance(kind, type) and issubclass(kind, Message):
        return kind.from_dict(value, where)
    raise TypeError(f'unsupported schema kind {kind!r}')  # a bug in this module, not input


def _printable(name: Any) -> str:
    """A name from a message as it may appear in a log line: short, on one line."""
    text = str(name)
    return text[:60] if text.isprintable() else repr(text)[:60]


def _depth_ok(data: Any, where: str) -> None:
    """Refuse JSON nested deeper than MAX_DEPTH (walked without recursion)."""
    todo = [(data, 1)]
    while todo:
        value, depth = todo.pop()
        if isinstance(value, dict):
            children = value.values()
        elif isinstance(value, list):
            children = value
        else:
            continue
        if depth > MAX_DEPTH:
            raise ProtocolError(f'{where}: nested deeper than {MAX_DEPTH} levels')
        todo.extend((child, depth + 1) for child in children)


class Message:
    """Base of every payload: ``SCHEMA`` maps field name to kind; all fields are required."""

    SCHEMA: Dict[str, Any] = {}

    @classmethod
    def from_dict(cls: Type[T], data: Any, where: str = '') -> T:
        where = where or cls.__name__
        if not isinstance(data, dict):
            raise ProtocolError(f'{where}: expected a JSON object, got {data!r:.60}')
        unknown = sorted(str(k) for k in data if k not in cls.SCHEMA)
        if unknown:
            # A layout that smuggles a command (or any field we do not know) is refused whole.
            raise ProtocolError(f'{where}: unknown field {unknown[0]!r:.60}')
        values = {}
        for name, kind in cls.SCHEMA.items():
            if name not in data:
                optional = isinstance(kind, tuple) and kind[0] == 'optional'
                if optional:
                    values[name] = None
                    continue
                raise ProtocolError(f'{where}: missing field {name!r}')
            values[name] = _check(data[name], kind, f'{where}.{name}')
        obj = cls(**values)
        obj.validate(where)
        return obj

    def validate(self, where: str) -> None:
        """Checks beyond types; override where a message has them."""

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(',', ':'), sort_keys=True)

    @classmethod
    def from_json(cls: Type[T], text: Any, topic: str = '') -> T:
        where = topic or cls.__name__
        if not isinstance(text, str):
            raise ProtocolError(f'{where}: expected JSON text')
        if len(text) > MAX_PAYLOAD_BYTES:
            raise ProtocolError(f'{where}: payload of {len(text)} bytes is over the '
                                f'{MAX_PAYLOAD_BYTES}-byte limit')
        try:
            data = json.loads(text, parse_constant=_reject_constant)
        except (ValueError, RecursionError) as e:
            raise ProtocolError(f'{where}: not valid JSON ({e})') from None
        _depth_ok(data, where)
        return cls.from_dict(data, where)


def _reject_constant(name: str) -> None:
    raise ValueError(f'{name} is not allowed')


def _signed_fields_ok(message: Any, where: str) -> None:
    seq, tag = message.seq, message.auth
    if seq is not None and not 0 <= seq <= MAX_GENERATION:
        raise ProtocolError(f'{where}.seq: must be in [0, 2**53]')
    if tag is not None and len(tag) > 128:
        raise ProtocolError(f'{where}.auth: too long')


# The fields every signed status message carries when the deployment has a key: the sending
# process (a random id drawn at its start), its message count, and the HMAC of the rest.
SIGNED_SCHEMA = {'sender': ('optional', str), 'seq': ('optional', int), 'auth': ('optional', str)}
SIGNED_FIELDS = tuple(SIGNED_SCHEMA)


def _without_unsigned(out: Dict[str, Any], message: Any) -> Dict[str, Any]:
    """``out`` without the signed fields an unsigned message leaves empty."""
    for key in SIGNED_FIELDS:
        if getattr(message, key) is None:
            out.pop(key, None)
    return out


def _sender_ok(message: Any, where: str) -> None:
    _signed_fields_ok(message, where)
    sender = message.sender
    if sender is not None and (not sender or len(sender) > 128 or not sender.isprintable()):
        raise ProtocolError(f'{where}.sender: empty, over 128 characters or not printable')


def _names_ok(mapping: Mapping[str, Any], where: str, what: str) -> None:
    for key in mapping:
        if not key or len(key) > 256:
            raise ProtocolError(f'{where}: bad {what} name {key!r:.60}')


def _term_ok(term: Optional[int], where: str) -> None:
    if term is not None and not 0 <= term <= MAX_GENERATION:
        raise ProtocolError(f'{where}.term: must be in [0, 2**53]')


@dataclass
class DeciderIdentity(Message):
    """Who publishes a layout: one decider process (a random id drawn at its start)."""

    id: str
    host: str
    pid: int
    started: float            # the decider's wall clock at its start
    SCHEMA = {'id': str, 'host': str, 'pid': int, 'started': float}

    def validate(self, where: str) -> None:
        if not self.id or len(self.id) > 64 or len(self.host) > 256 \
                or not (self.id + self.host).isprintable():
            raise ProtocolError(f'{where}: bad decider identity {self.id!r:.60}')

    def describe(self) -> str:
        return f'{self.id} (host {self.host:.60}, pid {self.pid})'


@dataclass
class Layout(Message):
    """The desired layout: node -> scale for every managed node, with a generation number.

    ``decider`` names the decider that publishes it (absent from older deciders), ``term`` is
    its leadership term (the fence: agents refuse a lower one than they follow; absent: 0),
    ``seq`` counts that decider's layout messages (re-publications included), and ``auth`` is
    the HMAC of the rest when the deployment has a key (protocol_auth).
    """

    generation: int
    deployment: str
    assignments: Dict[str, str]
    reason: str
    stamp: float
    decider: Optional[DeciderIdentity] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    term: Optional[int] = None
    SCHEMA = {'generation': int, 'deployment': str, 'assignments': ('map', str),
              'reason': str, 'stamp': float, 'decider': ('optional', DeciderIdentity),
              'seq': ('optional', int), 'auth': ('optional', str), 'term': ('optional', int)}

    def validate(self, where: str) -> None:
        if self.generation < 0:
            raise ProtocolError(f'{where}.generation: must be >= 0')
        if self.generation > MAX_GENERATION:
            raise ProtocolError(f'{where}.generation: {self.generation:.3g} is beyond the '
                                f'bound 2**53 (no decider counts that far)')
        _term_ok(self.term, where)
        _signed_fields_ok(self, where)
        _names_ok(self.assignments, where + '.assignments', 'node')

    def to_dict(self) -> Dict[str, Any]:
        out = asdict(self)
        for key in ('decider', 'seq', 'auth', 'term'):
            if out[key] is None:
                del out[key]    # an older agent's strict decoder still reads it
        return out


@dataclass
class NodeReport(Message):
    """What an agent knows of one node it supervises."""

    state: ProcState
    pid: int
    since: float
    restarts: int
    ready: bool
    exit_reason: str
    lifecycle: Optional[LifecycleState] = None     # a lifecycle node's state
    SCHEMA = {'state': ProcState, 'pid': int, 'since': float, 'restarts': int, 'ready': bool,
              'exit_reason': str, 'lifecycle': ('optional', LifecycleState)}


@dataclass
class AgentState(Message):
    """An agent's report of what actually runs on its scale."""

    scale: str
    generation: int           # the newest layout generation this agent has applied
    stamp: float
    nodes: Dict[str, NodeReport]
    decider: Optional[str] = None     # the id of the decider whose layouts it follows
    instance: Optional[str] = None    # the agent process (a random id drawn at its start)
    seq: Optional[int] = None         # counts this agent process's reports
    auth: Optional[str] = None        # HMAC of the rest, with a deployment key
    # The machine it runs on: scales with one host_id share it (single-machine mode,
    # runtime/hosts.py); host is its host name, for people.
    host_id: Optional[str] = None
    host: Optional[str] = None
    term: Optional[int] = None        # the leadership term of the decider it follows
    SCHEMA = {'scale': str, 'generation': int, 'stamp': float, 'nodes': ('map', NodeReport),
              'decider': ('optional', str), 'instance': ('optional', str),
              'seq': ('optional', int), 'auth': ('optional', str),
              'host_id': ('optional', str), 'host': ('optional', str),
              'term': ('optional', int)}

    def validate(self, where: str) -> None:
        if abs(self.generation) > MAX_GENERATION:
            raise ProtocolError(f'{where}.generation: beyond the bound 2**53')
        _term_ok(self.term, where)
        _signed_fields_ok(self, where)
        for key in ('host_id', 'host'):
            value = getattr(self, key)
            if value is not None and (len(value) > 256 or not value.isprintable()):
                raise ProtocolError(f'{where}.{key}: over 256 characters or not printable')

    def to_dict(self) -> Dict[str, Any]:
        out = {'scale': self.scale, 'generation': self.generation, 'stamp': self.stamp,
               'nodes': {k: asdict(v) for k, v in self.nodes.items()}}
        for key in ('decider', 'instance', 'seq', 'auth', 'host_id', 'host', 'term'):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    def running(self) -> Dict[str, NodeReport]:
        return {k: v for k, v in self.nodes.items() if v.state in LIVE_STATES}


@dataclass
class ScaleStatus(Message):
    """CPU (reference-core percent), memory and load of one scale and its managed nodes."""

    scale: str
    stamp: float
    cpu_total: float
    capacity_cpu: float
    cpu_by_node: Dict[str, float]
    mem_percent: float
    load_1m: float
    # What cpu_total measures: 'cgroup', 'machine' or 'processes' (the agent's process tree,
    # single-machine mode; runtime/cpu.py); absent from older agents.
    cpu_source: Optional[str] = None
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'scale': str, 'stamp': float, 'cpu_total': float, 'capacity_cpu': float,
              'cpu_by_node': ('map', float), 'mem_percent': float, 'load_1m': float,
              'cpu_source': ('optional', str), **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        if self.cpu_source is not None and self.cpu_source not in CPU_SOURCES:
            raise ProtocolError(f'{where}.cpu_source: expected one of '
                                f'{", ".join(CPU_SOURCES)}, got {self.cpu_source!r:.40}')
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        out = asdict(self)
        if out['cpu_source'] is None:
            del out['cpu_source']
        return _without_unsigned(out, self)


@dataclass
class LinkStatus(Message):
    """One link as the agent that watches it sees it (Deployment.link_monitor): the master's
    view of its link to a remote scale, or a remote scale's view of its link to another."""

    master: str          # the scale that watches the link (the master for its own links)
    remote: str          # the far end
    stamp: float
    up: bool
    rtt_ms: Optional[float]
    loss: float                                  # fraction of recent beats lost
    # the last probe's figure, or a congestion's (runtime/bandwidth.py); None = none yet
    bandwidth_available_kbps: Optional[float]
    bandwidth_available_age_s: Optional[float]
    bandwidth_used_kbps: float                   # measured traffic of crossing connections
    queueing_delay_ms: Optional[float] = None    # RTT beyond the base; None = not judged yet
    congested: bool = False                      # queueing delay past congestion_delay_ms
    # What the remote scale's warden says of its agent (agent/warden.py: alive, restarting,
    # gone, fenced) and for how long; None while the link is down or before its first echo.
    peer_agent: Optional[str] = None
    peer_agent_for_s: Optional[float] = None
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'master': str, 'remote': str, 'stamp': float, 'up': bool,
              'rtt_ms': ('optional', float), 'loss': float,
              'bandwidth_available_kbps': ('optional', float),
              'bandwidth_available_age_s': ('optional', float),
              'bandwidth_used_kbps': float, 'queueing_delay_ms': ('optional', float),
              'congested': bool, 'peer_agent': ('optional', str),
              'peer_agent_for_s': ('optional', float), **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        return _without_unsigned(asdict(self), self)


@dataclass
class ConnectionReading(Message):
    rate_hz: float
    bytes_per_s: float
    below_for_s: float        # the open stretch below freq_min (runtime/delta.py; 0 if none)
    level: int                # OK / WARN (below, within tolerance) / ERROR (past tolerance)
    # The longest stretch below that ended since the previous reading (None or 0: none), so
    # that a stretch past Δ that ended between two readings is still reported.
    ended_below_s: Optional[float] = None
    # Bytes per second over the last runtime/bandwidth.DELIVERY_SPAN_S only: what a link
    # delivers now (bytes_per_s spans the whole probe window).
    recent_bytes_per_s: Optional[float] = None
    # Where the topic's writers are told apart (the publisher is migratable): how many were
    # heard lately, and how long two or more have been heard at once (0: not now).
    senders: Optional[int] = None
    senders_for_s: Optional[float] = None
    SCHEMA = {'rate_hz': float, 'bytes_per_s': float, 'below_for_s': float, 'level': int,
              'ended_below_s': ('optional', float), 'recent_bytes_per_s': ('optional', float),
              'senders': ('optional', int), 'senders_for_s': ('optional', float)}

    def validate(self, where: str) -> None:
        if self.level not in (OK, WARN, ERROR, STALE):
            raise ProtocolError(f'{where}.level: expected 0-3 (OK, WARN, ERROR, STALE), '
                                f'got {str(self.level)[:20]}')
        if self.senders is not None and not 0 <= self.senders <= 1000:
            raise ProtocolError(f'{where}.senders: expected 0-1000, got {self.senders}')
        if self.senders_for_s is not None and not self.senders_for_s >= 0:
            raise ProtocolError(f'{where}.senders_for_s: expected >= 0, '
                                f'got {self.senders_for_s}')


@dataclass
class ConnectionStatus(Message):
    """Readings of every probe on one scale (the scale where each subscriber runs)."""

    scale: str
    stamp: float
    connections: Dict[str, ConnectionReading]
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'scale': str, 'stamp': float, 'connections': ('map', ConnectionReading),
              **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        out = {'scale': self.scale, 'stamp': self.stamp,
               'connections': {k: asdict(v) for k, v in self.connections.items()},
               'sender': self.sender, 'seq': self.seq, 'auth': self.auth}
        return _without_unsigned(out, self)


@dataclass
class Event(Message):
    """One decision of the decider, with its reason."""

    stamp: float
    kind: str         # migrate, migrate_back, adopt, scale_lost, warning, layout, ...
    node: str
    from_scale: str
    to_scale: str
    reason: str
    generation: int
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'stamp': float, 'kind': str, 'node': str, 'from_scale': str, 'to_scale': str,
              'reason': str, 'generation': int, **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        return _without_unsigned(asdict(self), self)


DECIDER_ROLES = ('leader', 'standby')


@dataclass
class DeciderBeat(Message):
    """A decider's beat on /anyscale/decider, every ``decider.beat_s``: who it is, whether it
    leads or stands by, its term and the generation it leads at (runtime/leadership.py)."""

    stamp: float
    deployment: str
    decider: DeciderIdentity
    role: str
    term: int
    generation: int
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'stamp': float, 'deployment': str, 'decider': DeciderIdentity, 'role': str,
              'term': int, 'generation': int, **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        if self.role not in DECIDER_ROLES:
            raise ProtocolError(f'{where}.role: expected one of {", ".join(DECIDER_ROLES)}, '
                                f'got {self.role!r:.40}')
        _term_ok(self.term, where)
        if not 0 <= self.generation <= MAX_GENERATION:
            raise ProtocolError(f'{where}.generation: must be in [0, 2**53]')
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        return _without_unsigned(asdict(self), self)


@dataclass
class Objective(Message):
    """The ICAR cost function: Perf_map now, and its integral over the run."""

    stamp: float
    perf_map: float
    integral: float
    elapsed_s: float
    decider: Optional[str] = None     # the id of the decider that publishes it
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'stamp': float, 'perf_map': float, 'integral': float, 'elapsed_s': float,
              'decider': ('optional', str), 'seq': ('optional', int), 'auth': ('optional', str)}

    def validate(self, where: str) -> None:
        _signed_fields_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        return {k: v for k, v in asdict(self).items()
                if v is not None or k not in ('decider', 'seq', 'auth')}


@dataclass
class PlanNode(Message):
    expected_hz: float
    measured_hz: float
    expected_performance: float
    measured_performance: float
    deviation: float
    SCHEMA = {'expected_hz': float, 'measured_hz': float, 'expected_performance': float,
              'measured_performance': float, 'deviation': float}


@dataclass
class PlanCheck(Message):
    """Plan against reality (IROS 2016 Eq. 10) per node and overall."""

    stamp: float
    nodes: Dict[str, PlanNode]
    overall_deviation: float
    overloaded: Dict[str, float] = field(default_factory=dict)
    sender: Optional[str] = None
    seq: Optional[int] = None
    auth: Optional[str] = None
    SCHEMA = {'stamp': float, 'nodes': ('map', PlanNode), 'overall_deviation': float,
              'overloaded': ('map', float), **SIGNED_SCHEMA}

    def validate(self, where: str) -> None:
        _sender_ok(self, where)

    def to_dict(self) -> Dict[str, Any]:
        out = {'stamp': self.stamp, 'overall_deviation': self.overall_deviation,
               'nodes': {k: asdict(v) for k, v in self.nodes.items()},
               'overloaded': dict(self.overloaded),
               'sender': self.sender, 'seq': self.seq, 'auth': self.auth}
        return _without_unsigned(out, self)


__all__ = [
    'AgentState', 'ConnectionReading', 'ConnectionStatus', 'DeciderBeat', 'DeciderIdentity',
    'ERROR', 'Event', 'LIVE_STATES', 'Layout', 'LifecycleState', 'LinkStatus', 'MAX_GENERATION',
    'MAX_GENERATION_STEP', 'Message', 'NODE_STATES', 'NodeReport', 'OK', 'Objective',
    'PlanCheck', 'PlanNode', 'ProcState', 'ProtocolError', 'STALE', 'ScaleStatus', 'WARN',
]
