"""What a person sees of a test-bed run: the live status table, the timeline figure, the log.

Pure functions of a ``Record`` (and matplotlib with the Agg backend for the figure).
"""

import json
import math
import os
from typing import Dict, List, Optional, Tuple

from .. import protocol as p
from ..model.types import Deployment
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


def location(record: Record, node: str, t: float) -> str:
    """The remote scale that runs it (ready), else the master if it does, else ''."""
    scales = record.where(node, t)
    master = record.deployment.master.name
    remote = [s for s in scales if s != master]
    if remote:
        return remote[0]
    return master if master in scales else ''


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

def status_table(record: Record, now: float, t0: float, mode: str) -> str:
    d: Deployment = record.deployment
    lines = [f't = {now - t0:6.1f} s   [{mode}]']
    for link in d.links:
        lines.extend(_link_lines(record, link.name, now))
    lines.append('')
    return _status_rest(record, now, lines)


def _link_lines(record: Record, name: str, now: float) -> List[str]:
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
        seen = (f'  monitor: {state}, rtt {rtt_text(measurable, link_obs.rtt_ms)}, loss '
                f'{link_obs.loss:.0%}, available {avail}, used '
                f'{link_obs.bandwidth_used_kbps / 1000:.2f} Mbit/s')
    lines = [f'link {name}: {"UP" if up else "CUT"} {rate / 1000:.1f} Mbit/s']
    return lines + ([seen] if seen else [])


def _status_rest(record: Record, now: float, lines: List[str]) -> str:
    d: Deployment = record.deployment
    lines.append(f'{"scale":8} {"CPU":>13}   nodes running')
    placement = record.placement(now, ready_only=False)
    for s in d.scales:
        history = record.scale_status.get(s.name)
        cpu = (f'{history[-1][1].cpu_total:5.0f} / {s.capacity_cpu:<5.0f}' if history
               else f'{"-":>5} / {s.capacity_cpu:<5.0f}')
        nodes = sorted(n for n, where in placement.items() if s.name in where)
        lines.append(f'{s.name:8} {cpu:>13}   {" ".join(nodes)}')
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
        lines.append(f'  {e.kind} {e.node} {e.from_scale} -> {e.to_scale}: {e.reason[:90]}')
    return '\n'.join(lines)


def _num(value: Optional[float]) -> str:
    return '-' if value is None else f'{value:g}'


# --- the timeline figure ----------------------------------------------------------------------

def spans(record: Record, t0: float, t1: float, step_s: float = 0.25
          ) -> List[Tuple[float, float, str, str]]:
    """(start, end, label, colour) runs of the Fig. 5 category, relative to t0."""
    out: List[Tuple[float, float, str, str]] = []
    t = t0
    while t <= t1:
        label, colour = category(record, t)
        if out and out[-1][2] == label:
            out[-1] = (out[-1][0], t - t0 + step_s, label, colour)
        else:
            out.append((t - t0, t - t0 + step_s, label, colour))
        t += step_s
    return out


def draw_timeline(record: Record, path: str, t0: float, t1: float, title: str = '') -> str:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    d = record.deployment
    migratable = set(d.migratable_nodes)
    conns = [c for c in d.connections
             if c.monitored and (c.publisher in migratable or c.subscriber in migratable)]
    links = list(record.link_truth)
    rows = 1 + len(links) + len(conns)
    fig, axes = plt.subplots(rows, 1, figsize=(11, 1.2 + 1.6 * rows), sharex=True,
                             gridspec_kw={'height_ratios': [0.8] + [0.5] * len(links) +
                                          [1.4] * len(conns)})
    ax = axes[0]
    for start, end, _, colour in spans(record, t0, t1):
        ax.axvspan(start, end, color=colour, lw=0)
    ax.set_yticks([])
    ax.set_ylabel('layout', rotation=0, ha='right', va='center')
    used = {label for _, _, label, _ in spans(record, t0, t1)}
    seen = {label: colour for _, _, label, colour in spans(record, t0, t1)}
    known = list(CATEGORIES.values()) if len(d.scale_names) == 2 else list(seen.items())
    handles = [Patch(color=c, label=lab) for lab, c in known + [UNKNOWN] if lab in used]
    ax.legend(handles=handles, loc='upper center', bbox_to_anchor=(0.5, 1.9), ncol=4,
              fontsize=8, frameon=False)

    for ax, link in zip(axes[1:], links):
        truth = [(t - t0, up, rate) for t, up, rate in record.link_truth[link]] + \
            [(t1 - t0, None, None)]
        full = max((r for _, _, r in truth if r), default=1.0)
        for (a, up, rate), (b, _, _) in zip(truth, truth[1:]):
            if up is None:
                continue
            colour = '#222222' if not up else ('#8fd18f' if rate >= full else '#f0a040')
            ax.axvspan(max(a, 0.0), b, color=colour, lw=0)
            if up and rate < full:
                ax.text(max(a, 0.0) + 0.3, 0.5, f'{rate / 1000:g} Mbit/s', va='center',
                        fontsize=7)
        ax.set_yticks([])
        ax.set_ylabel('link' if len(links) == 1 else f'link {link}', rotation=0, ha='right',
                      va='center')

    for ax, c in zip(axes[1 + len(links):], conns):
        pts = [(t - t0, r.rate_hz) for t, _, r in record.readings.get(c.name, [])
               if t0 <= t <= t1]
        if pts:
            xs, ys = zip(*pts)
            ax.plot(xs, ys, '.-', ms=2, lw=0.8, color='#333333', label='measured rate')
        if c.freq_min_hz is not None:
            ax.axhline(c.freq_min_hz, color='#d62728', ls='--', lw=1,
                       label=f'freq_min {c.freq_min_hz:g} Hz (Δ {c.tolerance_s:g} s)')
        if c.freq_opt_hz is not None:
            ax.axhline(c.freq_opt_hz, color='#2ca02c', ls=':', lw=1,
                       label=f'freq_opt {c.freq_opt_hz:g} Hz')
        for v in record.reported_violations(t0, t1, [c.name], serving_only=True):
            ax.axvspan(v.start - t0, v.end - t0, color='#d62728', alpha=0.15, lw=0)
        ax.set_ylabel(f'{c.name}\nHz', rotation=0, ha='right', va='center', fontsize=8)
        ax.legend(loc='upper right', fontsize=7, frameon=False)
        ax.set_ylim(bottom=0)
    for t, e in record.moves(t0, t1):
        for ax in axes:
            ax.axvline(t - t0, color='#555555', lw=0.6, alpha=0.6)
    axes[-1].set_xlabel('time since the test-bed was ready (s)')
    axes[-1].set_xlim(0, max(1.0, t1 - t0))
    if title:
        fig.suptitle(title, y=0.995, fontsize=10)
    fig.tight_layout()
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


def write_event_log(record: Record, folder: str, t0: float) -> Tuple[str, str]:
    rows = event_log(record, t0)
    os.makedirs(folder, exist_ok=True)
    jsonl = os.path.join(folder, 'events.jsonl')
    text = os.path.join(folder, 'events.txt')
    with open(jsonl, 'w') as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + '\n')
    with open(text, 'w') as f:
        for row in rows:
            if row['source'] == 'harness':
                f.write(f'{row["t"]:8.1f}  HARNESS   {row["reason"]}\n')
            elif row['kind'] in MIGRATION_KINDS + ('relocate', 'failover'):
                f.write(f'{row["t"]:8.1f}  {row["kind"]:12} {row["node"]} {row["from_scale"]} '
                        f'-> {row["to_scale"]}: {row["reason"]}\n')
            else:
                f.write(f'{row["t"]:8.1f}  {row["kind"]:12} {row["node"]} {row["reason"]}\n')
    return jsonl, text


def placement_shares(record: Record, t0: float, t1: float) -> Dict[str, float]:
    """Fraction of [t0, t1] spent in each Fig. 5 category."""
    total: Dict[str, float] = {}
    for start, end, label, _ in spans(record, t0, t1):
        total[label] = total.get(label, 0.0) + (end - start)
    length = max(1e-9, sum(total.values()))
    return {k: v / length for k, v in sorted(total.items())}


__all__ = ['CATEGORIES', 'category', 'draw_timeline', 'event_log', 'link_at', 'location',
           'placement_shares', 'spans', 'status_table', 'write_event_log']
