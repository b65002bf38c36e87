"""Read a deployment YAML (a valid ROS 2 parameters file) into validated frozen dataclasses.

The file looks like::

    /**:
      ros__parameters:
        deployment: {name: ..., description: ...}
        scales: {names: [robot, laptop], robot: {...}, laptop: {...}}
        links: {names: [wifi], wifi: {ends: [robot, laptop], ...}}
        nodes: {names: [...], amcl: {launch: {...}, cpu: 50.0, ...}}
        connections: {names: [...], laser_amcl: {topic: /scan, ...}}
        decider: {...}
        monitoring: {...}
        agent: {...}
        security: {key_file: ..., replay_window_s: ...}

ROS parameters have no lists of maps, so every collection is a map of named sections plus a
``names`` list that fixes the order. Every error names the file, the path inside it and what
was expected; all errors are collected and reported at once, one line each: the cross checks
(references, residence and coresidence, criticality) run on whatever was read, so a typo in one key
does not hide a contradiction elsewhere in the same file.
"""

import difflib
import math
import os
import re
from dataclasses import dataclass, fields, replace
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

import yaml

from . import types as t

NAME_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
TOPIC_RE = re.compile(r'^/?[A-Za-z~{][A-Za-z0-9_/{}~]*$')
MISSING = object()


@dataclass(frozen=True)
class Problem:
    source: str
    path: str
    message: str

    def __str__(self) -> str:
        where = f'{self.source}: {self.path}' if self.path else self.source
        return f'{where}: {self.message}'


class DeploymentError(ValueError):
    """A deployment file that cannot be used; carries every problem found."""

    def __init__(self, problems: List[Problem]):
        self.problems = list(problems)
        super().__init__('\n'.join(str(p) for p in self.problems))


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + '...'


def did_you_mean(word: Any, candidates) -> str:
    """' (did you mean X?)' for the closest candidate, or '' when none is close."""
    close = difflib.get_close_matches(str(word), [str(c) for c in candidates], n=1)
    return f' (did you mean {close[0]}?)' if close else ''


class _Context:
    def __init__(self, source: str):
        self.source = source
        self.problems: List[Problem] = []
        self._damaged: List[str] = []     # paths whose value was not read as written
        self.declared: Dict[str, set] = {}   # collection -> every name it mentions
        self.broken = set()                  # collections whose names could not be read

    def error(self, path: str, message: str, damages: bool = True) -> None:
        """Record a problem once; ``damages``: the value at ``path`` was replaced by a default
        (an unknown key damages nothing: it is only left out)."""
        problem = Problem(self.source, path, message)
        if problem not in self.problems:
            self.problems.append(problem)
        if damages:
            self.mark_damaged(path)

    def mark_damaged(self, path: str) -> None:
        self._damaged.append(path)

    def damaged(self, path: str, inside: bool = True) -> bool:
        """True when ``path``, what holds it (or, with ``inside``, anything in it) was not read
        as written."""
        return any(p == path or path.startswith((f'{p}.', f'{p}['))
                   or inside and p.startswith((f'{path}.', f'{path}['))
                   for p in self._damaged if p)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class _Section:
    """One map in the file: typed reads that record errors instead of raising."""

    def __init__(self, ctx: _Context, path: str, data: Any):
        self.ctx = ctx
        self.path = path
        self.ok = isinstance(data, dict)
        if not self.ok:
            ctx.error(path, f'expected a map, got {_describe(data)}')
        self.data: Dict[str, Any] = data if self.ok else {}
        self.seen = set()
        self.known = set()    # every key the reader asked for: the "did you mean" candidates

    def sub(self, key: str) -> str:
        return f'{self.path}.{key}' if self.path else key

    def has(self, key: str) -> bool:
        self.known.add(key)
        return key in self.data

    def read(self, *keys: str) -> bool:
        """Whether these keys were read as written (absent counts as read): a check of how
        they fit together means something only then."""
        return not any(self.ctx.damaged(self.sub(k)) for k in keys)

    def raw(self, key: str, default: Any = MISSING) -> Any:
        self.seen.add(key)
        self.known.add(key)
        if key not in self.data:
            if default is MISSING and self.ok:   # else "expected a map" said it all
                self.ctx.error(self.sub(key), 'required key is missing')
            return default
        return self.data[key]

    def section(self, key: str, required: bool = True) -> '_Section':
        value = self.raw(key, MISSING if required else {})
        return _Section(self.ctx, self.sub(key), value if value is not MISSING else {})

    def string(self, key: str, default: Any = MISSING, pattern: Optional[re.Pattern] = None,
               choices: Optional[Tuple[str, ...]] = None) -> Any:
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return default
        if not isinstance(v, str):
            self.ctx.error(self.sub(key), f'expected a string, got {_describe(v)}')
            return default if default is not MISSING else ''
        if choices is not None and v not in choices:
            self.ctx.error(self.sub(key), f'expected one of {", ".join(choices)}, got {v!r}'
                                          f'{did_you_mean(v, choices)}')
        if pattern is not None and not pattern.match(v):
            self.ctx.error(self.sub(key), f'{v!r} is not a valid name here')
        return v

    def number(self, key: str, default: Any = MISSING, low: float = -math.inf,
               high: float = math.inf, low_open: bool = False, unit: str = '') -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not _is_number(v):
            self.ctx.error(self.sub(key), f'expected a number{unit and " in " + unit}, '
                                          f'got {_describe(v)}')
            return default if default is not MISSING else 0.0
        bad_low = v <= low if low_open else v < low
        if bad_low or v > high:
            lo = '(' if low_open else '['
            self.ctx.error(self.sub(key), f'{v} is out of range: expected a value in '
                                          f'{lo}{low}, {high}]{unit and " " + unit}')
        return float(v)

    def integer(self, key: str, default: Any = MISSING, low: int = 0,
                high: int = 2 ** 31) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, int) or isinstance(v, bool):
            self.ctx.error(self.sub(key), f'expected an integer, got {_describe(v)}')
            return default if default is not MISSING else 0
        if not low <= v <= high:
            self.ctx.error(self.sub(key), f'{v} is out of range: expected {low}..{high}')
        return v

    def boolean(self, key: str, default: Any = MISSING) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, bool):
            self.ctx.error(self.sub(key), f'expected true or false, got {_describe(v)}')
            return default if default is not MISSING else False
        return v

    def _list(self, key: str, default: Any, item_ok: Callable[[Any], bool],
              what: str) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, list):
            self.ctx.error(self.sub(key), f'expected a list of {what}, got {_describe(v)}')
            return ()
        if not v:
            # rcl's parameter parser rejects empty sequences: omit the key instead.
            self.ctx.error(self.sub(key), 'an empty list is not a valid ROS parameter; '
                                          'leave the key out instead')
            return ()
        bad = [i for i, x in enumerate(v) if not item_ok(x)]
        if bad:
            self.ctx.error(f'{self.sub(key)}[{bad[0]}]',
                           f'expected {what}, got {_describe(v[bad[0]])}')
            return ()
        return tuple(v)

    def strings(self, key: str, default: Any = MISSING) -> Any:
        return self._list(key, default, lambda x: isinstance(x, str), 'strings')

    def numbers(self, key: str, default: Any = MISSING) -> Any:
        v = self._list(key, default, _is_number, 'numbers')
        if isinstance(v, tuple) and v and len({type(x) for x in v}) > 1:
            # A ROS parameter array has one type: [1, 2.5] fails to load as parameters.
            self.ctx.error(self.sub(key), 'mixes integers and decimals, which ROS parameter '
                                          'files reject: write every value as a decimal')
        return tuple(float(x) for x in v) if isinstance(v, tuple) else v

    def scalar_map(self, key: str) -> Mapping[str, Any]:
        v = self.raw(key, {})
        if not isinstance(v, dict):
            self.ctx.error(self.sub(key), f'expected a map, got {_describe(v)}')
            return t.frozen_map()
        out = {}
        for k, x in v.items():
            if isinstance(x, (dict, type(None))) or (isinstance(x, list) and not x):
                self.ctx.error(f'{self.sub(key)}.{k}',
                               f'expected a scalar or a non-empty list, got {_describe(x)}')
            else:
                out[str(k)] = x
        return t.frozen_map(out)

    def done(self) -> None:
        for key in self.data:
            if key not in self.seen:
                self.ctx.error(self.sub(str(key)), f'unknown key{did_you_mean(key, self.known)}',
                               damages=False)


def _quoted(names: List[str], limit: int = 6) -> str:
    shown = ', '.join(repr(n) for n in names[:limit])
    return shown + (f' and {len(names) - limit} more' if len(names) > limit else '')


def _named_sections(parent: _Section, key: str, required: bool = True
                    ) -> List[Tuple[str, _Section]]:
    """A collection written as ``names: [...]`` plus one map per name."""
    sec = parent.section(key, required=required)
    ctx = sec.ctx
    if not sec.ok or (not required and not sec.data):
        sec.seen.update(sec.data)
        if not sec.ok:
            ctx.broken.add(key)
        return []
    if 'names' not in sec.data and not ctx.damaged(sec.path):
        ctx.error(sec.sub('names'), 'required key is missing: a list of the sections in order, '
                                    f'such as names: [{", ".join(map(str, sec.data))}]')
    names = sec.strings('names', ())
    if ctx.damaged(sec.path, inside=False) or ctx.damaged(sec.sub('names')):
        ctx.broken.add(key)
    unlisted = [str(k) for k in sec.data if k != 'names' and k not in names]
    # A name listed without a section next to a section not listed, alike: one misspelling,
    # reported once, at the section.
    without = [n for n in names if NAME_RE.match(n) and n not in sec.data]
    typo = {}
    for n in without:
        close = difflib.get_close_matches(n, [k for k in unlisted if k not in typo], n=1)
        if close:
            typo[close[0]] = n
    if not typo and len(without) == len(unlisted) == 1:
        typo[unlisted[0]] = without[0]      # one of each, however unlike: a rename
    # Every name the file mentions, good or bad: a reference to one of them is not "unknown"
    # (the problem with the name itself is reported once, where it is).
    ctx.declared[key] = {str(n) for n in names} | set(unlisted)
    out = []
    seen = set()
    for name in names:
        if not NAME_RE.match(name):
            ctx.error(sec.sub('names'), f'{name!r} is not a valid name: use letters, '
                                        'digits and underscores, starting with a letter')
            continue
        if name in seen:
            ctx.error(sec.sub('names'), f'{name!r} is listed twice')
            continue
        seen.add(name)
        if name not in sec.data:
            if name in typo.values():
                ctx.mark_damaged(sec.sub(name))
            else:
                ctx.error(sec.sub(name), f'{name!r} is listed in names but has no section')
            continue
        out.append((name, sec.section(name)))
    sec.seen.update(sec.data)
    if key not in ctx.broken:   # else the names list is the one problem, reported already
        for k in typo:
            ctx.error(sec.sub(k), f'section {k!r} is not listed in {sec.sub("names")}, which '
                                  f'lists {typo[k]!r} with no section: one of the two is misspelt')
        left_out = [k for k in unlisted if k not in typo]
        if len(left_out) == 1:
            ctx.error(sec.sub(left_out[0]), f'section {left_out[0]!r} is not listed in '
                                            f'{sec.sub("names")}')
        elif left_out:
            ctx.error(sec.sub('names'), f'sections {_quoted(left_out)} are not listed: list '
                                        'every section, in the order wanted')
        for k in left_out:
            ctx.mark_damaged(sec.sub(k))
    return out


def _dataclass_settings(parent: _Section, key: str, cls: type) -> Any:
    """A flat settings section whose keys are the fields of ``cls`` with their defaults,
    checked against what each field's ``setting`` declares."""
    sec = parent.section(key, required=False)
    checks = t.checks_of(cls)
    values = {}
    for f in fields(cls):
        if not sec.has(f.name):
            continue
        default = getattr(cls(), f.name)
        spec = checks.get(f.name, {})
        if isinstance(default, bool):
            values[f.name] = sec.boolean(f.name)
        elif isinstance(default, int):
            values[f.name] = sec.integer(f.name, **spec)
        elif isinstance(default, float):
            values[f.name] = sec.number(f.name, **spec)
        elif isinstance(default, str):
            values[f.name] = sec.string(f.name, **spec)
        else:
            values[f.name] = sec.scalar_map(f.name)
    sec.done()
    return cls(**{k: v for k, v in values.items() if v is not MISSING})


def _settled(obj: Any) -> Any:
    """``obj`` with each value that could not be read (still MISSING) emptied: '', 0 or (), so
    that the checks after reading can look at the rest of the file."""
    empty = {str: '', float: 0.0, int: 0}
    changes = {f.name: empty.get(f.type, ()) for f in fields(obj)
               if getattr(obj, f.name) is MISSING}
    return replace(obj, **changes) if changes else obj


def _read_scale(name: str, sec: _Section) -> t.Scale:
    scale = t.Scale(
        name=name,
        role=sec.string('role', choices=(t.MASTER, t.REMOTE)),
        kind=sec.string('kind', choices=(t.ROBOT, t.SERVER)),
        capacity_cpu=sec.number('capacity_cpu', low=0, unit='reference-core percent'),
        cores=sec.integer('cores', 1, low=1, high=4096),
        clock_ghz=sec.number('clock_ghz', 1.0, low=0, high=100, low_open=True, unit='GHz'),
        gain=sec.number('gain', 1.0, low=0, high=1e6, low_open=True),
        host=sec.string('host', 'localhost'),
        port=sec.integer('port', 0, low=0, high=65535),
    )
    sec.done()
    return _settled(scale)


def _read_link(name: str, sec: _Section) -> t.Link:
    ends = sec.strings('ends')
    if isinstance(ends, tuple) and len(ends) != 2 and sec.read('ends'):
        sec.ctx.error(sec.sub('ends'), f'expected exactly two scale names, got {len(ends)}')
    link = t.Link(
        name=name,
        ends=tuple(ends[:2]) if isinstance(ends, tuple) and len(ends) >= 2 else ('', ''),
        bandwidth_kbps=sec.number('bandwidth_kbps', low=0, low_open=True, unit='kbit/s'),
        medium=sec.string('medium', t.WIRELESS, choices=(t.WIRED, t.WIRELESS)),
    )
    sec.done()
    return _settled(link)


def _read_launch(sec: _Section) -> t.Launch:
    launch = t.Launch(
        package=sec.string('package', ''),
        executable=sec.string('executable', ''),
        command=sec.strings('command', ()),
        arguments=sec.strings('arguments', ()),
        env=sec.scalar_map('env'),
        parameters=sec.scalar_map('parameters'),
        ros_name=sec.string('ros_name', ''),
    )
    # Whether the forms are mixed means something only if each was read as written.
    forms_read = sec.read('package', 'executable', 'command')
    if forms_read and launch.command and (launch.package or launch.executable):
        sec.ctx.error(sec.path, 'give either command or package and executable, not both')
    elif forms_read and bool(launch.package) != bool(launch.executable):
        sec.ctx.error(sec.path, 'package and executable go together')
    for k, v in launch.env.items():
        if not isinstance(v, str):
            sec.ctx.error(f'{sec.sub("env")}.{k}', f'expected a string, got {_describe(v)}')
    sec.done()
    return launch


def _read_settings(sec: _Section) -> t.Settings:
    forms = t.REGRESSION_FORMS
    s = t.Settings(
        parameter=sec.string('parameter', 'cpu'),
        values=sec.numbers('values', ()),
        cpu=sec.numbers('cpu'),
        performance=sec.numbers('performance'),
        form=sec.string('form', 'linear', choices=forms),
        parameter_form=sec.string('parameter_form', 'linear', choices=forms),
        frequency_hz=sec.numbers('frequency_hz', ()),
    )
    s = _settled(s)
    n = len(s.cpu)
    off = [k for k in ('values', 'performance', 'frequency_hz')
           if getattr(s, k) and n and len(getattr(s, k)) != n]
    if len(off) > 1 and len({len(getattr(s, k)) for k in off}) == 1:
        # The others agree with each other: cpu is the odd one out, one problem.
        sec.ctx.error(sec.sub('cpu'), f'{n} samples, but {" and ".join(off)} have '
                                      f'{len(getattr(s, off[0]))}: one value per sample in each')
    else:
        for key in off:
            sec.ctx.error(sec.sub(key), f'expected {n} values (one per cpu sample), '
                                        f'got {len(getattr(s, key))}')
    if any(c <= 0 for c in s.cpu):
        # Every regression form needs it (log most of all): one line, at the samples.
        sec.ctx.error(sec.sub('cpu'), 'every CPU sample must be > 0')
    sec.done()
    return s


def _read_node(name: str, sec: _Section) -> t.Node:
    launch = _read_launch(sec.section('launch', required=False))
    settings = None
    if sec.has('settings'):
        settings = _read_settings(sec.section('settings'))
    cpu_default = settings.cpu[len(settings.cpu) // 2] if settings and settings.cpu else MISSING
    perf_default = (settings.performance[len(settings.performance) // 2]
                    if settings and settings.performance else 0.0)
    migratable = sec.boolean('migratable', None) if sec.has('migratable') else None
    critical = sec.boolean('critical', None) if sec.has('critical') else None
    standby = (sec.strings('standby', ()) or False) if isinstance(sec.data.get('standby'), list) \
        else sec.boolean('standby', False)
    node = t.Node(
        name=name,
        launch=launch,
        cpu=sec.number('cpu', cpu_default, low=0, unit='reference-core percent'),
        performance=sec.number('performance', perf_default),
        weight=sec.number('weight', 1.0, low=0),
        residence=sec.strings('residence', ()),
        coresidence=sec.strings('coresidence', ()),
        migratable=migratable,
        critical=critical,
        managed=sec.boolean('managed', True),
        move_order=sec.string('move_order', t.START_BEFORE_STOP,
                              choices=(t.START_BEFORE_STOP, t.STOP_BEFORE_START)),
        lifecycle=sec.boolean('lifecycle', False),
        standby=standby is not False,
        standby_on=standby if isinstance(standby, tuple) else (),
        settings=settings,
        nice=sec.integer('nice', 0, low=0, high=19),
    )
    sec.done()
    return _settled(node)


def _read_connection(name: str, sec: _Section) -> t.Connection:
    c = t.Connection(
        name=name,
        topic=sec.string('topic', pattern=TOPIC_RE),
        publisher=sec.string('publisher'),
        subscriber=sec.string('subscriber'),
        bandwidth_kbps=sec.number('bandwidth_kbps', 0.0, low=0, unit='kbit/s'),
        freq_min_hz=sec.number('freq_min_hz', None, low=0, high=1e6, unit='Hz'),
        freq_opt_hz=sec.number('freq_opt_hz', None, low=0, high=1e6, unit='Hz'),
        tolerance_s=sec.number('tolerance_s', None, low=0, high=1e6, unit='s'),
        msg_type=sec.string('msg_type', ''),
    )
    c = _settled(c)
    if (c.freq_min_hz is None) != (c.tolerance_s is None) \
            and sec.read('freq_min_hz', 'tolerance_s'):
        sec.ctx.error(sec.path, 'freq_min_hz and tolerance_s go together: a monitored '
                                'connection needs both')
    if c.freq_min_hz is not None and c.freq_opt_hz is not None \
            and c.freq_opt_hz < c.freq_min_hz and sec.read('freq_min_hz', 'freq_opt_hz'):
        sec.ctx.error(sec.sub('freq_opt_hz'), f'{c.freq_opt_hz} is below freq_min_hz '
                                              f'{c.freq_min_hz}')
    if c.msg_type and not re.match(r'^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$', c.msg_type):
        sec.ctx.error(sec.sub('msg_type'), f'expected package/msg/Type, got {c.msg_type!r}'
                                           f'{_msg_type_hint(c.msg_type)}')
    sec.done()
    return c


def _msg_type_hint(text: str) -> str:
    """What a malformed msg_type was probably meant to be: ROS 1's pkg/Type, a service or
    action type (a topic carries messages), or a C++/Python spelling."""
    parts = re.split(r'/|::|\.', text.strip('/'))
    if len(parts) == 2 and all(re.match(r'^[A-Za-z0-9_]+$', x) for x in parts):
        return f' (did you mean {parts[0]}/msg/{parts[1]}?)'
    if len(parts) == 3 and all(re.match(r'^[A-Za-z0-9_]+$', x) for x in parts):
        if parts[1] in ('srv', 'action'):
            return f' (a topic carries messages: {parts[1]} types have no topic of their own)'
        return f' (did you mean {parts[0]}/msg/{parts[2]}?)'
    return ''


def _unknown(ctx: _Context, path: str, kind: str, name: Any, known) -> None:
    """A reference to a name the file never declares. A name it declares badly (invalid, listed
    without a section, a section not listed) was reported where it is declared: not again."""
    collection = f'{kind}s'
    if collection in ctx.broken or str(name) in ctx.declared.get(collection, ()):
        return
    ctx.error(path, f'unknown {kind} {name!r}{did_you_mean(name, known)}')


def _all_read(ctx: _Context, collection: str, *keys: str) -> bool:
    """Whether every section the collection declares was read, with these keys of each."""
    names = ctx.declared.get(collection, ())
    return collection not in ctx.broken \
        and not any(ctx.damaged(p, inside=False) for p in (collection, f'{collection}.names')) \
        and not any(ctx.damaged(f'{collection}.{n}', inside=False) for n in names) \
        and not any(ctx.damaged(f'{collection}.{n}.{k}') for n in names for k in keys)


LOOPBACK_HOSTS = ('localhost', '127.0.0.1', '::1', '', '0.0.0.0')


def _port_check(ctx: _Context, d: t.Deployment) -> None:
    """Each scale's warden and probe server take one port on its host: two scales of one host
    must not share it."""
    if not _all_read(ctx, 'scales', 'port', 'host') \
            or ctx.damaged('monitoring.bandwidth_probe_port'):
        return
    taken: Dict[Tuple[str, int], str] = {}
    for s in d.scales:
        port = d.scale_port(s.name)
        where = f'scales.{s.name}.port'
        if port > 65535:
            ctx.error(where, f'no port of its own, and monitoring.bandwidth_probe_port + 1 + '
                             f'{d.scale_names.index(s.name)} = {port} is past 65535: give it a '
                             'port or lower the base')
            continue
        host = 'localhost' if s.host.lower() in LOOPBACK_HOSTS else s.host.lower()
        other = taken.setdefault((host, port), s.name)
        if other != s.name:
            ctx.error(where, f'port {port} on host {s.host!r} is also the port of scale '
                             f'{other!r}: the warden and probe server of each scale need their '
                             'own (set port, or leave it out on both to derive one per scale)')


def _cross_check(ctx: _Context, d: t.Deployment) -> None:
    scales = d.scale_names
    nodes = d.node_names
    masters = [s.name for s in d.scales if s.is_master]
    if len(masters) != 1 and _all_read(ctx, 'scales', 'role'):
        ctx.error('scales', f'expected exactly one scale with role master, got {len(masters)}'
                            + (f' ({", ".join(masters)})' if masters else ''))
    _port_check(ctx, d)
    for link in d.links:
        for end in link.ends:
            if end and end not in scales:
                _unknown(ctx, f'links.{link.name}.ends', 'scale', end, scales)
        if link.ends[0] and link.ends[0] == link.ends[1]:
            ctx.error(f'links.{link.name}.ends', 'a link joins two different scales')
    pairs = {}
    for link in d.links:
        key = frozenset(link.ends)
        if key in pairs and all(link.ends):
            ctx.error(f'links.{link.name}', f'scales {" and ".join(link.ends)} are already '
                                            f'joined by link {pairs[key]!r}')
        pairs.setdefault(key, link.name)
    for n in d.nodes:
        # What a node's own fields contradict is said whatever else is wrong in the file.
        lifecycle_read = not ctx.damaged(f'nodes.{n.name}.lifecycle')
        if n.standby and not n.lifecycle and lifecycle_read:
            ctx.error(f'nodes.{n.name}.standby', 'a standby copy is an inactive lifecycle node: '
                                                 'set lifecycle: true (and make the node a '
                                                 'lifecycle node, docs/lifecycle.md)')
        if n.lifecycle and not n.managed:
            ctx.error(f'nodes.{n.name}.lifecycle', 'only a node the agents start (managed) is '
                                                   'driven through its lifecycle')
        for s in n.residence:
            if s not in scales:
                _unknown(ctx, f'nodes.{n.name}.residence', 'scale', s, scales)
        for other in n.coresidence:
            if other == n.name:
                ctx.error(f'nodes.{n.name}.coresidence', 'a node is always on its own scale')
            elif other not in nodes:
                _unknown(ctx, f'nodes.{n.name}.coresidence', 'node', other, nodes)
    for c in d.connections:
        for role in ('publisher', 'subscriber'):
            ref = getattr(c, role)
            if ref and ref not in nodes:
                _unknown(ctx, f'connections.{c.name}.{role}', 'node', ref, nodes)
        if c.publisher and c.publisher == c.subscriber:
            ctx.error(f'connections.{c.name}', 'publisher and subscriber are the same node')
    layout = d.decider.layout
    for node, scale in layout.items():
        if node not in nodes:
            _unknown(ctx, f'decider.layout.{node}', 'node', node, nodes)
        if scale not in scales:
            _unknown(ctx, f'decider.layout.{node}', 'scale', scale, scales)
    if d.decider.initial_layout == 'explicit' and not layout:
        ctx.error('decider.layout', 'initial_layout is explicit but no layout is given')
    beat, takeover = d.decider.beat_s, d.decider.takeover_s
    if takeover < 3 * beat and not any(ctx.damaged(f'decider.{k}')
                                       for k in ('beat_s', 'takeover_s')):
        ctx.error('decider.takeover_s', f'{takeover:g} s is under three beats ({beat:g} s '
                                        'each): one late beat would pass for a dead leader')


def _known_references(d: t.Deployment) -> t.Deployment:
    """``d`` without the residence and coresidence entries that name no scale or node (the cross
    checks reported them): the derived sets are computed on the rest."""
    scales, names = set(d.scale_names), set(d.node_names)
    return replace(d, nodes=tuple(
        replace(n, residence=tuple(s for s in n.residence if s in scales),
                coresidence=tuple(o for o in n.coresidence if o in names and o != n.name))
        for n in d.nodes))


# A tolerance-0 connection pins both ends; how to pin only one of them.
PIN_ONE_END = ('to pin only the other end, mark that node critical: true and give the '
               'connection a tolerance_s above 0')


def _derived_checks(ctx: _Context, d: t.Deployment) -> None:
    # Every rule below is relative to the master and to every scale; a node whose input could
    # not be read would pass for a data provider. Missing parts make for looser rules (fewer
    # constraints, no false alarm) except these, whose problems are reported already.
    if sum(s.is_master for s in d.scales) != 1 or not _all_read(ctx, 'scales', 'role') \
            or 'connections' not in ctx.broken \
            and not _all_read(ctx, 'connections', 'subscriber'):
        return
    d = _known_references(d)
    critical = set(d.critical_nodes)
    master = d.master.name
    reported_groups = set()
    for n in d.nodes:
        why = d.why_critical(n.name)
        zero = d.zero_tolerance_connections(n.name)
        # Values replaced by a default when they could not be read: the checks that depend on
        # them would only repeat that problem.
        unread = any(ctx.damaged(f'nodes.{n.name}.{k}') for k in ('launch', 'lifecycle'))
        if n.name in critical and n.migratable is True:
            ctx.error(f'nodes.{n.name}.migratable',
                      f'declared migratable, but the node is critical ({why}), pinned to the '
                      f'master scale {master!r}' + (f'; {PIN_ONE_END}' if zero else ''))
        if n.critical is False and zero:
            ctx.error(f'nodes.{n.name}.critical',
                      f'declared critical: false, but {why}: a connection that tolerates no '
                      f'outage never crosses a link, so both its ends stay on the master; '
                      f'{PIN_ONE_END}')
        if n.name in critical and n.residence and master not in n.residence:
            ctx.error(f'nodes.{n.name}.residence',
                      f'critical node must run on the master scale {master!r} ({why}), '
                      f'but residence allows only {", ".join(n.residence)}')
        group = d.coresidence_group(n.name)
        allowed = d.allowed_scales(n.name)
        if not allowed:
            # One line per group, at its first node that declares a coresidence.
            if group not in reported_groups:
                reported_groups.add(group)
                at = next((m for m in group if d.node(m).coresidence), n.name)
                each = '; '.join(f'{m} {d.why_own_scales(m)}' for m in group
                                 if d.why_own_scales(m))
                ctx.error(f'nodes.{at}.coresidence',
                          f'no scale satisfies every node that must share a scale '
                          f'({", ".join(group)}): {each}')
            continue        # nothing below means anything for a node with nowhere to run
        if n.standby and n.name not in d.migratable_nodes and not unread:
            ctx.error(f'nodes.{n.name}.standby', 'a standby copy is kept only for a migratable '
                                                 f'node, and this node cannot migrate: '
                                                 f'{d.why_not_migratable(n.name)}')
        for i, scale in enumerate(n.standby_on):
            if scale not in d.scale_names:
                ctx.error(f'nodes.{n.name}.standby[{i}]',
                          f'unknown scale {scale!r}{did_you_mean(scale, d.scale_names)}')
            elif scale not in allowed:
                ctx.error(f'nodes.{n.name}.standby[{i}]',
                          f'{scale!r} is not a scale the node may run on (allowed: '
                          f'{", ".join(allowed)})')
        if n.migratable is True and n.name not in d.migratable_nodes \
                and n.name not in critical and not unread:
            ctx.error(f'nodes.{n.name}.migratable',
                      f'declared migratable, but {d.why_not_migratable(n.name)}')
    for node, scale in d.decider.layout.items():
        if node in d.node_names and scale in d.scale_names and d.allowed_scales(node) \
                and scale not in d.allowed_scales(node):
            ctx.error(f'decider.layout.{node}', f'node {node!r} may not run on {scale!r} '
                                                f'(allowed: {", ".join(d.allowed_scales(node))})')


def _unwrap_ros(ctx: _Context, data: Any) -> Any:
    """Accept the ROS parameters-file wrapper ``/**: {ros__parameters: {...}}``."""
    if not isinstance(data, dict) or len(data) != 1:
        ctx.error('', 'expected a ROS 2 parameters file: one top-level key such as /** '
                      'holding ros__parameters')
        return None
    (key, inner), = data.items()
    if not isinstance(inner, dict) or set(inner) != {'ros__parameters'}:
        ctx.error(str(key), 'expected exactly one key, ros__parameters')
        return None
    return inner['ros__parameters']


def load_mapping(data: Any, source: str = '<mapping>', wrapped: bool = True) -> t.Deployment:
    """Validate a parsed deployment; ``wrapped`` means it still has the ROS file wrapper."""
    ctx = _Context(source)
    if wrapped:
        data = _unwrap_ros(ctx, data)
        if data is None:
            raise DeploymentError(ctx.problems)
    root = _Section(ctx, '', data)
    if not root.ok:
        raise DeploymentError(ctx.problems)
    meta = root.section('deployment', required=False)
    name = meta.string('name', 'deployment')
    description = meta.string('description', '')
    meta.done()
    scales = tuple(_read_scale(n, s) for n, s in _named_sections(root, 'scales'))
    links = tuple(_read_link(n, s) for n, s in _named_sections(root, 'links', required=False))
    nodes = tuple(_read_node(n, s) for n, s in _named_sections(root, 'nodes'))
    connections = tuple(_read_connection(n, s)
                        for n, s in _named_sections(root, 'connections', required=False))
    decider = _dataclass_settings(root, 'decider', t.DeciderSettings)
    monitoring = _dataclass_settings(root, 'monitoring', t.MonitorSettings)
    agent = _dataclass_settings(root, 'agent', t.AgentSettings)
    security = _dataclass_settings(root, 'security', t.SecuritySettings)
    if security.key_file and not os.path.isabs(os.path.expanduser(security.key_file)):
        # The decider, each agent and validate run in different folders: one meaning only.
        ctx.error('security.key_file', f'expected an absolute path, got {security.key_file!r}')
    root.done()
    # What could not be read holds an empty value: the checks below still look at the rest.
    deployment = t.Deployment(name=name, source=source, scales=scales, links=links,
                              nodes=nodes, connections=connections, decider=decider,
                              monitoring=monitoring, agent=agent, description=description,
                              security=security)
    _cross_check(ctx, deployment)
    _derived_checks(ctx, deployment)
    if ctx.problems:
        raise DeploymentError(ctx.problems)
    return deployment


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses duplicate keys instead of keeping the last one."""


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False):
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f'duplicate key {key!r} (first at line {seen[key] + 1})',
                key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                                 _construct_mapping)


def load_deployment(path: str) -> t.Deployment:
    """Load and validate a deployment file; raises DeploymentError naming every problem."""
    source = str(path)
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.load(f, Loader=_UniqueKeyLoader)
    except OSError as e:
        raise DeploymentError([Problem(source, '', f'cannot read: {e.strerror}')]) from e
    except yaml.YAMLError as e:
        mark = getattr(e, 'problem_mark', None)
        where = f'line {mark.line + 1}, column {mark.column + 1}' if mark else ''
        what = getattr(e, 'problem', None) or str(e)
        raise DeploymentError([Problem(source, where, f'invalid YAML: {what}')]) from e
    return load_mapping(data, source)


def nest_parameters(flat: Mapping[str, Any]) -> Dict[str, Any]:
    """Turn ROS parameter names with dots (``scales.robot.gain``) back into nested maps."""
    root: Dict[str, Any] = {}
    for name in sorted(flat):
        value = flat[name]
        if isinstance(value, (list, tuple)):
            value = list(value)
        parts = name.split('.')
        here = root
        for part in parts[:-1]:
            here = here.setdefault(part, {})
            if not isinstance(here, dict):
                break
        else:
            here[parts[-1]] = value
    return root


def load_from_parameters(flat: Mapping[str, Any], source: str = '<ROS parameters>'
                         ) -> t.Deployment:
    """Rebuild a deployment from a node's parameters (loaded with --params-file)."""
    sections = ('deployment', 'scales', 'links', 'nodes', 'connections', 'decider',
                'monitoring', 'agent', 'security')
    picked = {k: v for k, v in flat.items() if k.split('.', 1)[0] in sections}
    return load_mapping(nest_parameters(picked), source, wrapped=False)
