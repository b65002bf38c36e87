"""The chaos soak's pure parts: a seeded fault schedule, and the judgements of what was seen.

No ROS and no processes here: ``generate`` turns a seed into a list of faults, and the judges
read a run's ``Record`` (what the harness's observer heard) and the soak's own samples. The
runner that applies the faults to a real test-bed is ``testbed/soak.py``; the rules are in
docs/testbed.md (the chaos soak).
"""

import math
import random
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Set, Tuple

KINDS = ('cut', 'throttle', 'flap', 'kill_agent_laptop', 'kill_agent_robot', 'kill_decider',
         'stop_decider', 'kill_node', 'hostile', 'rival_decider', 'lose_agent_laptop',
         'hup_agent_laptop', 'hup_agent_robot', 'crash_loop')
# How often each kind is drawn in a long soak (relative).
WEIGHTS = {'cut': 3.0, 'throttle': 2.0, 'flap': 2.0, 'kill_agent_laptop': 1.5,
           'kill_agent_robot': 1.5, 'kill_decider': 1.5, 'stop_decider': 1.0, 'kill_node': 3.0,
           'hostile': 1.5, 'rival_decider': 1.0, 'lose_agent_laptop': 0.5,
           'hup_agent_laptop': 1.0, 'hup_agent_robot': 1.0, 'crash_loop': 1.0}
# The time each kind takes beyond its hold, reaction included, to space the schedule (s).
EXTRA_S = {'cut': 2.0, 'throttle': 3.0, 'flap': 2.0, 'kill_agent_laptop': 6.0,
           'kill_agent_robot': 6.0, 'kill_decider': 6.0, 'stop_decider': 3.0, 'kill_node': 6.0,
           'hostile': 3.0, 'rival_decider': 10.0, 'lose_agent_laptop': 8.0,
           'hup_agent_laptop': 5.0, 'hup_agent_robot': 5.0, 'crash_loop': 10.0}
# A laptop agent lost (SIGKILLed, no successor) stays away this long: twice the bound within
# which its nodes must be gone (the test-bed's adopt_grace_s 5 + fence_grace_s 0.5 + 1.5 s of
# slack for this machine), so that it is fencing that stops them, not a new agent.
LOSE_AGENT_S = 15.0
# A crash loop: the serving copy of one node is SIGKILLed this many times, each time once it
# serves again.
CRASH_LOOP_KILLS = 3
# A throttle below AR's 6 Mbit/s (AR must come back, AMCL may stay) and one everything fits.
THROTTLE_KBPS = (5000.0, 20000.0)


@dataclass(frozen=True)
class Fault:
    """One fault of the schedule, ``at_s`` seconds after the soak starts."""

    index: int
    at_s: float
    kind: str
    # cut, throttle, stop_decider: how long it lasts; hostile: how long it sends
    hold_s: float = 0.0
    rate_kbps: Optional[float] = None                # throttle
    flaps: Tuple[Tuple[float, float], ...] = ()     # flap: (down_s, up_s) per cycle
    node: str = ''                                   # kill_node, crash_loop
    copy: str = ''                                   # kill_node: active | standby
    seed: int = 0                                    # hostile: its own generator's seed

    @property
    def length_s(self) -> float:
        """Its expected length, reaction included (the schedule's spacing)."""
        base = sum(d + u for d, u in self.flaps) if self.kind == 'flap' else self.hold_s
        return base + EXTRA_S[self.kind]

    def describe(self) -> str:
        if self.kind == 'cut':
            return f'cut {self.hold_s:.1f} s'
        if self.kind == 'throttle':
            return f'throttle {self.rate_kbps:g} kbit/s for {self.hold_s:.1f} s'
        if self.kind == 'flap':
            return f'flap x{len(self.flaps)} (' + ', '.join(
                f'{d:.1f}/{u:.1f}' for d, u in self.flaps) + ' s down/up)'
        if self.kind == 'kill_node':
            return f'SIGKILL {self.node} ({self.copy} copy)'
        if self.kind == 'crash_loop':
            return f'crash loop: {self.node} SIGKILLed {CRASH_LOOP_KILLS} times'
        if self.kind == 'lose_agent_laptop':
            return f"SIGKILL the laptop's agent, back after {self.hold_s:g} s"
        if self.kind == 'hostile':
            return f'hostile publisher {self.hold_s:.1f} s'
        if self.kind == 'rival_decider':
            return 'third decider started'
        if self.kind == 'stop_decider':
            return f'SIGSTOP the leading decider for {self.hold_s:.1f} s'
        return {'kill_agent_laptop': "SIGKILL the laptop's agent",
                'kill_agent_robot': "SIGKILL the robot's agent",
                'hup_agent_laptop': "SIGHUP the laptop's agent (restart in place)",
                'hup_agent_robot': "SIGHUP the robot's agent (restart in place)",
                'kill_decider': 'SIGKILL the leading decider'}[self.kind]


def _draw(rng: random.Random, kind: str, index: int, at_s: float,
          standby_nodes: Sequence[str], plain_nodes: Sequence[str]) -> Fault:
    if kind == 'cut':
        return Fault(index, at_s, kind, hold_s=round(rng.uniform(3.0, 12.0), 1))
    if kind == 'throttle':
        return Fault(index, at_s, kind, hold_s=round(rng.uniform(8.0, 15.0), 1),
                     rate_kbps=rng.choice(THROTTLE_KBPS))
    if kind == 'flap':
        cycles = rng.randint(3, 6)
        flaps = tuple((round(rng.uniform(0.3, 1.5), 1), round(rng.uniform(0.5, 2.0), 1))
                      for _ in range(cycles))
        return Fault(index, at_s, kind, flaps=flaps)
    if kind == 'kill_node':
        copies = [(n, c) for n in standby_nodes for c in ('active', 'standby')]
        copies += [(n, 'active') for n in plain_nodes]
        node, copy = rng.choice(copies)
        return Fault(index, at_s, kind, node=node, copy=copy)
    if kind == 'hostile':
        return Fault(index, at_s, kind, hold_s=round(rng.uniform(4.0, 8.0), 1),
                     seed=rng.randrange(1 << 30))
    if kind == 'stop_decider':
        return Fault(index, at_s, kind, hold_s=round(rng.uniform(1.0, 4.0), 1))
    if kind == 'lose_agent_laptop':
        return Fault(index, at_s, kind, hold_s=LOSE_AGENT_S)
    if kind == 'crash_loop':
        return Fault(index, at_s, kind, node=rng.choice(list(standby_nodes) + list(plain_nodes)))
    return Fault(index, at_s, kind)


def generate(seed: int, duration_s: float, standby_nodes: Sequence[str] = ('amcl', 'ar'),
             plain_nodes: Sequence[str] = ('odometry', 'ekf', 'navigation'),
             kinds: Sequence[str] = KINDS, ensure_each: bool = False,
             gap_s: Tuple[float, float] = (6.0, 12.0), first_at_s: float = 10.0
             ) -> Tuple[Fault, ...]:
    """A schedule of faults that fits in ``duration_s``, the same for the same arguments.

    Faults never overlap: each starts ``gap_s`` (drawn) after the previous one's expected end.
    ``ensure_each``: the first faults are one of every kind, in a drawn order (a short soak
    then covers every kind); the rest are drawn by ``WEIGHTS``. A fault that would not end
    before ``duration_s`` is not added.
    """
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f'unknown fault kind {unknown[0]!r}; expected some of '
                         f'{", ".join(KINDS)}')
    if not kinds:
        raise ValueError('no fault kinds to draw from')
    if not duration_s > 0:
        raise ValueError(f'duration must be > 0 s, got {duration_s!r}')
    if not 0 <= gap_s[0] <= gap_s[1]:
        raise ValueError(f'gap_s must be (low, high) with 0 <= low <= high, got {gap_s!r}')
    if not standby_nodes and not plain_nodes and {'kill_node', 'crash_loop'} & set(kinds):
        raise ValueError('kill_node and crash_loop need nodes to kill')
    rng = random.Random(seed)
    first = list(kinds) if ensure_each else []
    rng.shuffle(first)
    weights = [WEIGHTS[k] for k in kinds]
    out: List[Fault] = []
    at = first_at_s
    while True:
        kind = first.pop(0) if first else rng.choices(list(kinds), weights)[0]
        fault = _draw(rng, kind, len(out), round(at, 1), standby_nodes, plain_nodes)
        if fault.at_s + fault.length_s > duration_s:
            break
        out.append(fault)
        at = fault.at_s + fault.length_s + rng.uniform(*gap_s)
    return tuple(out)


# --- statistics -------------------------------------------------------------------------------

def percentile(values: Iterable[float], q: float) -> Optional[float]:
    """Linear interpolation between closest ranks; None for no values."""
    xs = sorted(values)
    if not xs:
        return None
    k = (len(xs) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def reaction_summary(results: Sequence[Mapping]) -> Dict[str, Dict[str, object]]:
    """Per fault kind: how many, how many had something to react to, p50/p95/max of the
    reaction times (seconds)."""
    out: Dict[str, Dict[str, object]] = {}
    for r in results:
        row = out.setdefault(r['kind'], {'faults': 0, 'reactions': []})
        row['faults'] += 1
        if r.get('reaction_s') is not None:
            row['reactions'].append(r['reaction_s'])
    for row in out.values():
        xs = row.pop('reactions')
        row['timed'] = len(xs)
        row['p50_s'] = _round(percentile(xs, 0.5))
        row['p95_s'] = _round(percentile(xs, 0.95))
        row['max_s'] = _round(max(xs) if xs else None)
    return out


def _round(x: Optional[float], digits: int = 2) -> Optional[float]:
    return None if x is None else round(x, digits)


# --- two copies publishing at once ------------------------------------------------------------

def writer_streams(times: Sequence[float], seqs: Sequence[int],
                   forget_s: float = 10.0) -> List[List[float]]:
    """Arrival times of one topic split by writer, from the publication sequence numbers.

    Every DDS writer numbers its messages 1, 2, 3, ...: a message continues the stream whose
    last number is the largest below its own; one that continues none starts a new stream (a
    writer that started later). A stream unheard for ``forget_s`` is closed. Messages without a
    number (-1) are left out."""
    open_: List[List[float]] = []      # [last seq, last time, index into out]
    out: List[List[float]] = []
    for t, seq in zip(times, seqs):
        if seq is None or seq < 0:
            continue
        open_ = [s for s in open_ if t - s[1] <= forget_s]
        before = [s for s in open_ if s[0] < seq]
        if before:
            s = max(before, key=lambda s: s[0])
            s[0], s[1] = seq, t
            out[int(s[2])].append(t)
        else:
            open_.append([seq, t, len(out)])
            out.append([t])
    return out


def active_spans(times: Sequence[float], gap_s: float) -> List[Tuple[float, float]]:
    """Spans of a stream's arrivals: consecutive ones at most ``gap_s`` apart are one span."""
    spans: List[Tuple[float, float]] = []
    for t in times:
        if spans and t - spans[-1][1] <= gap_s:
            spans[-1] = (spans[-1][0], t)
        else:
            spans.append((t, t))
    return spans


def concurrent_spans(streams: Sequence[Sequence[Tuple[float, float]]]
                     ) -> List[Tuple[float, float]]:
    """Where two or more streams are active at once (each stream: its active spans)."""
    edges: List[Tuple[float, int]] = []
    for spans in streams:
        for a, b in spans:
            if b > a:
                edges += [(a, 1), (b, -1)]
    edges.sort(key=lambda e: (e[0], e[1]))
    out: List[Tuple[float, float]] = []
    depth, since = 0, 0.0
    for t, step in edges:
        before = depth
        depth += step
        if before < 2 <= depth:
            since = t
        elif before >= 2 > depth:
            out.append((since, t))
    return out


class _Span:
    """A span of time with ``start`` and ``end`` (fields of the dataclass that uses it)."""

    start: float
    end: float

    @property
    def length_s(self) -> float:
        return self.end - self.start


@dataclass
class Duplicate(_Span):
    node: str
    topic: str
    start: float
    end: float


def duplicates(arrivals: Mapping[str, Sequence[float]], seqs: Mapping[str, Sequence[int]],
               publishers: Mapping[str, str], start: float, end: float, bound_s: float,
               gap_s: float = 1.0) -> Tuple[List[Duplicate], Dict[str, float]]:
    """Spans in [start, end] where two writers of a node's output topic were heard at once
    for longer than ``bound_s``, and the longest such overlap per node (for the report).
    ``publishers``: topic -> the node that publishes it."""
    found: List[Duplicate] = []
    longest: Dict[str, float] = {}
    for topic, node in sorted(publishers.items()):
        times, numbers = arrivals.get(topic, []), seqs.get(topic, [])
        lo, hi = bisect_left(times, start), bisect_right(times, end)
        streams = writer_streams(times[lo:hi], numbers[lo:hi])
        both = concurrent_spans([active_spans(s, gap_s) for s in streams])
        for a, b in both:
            longest[node] = max(longest.get(node, 0.0), round(b - a, 2))
            if b - a > bound_s:
                found.append(Duplicate(node, topic, a, b))
    return found, longest


# --- a node that runs nowhere -----------------------------------------------------------------

@dataclass
class Nowhere(_Span):
    node: str
    start: float
    end: float
    backoff_s: float = 0.0      # of which an agent reported the node waiting out its backoff


def _serving(report) -> bool:
    """A node report that says the node serves: running (and, for a lifecycle copy, active)."""
    if report.state != 'running':
        return False
    return report.ready if report.lifecycle is not None else True


class _Sweep:
    """The last item at or before t of a time-sorted history, for increasing t."""

    def __init__(self, history: Sequence[Tuple[float, object]]):
        self.history = history
        self.i = 0

    def at(self, t: float) -> Optional[Tuple[float, object]]:
        h = self.history
        while self.i < len(h) and h[self.i][0] <= t:
            self.i += 1
        return h[self.i - 1] if self.i else None


def nowhere(nodes: Sequence[str], histories: Sequence[Sequence[Tuple[float, object]]],
            outputs: Mapping[str, str], arrivals: Mapping[str, Sequence[float]],
            processes: Sequence[Tuple[float, Mapping[str, int]]], start: float, end: float,
            max_age_s: float, bound_s: float, heard_s: float = 1.0, step_s: float = 0.25,
            process_nodes: Iterable[str] = (),
            layouts: Sequence[Tuple[float, Mapping[str, str]]] = (),
            backoff_in_bound_s: float = 0.0) -> List[Nowhere]:
    """Spans longer than ``bound_s`` in [start, end] in which a node ran nowhere.

    A node runs at t when any agent's report (``histories``: (time, AgentState) of one agent as
    one observer heard it, at most ``max_age_s`` old) says it serves, or its output topic
    (``outputs``: node -> topic) was heard within ``heard_s``, or, for ``process_nodes``
    (nodes without standby copies: a live process serves), the harness's process sample
    nearest before t counted one (``processes``: (time, node -> live processes)).

    The time the agent of the scale the layout places the node on (``layouts``: (time,
    assignments), the deciders' own; without them any agent) reports it, fresh, in its crash
    backoff (``restart_backoff_s``, doubling for a node that crashes again soon after a
    restart: the configured restart policy, not a failure to place it) does not count towards
    ``bound_s``, beyond the ``backoff_in_bound_s`` that ``bound_s`` already allows for; it is
    given as ``backoff_s``."""
    sweeps = [_Sweep(h) for h in histories]
    psweep = _Sweep(processes)
    lsweep = _Sweep(layouts)
    pnodes = set(process_nodes)
    since: Dict[str, Optional[float]] = {n: None for n in nodes}
    waited: Dict[str, float] = {n: 0.0 for n in nodes}
    out: List[Nowhere] = []

    def excused(n: str) -> float:
        return max(0.0, waited[n] - backoff_in_bound_s)
    t = start
    while t <= end + 1e-9:
        serving: Set[str] = set()
        backing_off: Set[str] = set()
        placed = lsweep.at(t)
        for s in sweeps:
            last = s.at(t)
            if last is not None and t - last[0] <= max_age_s:
                serving |= {n for n, r in last[1].nodes.items() if _serving(r)}
                backing_off |= {n for n, r in last[1].nodes.items() if r.state == 'backoff'
                                and (placed is None or placed[1].get(n) == last[1].scale)}
        sample = psweep.at(t)
        for n in nodes:
            runs = n in serving
            if not runs and n in outputs:
                times = arrivals.get(outputs[n], [])
                i = bisect_right(times, t)
                runs = bool(i) and t - times[i - 1] <= heard_s
            if not runs and n in pnodes and sample is not None and t - sample[0] <= 5.0:
                runs = sample[1].get(n, 0) > 0
            if runs:
                if since[n] is not None and t - since[n] - excused(n) > bound_s:
                    out.append(Nowhere(n, since[n], t, waited[n]))
                since[n] = None
            else:
                if since[n] is None:
                    since[n], waited[n] = t, 0.0
                if n in backing_off and t < end:
                    waited[n] += min(step_s, end - t)
        t += step_s
    for n, s in since.items():
        if s is not None and end - s - excused(n) > bound_s:
            out.append(Nowhere(n, s, end, waited[n]))
    return sorted(out, key=lambda x: x.start)


# --- Δ: which violations are the system's fault -----------------------------------------------

def downstream(connections: Sequence[Tuple[str, str]], node: str) -> Set[str]:
    """The node and every node its outputs reach (``connections``: (publisher, subscriber))."""
    seen, todo = {node}, [node]
    while todo:
        n = todo.pop()
        for pub, sub in connections:
            if pub == n and sub not in seen:
                seen.add(sub)
                todo.append(sub)
    return seen


@dataclass(frozen=True)
class Excuse:
    """A span in which the named connections' Δ is not judged, and why."""

    start: float
    end: float
    connections: frozenset
    why: str


def kill_excuse(connections: Sequence[Tuple[str, str, str]], node: str, killed: float,
                back: float, margin_s: float, why: str) -> Excuse:
    """A serving copy killed at ``killed`` and serving again at ``back``: the connections it
    feeds (itself or anything downstream publishing) and its own inputs are not judged until
    ``back`` + ``margin_s`` (a rate window and the longest Δ: the time the rate takes to be
    read back above freq_min). ``connections``: (name, publisher, subscriber)."""
    hit = downstream([(p, s) for _, p, s in connections], node)
    names = frozenset(name for name, p, s in connections if p in hit or s == node)
    return Excuse(killed, back + margin_s, names, why)


def excused(connection: str, expired_at: float, excuses: Sequence[Excuse]) -> Optional[Excuse]:
    """The excuse covering a violation of ``connection`` whose Δ ran out at ``expired_at``."""
    for e in excuses:
        if connection in e.connections and e.start <= expired_at <= e.end:
            return e
    return None


# --- after the run ----------------------------------------------------------------------------

TRACEBACK = 'Traceback (most recent call last)'


def tracebacks(texts: Mapping[str, str], context: int = 6) -> List[Dict[str, str]]:
    """Every Python traceback in the given log texts (file -> text), with its last lines."""
    out = []
    for path, text in sorted(texts.items()):
        lines = text.splitlines()
        for i, line in enumerate(lines):
            if TRACEBACK in line:
                tail = [x for x in lines[i + 1:i + 1 + 40]]
                # The exception line: the first one after the frames that is not indented.
                end = next((j for j, x in enumerate(tail) if x and not x.startswith(' ')),
                           len(tail) - 1)
                excerpt = tail[max(0, end - context + 1):end + 1]
                out.append({'file': path, 'line': i + 1, 'text': '\n'.join(excerpt)})
    return out


@dataclass
class Resources:
    """CPU and RSS of the project's own processes, sampled by the runner."""

    samples: List[Tuple[float, str, int, float, int]] = field(default_factory=list)

    def add(self, t: float, name: str, pid: int, cpu_s: float, rss: int) -> None:
        self.samples.append((t, name, pid, cpu_s, rss))

    def window(self, name: str, t0: float, t1: float) -> Optional[Dict[str, object]]:
        """CPU (% of one core) and RSS (MiB, the last sample) of ``name`` in [t0, t1], over the
        longest stretch of one process in that window."""
        rows = [s for s in self.samples if s[1] == name and t0 <= s[0] <= t1]
        by_pid: Dict[int, List[Tuple[float, str, int, float, int]]] = {}
        for r in rows:
            by_pid.setdefault(r[2], []).append(r)
        best = max(by_pid.values(), key=lambda rs: rs[-1][0] - rs[0][0], default=None)
        if not best or best[-1][0] <= best[0][0]:
            return None
        span = best[-1][0] - best[0][0]
        return {'pid': best[0][2], 'over_s': round(span, 1),
                'cpu_percent': round(100.0 * (best[-1][3] - best[0][3]) / span, 2),
                'rss_mib': round(best[-1][4] / 2 ** 20, 1)}

    def growth(self, name: str, min_life_s: float, skip_s: float = 60.0
               ) -> Optional[Dict[str, object]]:
        """RSS growth of the longest-lived process of ``name`` (if it lived ``min_life_s``):
        from ``skip_s`` after its first sample (start-up done) to its last sample."""
        by_pid: Dict[int, List[Tuple[float, str, int, float, int]]] = {}
        for r in self.samples:
            if r[1] == name:
                by_pid.setdefault(r[2], []).append(r)
        best = max(by_pid.values(), key=lambda rs: rs[-1][0] - rs[0][0], default=None)
        if not best or best[-1][0] - best[0][0] < min_life_s:
            return None
        # A soak shorter than its start-up has nothing after it to compare.
        first = next((r for r in best if r[0] >= best[0][0] + skip_s), None)
        if first is None:
            return None
        last = best[-1]
        return {'pid': last[2], 'from_s': round(first[0] - best[0][0], 1),
                'over_s': round(last[0] - first[0], 1),
                'rss_from_mib': round(first[4] / 2 ** 20, 1),
                'rss_to_mib': round(last[4] / 2 ** 20, 1),
                'growth_mib': round((last[4] - first[4]) / 2 ** 20, 2)}


def finite_or_none(x: Optional[float]) -> Optional[float]:
    return x if x is not None and math.isfinite(x) else None


__all__ = ['Duplicate', 'EXTRA_S', 'Excuse', 'Fault', 'KINDS', 'Nowhere', 'Resources',
           'THROTTLE_KBPS', 'TRACEBACK', 'WEIGHTS', 'active_spans', 'concurrent_spans',
           'downstream', 'duplicates', 'excused', 'generate', 'kill_excuse', 'nowhere',
           'percentile', 'reaction_summary', 'tracebacks', 'writer_streams']
