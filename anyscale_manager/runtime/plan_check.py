"""Plan against reality: the IROS 2016 paper's validation (Eq. 10) at run time.

For each node the plan (or the deployment's nominal values) gives an expected output frequency
and an expected performance. At run time the node's measured output frequency (the rate its
outgoing connections are received at) gives its measured performance

    P_measured = P_expected x F_measured / F_expected                      (Eq. 10)

and a relative deviation (P_measured - P_expected) / P_expected = F_measured / F_expected - 1.
The overall deviation is that of the summed performance (each node weighted by its expected
performance; a plain mean when no node has one). A scale whose CPU reaches
``overload_fraction`` of its capacity is reported overloaded: its nodes cannot get the CPU the
plan gave them, so the plan does not hold there (the paper's RQ2 and RQ3).
"""

from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

from ..model.types import DeciderSettings, Deployment, Node, frozen_map
from .constraints import is_fresh
from .observations import Observations


@dataclass(frozen=True)
class NodeExpectation:
    node: str
    expected_hz: float
    expected_performance: float
    outputs: Tuple[str, ...]          # connections whose received rate measures its output
    source: str                       # where expected_hz comes from


@dataclass(frozen=True)
class NodeCheck:
    node: str
    expected_hz: float
    measured_hz: float
    expected_performance: float
    measured_performance: float
    deviation: float                  # relative: F_measured / F_expected - 1


@dataclass(frozen=True)
class PlanCheckReport:
    now: float
    nodes: Mapping[str, NodeCheck] = field(default_factory=frozen_map)
    overall_deviation: float = 0.0
    overloaded: Mapping[str, float] = field(default_factory=frozen_map)  # scale -> CPU fraction
    warnings: Tuple[str, ...] = ()


def _interpolate(xs: Tuple[float, ...], ys: Tuple[float, ...], x: float) -> float:
    pairs = sorted(zip(xs, ys))
    if x <= pairs[0][0]:
        return pairs[0][1]
    for (x0, y0), (x1, y1) in zip(pairs, pairs[1:]):
        if x <= x1:
            return y0 if x1 == x0 else y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return pairs[-1][1]


def _expected_hz(deployment: Deployment, node: Node, cpu: Optional[float],
                 parameter_value: Optional[float] = None) -> Tuple[Optional[float], str]:
    st = node.settings
    at = node.cpu if cpu is None else cpu
    if st is not None and st.frequency_hz and len(st.frequency_hz) == len(st.cpu):
        return _interpolate(st.cpu, st.frequency_hz, at), 'settings'
    if st is not None and st.parameter.endswith('frequency_hz') and st.values:
        # the configurable parameter is the output rate itself
        if parameter_value is not None:
            return float(parameter_value), 'parameter'
        if len(st.values) == len(st.cpu):
            return _interpolate(st.cpu, st.values, at), 'parameter'
    outs = [c for c in deployment.connections if c.publisher == node.name]
    rates = [rate for rate in (c.freq_opt_hz or c.freq_min_hz for c in outs) if rate]
    if rates:
        return max(rates), 'freq_opt'
    return None, ''


def expectations(deployment: Deployment, placements: Optional[Mapping[str, Any]] = None
                 ) -> Dict[str, NodeExpectation]:
    """Expected output frequency and performance per node that has measurable outputs.

    ``placements``: node -> a planner placement (with ``cpu`` and ``performance``); without
    it, the nodes' nominal CPU and performance. The expected frequency is read off the node's
    profiled ``frequency_hz`` samples at the planned CPU when it has them, else it is the
    design rate (freq_opt, else freq_min) of its outgoing connections. A node whose configurable
    parameter is itself a rate (``*frequency_hz``) is expected at the planned value.
    """
    out = {}
    for node in deployment.nodes:
        outputs = tuple(c.name for c in deployment.connections if c.publisher == node.name)
        if not outputs:
            continue
        placement = (placements or {}).get(node.name)
        cpu = getattr(placement, 'cpu', None)
        perf = getattr(placement, 'performance', None)
        hz, source = _expected_hz(deployment, node, cpu,
                                  getattr(placement, 'parameter_value', None))
        if hz is None or hz <= 0:
            continue
        out[node.name] = NodeExpectation(
            node=node.name, expected_hz=hz,
            expected_performance=float(node.performance if perf is None else perf),
            outputs=outputs, source=source)
    return out


def check_plan(deployment: Deployment, expected: Mapping[str, NodeExpectation],
               obs: Observations, settings: Optional[DeciderSettings] = None,
               overload_fraction: float = 0.95) -> PlanCheckReport:
    """Eq. 10 per node from the fresh connection readings, and overloaded scales."""
    settings = settings or deployment.decider
    now = obs.now
    checks: Dict[str, NodeCheck] = {}
    for name, e in expected.items():
        if name not in obs.running:
            continue
        rates = [obs.connections[c].rate_hz for c in e.outputs
                 if c in obs.connections and is_fresh(obs.connections[c].stamp, now, settings)]
        if not rates:
            continue
        measured_hz = sum(rates) / len(rates)
        ratio = measured_hz / e.expected_hz
        checks[name] = NodeCheck(node=name, expected_hz=e.expected_hz, measured_hz=measured_hz,
                                 expected_performance=e.expected_performance,
                                 measured_performance=e.expected_performance * ratio,
                                 deviation=ratio - 1.0)
    total_expected = sum(c.expected_performance for c in checks.values())
    if total_expected > 0:
        overall = (sum(c.measured_performance for c in checks.values()) - total_expected) \
            / total_expected
    elif checks:
        overall = sum(c.deviation for c in checks.values()) / len(checks)
    else:
        overall = 0.0
    overloaded: Dict[str, float] = {}
    warnings: List[str] = []
    for s in deployment.scales:
        so = obs.scales.get(s.name)
        if so is None or not is_fresh(so.stamp, now, settings) or s.capacity_cpu <= 0:
            continue
        fraction = so.cpu_total / s.capacity_cpu
        if fraction >= overload_fraction:
            overloaded[s.name] = fraction
            hosted = sorted(n for n, where in obs.running.items() if where == s.name)
            short = [n for n in hosted if n in checks and checks[n].deviation < 0]
            warnings.append(
                f'scale {s.name} at {fraction:.0%} of its CPU capacity: its nodes cannot get '
                f'their planned CPU, the plan does not hold there'
                + (f' ({", ".join(short)} below their expected rate)' if short else ''))
    return PlanCheckReport(now=now, nodes=frozen_map(checks), overall_deviation=overall,
                           overloaded=frozen_map(overloaded), warnings=tuple(warnings))
