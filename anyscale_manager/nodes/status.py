"""``anyscale-manager status``: a live table of a running deployment, read from its topics.

Scales' CPU, the link's state and bandwidth, each connection's rate against its freq_min with
its Δ timer (as the probe reports it), where each node should run and where it runs, the layout
generation and the objective. ``--once`` prints one snapshot and exits.
"""

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

from .. import protocol as p
from ..model.loader import DeploymentError, load_deployment
from ..model.types import Deployment


@dataclass
class StatusBook:
    """The latest message of each kind, with the local time it arrived (pure, no ROS)."""

    deployment: Deployment
    layout: Optional[Tuple[p.Layout, float]] = None
    objective: Optional[Tuple[p.Objective, float]] = None
    agents: Dict[str, Tuple[p.AgentState, float]] = field(default_factory=dict)
    scales: Dict[str, Tuple[p.ScaleStatus, float]] = field(default_factory=dict)
    links: Dict[str, Tuple[p.LinkStatus, float]] = field(default_factory=dict)
    readings: Dict[Tuple[str, str], Tuple[p.ConnectionReading, float]] = \
        field(default_factory=dict)
    events: List[p.Event] = field(default_factory=list)
    ignored: int = 0

    def take(self, topic: str, text: str, now: float) -> None:
        """Decode one message of ``topic``; malformed ones are counted and dropped."""
        try:
            if topic == p.TOPIC_LAYOUT:
                self.layout = (p.Layout.from_json(text, topic), now)
            elif topic == p.TOPIC_OBJECTIVE:
                self.objective = (p.Objective.from_json(text, topic), now)
            elif topic == p.TOPIC_AGENT_STATE:
                m = p.AgentState.from_json(text, topic)
                self.agents[m.scale] = (m, now)
            elif topic == p.TOPIC_SCALE_STATUS:
                m = p.ScaleStatus.from_json(text, topic)
                self.scales[m.scale] = (m, now)
            elif topic == p.TOPIC_LINK_STATUS:
                m = p.LinkStatus.from_json(text, topic)
                self.links[m.remote] = (m, now)
            elif topic == p.TOPIC_CONNECTION_STATUS:
                m = p.ConnectionStatus.from_json(text, topic)
                for name, r in m.connections.items():
                    self.readings[(m.scale, name)] = (r, now)
            elif topic == p.TOPIC_EVENTS:
                self.events = (self.events + [p.Event.from_json(text, topic)])[-8:]
        except p.ProtocolError:
            self.ignored += 1

    @property
    def heard_anything(self) -> bool:
        return bool(self.layout or self.agents or self.scales or self.links or self.readings)

    def complete(self) -> bool:
        return self.layout is not None and all(s in self.agents
                                               for s in self.deployment.scale_names)


def _age(now: float, then: float) -> str:
    return f'{now - then:.1f} s ago'


def _table(rows: List[List[str]]) -> List[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ['  '.join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def render(book: StatusBook, now: float) -> str:
    """The status table as text."""
    d = book.deployment
    max_age = d.decider.observation_max_age_s
    lines = []
    head = f'deployment {d.name}'
    if book.layout:
        head += f'   layout generation {book.layout[0].generation} ({_age(now, book.layout[1])})'
        if book.layout[0].decider is not None:
            head += f' of decider {book.layout[0].decider.describe()}'
    else:
        head += '   no layout heard (is the decider running?)'
    if book.objective:
        o = book.objective[0]
        head += f'   perf_map {o.perf_map:.1f}, integral {o.integral:.0f} over {o.elapsed_s:.0f} s'
    lines += [head, '']

    rows = [['SCALE', 'ROLE', 'CPU USED / CAPACITY', 'AGENT']]
    for s in d.scales:
        cpu = '-'
        if s.name in book.scales:
            st, at = book.scales[s.name]
            stale = ' (stale)' if now - at > max_age else ''
            cpu = f'{st.cpu_total:.0f} / {s.capacity_cpu:.0f} ' \
                  f'({st.cpu_total / s.capacity_cpu:.0%}){stale}'
        agent = 'not heard'
        if s.name in book.agents:
            a, at = book.agents[s.name]
            silent = now - at > d.decider.agent_timeout_s
            agent = f'{"SILENT" if silent else "ok"}, generation {a.generation}, {_age(now, at)}'
            if a.decider:
                agent += f', follows {a.decider}'
        rows.append([s.name, s.role, cpu, agent])
    lines += _table(rows) + ['']

    rows = [['LINK', 'ENDS', 'STATE', 'RTT', 'AVAILABLE / NOMINAL kbit/s', 'USED kbit/s']]
    master = d.master.name
    for link in d.links:
        remote = link.other(master) if master in link.ends else None
        state, rtt, avail, used = 'not monitored', '-', f'- / {link.bandwidth_kbps:.0f}', '-'
        if remote is not None and remote in book.links:
            ls, at = book.links[remote]
            state = 'SILENT' if now - at > max_age else (
                ('up, CONGESTED' if ls.congested else 'up') if ls.up else 'DOWN')
            rtt = '-' if ls.rtt_ms is None else f'{ls.rtt_ms:.1f} ms'
            measured = ls.bandwidth_available_kbps
            avail = ('nominal' if measured is None else f'{measured:.0f}') + \
                f' / {link.bandwidth_kbps:.0f}'
            used = f'{ls.bandwidth_used_kbps:.0f}'
        elif remote is not None:
            state = 'not heard'
        rows.append([link.name, '-'.join(link.ends), state, rtt, avail, used])
    lines += _table(rows) + ['']

    running: Dict[str, Tuple[str, str]] = {}
    standby: Dict[str, list] = {}
    for scale, (a, _) in book.agents.items():
        for n, r in a.nodes.items():
            if r.state == 'standby':
                standby.setdefault(n, []).append(scale if r.lifecycle == 'inactive'
                                                 else f'{scale} ({r.lifecycle})')
            elif n not in running or r.state == 'running' or running[n][1] == 'stopped':
                running[n] = (scale, r.state)
    rows = [['CONNECTION', 'RATE Hz', 'MIN Hz', 'BELOW s / Δ s', 'STATUS']]
    for c in d.connections:
        if not c.monitored:
            continue
        home = running.get(c.subscriber, (None, ''))[0]
        found = book.readings.get((home, c.name)) if home else None
        if found is None:
            found = max((v for (s, n), v in book.readings.items() if n == c.name),
                        key=lambda v: v[1], default=None)
        if found is None:
            rows.append([c.name, '-', f'{c.freq_min_hz:g}', f'- / {c.tolerance_s:g}',
                         'no reading'])
            continue
        r, at = found
        if now - at > max_age:
            status = 'STALE (counts as 0 Hz)'
        elif r.rate_hz >= c.freq_min_hz:
            status = 'ok'
        elif r.below_for_s > c.tolerance_s:
            status = 'VIOLATED (past Δ)'
        else:
            status = 'below, within Δ'
        rows.append([c.name, f'{r.rate_hz:.1f}', f'{c.freq_min_hz:g}',
                     f'{r.below_for_s:.1f} / {c.tolerance_s:g}', status])
    lines += _table(rows) + ['']

    wanted = book.layout[0].assignments if book.layout else {}
    rows = [['NODE', 'LAYOUT', 'RUNNING ON', 'STATE', 'STANDBY ON']]
    for n in d.nodes:
        if not n.managed:
            continue
        where, state = running.get(n.name, ('-', 'not reported'))
        mark = '' if wanted.get(n.name, where) == where else '  (moving)'
        rows.append([n.name, wanted.get(n.name, '-'), where + mark, state,
                     ', '.join(sorted(standby.get(n.name, ()))) or '-'])
    lines += _table(rows)
    if book.events:
        lines += ['', 'RECENT EVENTS']
        lines += [f'  {e.kind} {e.node} {e.from_scale}->{e.to_scale}: {e.reason}'[:160]
                  if e.node else f'  {e.kind}: {e.reason}'[:160] for e in book.events]
    if book.ignored:
        lines += ['', f'{book.ignored} malformed message(s) ignored']
    return '\n'.join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--params-file', required=True, metavar='DEPLOYMENT.yaml',
                        help='the deployment file the decider and agents were started with')
    parser.add_argument('--once', action='store_true',
                        help='print one snapshot and exit')
    parser.add_argument('--wait', type=float, default=3.0, metavar='S',
                        help='with --once: listen at most this long before printing '
                             '(default 3; stops early once the layout and every agent '
                             'have been heard)')
    parser.add_argument('--interval', type=float, default=1.0, metavar='S',
                        help='refresh period of the live table (default 1)')


def run(args: argparse.Namespace) -> int:
    try:
        deployment = load_deployment(args.params_file)
    except DeploymentError as e:
        print(f'anyscale-manager status: {e}', file=sys.stderr)
        return 2
    if not (args.wait > 0 and args.interval > 0):
        print('anyscale-manager status: --wait and --interval must be > 0', file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    from .qos import LATCHED_READER as latched, MONITOR_READER as sensor
    book = StatusBook(deployment)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(f'anyscale_status_{os.getpid()}', context=ctx)
    topics = {p.TOPIC_LAYOUT: latched, p.TOPIC_AGENT_STATE: latched,
              p.TOPIC_EVENTS: 50, p.TOPIC_OBJECTIVE: 10, p.TOPIC_SCALE_STATUS: sensor,
              p.TOPIC_LINK_STATUS: sensor, p.TOPIC_CONNECTION_STATUS: sensor}
    for topic, qos in topics.items():
        node.create_subscription(
            String, topic, lambda m, t=topic: book.take(t, m.data, time.monotonic()), qos)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        if args.once:
            deadline = time.monotonic() + args.wait
            while time.monotonic() < deadline and not book.complete():
                executor.spin_once(timeout_sec=0.05)
            # a little more so the monitors' periodic readings arrive too
            extra = time.monotonic() + min(1.0, args.wait)
            while time.monotonic() < extra:
                executor.spin_once(timeout_sec=0.05)
            print(render(book, time.monotonic()))
            if not book.heard_anything:
                print(f'nothing heard within {args.wait:g} s on ROS_DOMAIN_ID='
                      f'{os.environ.get("ROS_DOMAIN_ID", "0")}', file=sys.stderr)
                return 1
            return 0
        tty = sys.stdout.isatty()
        while True:
            until = time.monotonic() + args.interval
            while time.monotonic() < until:
                executor.spin_once(timeout_sec=0.05)
            text = render(book, time.monotonic())
            print(('\x1b[H\x1b[2J' if tty else '') + text + ('' if tty else '\n'),
                  flush=True)
    except KeyboardInterrupt:
        return 0
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
