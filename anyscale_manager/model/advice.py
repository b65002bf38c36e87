"""Warnings about a valid deployment: settings that work, but not as a user would expect.

Pure: a deployment in, one line per warning out, each naming what, where, and what to do.
"""

from typing import Dict, List

from . import types as t

# A plain rclpy node's cold move on an unloaded machine, layout -> first message at a consumer
# on another scale (bench/bench_agent.py, p95); a real node's own start (loading a map, a model)
# comes on top of it.
COLD_MOVE_S = 0.8


def cold_move_budget_s(d: t.Deployment) -> float:
    """How long a connection of a node moved cold stays unserved after a link cut, at best: the
    cut is seen after heartbeat_misses_down beats, then the node starts on its new scale."""
    m = d.monitoring
    return m.heartbeat_misses_down / m.heartbeat_rate_hz + COLD_MOVE_S


UNSIGNED = ('layouts are not signed: anyone on the ROS domain can move or stop the managed '
            'nodes. Write a key with anyscale-manager keygen PATH, copy it to every scale '
            '(mode 0600) and set security.key_file (docs/decider.md, security)')


def _machine_of(host: str) -> str:
    """A scale's host as a machine: every loopback name is this machine."""
    h = host.strip().lower()
    if h in ('localhost', 'ip6-localhost', 'ip6-loopback', '::1', '0:0:0:0:0:0:0:1') \
            or h.startswith('127.') or h.endswith('.localhost'):
        return 'localhost'
    return h


def single_machine(d: t.Deployment) -> str:
    """What the file says when two or more of its scales name one host (``localhost``, the
    default, for all of them: how every user starts), else ''."""
    by_machine: Dict[str, List[str]] = {}
    for s in d.scales:
        by_machine.setdefault(_machine_of(s.host), []).append(s.name)
    groups = [(machine, scales) for machine, scales in by_machine.items() if len(scales) > 1]
    if not groups:
        return ''
    where = '; '.join(f'{", ".join(scales)} on {machine}' for machine, scales in groups)
    return (f'single machine: scales {where} (scales.<s>.host). When their agents run on one '
            'machine (they tell it by its boot id, whatever the file says), the decider says '
            "single-machine mode: each scale's CPU is its own agent's processes (the agent, its "
            "monitors, its nodes), not the machine's, unless a cgroup quota confines the scale, "
            'so a load one scale causes never moves a node back from the other; and the link '
            'between them is loopback, whose measured bandwidth (memory copies) is capped at '
            "the link's bandwidth_kbps (docs/monitoring.md)")


def warnings(d: t.Deployment) -> List[str]:
    out: List[str] = []
    if not d.security.key_file:
        out.append(f'{d.source}: security.key_file is not set: {UNSIGNED}')
    budget = cold_move_budget_s(d)
    for name in d.migratable_nodes:
        if d.standby_scales(name):
            continue
        short = [c for c in d.connections_of(name)
                 if c.tolerance_s is not None and not c.pins_both_ends
                 and c.tolerance_s < budget]
        if not short:
            continue
        names = ', '.join(f'{c.name} ({c.tolerance_s:g} s)' for c in short)
        m = d.monitoring
        out.append(
            f'{d.source}: nodes.{name}: a cold move cannot meet the tolerance_s of {names}: '
            f'after a link cut it is unserved for at least {budget:.2f} s (the cut seen after '
            f'{m.heartbeat_misses_down} heartbeats at {m.heartbeat_rate_hz:g} Hz, then a '
            f"plain rclpy node starts in about {COLD_MOVE_S:g} s, plus the node's own "
            f'start). Make it a lifecycle node with standby: true (lifecycle: true; see '
            f'docs/lifecycle.md), so a move is an activation, or give each of them a '
            f'tolerance_s of at least {budget:.1f} s')
    out += [f'{d.source}: {line}' for line in other_robots(d)]
    return out


def other_robots(d: t.Deployment) -> List[str]:
    """What the file says when a remote scale is a robot: its master decides for that robot
    too, and a cut of the master's link leaves it undecided. A fleet gives each robot its own
    deployment and shares the servers (scales.<s>.shared)."""
    robots = [s.name for s in d.remote_scales if s.kind == t.ROBOT]
    if not robots:
        return []
    return [f'scales {", ".join(robots)}: a remote robot: the decider on {d.master.name} '
            f"decides where its nodes run, and a cut of {d.master.name}'s link leaves it "
            'undecided. For a fleet, give each robot a deployment of its own (its own master, '
            'decider, ROS domain) naming the servers it uses with shared: true; their agents '
            "then share each server's capacity by claims (docs/agent.md, a shared scale)"]
