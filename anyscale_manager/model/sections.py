"""The readers of a deployment file's sections: one per kind, each returning its dataclass.

ROS parameters have no lists of maps, so every collection is a map of named sections plus a
``names`` list that fixes the order. Each reader checks what its own section says (types,
ranges, keys that go together); how sections fit together is model/checks.py's business.
"""

import difflib
import os
import re
from dataclasses import fields, replace
from typing import Any, Dict, List, Mapping, Set, Tuple, Type, TypeVar

from . import types as t
from .reader import MISSING, Context, Section, describe

NAME_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
TOPIC_RE = re.compile(r'^/?[A-Za-z~{][A-Za-z0-9_/{}~]*$')
MSG_TYPE_RE = re.compile(r'^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$')

D = TypeVar('D', bound=t.Dataclass)


def _quoted(names: List[str], limit: int = 6) -> str:
    shown = ', '.join(repr(n) for n in names[:limit])
    return shown + (f' and {len(names) - limit} more' if len(names) > limit else '')


def _names(sec: Section) -> Tuple[str, ...]:
    """The ``names`` list of a collection; an entry that is not a string is reported and left
    out, so that the sections of the others are still read and checked."""
    names = sec.strings('names', ())
    listed = sec.data.get('names')
    if names or not isinstance(listed, list):
        return tuple(names)
    for i, name in enumerate(listed):
        if not isinstance(name, str):
            sec.ctx.error(f'{sec.sub("names")}[{i}]', f'expected strings, got {describe(name)}')
    return tuple(name for name in listed if isinstance(name, str))


def named_sections(parent: Section, key: str, required: bool = True
                   ) -> List[Tuple[str, Section]]:
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
    names = _names(sec)
    if ctx.damaged(sec.path, inside=False) or ctx.damaged(sec.sub('names')):
        ctx.broken.add(key)
    unlisted = [str(k) for k in sec.data if k != 'names' and k not in names]
    # A name listed without a section next to a section not listed, alike: one misspelling,
    # reported once, at the section.
    without = [n for n in names if NAME_RE.match(n) and n not in sec.data]
    typo: Dict[str, str] = {}
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
    seen: Set[str] = set()
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


def settings_values(sec: Section, cls: Type[t.Dataclass]) -> Dict[str, Any]:
    """The values a flat settings section gives the fields of ``cls``, each read as its
    ``types.setting`` declares it: the type of its default, its range or choices and unit.
    A key the section leaves out is left out."""
    checks = t.checks_of(cls)
    defaults = cls()
    values = {}
    for f in fields(cls):
        if not sec.has(f.name):
            continue
        default = getattr(defaults, f.name)
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
    return {k: v for k, v in values.items() if v is not MISSING}


def read_settings(parent: Section, key: str, cls: Type[D]) -> D:
    """A flat settings section whose keys are the fields of ``cls``, with their defaults."""
    sec = parent.section(key, required=False)
    values = settings_values(sec, cls)
    sec.done()
    return cls(**values)


def settings_with(settings: D, changes: Mapping[str, Any], section: str = 'decider') -> D:
    """``settings`` with ``changes`` to its live settings, each checked as the same key in a
    deployment file is; ValueError names the first bad one."""
    live = {f.name for f in fields(settings) if f.metadata.get('live')}
    for name in changes:
        if name not in live:
            raise ValueError(f'{section}.{name}: cannot be changed while the decider runs')
    ctx = Context('')
    values = settings_values(Section(ctx, section, dict(changes)), type(settings))
    if ctx.problems:
        raise ValueError(f'{ctx.problems[0].path}: {ctx.problems[0].message}')
    return replace(settings, **values)


def _settled(obj: D) -> D:
    """``obj`` with each value that could not be read (still MISSING) emptied: '', 0 or (), so
    that the checks after reading can look at the rest of the file."""
    empty: Dict[Any, Any] = {str: '', float: 0.0, int: 0}
    changes = {f.name: empty.get(f.type, ()) for f in fields(obj)
               if getattr(obj, f.name) is MISSING}
    return replace(obj, **changes) if changes else obj


def read_scale(name: str, sec: Section) -> t.Scale:
    scale = t.Scale(
        name=name,
        role=sec.string('role', choices=(t.MASTER, t.REMOTE)),
        kind=sec.string('kind', choices=(t.ROBOT, t.SERVER)),
        capacity_cpu=sec.number('capacity_cpu', low=0, unit='reference-core percent'),
        cores=sec.integer('cores', 1, low=1, high=4096),
        clock_ghz=sec.number('clock_ghz', 1.0, low=0, high=100, low_open=True, unit='GHz'),
        gain=sec.number('gain', None, low=0, high=1e6, low_open=True),
        host=sec.string('host', 'localhost'),
        port=sec.integer('port', 0, low=0, high=65535),
        shared=sec.boolean('shared', False),
        memory_mb=sec.number('memory_mb', 0.0, low=0, high=1e9, unit='MiB'),
    )
    sec.done()
    return _settled(scale)


def read_link(name: str, sec: Section) -> t.Link:
    ends = sec.strings('ends')
    if isinstance(ends, tuple) and len(ends) != 2 and sec.read('ends'):
        sec.ctx.error(sec.sub('ends'), f'expected exactly two scale names, got {len(ends)}')
    link = t.Link(
        name=name,
        ends=(ends[0], ends[1]) if isinstance(ends, tuple) and len(ends) >= 2 else ('', ''),
        bandwidth_kbps=sec.number('bandwidth_kbps', low=0, low_open=True, unit='kbit/s'),
        medium=sec.string('medium', t.WIRELESS, choices=(t.WIRED, t.WIRELESS)),
    )
    sec.done()
    return _settled(link)


def read_launch(sec: Section) -> t.Launch:
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
            sec.ctx.error(f'{sec.sub("env")}.{k}', f'expected a string, got {describe(v)}')
    sec.done()
    return launch


def read_profile(sec: Section) -> t.Settings:
    """A node's ``settings``: its profiling samples."""
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


def read_node(name: str, sec: Section) -> t.Node:
    launch = read_launch(sec.section('launch', required=False))
    settings = None
    if sec.has('settings'):
        settings = read_profile(sec.section('settings'))
    cpu_default = settings.cpu[len(settings.cpu) // 2] if settings and settings.cpu else MISSING
    perf_default = (settings.performance[len(settings.performance) // 2]
                    if settings and settings.performance else 0.0)
    migratable = sec.boolean('migratable', None) if sec.has('migratable') else None
    critical = sec.boolean('critical', None) if sec.has('critical') else None
    standby = (sec.strings('standby', ()) or False) if isinstance(sec.data.get('standby'), list) \
        else sec.boolean('standby', False)
    state = read_state(sec.section('state')) if sec.has('state') else None
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
        state=state,
        memory_mb=sec.number('memory_mb', 0.0, low=0, high=1e9, unit='MiB'),
    )
    sec.done()
    return _settled(node)


def read_state(sec: Section) -> t.StateSpec:
    """A node's ``state``: the output that holds it and the input that restores it."""
    state = t.StateSpec(topic=sec.string('topic', pattern=TOPIC_RE),
                        restore=sec.string('restore', pattern=TOPIC_RE),
                        msg_type=sec.string('msg_type', ''))
    if state.msg_type and not MSG_TYPE_RE.match(state.msg_type):
        sec.ctx.error(sec.sub('msg_type'), f'expected package/msg/Type, got {state.msg_type!r}'
                                           f'{_msg_type_hint(state.msg_type)}')
    if state.topic and state.topic == state.restore and sec.read('topic', 'restore'):
        sec.ctx.error(sec.sub('restore'), f'the node publishes its state on {state.topic!r}: '
                                          'it restores from another topic (AMCL: state '
                                          '/amcl_pose, restore /initialpose)')
    sec.done()
    return _settled(state)


def read_connection(name: str, sec: Section) -> t.Connection:
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
    if c.msg_type and not MSG_TYPE_RE.match(c.msg_type):
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


def read_deployment(root: Section) -> t.Deployment:
    """The whole file, section by section. What could not be read holds an empty value, so
    that the whole-deployment checks still look at the rest."""
    ctx = root.ctx
    meta = root.section('deployment', required=False)
    name = meta.string('name', 'deployment')
    description = meta.string('description', '')
    priority = meta.integer('priority', 0, low=-1000, high=1000)
    meta.done()
    scales = tuple(read_scale(n, s) for n, s in named_sections(root, 'scales'))
    links = tuple(read_link(n, s) for n, s in named_sections(root, 'links', required=False))
    nodes = tuple(read_node(n, s) for n, s in named_sections(root, 'nodes'))
    connections = tuple(read_connection(n, s)
                        for n, s in named_sections(root, 'connections', required=False))
    decider = read_settings(root, 'decider', t.DeciderSettings)
    monitoring = read_settings(root, 'monitoring', t.MonitorSettings)
    agent = read_settings(root, 'agent', t.AgentSettings)
    security = read_settings(root, 'security', t.SecuritySettings)
    discovery = read_settings(root, 'discovery', t.DiscoverySettings)
    if discovery.mode == t.SERVER and len(scales) > 16:
        ctx.error('discovery.mode', f'a deployment of {len(scales)} scales cannot use '
                                    'discovery servers: 16 at most (each scale one port)')
    if security.key_file and not os.path.isabs(os.path.expanduser(security.key_file)):
        # The decider, each agent and validate run in different folders: one meaning only.
        ctx.error('security.key_file', f'expected an absolute path, got {security.key_file!r}')
    root.done()
    return t.Deployment(name=name, source=ctx.source, scales=scales, links=links, nodes=nodes,
                        connections=connections, decider=decider, monitoring=monitoring,
                        agent=agent, description=description, security=security,
                        priority=priority, discovery=discovery)
