"""``anyscale-manager demo --fleet``: two robots share one server, in network namespaces.

Each robot is its own deployment (its decider, its agents, its ROS domain: testbed/fleet.py)
running the graph ``--graph`` names (testbed/fleet_graphs.py): ``icar`` (the default), its own
copy of the ICAR 2015 test-bed, whose AMCL and AR would go to the server, which has room for one
robot's pair; ``worker``, a sensor -> worker -> consumer graph whose worker (CPU 60) would go
there, room for one worker. A schedule drives the run (default ``FLEET_SCHEDULE``): robot_a
starts and takes the server, its link is cut (its nodes go home, its claims are released) and
restored (it takes the server back after its hysteresis), then robot_b arrives with a higher
priority and preempts it (robot_a takes its nodes home first, only then do robot_b's serve
there). The run is judged from outside (testbed/fleet_netns.py): where each robot's nodes
serve, the server's claims by robot, and what each robot's users hear on every connection its
graph judges, in its own namespace. Writes timeline.png, events.txt and summary.json; exits 1
when the server was over-committed or a robot's connection stayed below freq_min past its Δ.
"""

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

from .fleet import FleetShape, HOME, SERVER, other_domain, stretches_past_delta
from .fleet_graphs import graph_of
from .fleet_record import FleetRecord, FleetSample, over_capacity

ROBOTS = ('robot_a', 'robot_b')
FLEET_SCHEDULE = '0:start@robot_a,25:cut@robot_a,40:restore@robot_a,60:start=1@robot_b'
FLEET_DURATION_S = 85.0
# Short enough that a demo shows a move back within a minute; the fleet's tests use the same.
HYSTERESIS_S = 6.0
SAMPLE_S = 0.25
RATE_BIN_S = 0.5
COLOURS = {HOME: '#4c72b0', SERVER: '#dd8452', 'both': '#c44e52', 'none': '#dddddd'}


@dataclass(frozen=True)
class FleetStep:
    """One step of a fleet schedule, ``at_s`` seconds after the run starts."""

    at_s: float
    action: str              # start, cut, restore
    robot: str
    priority: int = 0        # start only

    def __str__(self) -> str:
        what = f'start (priority {self.priority})' if self.action == 'start' else self.action
        return f'{self.at_s:g} s {what} {self.robot}'


def parse_fleet_schedule(text: str, robots: Sequence[str] = ROBOTS) -> List[FleetStep]:
    """'T:ACTION@ROBOT,...' (ACTION: start, start=PRIORITY, cut, restore) -> the steps in
    time order; ValueError naming the step and what is wrong. Each robot starts once, before
    its link is cut or restored; a link is cut only while up."""
    steps = []
    for raw in (s.strip() for s in text.split(',')):
        if not raw:
            continue
        when, sep, rest = raw.partition(':')
        action, at, robot = rest.partition('@')
        try:
            at_s = float(when)
        except ValueError:
            raise ValueError(f'step {raw!r}: {when!r} is not a time in seconds') from None
        if not sep or not at or not math.isfinite(at_s) or at_s < 0:
            raise ValueError(f'step {raw!r}: expected T:ACTION@ROBOT with T >= 0 s')
        if robot not in robots:
            raise ValueError(f'step {raw!r}: unknown robot {robot!r}; expected one of '
                             f'{", ".join(robots)}')
        name, _, value = action.partition('=')
        if name not in ('start', 'cut', 'restore') or (value and name != 'start'):
            raise ValueError(f'step {raw!r}: unknown action {action!r}; expected start, '
                             'start=PRIORITY, cut or restore')
        try:
            priority = int(value) if value else 0
        except ValueError:
            raise ValueError(f'step {raw!r}: priority {value!r} is not a whole number') from None
        steps.append(FleetStep(at_s, name, robot, priority))
    steps.sort(key=lambda s: s.at_s)
    started, up = set(), {r: True for r in robots}
    for step in steps:
        if step.action == 'start':
            if step.robot in started:
                raise ValueError(f'{step}: {step.robot} starts twice')
            started.add(step.robot)
            continue
        if step.robot not in started:
            raise ValueError(f'{step}: {step.robot} has not started yet')
        if (step.action == 'cut') != up[step.robot]:
            raise ValueError(f'{step}: its link is already '
                             f'{"cut" if step.action == "cut" else "up"}')
        up[step.robot] = step.action != 'cut'
    if not started:
        raise ValueError('the schedule starts no robot')
    return steps


# --- judging ---------------------------------------------------------------------------------

def over_commit_s(samples: Sequence[FleetSample], shape: FleetShape) -> float:
    """Seconds with the server over its capacity (fleet_record.over_capacity; each such sample
    holds until the next)."""
    over = {id(s) for s in over_capacity(samples, shape.capacity_cpu, shape.lifecycle)}
    return sum(b.t - a.t for a, b in zip(samples, samples[1:]) if id(a) in over)


def moves(samples: Sequence[FleetSample], robot: str) -> List[Tuple[float, str, str]]:
    """(time, from, to) each time ``robot``'s worker changed where it runs ('both' and 'none'
    are passed through: a move is from one place to another)."""
    out: List[Tuple[float, str, str]] = []
    last: Optional[str] = None
    for s in samples:
        where = s.where(robot)
        if where in (HOME, SERVER):
            if last is not None and where != last:
                out.append((s.t, last, where))
            last = where
    return out


def robot_summary(record: FleetRecord, robot: str, shape: FleetShape, t0: float,
                  end: float) -> Dict[str, Any]:
    """What ``robot``'s users lived on each connection its graph judges: Δ violations and the
    longest stretch below freq_min, each from its first message heard; and its moves."""
    row: Dict[str, Any] = {'moves': [
        {'at_s': round(t - t0, 2), 'from': a, 'to': b}
        for t, a, b in moves(record.between(t0, end), robot)]}
    connections: Dict[str, Any] = {}
    for j in graph_of(shape).judged(robot):
        heard = record.heard(robot, j.topic)
        first = next((t for t in heard if t >= t0), None)
        if first is None:
            continue
        past, longest = stretches_past_delta(heard, first, end, j)
        connections[j.name] = {'delta_violations': past, 'longest_below_s': round(longest, 2),
                               'heard': sum(1 for t in heard if first <= t <= end)}
    if not connections:
        row.update(delta_violations=None, longest_below_s=None, heard=0)
        return row
    row.update(delta_violations=sum(c['delta_violations'] for c in connections.values()),
               longest_below_s=max(c['longest_below_s'] for c in connections.values()),
               heard=sum(c['heard'] for c in connections.values()), connections=connections)
    return row


# --- the figure ------------------------------------------------------------------------------

def rate_series(arrivals: Sequence[float], t0: float, t1: float,
                bin_s: float = RATE_BIN_S) -> Tuple[List[float], List[float]]:
    """(bin starts from t0, messages a second in each bin) over [t0, t1)."""
    n = max(1, int((t1 - t0) / bin_s))        # whole bins: a partial last one reads low
    counts = [0] * n
    for t in arrivals:
        if t0 <= t < t1:
            counts[min(n - 1, int((t - t0) / bin_s))] += 1
    return [i * bin_s for i in range(n)], [c / bin_s for c in counts]


def draw_fleet_timeline(record: FleetRecord, path: str, robots: Sequence[str],
                        shape: FleetShape, t0: float, t1: float, title: str = '') -> str:
    """Per robot: where its migratable nodes serve with its link under it, and the rate its
    users hear of one connection (the graph's shown one) against its freq_min; then the
    server's claims by robot against its capacity. Schedule steps are grey vertical lines,
    named at the top."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    graph = graph_of(shape)
    what = graph.what
    samples = record.between(t0, t1)
    rows = 2 * len(robots) + 1
    fig, axes = plt.subplots(rows, 1, figsize=(13, 1.2 + 1.5 * rows), sharex=True,
                             gridspec_kw={'height_ratios': [0.8, 1.3] * len(robots) + [1.5]})
    legend = {'loc': 'center left', 'bbox_to_anchor': (1.01, 0.5), 'fontsize': 7,
              'frameon': False}
    for i, robot in enumerate(robots):
        ax = axes[2 * i]
        for a, b in zip(samples, samples[1:]):
            if robot not in a.workers:        # not started yet
                continue
            ax.axvspan(a.t - t0, b.t - t0, ymin=0.35, ymax=1.0, lw=0,
                       color=COLOURS[a.where(robot)])
            up = a.links_up.get(robot, True)
            ax.axvspan(a.t - t0, b.t - t0, ymin=0.0, ymax=0.25, lw=0,
                       facecolor='#55a868' if up else 'white',
                       edgecolor=None if up else '#c44e52', hatch=None if up else '////')
        ax.set_yticks([])
        ax.set_ylabel(robot, rotation=0, ha='right', va='center', fontsize=8)
        ax.legend(handles=[Patch(color=COLOURS[HOME], label=f'{what} home'),
                           Patch(color=COLOURS[SERVER], label=f'{what} on the server'),
                           Patch(color=COLOURS['both'], label='both (a move, or a copy cut off)'),
                           Patch(color=COLOURS['none'], label='not running'),
                           Patch(color='#55a868', label='link up (lower lane)'),
                           Patch(facecolor='white', edgecolor='#c44e52', hatch='////',
                                 label='link cut')], **legend)
        ax = axes[2 * i + 1]
        shown = graph.shown(robot)
        xs, ys = rate_series(record.heard(robot, shown.topic), t0, t1)
        ax.step(xs, ys, where='post', color='#4c72b0', lw=1,
                label=f'{shown.topic} heard ({shown.name})')
        ax.axhline(shown.freq_min_hz, color='#c44e52', ls='--', lw=0.8,
                   label=f'freq_min {shown.freq_min_hz:g} Hz (Δ {shown.tolerance_s:g} s)')
        ax.set_ylim(0, max([shown.freq_min_hz * 2.5] + ys) * 1.25)
        ax.set_ylabel('Hz', fontsize=8)
        ax.legend(**legend)
    ax = axes[-1]
    xs = [s.t - t0 for s in samples]
    stacks = [[s.claims_cpu.get(r, 0.0) for s in samples] for r in robots]
    if xs:
        ax.stackplot(xs, *stacks, step='post', labels=[f"{r}'s claim" for r in robots],
                     colors=['#8172b3', '#937860', '#da8bc3'][:len(robots)], alpha=0.8)
    ax.axhline(shape.capacity_cpu, color='black', ls='--', lw=0.8,
               label=f'server capacity {shape.capacity_cpu:g}')
    ax.set_ylim(0, shape.capacity_cpu * 1.5)
    ax.set_ylabel('server CPU', fontsize=8)
    ax.set_xlabel('seconds from the start of the schedule')
    ax.legend(**legend)
    for t, text in record.marks:
        if t0 <= t <= t1:
            for a in axes:
                a.axvline(t - t0, color='grey', lw=0.6, alpha=0.7)
            axes[0].annotate(text, (t - t0, 1.02), xycoords=('data', 'axes fraction'),
                             fontsize=6, rotation=20, va='bottom')
    axes[0].set_xlim(0, max(1.0, t1 - t0))
    fig.suptitle(title or f'two robots share one server (capacity {shape.capacity_cpu:g}, '
                 f'{graph.needs()})', y=0.995)
    fig.text(0.01, 0.002, 'grey lines: schedule steps (named at the top)', fontsize=7)
    fig.tight_layout(rect=(0, 0.01, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def event_lines(record: FleetRecord, robots: Sequence[str], t0: float, t1: float,
                what: str = 'worker') -> List[str]:
    """The schedule's steps and each robot's moves (of its ``what``), in time order."""
    rows = [(t, f'{t - t0:7.2f}  {text}') for t, text in record.marks if t0 <= t <= t1]
    for robot in robots:
        rows += [(t, f'{t - t0:7.2f}  {robot}: {what} {a} -> {b}')
                 for t, a, b in moves(record.between(t0, t1), robot)]
    return [text for _, text in sorted(rows)]


# --- the run ---------------------------------------------------------------------------------

def status_line(sample: FleetSample, robots: Sequence[str], t0: float,
                what: str = 'worker') -> str:
    parts = []
    for r in robots:
        if r not in sample.workers:
            parts.append(f'{r}: -')
            continue
        link = 'up' if sample.links_up.get(r, True) else 'CUT'
        parts.append(f'{r}: {what} {sample.where(r)}, link {link}, '
                     f'claim {sample.claims_cpu.get(r, 0.0):g}')
    return f'{sample.t - t0:6.1f} s  ' + ' | '.join(parts)


def _fail(message: str) -> int:
    print(f'anyscale-manager demo --fleet: {message}', file=sys.stderr)
    return 2


def _arguments(args: argparse.Namespace) -> Tuple[float, List[FleetStep], Dict[str, int], str]:
    """The run's length, schedule, each robot's ROS domain and output folder, from the
    command line; ValueError saying what is wrong."""
    from . import netns
    from .cli import domain_of
    duration = FLEET_DURATION_S if args.duration is None else args.duration
    if not 0 < duration <= 24 * 3600:
        raise ValueError(f'--duration must be between 0 and 86400 s, got {duration:g}')
    try:
        steps = parse_fleet_schedule(args.schedule or FLEET_SCHEDULE)
    except ValueError as e:
        raise ValueError(f'--schedule: {e}') from None
    late = [s for s in steps if s.at_s >= duration]
    if late:
        raise ValueError(f"--schedule: {late[0]} is past the run's {duration:g} s (--duration)")
    domain = domain_of(args)
    ok, why = netns.available()
    if not ok:
        raise ValueError(f'a fleet runs in network namespaces: {why}')
    out = os.path.abspath(args.out or f'anyscale_fleet_demo_{time.strftime("%Y%m%d_%H%M%S")}')
    return duration, steps, {ROBOTS[0]: domain, ROBOTS[1]: other_domain(domain)}, out


def _play(bed, steps: Sequence[FleetStep], domains: Dict[str, int], duration: float,
          refresh_s: float) -> Tuple[float, float]:
    """Set the fleet up and play the schedule, a status line every ``refresh_s``; (start,
    end) of the schedule on the monotonic clock. HarnessError when a process died."""
    from .errors import HarnessError
    bed.setup()
    t0 = time.monotonic()
    bed.record.t0 = t0
    pending = list(steps)
    next_show = t0
    while True:
        now = time.monotonic()
        while pending and now - t0 >= pending[0].at_s:
            step = pending.pop(0)
            if step.action == 'start':
                bed.start(step.robot, domains[step.robot], step.priority)
            elif step.action == 'cut':
                bed.cut(step.robot)
            else:
                bed.restore(step.robot)
        if now - t0 >= duration:
            break
        sample = bed.sample()
        dead = bed.dead()
        if dead is not None:
            raise HarnessError(dead)
        if now >= next_show:
            print(status_line(sample, ROBOTS, t0, bed.graph.what), flush=True)
            next_show = now + refresh_s
        time.sleep(SAMPLE_S)
    t1 = time.monotonic()
    bed.mark('schedule ended')
    wait_end = time.monotonic() + 5.0
    while time.monotonic() < wait_end and any(
            bed.record.judged_until(r) < t1 for r in bed.fleet.procs):
        time.sleep(0.1)
    return t0, t1


def _write(record: FleetRecord, shape: FleetShape, steps: Sequence[FleetStep], out: str,
           t0: float, t1: float, notes: List[str]) -> Tuple[Dict[str, Any], List[str]]:
    """summary.json, events.txt and the timeline in ``out``: (the summary, the files)."""
    graph = graph_of(shape)
    summary: Dict[str, Any] = {
        'schedule': [str(s) for s in steps], 'duration_s': round(t1 - t0, 2),
        'graph': shape.graph, 'server_capacity_cpu': shape.capacity_cpu,
        'migratable_cpu': {n: graph.cpu(n) for n in graph.moving},
        'hysteresis_s': shape.hysteresis_s, 'tolerance_s': shape.tolerance_s,
        'over_commit_s': round(over_commit_s(record.between(t0, t1), shape), 2),
        'most_copies_on_server': record.most_on_server(t0, t1),
        'most_serving_cpu': max((x.serving_cpu for x in record.between(t0, t1)), default=0.0),
        'most_claimed_cpu': record.most_claimed(t0, t1),
        'robots': {r: robot_summary(record, r, shape, t0, t1) for r in ROBOTS},
        'teardown_notes': notes}
    files = []
    if t1 > t0:
        files.append(draw_fleet_timeline(record, os.path.join(out, 'timeline.png'), ROBOTS,
                                         shape, t0, t1))
    events = os.path.join(out, 'events.txt')
    with open(events, 'w') as f:
        f.write('\n'.join(event_lines(record, ROBOTS, t0, t1, graph.what)) + '\n')
    files.append(events)
    path = os.path.join(out, 'summary.json')
    with open(path, 'w') as f:
        json.dump(summary, f, indent=2, sort_keys=True)
    files.append(path)
    return summary, files


def _say_result(summary: Dict[str, Any], shape: FleetShape) -> bool:
    """Print the server's and each robot's outcome; whether the run failed."""
    print('')
    print(f'server: over-committed {summary["over_commit_s"]:g} s; at most '
          f'{summary["most_serving_cpu"]:g} CPU serving there and '
          f'{summary["most_claimed_cpu"]:g} CPU claimed, of {shape.capacity_cpu:g}')
    failed = summary['over_commit_s'] > 0
    for robot, row in summary['robots'].items():
        moved = ', '.join(f'{m["from"]} -> {m["to"]} at {m["at_s"]:g} s'
                          for m in row['moves']) or 'none'
        if row['delta_violations'] is None:
            print(f'{robot}: its output was never heard; moves: {moved}')
            continue
        failed |= bool(row['delta_violations'])
        worst = max(row['connections'], key=lambda c: row['connections'][c]['longest_below_s'])
        print(f'{robot}: moves {moved}; below freq_min at most {row["longest_below_s"]:g} s '
              f'({worst}), {row["delta_violations"]} past Δ over '
              f'{len(row["connections"])} connection(s)')
    return failed


def run(args: argparse.Namespace) -> int:
    from .errors import HarnessError
    from .fleet_netns import FleetBed
    try:
        duration, steps, domains, out = _arguments(args)
    except ValueError as e:
        return _fail(str(e))
    run_dir = os.path.join(out, 'run')
    try:
        os.makedirs(run_dir, exist_ok=True)
    except OSError as e:
        return _fail(f'cannot create {out}: {e.strerror}')
    shape = FleetShape(hysteresis_s=HYSTERESIS_S, graph=args.graph or 'icar')
    graph = graph_of(shape)
    print('anyscale-manager demo --fleet: robot_a and robot_b (one deployment and ROS domain '
          f'each: {domains[ROBOTS[0]]}, {domains[ROBOTS[1]]}; graph {shape.graph}) share a '
          f'server of capacity {shape.capacity_cpu:g}; {graph.needs()}')
    print('schedule: ' + ', '.join(str(s) for s in steps) + f'; {duration:g} s', flush=True)
    code = 0
    bed = FleetBed(run_dir, ROBOTS, shape)
    t0 = t1 = time.monotonic()
    notes: List[str] = []
    try:
        t0, t1 = _play(bed, steps, domains, duration, args.refresh)
    except HarnessError as e:
        print(f'anyscale-manager demo --fleet: {e}', file=sys.stderr)
        code = 1
        t0, t1 = bed.record.t0, time.monotonic()
    except KeyboardInterrupt:
        print('\ninterrupted: tearing down', file=sys.stderr)
        code = 130
        t0, t1 = bed.record.t0, time.monotonic()
    finally:
        print('stopping both robots and tearing the namespaces down ...', flush=True)
        notes = bed.close()
    for note in notes:
        print(f'teardown: {note}', file=sys.stderr)
    summary, files = _write(bed.record, shape, steps, out, t0, t1, notes)
    failed = _say_result(summary, shape)
    print('written:')
    for f_path in files:
        print(f'  {f_path}')
    print(f'  process logs: {run_dir}')
    if failed or notes:
        code = code or 1
    return code


__all__ = ['FLEET_SCHEDULE', 'FleetStep', 'draw_fleet_timeline', 'over_commit_s',
           'parse_fleet_schedule', 'robot_summary', 'run']
