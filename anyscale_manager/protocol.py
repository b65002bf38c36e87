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
import types
import typing
from dataclasses import KW_ONLY, dataclass, field, fields
from enum import StrEnum
from typing import Any, ClassVar, Dict, Optional, Tuple, Type, TypeVar, Union

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


# What the decoder's errors say, most specific first: each is a kind of malformed message that
# a throttled log says on its own (``error_kind``).
DECODE_ERRORS = ('is not allowed', 'not valid JSON', 'expected JSON text', 'is over the',
                 'nested deeper than', 'expected a JSON object', 'unknown field',
                 'missing field', 'expected a finite number', 'is beyond the bound', 'must be',
                 'expected one of', 'expected an integer', 'expected true or false',
                 'expected a string', 'expected a map', 'characters', 'bad decider identity')


def error_kind(text: str) -> str:
    """The kind of a ProtocolError's text: the first of ``DECODE_ERRORS`` in it, else
    'malformed'. A key from a fixed set: a message's own words can at most choose among
    them."""
    return next((kind for kind in DECODE_ERRORS if kind in text), 'malformed')


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
# DeciderBeat.role (runtime/leadership.py).
DECIDER_ROLES = ('leader', 'standby')
# NodeReport.log_tail: the last line of a node's log, cut to this many characters.
LOG_TAIL_CHARS = 300

T = TypeVar('T', bound='Message')


# --- checks a type cannot say, declared with the field (its metadata) --------------------------

def _shown(number: Any) -> str:
    """A number in an error message: whole when short."""
    if abs(number) == MAX_GENERATION:
        return ('-' if number < 0 else '') + '2**53'
    text = str(number)
    return text if len(text) <= 20 else f'{number:.3g}'


class Rule:
    """A check of one field's value beyond its type; ProtocolError names the field."""

    kinds: ClassVar[Tuple[Any, ...]] = ()     # the schema kinds it applies to

    def check(self, value: Any, where: str) -> None:
        raise NotImplementedError


@dataclass(frozen=True)
class Within(Rule):
    """A number in [lo, hi]; with no hi, at least lo (MAX_MAGNITUDE bounds every float)."""

    lo: float
    hi: Optional[float] = None
    kinds: ClassVar[Tuple[Any, ...]] = (int, float)

    def check(self, value: Any, where: str) -> None:
        if self.hi is None:
            if not value >= self.lo:
                raise ProtocolError(f'{where}: must be >= {_shown(self.lo)}, '
                                    f'got {_shown(value)}')
            return
        if self.lo <= value <= self.hi:
            return
        lo, hi = _shown(self.lo), _shown(self.hi)
        if value < self.lo:
            raise ProtocolError(f'{where}: must be in [{lo}, {hi}] (must be >= {lo}, '
                                f'got {_shown(value)})')
        raise ProtocolError(f'{where}: must be in [{lo}, {hi}] ({_shown(value)} is beyond '
                            f'the bound {hi})')


@dataclass(frozen=True)
class OneOf(Rule):
    """One of a closed set of values that the wire carries as plain strings or numbers."""

    choices: Tuple[Any, ...]
    kinds: ClassVar[Tuple[Any, ...]] = (int, str)

    def check(self, value: Any, where: str) -> None:
        if value not in self.choices:
            raise ProtocolError(f'{where}: expected one of '
                                f'{", ".join(map(str, self.choices))}, got {value!r:.40}')


@dataclass(frozen=True)
class Text(Rule):
    """A string of min_len to max_len characters, printable ones unless said otherwise."""

    min_len: int
    max_len: int
    printable: bool = True
    kinds: ClassVar[Tuple[Any, ...]] = (str,)

    def check(self, value: Any, where: str) -> None:
        if not self.min_len <= len(value) <= self.max_len \
                or (self.printable and not value.isprintable()):
            size = (f'{self.min_len} to {self.max_len}' if self.min_len
                    else f'at most {self.max_len}')
            kind = ' printable' if self.printable else ''
            raise ProtocolError(f'{where}: expected {size}{kind} characters, '
                                f'got {value!r:.60}')


@dataclass(frozen=True)
class Keys(Rule):
    """Every key of a map passes ``rule``."""

    rule: Text
    kinds: ClassVar[Tuple[Any, ...]] = ('map',)

    def check(self, value: Any, where: str) -> None:
        for key in value:
            self.rule.check(key, f'{where} key')


_RULES = 'rules'      # the key of a field's rules in its metadata


def _rules(*rules: Rule) -> Dict[str, Tuple[Rule, ...]]:
    """A field's metadata: the checks of its value that its type cannot say."""
    return {_RULES: rules}


def _optional(*rules: Rule) -> Any:
    """An optional field (absent or null on the wire: None), with these checks when set."""
    return field(default=None, metadata=_rules(*rules))


# Generations, terms and sequence numbers: counts no sender takes past 2**53.
_COUNT = Within(0, MAX_GENERATION)
_AUTH = Text(0, 128, printable=False)
_HOST = Text(0, 256)


@dataclass
class Sealed:
    """The fields of a message that is signed when the deployment has a key: its sender's
    message count and the HMAC of the rest (hex; whether it is right is protocol_auth's to say).
    Keyword-only, so that a message's own fields keep their positions."""

    _: KW_ONLY
    seq: Optional[int] = _optional(_COUNT)
    auth: Optional[str] = _optional(_AUTH)


@dataclass
class Signed(Sealed):
    """A signed status message, which names its sender: the sending process (a random id
    drawn at its start)."""

    _: KW_ONLY
    sender: Optional[str] = _optional(Text(1, 128))


SIGNED_FIELDS = tuple(f.name for f in fields(Signed))


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
        todo.extend((child, depth + 1) for child in children
                    if isinstance(child, (dict, list)))


class Message:
    """Base of every payload: a dataclass under ``@_wire``, which derives its wire schema.

    ``SCHEMA`` maps each field to its kind, from its type hint: Optional[X] may be absent or
    null (None), Dict[str, X] is a JSON object of X, anything else is required. ``RULES`` maps a
    field to the checks its type cannot say, from its metadata (``_rules``, ``_optional``).
    """

    SCHEMA: ClassVar[Dict[str, Any]] = {}
    RULES: ClassVar[Dict[str, Tuple[Rule, ...]]] = {}
    # Optional fields added after the message's form inside another was fixed: left out when
    # None there too (an earlier version's strict decoder refuses a field it does not know,
    # null or not), while the older optional fields keep travelling as null.
    OMIT_WHEN_NONE: ClassVar[Tuple[str, ...]] = ()

    @classmethod
    def from_dict(cls: Type[T], data: Any, where: str = '') -> T:
        where = where or cls.__name__
        if not isinstance(data, dict):
            raise ProtocolError(f'{where}: expected a JSON object, got {data!r:.60}')
        unknown = () if data.keys() <= cls.SCHEMA.keys() \
            else sorted(str(k) for k in data if k not in cls.SCHEMA)
        if unknown:
            # A layout that smuggles a command (or any field we do not know) is refused whole.
            raise ProtocolError(f'{where}: unknown field {unknown[0]!r:.60}')
        values = {}
        for name, kind in cls.SCHEMA.items():
            if name not in data:
                if _is_optional(kind):
                    values[name] = None
                    continue
                raise ProtocolError(f'{where}: missing field {name!r}')
            value = values[name] = _check(data[name], kind, f'{where}.{name}')
            if value is not None:
                for rule in cls.RULES.get(name, ()):
                    rule.check(value, f'{where}.{name}')
        obj = cls(**values)
        obj.validate(where)
        return obj

    def validate(self, where: str) -> None:
        """Checks of several fields together; override where a message has them."""

    def to_dict(self) -> Dict[str, Any]:
        """The JSON object. An optional field that is None is left out: the strict decoder of
        an earlier version, which refuses fields it does not know, still reads it."""
        out = {}
        for name, optional in _field_names(type(self)):
            value = getattr(self, name)
            if value is not None or not optional:
                out[name] = _nested(value)
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(',', ':'), sort_keys=True)

    @classmethod
    def from_json(cls: Type[T], text: Any, topic: str = '') -> T:
        """The message ``text`` holds, checked field by field. The last message decoded is
        kept with the very text it came from: the readers of one delivery
        (nodes/readers.py: the agent, its link monitor and the master's decider take the same
        message) are handed one object, decoded once, which none of them may change."""
        global _LAST_DECODED
        last = _LAST_DECODED
        if last[1] is text and last[0] is cls:
            return last[2]
        obj = cls._decode(text, topic)
        _LAST_DECODED = (cls, text, obj)
        return obj

    @classmethod
    def _decode(cls: Type[T], text: Any, topic: str) -> T:
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


_LAST_DECODED: Tuple[Any, Any, Any] = (None, None, None)     # (class, text, message)


def _nested(value: Any) -> Any:
    """A field's value as JSON: a message inside another as its fields (its optional ones null,
    but those of ``OMIT_WHEN_NONE`` left out when None)."""
    if isinstance(value, Message):
        out = _plain(value)
        for key in type(value).OMIT_WHEN_NONE:
            if out.get(key) is None:
                out.pop(key, None)
        return out
    if isinstance(value, dict):
        return {k: _nested(v) for k, v in value.items()}
    return _plain(value)


_SCALARS = frozenset({str, int, float, bool, type(None)})
_FIELD_NAMES: Dict[type, Tuple[Tuple[str, bool], ...]] = {}


def _field_names(cls: type) -> Tuple[Tuple[str, bool], ...]:
    """A dataclass's (field name, whether the wire's schema makes it optional), in order."""
    names = _FIELD_NAMES.get(cls)
    if names is None:
        schema = getattr(cls, 'SCHEMA', {})
        names = _FIELD_NAMES[cls] = tuple((f.name, f.name in schema and
                                           _is_optional(schema[f.name])) for f in fields(cls))
    return names


def _plain(value: Any) -> Any:
    """What ``dataclasses.asdict`` makes of ``value`` (dataclasses as dicts of their fields,
    containers of the same type, recursively), without its deep copy of every leaf: a
    message's leaves are immutable values, and the JSON of both is the same."""
    cls = type(value)
    if cls in _SCALARS:
        return value
    if hasattr(cls, '__dataclass_fields__'):
        return {name: _plain(getattr(value, name)) for name, _ in _field_names(cls)}
    if isinstance(value, dict):
        return cls((_plain(k), _plain(v)) for k, v in value.items())
    if isinstance(value, tuple) and hasattr(value, '_fields'):
        return cls(*[_plain(v) for v in value])
    if isinstance(value, (list, tuple)):
        return cls(_plain(v) for v in value)
    return value


def _reject_constant(name: str) -> None:
    raise ValueError(f'{name} is not allowed')


def _is_optional(kind: Any) -> bool:
    return isinstance(kind, tuple) and kind[0] == 'optional'


def _kind(hint: Any, where: str) -> Any:
    """A field's type hint in _check's small type language."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType) and len(args) == 2 and type(None) in args:
        return ('optional', _kind(next(a for a in args if a is not type(None)), where))
    if origin is dict and args[0] is str:
        return ('map', _kind(args[1], where))
    if hint in (float, int, bool, str) \
            or isinstance(hint, type) and issubclass(hint, (_Vocabulary, Message)):
        return hint
    raise TypeError(f'{where}: no wire form for {hint!r}')   # a bug in this module, not input


def _wire(cls: Type[T]) -> Type[T]:
    """Set a message's SCHEMA and RULES from its dataclass fields, the one declaration."""
    hints = typing.get_type_hints(cls)
    schema: Dict[str, Any] = {}
    rules: Dict[str, Tuple[Rule, ...]] = {}
    for f in fields(cls):      # type: ignore[arg-type]
        where = f'{cls.__name__}.{f.name}'
        kind = schema[f.name] = _kind(hints[f.name], where)
        base = kind[1] if _is_optional(kind) else kind
        base = base[0] if isinstance(base, tuple) else base
        declared = tuple(f.metadata.get(_RULES, ()))
        for rule in declared:
            if base not in rule.kinds:      # a bug in this module: the check could not run
                raise TypeError(f'{where}: {rule!r} does not apply to {base!r}')
        if declared:
            rules[f.name] = declared
    cls.SCHEMA, cls.RULES = schema, rules
    return cls


@_wire
@dataclass
class DeciderIdentity(Message):
    """Who publishes a layout: one decider process (a random id drawn at its start)."""

    id: str
    host: str
    pid: int
    started: float            # the decider's wall clock at its start

    def validate(self, where: str) -> None:
        if not self.id or len(self.id) > 64 or len(self.host) > 256 \
                or not (self.id + self.host).isprintable():
            raise ProtocolError(f'{where}: bad decider identity {self.id!r:.60}')

    def describe(self) -> str:
        return f'{self.id} (host {self.host:.60}, pid {self.pid})'


@_wire
@dataclass
class Layout(Sealed, Message):
    """The desired layout: node -> scale for every managed node, with a generation number.

    ``decider`` names the decider that publishes it (absent from older deciders), ``term`` is
    its leadership term (the fence: agents refuse a lower one than they follow; absent: 0),
    ``seq`` counts that decider's layout messages (re-publications included), and ``auth`` is
    the HMAC of the rest when the deployment has a key (protocol_auth).
    """

    generation: int = field(metadata=_rules(_COUNT))
    deployment: str
    assignments: Dict[str, str] = field(metadata=_rules(Keys(Text(1, 256, printable=False))))
    reason: str
    stamp: float
    decider: Optional[DeciderIdentity] = None
    term: Optional[int] = _optional(_COUNT)


@_wire
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
    # Of a copy that exited unasked, while it waits for its restart (and starts again): its
    # exit code (-N: killed by signal N) and the last line its process wrote to its log, on one
    # line of printable characters (agent/log_tail.py last_line); absent otherwise.
    exit_code: Optional[int] = _optional(Within(-128, 255))
    log_tail: Optional[str] = _optional(Text(0, LOG_TAIL_CHARS))
    OMIT_WHEN_NONE: ClassVar[Tuple[str, ...]] = ('exit_code', 'log_tail')


@_wire
@dataclass
class ShareClaim(Message):
    """One claim on a shared host (agent/ledger.py): an active copy's CPU, its memory."""

    cpu: float = field(metadata=_rules(Within(0)))
    memory_mb: float = field(metadata=_rules(Within(0)))
    priority: int = field(metadata=_rules(Within(-1000, 1000)))
    active: bool


@_wire
@dataclass
class HostShare(Message):
    """A shared scale's host as its agent sees it: the host's capacity, every other
    deployment's claims ('deployment/node' -> claim), this deployment's nodes it may not start
    or serve (``refused``: no room; ``waiting``: lower claims were asked to leave), and its
    nodes asked to leave by a claim of a higher priority (node -> 'deployment/node')."""

    capacity_cpu: float = field(metadata=_rules(Within(0)))
    memory_mb: float = field(metadata=_rules(Within(0)))
    claims: Dict[str, ShareClaim] = field(metadata=_rules(Keys(Text(1, 512))))
    refused: Dict[str, str] = field(metadata=_rules(Keys(Text(1, 256))))
    waiting: Dict[str, str] = field(metadata=_rules(Keys(Text(1, 256))))
    asked: Dict[str, str] = field(metadata=_rules(Keys(Text(1, 256))))


@_wire
@dataclass
class AgentState(Sealed, Message):
    """An agent's report of what actually runs on its scale."""

    scale: str
    # The newest layout generation this agent has applied.
    generation: int = field(metadata=_rules(Within(-MAX_GENERATION, MAX_GENERATION)))
    stamp: float
    nodes: Dict[str, NodeReport]
    decider: Optional[str] = None     # the id of the decider whose layouts it follows
    # The agent process (a random id drawn at its start), whose reports seq counts.
    instance: Optional[str] = None
    # The machine it runs on: scales with one host_id share it (single-machine mode,
    # runtime/hosts.py); host is its host name, for people.
    host_id: Optional[str] = _optional(_HOST)
    host: Optional[str] = _optional(_HOST)
    term: Optional[int] = _optional(_COUNT)   # the leadership term of the decider it follows
    share: Optional[HostShare] = None    # a shared scale's host (agent/claims.py)

    def running(self) -> Dict[str, NodeReport]:
        return {k: v for k, v in self.nodes.items() if v.state in LIVE_STATES}


@_wire
@dataclass
class ScaleStatus(Signed, Message):
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
    cpu_source: Optional[str] = _optional(OneOf(CPU_SOURCES))
    # The CPUs the readings are spread over (runtime/cpu.py effective_cores: the machine's, or
    # its quota's): one of them busy reads capacity_cpu / cores. Absent from older agents.
    cores: Optional[float] = _optional(Within(0.001, 65536))


@_wire
@dataclass
class LinkStatus(Signed, Message):
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

    def to_dict(self) -> Dict[str, Any]:
        # A reading not known travels as null, as link monitors have always sent it; only the
        # signed fields are left out when unset.
        out = _plain(self)
        for key in SIGNED_FIELDS:
            if out[key] is None:
                del out[key]
        return out


@_wire
@dataclass
class ConnectionReading(Message):
    rate_hz: float
    bytes_per_s: float
    below_for_s: float        # the open stretch below freq_min (runtime/delta.py; 0 if none)
    # OK / WARN (below, within tolerance) / ERROR (past tolerance), or STALE
    level: int = field(metadata=_rules(OneOf((OK, WARN, ERROR, STALE))))
    # The longest stretch below that ended since the previous reading (None or 0: none), so
    # that a stretch past Δ that ended between two readings is still reported.
    ended_below_s: Optional[float] = None
    # Bytes per second over the last runtime/bandwidth.DELIVERY_SPAN_S only: what a link
    # delivers now (bytes_per_s spans the whole probe window).
    recent_bytes_per_s: Optional[float] = None
    # Where the topic's writers are told apart (the publisher is migratable): how many were
    # heard lately, and how long two or more have been heard at once (0: not now).
    senders: Optional[int] = _optional(Within(0, 1000))
    senders_for_s: Optional[float] = _optional(Within(0))


@_wire
@dataclass
class ConnectionStatus(Signed, Message):
    """Readings of every probe on one scale (the scale where each subscriber runs)."""

    scale: str
    stamp: float
    connections: Dict[str, ConnectionReading]


@_wire
@dataclass
class Event(Signed, Message):
    """One decision of the decider, with its reason."""

    stamp: float
    kind: str         # migrate, migrate_back, adopt, scale_lost, warning, layout, ...
    node: str
    from_scale: str
    to_scale: str
    reason: str
    generation: int


@_wire
@dataclass
class DeciderBeat(Signed, Message):
    """A decider's beat on /anyscale/decider, every ``decider.beat_s``: who it is, whether it
    leads or stands by, its term and the generation it leads at (runtime/leadership.py)."""

    stamp: float
    deployment: str
    decider: DeciderIdentity
    role: str = field(metadata=_rules(OneOf(DECIDER_ROLES)))
    term: int = field(metadata=_rules(_COUNT))
    generation: int = field(metadata=_rules(_COUNT))


@_wire
@dataclass
class Objective(Sealed, Message):
    """The ICAR cost function: Perf_map now, and its integral over the run."""

    stamp: float
    perf_map: float
    integral: float
    elapsed_s: float
    decider: Optional[str] = None     # the id of the decider that publishes it


@_wire
@dataclass
class PlanNode(Message):
    expected_hz: float
    measured_hz: float
    expected_performance: float
    measured_performance: float
    deviation: float


@_wire
@dataclass
class PlanCheck(Signed, Message):
    """Plan against reality (IROS 2016 Eq. 10) per node and overall."""

    stamp: float
    nodes: Dict[str, PlanNode]
    overall_deviation: float
    overloaded: Dict[str, float] = field(default_factory=dict)


__all__ = [
    'AgentState', 'ConnectionReading', 'ConnectionStatus', 'DeciderBeat', 'DeciderIdentity',
    'ERROR', 'Event', 'LIVE_STATES', 'LOG_TAIL_CHARS', 'Layout', 'LifecycleState', 'LinkStatus',
    'MAX_GENERATION', 'MAX_GENERATION_STEP', 'Message', 'NODE_STATES', 'NodeReport', 'OK',
    'Objective', 'PlanCheck', 'PlanNode', 'ProcState', 'ProtocolError', 'STALE', 'ScaleStatus',
    'WARN',
]
