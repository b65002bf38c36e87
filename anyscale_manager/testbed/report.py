"""What a person sees of a test-bed run: the live status table, the timeline figure, the log.

Pure functions of a ``Record`` (and matplotlib with the Agg backend for the figure).
"""

import json
import math
import os
import re
import textwrap
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from .. import protocol as p
from ..model.types import Connection, Deployment
from ..runtime.delta import rate_below
from ..view.status import bandwidth_stale_after_s, bandwidth_text, rtt_text, stale_mark
from .record import MIGRATION_KINDS, Record

# The paper's Fig. 5 colours: where AMCL and AR run.
CATEGORIES = {
    ('laptop', 'robot'): ('only AMCL on the laptop', '#2ca02c'),      # green
    ('robot', 'robot'): ('AMCL and AR on the robot', '#d62728'),       # red
    ('laptop', 'laptop'): ('AMCL and AR on the laptop', '#1f77b4'),    # blue
    ('robot', 'laptop'): ('only AR on the laptop', '#e6c300'),         # yellow
}
UNKNOWN = ('moving or not running', '#bbbbbb')
# With three scales or more: a colour per scale AMCL runs on, lighter when AR runs elsewhere.
SCALE_COLOURS = ('#d62728', '#1f77b4', '#2ca02c', '#9467bd', '#8c564b', '#e377c2')
LEVELS = {p.OK: 'OK', p.WARN: 'BELOW', p.ERROR: 'VIOLATED', p.STALE: 'STALE'}


def link_up(record: Record, a: str, b: str, t: float) -> bool:
    """Whether scales ``a`` and ``b`` hear each other at t: the same scale, or the link that
    joins them is up as the harness set it (nothing is forwarded through a third scale)."""
    if a == b:
        return True
    link = record.deployment.link_between(a, b)
    return link is not None and link_at(record, t, link.name)[0]


def consumer_scales(record: Record, node: str, t: float) -> Tuple[str, ...]:
    """Where the subscribers of the node's outputs are at t: where their agents report them
    serving, else the one scale they may run on, else where the layout put them; the master
    when none is known (or the node has no outputs)."""
    d = record.deployment
    out: List[str] = []
    for c in d.connections:
        if c.publisher != node:
            continue
        scales = record.where(c.subscriber, t)
        if not scales:
            allowed = d.allowed_scales(c.subscriber)
            layout = record.layout_at(t)
            placed = layout.assignments.get(c.subscriber) if layout is not None else None
            scales = allowed if len(allowed) == 1 else ((placed,) if placed else ())
        out.extend(s for s in scales if s not in out)
    return tuple(out) or (d.master.name,)


def serving(record: Record, node: str, t: float) -> Tuple[Tuple[str, ...], Tuple[str, ...]]:
    """(the scales whose copy of ``node`` its consumers hear at t, the scales whose copy is
    active but cut off from every consumer). A copy counts where its agent reports it running
    and ready; it is heard where a link that is up joins its scale to a consumer's."""
    consumers = consumer_scales(record, node, t)
    heard: List[str] = []
    cut: List[str] = []
    for scale in record.deployment.scale_names:
        if node in record.running_on(scale, t, ready_only=True):
            joined = any(link_up(record, scale, c, t) for c in consumers)
            (heard if joined else cut).append(scale)
    return tuple(heard), tuple(cut)


def location(record: Record, node: str, t: float) -> str:
    """Where the node serves at t: the remote scale whose copy its consumers hear, else the
    master if they hear its copy there, else '' (moving, or not running)."""
    heard, _ = serving(record, node, t)
    master = record.deployment.master.name
    remote = [s for s in heard if s != master]
    if remote:
        return remote[0]
    return master if master in heard else ''


def with_own_reports(record: Record, views: Mapping[str, Record]) -> Record:
    """The record with each scale's agent reports as that scale's own observer heard them,
    where it heard any: behind a cut link only the scale's own observer still hears its agent
    (how long a cut-off copy stays active)."""
    states = dict(record.agent_states)
    for scale, view in views.items():
        if view is not record and view.agent_states.get(scale):
            states[scale] = view.agent_states[scale]
    return replace(record, agent_states=states)


def category(record: Record, t: float, pair: Tuple[str, str] = ('amcl', 'ar')
             ) -> Tuple[str, str]:
    """(label, colour) of where the pair runs: the paper's Fig. 5 categories with two scales;
    with more, each pair of scales its own label and colour."""
    key = (location(record, pair[0], t), location(record, pair[1], t))
    names = record.deployment.scale_names
    if len(names) == 2:
        return CATEGORIES.get(key, UNKNOWN)
    if '' in key:
        return UNKNOWN
    base = SCALE_COLOURS[names.index(key[0]) % len(SCALE_COLOURS)]
    colour = base if key[0] == key[1] else _lighter(base, 0.25 + 0.2 * names.index(key[1]))
    return f'{pair[0].upper()} on {key[0]}, {pair[1].upper()} on {key[1]}', colour


def _lighter(colour: str, amount: float) -> str:
    rgb = [int(colour[i:i + 2], 16) for i in (1, 3, 5)]
    return '#' + ''.join(f'{int(c + (255 - c) * min(amount, 0.85)):02x}' for c in rgb)


def link_at(record: Record, t: float, link: Optional[str] = None) -> Tuple[bool, float]:
    """(up, rate) the harness had set ``link`` (default: the only one) to at time t."""
    if link is None:
        link = next(iter(record.link_truth), '')
    up, rate = True, math.nan
    for when, u, r in record.link_truth.get(link, []):
        if when > t:
            break
        up, rate = u, r
    return up, rate


# --- the live table ---------------------------------------------------------------------------

# A line of the table longer than the screen is wrapped at a word, its rest indented this much
# more than the line; an event's reason takes at most EVENT_LINES lines.
WRAP_INDENT = 4
EVENT_LINES = 3


def wrap_lines(text: str, width: int, indent: int = WRAP_INDENT) -> str:
    """Each line of ``text`` longer than ``width`` wrapped at word boundaries, the rest of it
    indented ``indent`` more than the line itself (a word longer than a line is split)."""
    out: List[str] = []
    for line in text.split('\n'):
        if len(line) <= width:
            out.append(line)
            continue
        lead = line[:len(line) - len(line.lstrip(' '))]
        out.extend(textwrap.wrap(line.strip(), width=max(8, width), initial_indent=lead,
                                 subsequent_indent=lead + ' ' * indent,
                                 break_on_hyphens=False) or [line[:width]])
    return '\n'.join(out)


def status_table(record: Record, now: float, t0: float, mode: str, width: int = 99) -> str:
    """The demo's live view at ``now``, its lines wrapped to ``width`` columns."""
    d: Deployment = record.deployment
    lines = [f't = {now - t0:6.1f} s   [{mode}]']
    for link in d.links:
        lines.extend(_link_lines(record, link.name, now, mode))
    lines.append('')
    return wrap_lines(_status_rest(record, now, lines, width), width)


def loss_window_s(deployment: Deployment) -> float:
    """How far back the beats a link monitor's loss counts reach: its loss window of beats and
    the misses_down periods a beat waits before it counts as lost."""
    # The monitor's own window (nodes/monitors/link.py; importing it loads rclpy).
    from ..nodes.monitors.link import heartbeat_tracker
    m = deployment.monitoring
    period = 1.0 / m.heartbeat_rate_hz
    tracker = heartbeat_tracker(period, m.heartbeat_misses_down)
    return (tracker.loss_window + tracker.misses_down) * period


def loss_text(reports: Sequence[Tuple[float, p.LinkStatus]], window_s: float) -> str:
    """The loss of the link's latest report, as a person should read it: '' while it is down
    (every beat is lost to the cut); none while the beats it counts reach back into a time the
    monitor reported the link down (they were lost to the cut, not by a lossy link); else the
    fraction of beats lost."""
    if not reports:
        return ''
    heard, last = reports[-1]
    if not last.up:
        return ''
    if any(not s.up for t, s in reports if t >= heard - window_s):
        return f'loss - (its last {window_s:.0f} s of beats hold the cut)'
    return f'loss {last.loss:.0%}'


def _link_lines(record: Record, name: str, now: float, mode: str = '') -> List[str]:
    """The link as the harness set it, and as its monitor last reported it."""
    d: Deployment = record.deployment
    up, rate = link_at(record, now, name)
    seen = ''
    reports = record.link_reports(name)
    if reports:
        # The same judgement as `anyscale-manager status` (view.status): no RTT on a link that
        # is down, the measured bandwidth against the nominal, old figures marked stale.
        heard, link_obs = reports[-1]
        link = d.link_between(link_obs.master, link_obs.remote)
        silent = now - heard > d.decider.observation_max_age_s
        measurable = link_obs.up and not silent
        if silent:
            state = f'SILENT, {stale_mark(now - heard)}'
        elif link_obs.up:
            state = 'up, CONGESTED' if link_obs.congested else 'up'
        else:
            state = 'DOWN'
        age = None if link_obs.bandwidth_available_age_s is None \
            else link_obs.bandwidth_available_age_s + (now - heard)
        avail = '-' if link is None else bandwidth_text(
            link_obs.bandwidth_available_kbps, link.bandwidth_kbps, measurable, age,
            bandwidth_stale_after_s(d), mbit=True)
        loss = loss_text(reports, loss_window_s(d)) if measurable else ''
        seen = (f'  monitor: {state}, rtt {rtt_text(measurable, link_obs.rtt_ms)}, '
                + (f'{loss}, ' if loss else '') + f'available {avail}, used '
                f'{link_obs.bandwidth_used_kbps / 1000:.2f} Mbit/s')
    if mode == 'loopback':
        # Nothing shapes loopback: the rate is the file's, not a limit.
        made = "emulated on loopback: not shaped, a cut freezes the far scale's processes"
        lines = [f'link {name}: {"UP" if up else "CUT"} ({made})']
    else:
        lines = [f'link {name}: ' + (f'UP, shaped to {rate / 1000:.1f} Mbit/s' if up
                                     else f'CUT (every packet dropped; {rate / 1000:.1f} '
                                          'Mbit/s when restored)')]
    return lines + ([seen] if seen else [])


def machine_note(record: Record, t: float, brief: bool = False) -> str:
    """What the decider's single-machine mode means for the scales' CPU at t, from their own
    status reports ('' unless its latest word on it at or before t is that scales share one
    machine). Scales that share a kernel share it (one boot id), but a scale confined by a
    cgroup quota still measures its CPU as that cgroup's usage, against its own quota.
    ``brief``: one short line, for the live table."""
    said = [e for when, e in record.events if e.kind == 'single_machine' and when <= t]
    if not said or not said[-1].reason.startswith('single-machine mode:'):
        return ''
    parts: List[str] = []
    confined: List[Tuple[str, Optional[float]]] = []
    for s in record.deployment.scale_names:
        # Its report at t, else its first one after (the note comes as the agents start).
        reports = record.scale_status.get(s, [])
        before = [x for when, x in reports if when <= t]
        status = before[-1] if before else (reports[0][1] if reports else None)
        source = status.cpu_source if status is not None else None
        if source == 'cgroup' and status is not None:
            confined.append((s, status.cores))
        else:
            parts.append(f'{s}: {CPU_SOURCE_TEXT.get(source or "", "CPU not reported yet")}')
    if brief:
        own = ', '.join(f'{s} {cores:.2g}' if cores is not None else s for s, cores in confined)
        return ("the scales share one machine (the decider's single-machine mode); "
                + '; '.join(([f"each scale's CPU is its own cgroup's ({own} CPUs)"]
                             if confined else []) + parts))
    if confined:
        spread = ', '.join(f'{s} {cores:.2g}' for s, cores in confined if cores is not None)
        parts.insert(0, 'each of ' + ', '.join(s for s, _ in confined) +
                     " measures its CPU as its own cgroup's usage, against its capacity" +
                     (f' spread over the CPUs its quota lets it use ({spread})' if spread
                      else ''))
    return ("the decider's single-machine mode: the scales share this machine's kernel and "
            'CPUs; ' + '; '.join(parts))


CPU_SOURCE_TEXT = {
    'cgroup': "CPU measured as its cgroup's, against its quota",
    'machine': "CPU measured as the whole machine's",
    'processes': "CPU measured as its agent's own processes (no quota confines it)",
}


def _status_rest(record: Record, now: float, lines: List[str], width: int = 99) -> str:
    d: Deployment = record.deployment
    lines.append(f'{"scale":8} {"CPU":>13}   nodes running')
    placement = record.placement(now, ready_only=False)
    for s in d.scales:
        history = record.scale_status.get(s.name)
        cpu = (f'{history[-1][1].cpu_total:5.0f} / {s.capacity_cpu:<5.0f}' if history
               else f'{"-":>5} / {s.capacity_cpu:<5.0f}')
        nodes = sorted(n for n, where in placement.items() if s.name in where)
        if history and now - history[-1][0] > d.decider.observation_max_age_s:
            nodes.insert(0, f'(CPU not heard for {now - history[-1][0]:.0f} s)')
        lines.append(f'{s.name:8} {cpu:>13}   {" ".join(nodes)}')
    note = machine_note(record, now, brief=True)
    if note:
        lines.append(note)
    lines.append('')
    lines.append(f'{"connection":18} {"rate Hz":>8} {"min":>5} {"opt":>5} {"Δ s":>4} '
                 f'{"below s":>8}  state     measured on')
    for c in d.connections:
        got = record.reading_at(c.name)
        if got is None or now - got[0] > 3.0:
            lines.append(f'{c.name:18} {"-":>8} {_num(c.freq_min_hz):>5} '
                         f'{_num(c.freq_opt_hz):>5} {_num(c.tolerance_s):>4} {"-":>8}  no reading')
            continue
        _, scale, r = got
        lines.append(f'{c.name:18} {r.rate_hz:8.1f} {_num(c.freq_min_hz):>5} '
                     f'{_num(c.freq_opt_hz):>5} {_num(c.tolerance_s):>4} {r.below_for_s:8.1f}  '
                     f'{LEVELS.get(r.level, r.level):9} {scale}')
    label, _ = category(record, now)
    lines.append('')
    lines.append(f'AMCL: {location(record, "amcl", now) or "-":7} AR: '
                 f'{location(record, "ar", now) or "-":7} ({label})')
    kinds = MIGRATION_KINDS + ('relocate', 'failover', 'scale_lost', 'adopt')
    recent = [e for _, e in record.events if e.kind in kinds][-3:]
    for e in recent:
        who = ' '.join(x for x in (e.node, e.from_scale) if x)
        text = f'{e.kind} {who}' + (f' -> {e.to_scale}' if e.to_scale else '') + \
            f': {e.reason}'
        lines.extend(textwrap.wrap(text, width=max(20, width), initial_indent='  ',
                                   subsequent_indent=' ' * (2 + WRAP_INDENT),
                                   max_lines=EVENT_LINES, placeholder=' ...',
                                   break_on_hyphens=False))
    return '\n'.join(lines)


def _num(value: Optional[float]) -> str:
    return '-' if value is None else f'{value:g}'


# --- the timeline figure ----------------------------------------------------------------------

def _runs(t0: float, t1: float, step_s: float, value: Callable[[float], Any]
          ) -> List[Tuple[float, float, Any]]:
    """(start, end, value(t)) runs of equal values over [t0, t1] sampled every step_s,
    relative to t0."""
    out: List[Tuple[float, float, Any]] = []
    t = t0
    while t <= t1:
        v = value(t)
        if out and out[-1][2] == v:
            out[-1] = (out[-1][0], t - t0 + step_s, v)
        else:
            out.append((t - t0, t - t0 + step_s, v))
        t += step_s
    return out


def spans(record: Record, t0: float, t1: float, step_s: float = 0.25
          ) -> List[Tuple[float, float, str, str]]:
    """(start, end, label, colour) runs of the Fig. 5 category of where AMCL and AR serve,
    relative to t0."""
    return [(a, b, v[0], v[1]) for a, b, v in
            _runs(t0, t1, step_s, lambda t: category(record, t))]


def cut_off_spans(record: Record, t0: float, t1: float, nodes: Sequence[str] = ('amcl', 'ar'),
                  step_s: float = 0.25) -> List[Tuple[float, float, str]]:
    """(start, end, text) runs, relative to t0, where a copy of one of ``nodes`` was active on
    a scale cut off from its consumers (it serves nobody), e.g. 'AMCL, AR on laptop'."""
    def text(t: float) -> str:
        where: Dict[str, List[str]] = {}
        for n in nodes:
            for scale in serving(record, n, t)[1]:
                where.setdefault(scale, []).append(n.upper())
        return '; '.join(f'{", ".join(ns)} on {s}' for s, ns in where.items())
    return [(a, b, str(v)) for a, b, v in _runs(t0, t1, step_s, text) if v]


@dataclass(frozen=True)
class Dip:
    """A stretch where the probe beside the serving subscriber read a connection below its
    freq_min (times on the record's clock)."""

    connection: str
    start: float
    end: float
    min_rate_hz: float
    below_s: float        # the longest stretch below by the Δ rule the probe reported in it
    past_delta: bool      # the probe said ERROR (past Δ) in it: a violation

    @property
    def allowed(self) -> bool:
        return not self.past_delta


def dips(connection: str, points: Sequence[Tuple[float, p.ConnectionReading]],
         freq_min_hz: Optional[float]) -> List[Dip]:
    """The stretches of ``points`` (one probe's readings, in time order) below freq_min: from
    when the probe says its stretch began (not before the reading above it) to its first
    reading back at freq_min (or its last reading). Past Δ only where the probe said so."""
    out: List[Dip] = []
    run: Optional[List] = None
    previous: Optional[float] = None
    for t, r in points:
        below = max(r.below_for_s, r.ended_below_s or 0.0)
        if rate_below(freq_min_hz, r.rate_hz):
            if run is None:
                start = t - r.below_for_s
                run = [max(start, previous) if previous is not None else start, t, r.rate_hz,
                       below, r.level == p.ERROR]
            else:
                run[1], run[2] = t, min(run[2], r.rate_hz)
                run[3], run[4] = max(run[3], below), run[4] or r.level == p.ERROR
        elif run is not None:
            run[1], run[3] = t, max(run[3], r.ended_below_s or 0.0)
            out.append(Dip(connection, *run))
            run = None
        previous = t
    if run is not None:
        out.append(Dip(connection, *run))
    return out


def probe_scale(record: Record, conn: Connection, t: float) -> str:
    """The scale whose probe measures what the serving subscriber hears at t: where it serves,
    else the one scale it may run on, else where the layout put it ('' if none)."""
    where = location(record, conn.subscriber, t)
    if where:
        return where
    allowed = record.deployment.allowed_scales(conn.subscriber)
    if len(allowed) == 1:
        return allowed[0]
    layout = record.layout_at(t)
    return (layout.assignments.get(conn.subscriber) or '') if layout is not None else ''


def split_readings(record: Record, conn: Connection, t0: float, t1: float,
                   step_s: float = 0.25
                   ) -> Tuple[List[Tuple[float, p.ConnectionReading]],
                              List[Tuple[float, str, p.ConnectionReading]]]:
    """A connection's readings in [t0, t1]: (those of the probe beside the serving subscriber,
    those of other scales' probes: a copy starting, standing down or cut off)."""
    scale_at: Dict[int, str] = {}
    served: List[Tuple[float, p.ConnectionReading]] = []
    others: List[Tuple[float, str, p.ConnectionReading]] = []
    for t, scale, r in record.readings.get(conn.name, []):
        if not t0 <= t <= t1:
            continue
        k = int((t - t0) // step_s)
        if k not in scale_at:
            scale_at[k] = probe_scale(record, conn, t0 + k * step_s)
        if scale == scale_at[k]:
            served.append((t, r))
        else:
            others.append((t, scale, r))
    return served, others


def connection_dips(record: Record, t0: float, t1: float, connections=None) -> List[Dip]:
    """The dips below freq_min of each monitored connection (or those named) as the probe
    beside its serving subscriber read them in [t0, t1]."""
    out: List[Dip] = []
    for c in record.deployment.connections:
        if not c.monitored or (connections is not None and c.name not in connections):
            continue
        served, _ = split_readings(record, c, t0, t1)
        out.extend(dips(c.name, served, c.freq_min_hz))
    return sorted(out, key=lambda x: x.start)


@dataclass(frozen=True)
class CpuSeries:
    """One scale's CPU as its status reports said (reference-core percent), times relative to
    the run's start; NaN where its reports stopped coming (a gap)."""

    scale: str
    times: Tuple[float, ...]
    cpu: Tuple[float, ...]
    capacity_cpu: float
    source: str                  # what it measures (ScaleStatus.cpu_source), '' if not said
    cores: Optional[float]       # the CPUs its capacity is spread over (its quota's, here)


def cpu_series(record: Record, t0: float, t1: float,
               gap_s: Optional[float] = None) -> List[CpuSeries]:
    """Each scale's CPU in [t0, t1] from the scale status reports the record holds, against
    the capacity they state; a gap longer than ``gap_s`` (default: the decider's
    observation_max_age_s) between two reports breaks the line."""
    d = record.deployment
    if gap_s is None:
        gap_s = d.decider.observation_max_age_s
    out: List[CpuSeries] = []
    for s in d.scales:
        rows = [(t, x) for t, x in record.scale_status.get(s.name, []) if t0 <= t <= t1]
        times: List[float] = []
        cpu: List[float] = []
        previous = math.nan
        for t, x in rows:
            if t - previous > gap_s:          # false before the first (NaN)
                times.append(math.nan)
                cpu.append(math.nan)
            times.append(t - t0)
            cpu.append(x.cpu_total)
            previous = t
        last = rows[-1][1] if rows else None
        out.append(CpuSeries(s.name, tuple(times), tuple(cpu),
                             last.capacity_cpu if last is not None else s.capacity_cpu,
                             (last.cpu_source or '') if last is not None else '',
                             last.cores if last is not None else None))
    return out


# Colours of the link row: the link as the harness set it.
LINK_UP, LINK_THROTTLED, LINK_CUT = '#8fd18f', '#f0a040', '#222222'
MOVE_COLOUR = '#555555'
ALLOWED_DIP = '#f5c242'     # below freq_min, within Δ
PAST_DELTA = '#d62728'


def draw_timeline(record: Record, path: str, t0: float, t1: float, title: str = '') -> str:
    """The run as a figure: where AMCL and AR serve (and copies cut off), each link, each
    scale's CPU, each migratable connection's rate; every legend right of its panel."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    d = record.deployment
    migratable = set(d.migratable_nodes)
    conns = [c for c in d.connections
             if c.monitored and (c.publisher in migratable or c.subscriber in migratable)]
    links = list(record.link_truth)
    rows = 2 + len(links) + len(conns)
    ratios = [1.0] + [0.45] * len(links) + [1.5] + [1.4] * len(conns)
    fig, axes = plt.subplots(rows, 1, figsize=(13, 1.0 + 1.45 * rows), sharex=True,
                             gridspec_kw={'height_ratios': ratios})
    legend = {'loc': 'center left', 'bbox_to_anchor': (1.01, 0.5), 'fontsize': 7,
              'frameon': False, 'borderaxespad': 0.0}

    # Where AMCL and AR serve (upper lane) and copies active on a cut-off scale (lower lane).
    ax = axes[0]
    runs = spans(record, t0, t1)
    for start, end, _, colour in runs:
        ax.axvspan(start, end, ymin=0.3, ymax=1.0, color=colour, lw=0)
    cut = cut_off_spans(record, t0, t1)
    for start, end, text in cut:
        ax.axvspan(start, end, ymin=0.0, ymax=0.25, facecolor='white', edgecolor='#444444',
                   hatch='////', lw=0)
        if end - start >= 0.12 * (t1 - t0):
            ax.text(start + 0.3, 0.125, f'{text}: cut off', va='center', fontsize=6)
    ax.set_yticks([])
    ax.set_ylim(0, 1)
    ax.set_ylabel('where AMCL\nand AR serve', rotation=0, ha='right', va='center',
                  fontsize=8)
    seen = {label: colour for _, _, label, colour in runs}
    known = list(CATEGORIES.values()) if len(d.scale_names) == 2 else list(seen.items())
    handles: List[Any] = [Patch(color=c, label=lab) for lab, c in known + [UNKNOWN]
                          if lab in seen]
    if cut:
        handles.append(Patch(facecolor='white', edgecolor='#444444', hatch='////',
                             label='active on a scale cut off from\nits consumers (serves '
                                   'nobody)'))
    handles.append(Line2D([], [], color=MOVE_COLOUR, lw=0.8,
                          label='a move the decider made\n(grey line, every panel)'))
    ax.legend(handles=handles, **legend)

    for ax, link in zip(axes[1:], links):
        truth = [(t - t0, up, rate) for t, up, rate in record.link_truth[link]]
        full = max((r for _, _, r in truth if r), default=1.0)
        states = set()
        for (a, up, rate), b in zip(truth, [x[0] for x in truth[1:]] + [t1 - t0]):
            if b <= 0:
                continue
            state = 'cut' if not up else ('up' if rate >= full else 'throttled')
            states.add(state)
            colour = {'cut': LINK_CUT, 'up': LINK_UP, 'throttled': LINK_THROTTLED}[state]
            ax.axvspan(max(a, 0.0), b, color=colour, lw=0)
            if state == 'throttled':
                ax.text(max(a, 0.0) + 0.3, 0.5, f'{rate / 1000:g} Mbit/s', va='center',
                        fontsize=7)
        ax.set_yticks([])
        ax.set_ylabel('link' if len(links) == 1 else f'link {link}', rotation=0, ha='right',
                      va='center', fontsize=8)
        ax.legend(handles=[Patch(color=c, label=lab) for key, c, lab in (
            ('up', LINK_UP, f'up, {full / 1000:g} Mbit/s'),
            ('throttled', LINK_THROTTLED, 'throttled (rate written)'),
            ('cut', LINK_CUT, 'cut (every packet dropped)')) if key in states],
            **legend)

    ax = axes[1 + len(links)]
    for i, series in enumerate(cpu_series(record, t0, t1)):
        colour = SCALE_COLOURS[i % len(SCALE_COLOURS)]
        quota = '' if series.source != 'cgroup' or series.cores is None else \
            f' = {series.cores:.2g} CPUs here'
        if series.times:
            ax.plot(series.times, series.cpu, '-', lw=1.0, color=colour,
                    label=f'{series.scale} CPU used')
        ax.axhline(series.capacity_cpu, color=colour, ls='--', lw=0.9,
                   label=f'{series.scale} capacity {series.capacity_cpu:g}{quota}')
    ax.set_ylim(bottom=0)
    ax.set_ylabel('CPU\n(% of a\nreference\ncore)', rotation=0, ha='right', va='center',
                  fontsize=8)
    ax.legend(**legend)

    for ax, c in zip(axes[2 + len(links):], conns):
        served, others = split_readings(record, c, t0, t1)
        if others:
            ax.plot([t - t0 for t, _, _ in others], [r.rate_hz for _, _, r in others], '.',
                    ms=3, color='#999999', label="other scales' probes\n(a copy not serving)")
        if served:
            ax.plot([t - t0 for t, _ in served], [r.rate_hz for _, r in served], '.-', ms=2,
                    lw=0.8, color='#333333', label='rate heard by the\nserving subscriber')
        if c.monitored:
            ax.axhline(c.freq_min_hz, color=PAST_DELTA, ls='--', lw=1,
                       label=f'freq_min {c.freq_min_hz:g} Hz (Δ {c.tolerance_s:g} s)')
        if c.freq_opt_hz is not None:
            ax.axhline(c.freq_opt_hz, color='#2ca02c', ls=':', lw=1,
                       label=f'freq_opt {c.freq_opt_hz:g} Hz')
        allowed = [x for x in dips(c.name, served, c.freq_min_hz) if x.allowed]
        labelled = -math.inf
        for x in allowed:
            ax.axvspan(x.start - t0, x.end - t0, color=ALLOWED_DIP, alpha=0.35, lw=0)
            if x.end - t0 - labelled > 0.06 * (t1 - t0):      # labels never overlap
                labelled = x.end - t0
                ax.annotate(f'{x.below_s:.1f} s below', (labelled, 0.95), fontsize=6,
                            xycoords=('data', 'axes fraction'), ha='left', va='top')
        violations = record.reported_violations(t0, t1, [c.name], serving_only=True)
        for v in violations:
            ax.axvspan(v.start - t0, v.end - t0, color=PAST_DELTA, alpha=0.15, lw=0)
        handles, _ = ax.get_legend_handles_labels()
        handles.append(Patch(color=ALLOWED_DIP, alpha=0.35,
                             label=f'below freq_min within Δ:\nallowed ({len(allowed)})'))
        handles.append(Patch(color=PAST_DELTA, alpha=0.15,
                             label=f'past Δ: a violation ({len(violations)})'))
        ax.set_ylabel(f'{c.name}\nHz', rotation=0, ha='right', va='center', fontsize=8)
        ax.legend(handles=handles, **legend)
        ax.set_ylim(bottom=0)
    for t, e in record.moves(t0, t1):
        for ax in axes:
            ax.axvline(t - t0, color=MOVE_COLOUR, lw=0.8, alpha=0.7, zorder=3)
    axes[-1].set_xlabel('time since the schedule started (s)')
    axes[-1].set_xlim(0, max(1.0, t1 - t0))
    height = fig.get_figheight()
    if title:
        fig.suptitle(title, fontsize=10, y=1.0 - 0.12 / height, va='top')
    fig.subplots_adjust(left=0.1, right=0.76, top=1.0 - 0.45 / height, bottom=0.5 / height,
                        hspace=0.25)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- the event log ----------------------------------------------------------------------------

def event_log(record: Record, t0: float) -> List[Dict]:
    """Decider events and the harness's own actions, in time order, relative to t0."""
    rows = [{'t': round(t - t0, 3), 'source': 'decider', **e.to_dict()}
            for t, e in record.events]
    rows += [{'t': round(t - t0, 3), 'source': 'harness', 'kind': 'action', 'reason': text}
             for t, text in record.marks]
    return sorted(rows, key=lambda r: r['t'])


# Decider events never folded: each is a decision of its own, whatever its words. A move of a
# node also ends the repeated notes that name it: they explained why it stayed.
UNFOLDED = MIGRATION_KINDS + ('relocate', 'failover', 'layout')
# Kinds the decider says again while they still hold (a note on why nothing moved, a plan
# warning): their repeats are one spell. Others repeated (a violation that comes and goes) are
# counted, not said to have held.
HELD_KINDS = ('note', 'warning')
# A note said again within this long, its numbers aside, is the same note still holding.
NOTE_GAP_S = 10.0
_NUMBER = re.compile(r'[-+]?\d+(?:\.\d+)?')
_DETAIL = re.compile(r'\([^()]*\)')


def note_key(row: Mapping) -> Tuple[str, str, str, str, str]:
    """What makes two decider events one repeated note: kind, node, scales and the words of
    the reason, its numbers and parenthesised details aside ('3.2 s ago' and '3.7 s ago', or
    '(amcl, ar below ...)' and '(ar below ...)', are one note)."""
    words = _NUMBER.sub('#', _DETAIL.sub('(...)', row.get('reason', '')))
    return (row['kind'], row.get('node', ''), row.get('from_scale', ''),
            row.get('to_scale', ''), words)


def fold_notes(rows: Sequence[Mapping], gap_s: float = NOTE_GAP_S) -> List[Dict]:
    """The event log with each repeated decider note said once: its first row, and, when it
    ends (not said again within ``gap_s``, or a node it names moved), one row at its last time
    in the words of the last, with ``times`` and ``held_s`` (from first to last). Moves,
    layouts and the harness's own rows are never folded."""
    out: List[Tuple[float, int, Dict]] = []
    open_runs: Dict[Tuple, Dict] = {}

    def close(key: Tuple) -> None:
        run = open_runs.pop(key)
        if run['times'] > 1:
            last = dict(run['last'])
            last.update(held_s=round(last['t'] - run['first']['t'], 3), times=run['times'])
            out.append((last['t'], len(out), last))
    for row in rows:
        for key in [k for k, run in open_runs.items() if row['t'] - run['last']['t'] > gap_s]:
            close(key)
        if row.get('source') != 'decider' or row.get('kind') in UNFOLDED:
            moved = row.get('node') if row.get('source') == 'decider' else ''
            if moved:
                named = re.compile(rf'\b{re.escape(moved)}\b')
                for key in [k for k, run in open_runs.items()
                            if run['first'].get('node') == moved
                            or named.search(run['first'].get('reason', ''))]:
                    close(key)
            out.append((row['t'], len(out), dict(row)))
            continue
        key = note_key(row)
        run = open_runs.get(key)
        if run is None:
            open_runs[key] = {'first': row, 'last': row, 'times': 1}
            out.append((row['t'], len(out), dict(row)))
        else:
            run['last'], run['times'] = row, run['times'] + 1
    for key in list(open_runs):
        close(key)
    return [row for _, _, row in sorted(out, key=lambda x: (x[0], x[1]))]


def event_line(row: Mapping) -> str:
    """One row of events.txt."""
    head = f'{row["t"]:8.1f}  '
    if row['source'] == 'harness':
        return head + f'HARNESS   {row["reason"]}'
    if row['kind'] in MIGRATION_KINDS + ('relocate', 'failover'):
        return head + (f'{row["kind"]:12} {row["node"]} {row["from_scale"]} -> '
                       f'{row["to_scale"]}: {row["reason"]}')
    folded = ''
    if 'held_s' in row:
        folded = (f'(held {row["held_s"]:.1f} s, {row["times"]} times) '
                  if row['kind'] in HELD_KINDS else
                  f'({row["times"]} times in {row["held_s"]:.1f} s, the last:) ')
    node = f'{row["node"]} ' if row.get('node') else ''
    return head + f'{row["kind"]:12} {folded}{node}{row["reason"]}'


def write_event_log(record: Record, folder: str, t0: float) -> Tuple[str, str]:
    """events.jsonl (every row) and events.txt (for people: repeated notes folded, the
    single-machine note followed by what it means for the scales' CPU here)."""
    rows = event_log(record, t0)
    os.makedirs(folder, exist_ok=True)
    jsonl = os.path.join(folder, 'events.jsonl')
    text = os.path.join(folder, 'events.txt')
    with open(jsonl, 'w') as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + '\n')
    with open(text, 'w') as f:
        for row in fold_notes(rows):
            f.write(event_line(row) + '\n')
            if row.get('kind') == 'single_machine' and 'held_s' not in row:
                # The note speaks of scales no quota confines; say what holds for these.
                # row['t'] is rounded: take the event itself in.
                note = machine_note(record, t0 + row['t'] + 0.01)
                if note:
                    f.write(' ' * 10 + f'here: {note}\n')
    return jsonl, text


def placement_shares(record: Record, t0: float, t1: float) -> Dict[str, float]:
    """Fraction of [t0, t1] spent in each Fig. 5 category."""
    total: Dict[str, float] = {}
    for start, end, label, _ in spans(record, t0, t1):
        total[label] = total.get(label, 0.0) + (end - start)
    length = max(1e-9, sum(total.values()))
    return {k: v / length for k, v in sorted(total.items())}


__all__ = ['CATEGORIES', 'CpuSeries', 'Dip', 'category', 'connection_dips', 'consumer_scales',
           'cpu_series', 'cut_off_spans', 'dips', 'draw_timeline', 'event_line', 'event_log',
           'fold_notes', 'link_at', 'link_up', 'location', 'loss_text', 'loss_window_s',
           'machine_note', 'note_key', 'placement_shares', 'serving', 'spans',
           'split_readings', 'status_table', 'with_own_reports', 'wrap_lines',
           'write_event_log']
