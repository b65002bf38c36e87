"""The deployment skeleton a profile writes: YAML text with its explanations in comments. Pure.

The file is a ROS 2 parameters file (``/**: ros__parameters:``) that ``anyscale-manager
validate`` accepts as written: one scale (this host, the master) holds every node, there are no
links, each node has its measured CPU, no launch and ``managed: false`` (no agent starts it
yet), each connection its message type and, when its rate was measured, suggested thresholds
(``suggest.py``) and its bandwidth. An agent run on it as it is already probes every
connection against those thresholds (an unmanaged node's connections are probed on its only
scale). What the user
has to decide is marked TODO; every suggested figure says so on its line.
"""

import re
import textwrap
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from .graph import Edge, MSG_TYPE_RE
from .processes import ProcessMatch
from .stats import CpuSummary, RateSummary, round_sig
from .suggest import LIFECYCLE_EVENT_TYPE, LaunchSuggestion, Suggestion, suggest, suggest_launch

KEY_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
PLAIN_RE = re.compile(r'^[A-Za-z_/.][A-Za-z0-9_/.+-]*$')
YAML_WORDS = {'true', 'false', 'yes', 'no', 'on', 'off', 'null', 'y', 'n', '~'}
RESERVED_KEYS = {'names'}     # a section may not be called like the list of its sections
SCALE = 'robot'
WIDTH = 99


@dataclass(frozen=True)
class HostInfo:
    hostname: str
    cores: int                         # logical CPUs
    clock_ghz: Optional[float] = None  # None: unknown here


@dataclass(frozen=True)
class NodeReport:
    """One node of the graph: where it ran and what CPU it used."""

    name: str                             # full ROS name, '/ns/name'
    cpu: Optional[CpuSummary] = None      # its share of its process; None: not measured
    process: Optional[ProcessMatch] = None
    cmdline: Tuple[str, ...] = ()         # of its (first) process
    no_cpu_reason: str = ''
    shares_with: Tuple[str, ...] = ()     # other nodes of the same process
    copies: int = 1                       # nodes of this name seen at once
    gone_s: float = 0.0                   # left the graph this long before the end
    lifecycle: bool = False               # it published its lifecycle transition events


@dataclass(frozen=True)
class TopicReport:
    """One measured topic (the profiler subscribes once per topic, as the probes do)."""

    topic: str
    msg_type: str
    rate: Optional[RateSummary] = None
    problem: str = ''                     # why it was not measured
    types: Tuple[str, ...] = ()           # every type its publishers declare


@dataclass(frozen=True)
class Profile:
    name: str
    host: HostInfo
    domain_id: str
    duration_s: float
    started: str                          # when the watch began, for the header
    nodes: Tuple[NodeReport, ...]
    edges: Tuple[Edge, ...]
    topics: Mapping[str, TopicReport] = field(default_factory=dict)
    interrupted: bool = False


# --- names ------------------------------------------------------------------------------------
def _key(text: str) -> str:
    key = re.sub(r'[^A-Za-z0-9_]+', '_', text).strip('_') or 'node'
    if not key[0].isalpha():
        key = 'n_' + key
    return key + '_node' if key in RESERVED_KEYS else key


def _unique(wanted: Iterable[Tuple[object, str]]) -> Dict[object, str]:
    out: Dict[object, str] = {}
    used = set()
    for item, key in wanted:
        candidate, n = key, 2
        while candidate in used:
            candidate, n = f'{key}_{n}', n + 1
        used.add(candidate)
        out[item] = candidate
    return out


def node_keys(names: Sequence[str]) -> Dict[str, str]:
    """Full ROS name -> section name: the base name, or namespace and name when two nodes
    share a base name; always a valid deployment name, each used once."""
    bases: Dict[str, int] = {}
    for full in names:
        base = _key(full.rsplit('/', 1)[-1])
        bases[base] = bases.get(base, 0) + 1
    wanted = []
    for full in names:
        base = _key(full.rsplit('/', 1)[-1])
        wanted.append((full, base if bases[base] == 1 else _key(full)))
    return _unique(wanted)


def connection_keys(edges: Sequence[Edge], keys: Mapping[str, str]) -> Dict[Edge, str]:
    """'<publisher>_<subscriber>', with the topic added when one pair has several topics."""
    pairs: Dict[Tuple[str, str], int] = {}
    for e in edges:
        pair = (e.publisher, e.subscriber)
        pairs[pair] = pairs.get(pair, 0) + 1
    wanted = []
    for e in edges:
        key = f'{keys[e.publisher]}_{keys[e.subscriber]}'
        if pairs[(e.publisher, e.subscriber)] > 1:
            key = f'{key}_{_key(e.topic)}'
        wanted.append((e, _key(key)))
    return _unique(wanted)


# --- YAML scalars -----------------------------------------------------------------------------
def scalar(value: object) -> str:
    """One YAML scalar as both PyYAML and the ROS parameter parser read it back."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = f'{value:.6f}'.rstrip('0')
        return text + '0' if text.endswith('.') else text
    text = str(value)
    if PLAIN_RE.match(text) and text.lower() not in YAML_WORDS:
        return text
    return "'" + text.replace("'", "''") + "'"


def flow_list(values: Iterable[object]) -> str:
    return '[' + ', '.join(scalar(v) for v in values) + ']'


class _Writer:
    def __init__(self):
        self.lines: List[str] = []

    def line(self, indent: int, text: str = '', comment: str = '') -> None:
        text = ' ' * indent + text if text else ''
        if comment:
            comment = ' '.join(comment.split())
            if text and len(text) + 3 + len(comment) <= WIDTH:
                self.lines.append(f'{text}  # {comment}')
                return
            self.comment(indent, comment)
        if text:
            self.lines.append(text)

    def comment(self, indent: int, text: str, hanging: int = 0) -> None:
        """A comment wrapped at WIDTH; ``hanging``: continuation lines indented that much."""
        text = ' '.join(text.split())
        prefix = ' ' * indent + '# '
        self.lines += textwrap.wrap(text, WIDTH, initial_indent=prefix,
                                    subsequent_indent=prefix + ' ' * hanging,
                                    break_long_words=False, break_on_hyphens=False) or [prefix]

    def raw_comment(self, indent: int, text: str) -> None:
        """One comment line as written (an example to uncomment keeps its indentation)."""
        self.lines.append(' ' * indent + '# ' + text)

    def commented_list(self, indent: int, key: str, values: Sequence[object],
                       inner: int = 0) -> None:
        """``# key: [a, b, ...]`` wrapped so that, uncommented, it is one YAML flow sequence;
        ``inner``: spaces between the ``#`` and the key (the example's own nesting)."""
        self.flow_list(indent, key, values, prefix='# ' + ' ' * inner)

    def flow_list(self, indent: int, key: str, values: Sequence[object],
                  prefix: str = '') -> None:
        """``key: [a, b, ...]``, wrapped at WIDTH as one YAML flow sequence."""
        prefix = ' ' * indent + prefix
        head = f'{key}: ['
        items = [scalar(v) for v in values]
        line, fresh = prefix + head, True
        for i, item in enumerate(items):
            piece = item + (']' if i == len(items) - 1 else ',')
            if not fresh and len(line) + 1 + len(piece) > WIDTH:
                self.lines.append(line)
                line, fresh = prefix + ' ' * len(head), True
            line += ('' if fresh else ' ') + piece
            fresh = False
        self.lines.append(line if items else line + ']')

    def blank(self) -> None:
        if self.lines and self.lines[-1]:
            self.lines.append('')

    def text(self) -> str:
        return '\n'.join(self.lines).rstrip() + '\n'


# --- the file ---------------------------------------------------------------------------------
def _fmt(x: float, digits: int = 3) -> str:
    return f'{round_sig(x, digits):g}'


def _cpu_percent(cpu: CpuSummary) -> float:
    """Cores of this host -> percent of one core of this host (the skeleton's unit)."""
    return round(cpu.mean * 100.0, 1)


@dataclass(frozen=True)
class _Roles:
    providers: Tuple[str, ...]    # publish to some node, subscribe to none
    sinks: Tuple[str, ...]        # subscribe to some node, publish to none


def _roles(nodes: Sequence[str], edges: Sequence[Edge]) -> _Roles:
    pubs = {e.publisher for e in edges}
    subs = {e.subscriber for e in edges}
    return _Roles(tuple(n for n in nodes if n in pubs and n not in subs),
                  tuple(n for n in nodes if n in subs and n not in pubs))


def counts(profile: Profile) -> Dict[str, int]:
    """Figures for the command's closing line."""
    suggestions = [suggest(_rate(profile, e)) for e in profile.edges]
    return {'nodes': len(profile.nodes), 'connections': len(profile.edges),
            'monitored': sum(1 for s in suggestions if s.monitored),
            'cpu': sum(1 for n in profile.nodes if n.cpu is not None)}


def _rate(profile: Profile, edge: Edge) -> Optional[RateSummary]:
    report = profile.topics.get(edge.topic)
    return report.rate if report else None


def render(profile: Profile) -> str:
    """The skeleton as YAML text with comments."""
    if not profile.nodes:
        raise ValueError('a deployment needs at least one node: the graph had none to keep')
    names = [n.name for n in profile.nodes]
    keys = node_keys(names)
    edges = list(profile.edges)
    ckeys = connection_keys(edges, keys)
    roles = _roles(names, edges)
    w = _Writer()
    _header(w, profile)
    w.line(0, '/**:')
    w.line(2, 'ros__parameters:')
    w.line(4, 'deployment:')
    w.line(6, f'name: {scalar(profile.name)}')
    w.line(6, 'description: ' + scalar(
        f'profiled on {profile.host.hostname}, ROS_DOMAIN_ID {profile.domain_id}, '
        f'{profile.duration_s:g} s from {profile.started}'))
    w.blank()
    _scales(w, profile.host)
    w.blank()
    w.line(4, 'nodes:')
    w.flow_list(6, 'names', [keys[n] for n in names])
    for node in profile.nodes:
        _node(w, node, keys, roles, profile, edges)
    if edges:
        w.blank()
        w.line(4, 'connections:')
        w.flow_list(6, 'names', [ckeys[e] for e in edges])
        for edge in edges:
            _connection(w, edge, ckeys[edge], keys, profile, edges)
    return w.text()


def _header(w: _Writer, p: Profile) -> None:
    cut = ' (cut short by Ctrl-C)' if p.interrupted else ''
    for text in (
            f'Deployment skeleton written by anyscale-manager profile from the ROS 2 graph on '
            f'{p.host.hostname} (ROS_DOMAIN_ID {p.domain_id}), watched {p.duration_s:g} s from '
            f'{p.started}{cut}. anyscale-manager validate accepts it as it is; to make it '
            f'yours (docs/profile.md):',
            'TODO 1. scales and links: one scale, this host, holds every node. Name your '
            'computers, exactly one master (the robot), and join them by links.',
            "TODO 2. nodes' launch: how an agent starts each node (the command line seen on "
            'this host is in a comment); then delete its managed: false, so that agents start '
            'it and the decider may move it. Until then agents only measure its connections.',
            'TODO 3. review every figure marked "suggestion": the profile saw what each '
            'connection did, not what its subscriber needs.',
            'TODO 4. pin what must stay on the robot: see the "critical candidate" comments.',
            "Measured: each topic at the profiler's own subscription, read as the agents' "
            'probes read it (the rate over a 2 s window, once a second: p50 and lowest '
            'reading); bandwidth from serialized message sizes; CPU in percent of one core of '
            'this host (the unit of capacity_cpu below), mean over the watch, for the nodes '
            'whose process runs on this host.'):
        w.comment(0, text, hanging=8 if text.startswith('TODO') else 0)


def _scales(w: _Writer, host: HostInfo) -> None:
    w.comment(4, f'TODO scales: one master scale, this host ({host.hostname}), holds every '
                 'node so that the file is valid. Rename it, give each computer its own '
                 'section and list it in names; exactly one has role master (where the decider '
                 'runs and critical nodes stay).')
    w.line(4, 'scales:')
    w.line(6, f'names: [{SCALE}]')
    w.line(6, f'{SCALE}:')
    w.line(8, 'role: master')
    w.line(8, 'kind: robot')
    w.line(8, f'capacity_cpu: {scalar(100.0 * host.cores)}',
           f'{host.cores} logical CPUs of this host x 100')
    w.line(8, f'cores: {host.cores}')
    if host.clock_ghz:
        w.line(8, f'clock_ghz: {scalar(round(host.clock_ghz, 2))}')
    else:
        w.line(8, 'clock_ghz: 1.0', 'TODO: the clock of this host could not be read')
    w.line(8, f'host: {scalar(host.hostname)}', 'TODO: the address other scales reach it at')
    w.raw_comment(6, 'laptop:     # a remote scale, for example: list it in names too')
    w.raw_comment(6, '  {role: remote, kind: server, capacity_cpu: 400.0, cores: 4, '
                     'clock_ghz: 2.8, gain: 3.5,')
    w.raw_comment(6, '   host: 192.168.1.20}')
    w.blank()
    w.comment(4, 'TODO links: one per pair of scales (none while there is one scale), e.g.')
    w.raw_comment(4, 'links:')
    w.raw_comment(4, '  names: [wifi]')
    w.raw_comment(4, '  wifi: {ends: [robot, laptop], bandwidth_kbps: 54000.0, medium: wireless}')


def _node(w: _Writer, node: NodeReport, keys: Mapping[str, str], roles: _Roles,
          profile: Profile, edges: Sequence[Edge]) -> None:
    key = keys[node.name]
    w.line(6, f'{key}:')
    where = node.name
    if node.process is not None:
        pids = ', '.join(str(pid) for pid in node.process.pids)
        where += f': pid {pids} on this host, found by {node.process.how}'
    w.comment(8, where)
    if node.copies > 1:
        w.comment(8, f'{node.copies} nodes named {node.name} were in the graph at once: one '
                     'section here; their CPU is summed.')
    if node.gone_s > 0:
        w.comment(8, f'left the graph {node.gone_s:.0f} s before the end of the watch.')
    out = sorted({e.topic for e in edges if e.publisher == node.name})
    into = sorted({e.topic for e in edges if e.subscriber == node.name})
    if node.name in roles.providers:
        w.comment(8, f'data provider: publishes {", ".join(out)} and subscribes to no node of '
                     'the file, so validate keeps it on the master scale unless it has a '
                     'residence.')
        w.comment(8, 'critical candidate: a data provider is often the driver of a sensor on '
                     'the robot; if it is, pin it there with critical: true (or a residence '
                     "naming the robot's scale).")
        w.comment(8, 'critical: true')
    elif node.name in roles.sinks:
        w.comment(8, f'critical candidate: subscribes to {", ".join(into)} and feeds no node '
                     "of the file; if it drives the robot's hardware (motors, a base "
                     'controller), pin it with critical: true.')
        w.comment(8, 'critical: true')
    if node.shares_with:
        others = [keys[o] for o in node.shares_with if o in keys]
        w.comment(8, f'runs in one process with {", ".join(others)}: they cannot be placed '
                     "apart (coresidence), and the process's CPU is split evenly among them.")
        w.flow_list(8, 'coresidence', others)
    # A node of the root namespace is known by its bare name, as the default (its key) is.
    ros_name = node.name.lstrip('/') if node.name.count('/') == 1 else node.name
    launch = suggest_launch(node.cmdline, node.lifecycle)
    if ros_name != key:
        w.line(8, 'launch:')
        w.line(10, f'ros_name: {scalar(ros_name)}', 'its name in the graph')
        _launch_hint(w, 10, launch, inside=True)
    else:
        _launch_hint(w, 8, launch, inside=False)
    w.line(8, 'managed: false', 'TODO: delete once it has a launch')
    if launch.lifecycle:
        _lifecycle_hint(w, 8, node, launch)
    if node.cpu is not None:
        w.line(8, f'cpu: {scalar(_cpu_percent(node.cpu))}',
               f'measured: mean over {len(node.cpu.readings)} one-second readings (max '
               f'{node.cpu.highest * 100:.1f}), % of one core of this host')
    else:
        w.line(8, 'cpu: 0.0', f'TODO: not measured: {node.no_cpu_reason or "no process found"}')


def _launch_hint(w: _Writer, indent: int, launch: LaunchSuggestion, inside: bool) -> None:
    seen = ' The command line seen on this host' if launch.command else ''
    if seen and launch.dropped:
        seen += (', less the remaps an agent adds itself when it starts the node (its name, '
                 "and its lifecycle services under the scale's name)")
    seen += ':' if seen else ''
    if inside:
        w.comment(indent, 'TODO: how an agent starts it: package and executable, or command.'
                  + seen)
        if launch.command:
            w.commented_list(indent, 'command', launch.command)
        return
    w.comment(indent, 'TODO launch: how an agent starts it (package and executable, or '
                      'command).' + seen)
    if launch.command:
        w.raw_comment(indent, 'launch:')
        w.commented_list(indent, 'command', launch.command, inner=2)


def _lifecycle_hint(w: _Writer, indent: int, node: NodeReport,
                    launch: LaunchSuggestion) -> None:
    how = []
    if node.lifecycle:
        how.append(f'it publishes its transition events ({LIFECYCLE_EVENT_TYPE})')
    if launch.dropped:
        how.append("its command line carries an agent's lifecycle remaps")
    w.comment(indent, f'lifecycle node: {" and ".join(how)}. Once it has a launch and no '
                      'managed: false, declare it (lifecycle: true): agents then configure it '
                      'and activate it where the layout places it (docs/lifecycle.md). '
                      'standby: true is then possible once it may run on a second scale: an '
                      'inactive copy waits on every scale it may run on, and a move is an '
                      'activation (milliseconds) instead of a process start.')
    w.raw_comment(indent, 'lifecycle: true')
    w.raw_comment(indent, 'standby: true')


def _connection(w: _Writer, edge: Edge, key: str, keys: Mapping[str, str], profile: Profile,
                edges: Sequence[Edge]) -> None:
    report = profile.topics.get(edge.topic)
    rate = report.rate if report else None
    s: Suggestion = suggest(rate)
    w.line(6, f'{key}:')
    w.line(8, f'topic: {scalar(edge.topic)}')
    w.line(8, f'publisher: {keys[edge.publisher]}')
    w.line(8, f'subscriber: {keys[edge.subscriber]}')
    if MSG_TYPE_RE.match(edge.msg_type):
        w.line(8, f'msg_type: {scalar(edge.msg_type)}')
    else:
        w.comment(8, f'msg_type: the graph gives {edge.msg_type!r}, not of the form '
                     'package/msg/Type: left to the graph')
    if report and len(report.types) > 1:
        w.comment(8, f'publishers of {edge.topic} declare several types '
                     f'({", ".join(report.types)}): measured as {report.msg_type} only.')
    writers = sorted({e.publisher for e in edges if e.topic == edge.topic})
    if len(writers) > 1:
        w.comment(8, f'{edge.topic} has {len(writers)} publisher nodes '
                     f'({", ".join(keys[n] for n in writers)}): the rate is all of theirs '
                     "together, as the agents' probes read it.")
    if rate is not None and rate.readings:
        w.comment(8, f'measured: p50 {_fmt(rate.median)} Hz, lowest {_fmt(rate.lowest)} '
                     f'Hz, highest {_fmt(rate.highest)} Hz over {len(rate.readings)} '
                     f'readings; {rate.messages} messages of {rate.mean_bytes:.0f} B on '
                     f'average (largest {rate.max_bytes} B)')
    elif rate is not None and rate.messages:
        w.comment(8, f'measured: {rate.messages} message(s) of {rate.mean_bytes:.0f} B on '
                     'average, too few for a rate')
    if not s.monitored:
        reason = report.problem if report and report.problem else s.unmonitored
        w.comment(8, f'no thresholds suggested: {reason}. Add freq_min_hz and tolerance_s '
                     '(and freq_opt_hz) to have it monitored.')
        return
    for why in s.why:
        w.comment(8, f'suggestion: {why}' if why.startswith('freq_') else why)
    w.line(8, f'freq_min_hz: {scalar(s.freq_min_hz)}', 'suggestion')
    w.line(8, f'freq_opt_hz: {scalar(s.freq_opt_hz)}', 'suggestion')
    w.line(8, f'tolerance_s: {scalar(s.tolerance_s)}', 'suggestion; 0 would pin both ends')
    w.line(8, f'bandwidth_kbps: {scalar(s.bandwidth_kbps)}',
           'measured: p50 rate x mean serialized size')
