"""Property tests of the planners on random small deployments, against brute force."""

import itertools
import math

from hypothesis import HealthCheck, given, settings, strategies as st

from anyscale_manager.model.types import (Connection, Deployment, Launch, Link, Node, Scale,
                                          Settings)
from anyscale_manager.planning import check_layout, solve
from anyscale_manager.planning.instance import Instance

SOLVERS = ('greedy', 'paper-greedy', 'exact')


@st.composite
def deployments(draw, max_nodes=4, max_scales=3, max_span=4):
    """2-3 scales (the first the master), some links, 2-4 nodes of which some configurable
    with a narrow CPU range, residence, one possible coresidence pair, connections."""
    n_scales = draw(st.integers(2, max_scales))
    scales = tuple(Scale(name=f's{i}', role='master' if i == 0 else 'remote',
                         kind=draw(st.sampled_from(('robot', 'server'))),
                         capacity_cpu=float(draw(st.integers(20, 90))), cores=2,
                         clock_ghz=2.0, gain=1.0, host=f's{i}')
                   for i in range(n_scales))
    names = [s.name for s in scales]
    links = tuple(Link(name=f'{a}_{b}', ends=(a, b),
                       bandwidth_kbps=float(draw(st.integers(1, 12))), medium='wireless')
                  for i, a in enumerate(names) for b in names[i + 1:]
                  if draw(st.booleans()) or draw(st.booleans()))
    n_nodes = draw(st.integers(2, max_nodes))
    nodes = []
    for i in range(n_nodes):
        residence = ()
        if draw(st.integers(0, 3)) == 0:
            residence = tuple(sorted(draw(st.sets(st.sampled_from(names), min_size=1,
                                                  max_size=n_scales))))
        if draw(st.booleans()):
            low = draw(st.integers(3, 30))
            span = draw(st.integers(1, max_span))
            mid = low + draw(st.integers(0, span))
            cpu = tuple(sorted({float(low), float(mid), float(low + span)}))
            perf = tuple(sorted(draw(st.lists(st.integers(1, 100), min_size=len(cpu),
                                              max_size=len(cpu), unique=True))))
            form = 'poly2' if len(cpu) == 3 and draw(st.booleans()) else 'linear'
            s = Settings(parameter='p', values=tuple(float(10 * c) for c in cpu), cpu=cpu,
                         performance=tuple(float(p) for p in perf), form=form,
                         parameter_form='linear')
            nodes.append(Node(name=f'n{i}', launch=Launch(), cpu=cpu[0],
                              performance=float(perf[0]), residence=residence, settings=s,
                              weight=float(draw(st.integers(1, 3)))))
        else:
            nodes.append(Node(name=f'n{i}', launch=Launch(), cpu=float(draw(st.integers(1, 40))),
                              performance=float(draw(st.integers(0, 10))),
                              residence=residence))
    if draw(st.booleans()):
        a, b = nodes[0], nodes[1]
        nodes[0] = Node(**{**a.__dict__, 'coresidence': (b.name,)})
    connections = []
    for i, (p, q) in enumerate(itertools.permutations(range(n_nodes), 2)):
        if draw(st.integers(0, 2)) == 0:
            connections.append(Connection(name=f'c{i}', topic=f'/t{i}',
                                          publisher=f'n{p}', subscriber=f'n{q}',
                                          bandwidth_kbps=float(draw(st.integers(1, 6)))))
    return Deployment(name='random', source='<hypothesis>', scales=scales, links=links,
                      nodes=tuple(nodes), connections=tuple(connections))


def brute_force(d: Deployment, problem: int, mode: str):
    """The best objective over every placement and every option, judged by check_layout."""
    inst = Instance(d, problem, mode)
    best = None
    allowed = [d.allowed_scales(n.name) for n in d.nodes]
    for placement in itertools.product(*allowed):
        layout = dict(zip(d.node_names, placement))
        if any(v.kind != 'cpu' for v in check_layout(d, layout, None, {
                s.name: math.inf for s in d.scales})):
            continue      # placement-only constraints fail whatever the settings
        for choice in itertools.product(*(range(len(o)) for o in inst.options)):
            cpu = {n: inst.options[i][k].cpu
                   for i, (n, k) in enumerate(zip(d.node_names, choice))}
            if problem == 1:
                if check_layout(d, layout, cpu):
                    continue
                value = sum(inst.value(i, k) for i, k in enumerate(choice))
                best = value if best is None else max(best, value)
            else:
                grown = {s.name: sum(c for n, c in cpu.items() if layout[n] == s.name)
                         for s in d.scales if s.kind == 'server'}
                if check_layout(d, layout, cpu, grown):
                    continue
                value = sum(grown.values())
                best = value if best is None else min(best, value)
    return best


def check_plans(d: Deployment, problem: int, mode: str):
    plans = {s: solve(d, problem, s, settings=mode) for s in SOLVERS}
    for name, plan in plans.items():
        if plan.feasible:
            layout = {n: p.scale for n, p in plan.layout.items()}
            cpu = {n: p.cpu for n, p in plan.layout.items()}
            assert check_layout(d, layout, cpu, plan.server_capacity) == (), name
        else:
            assert plan.violations and not plan.layout
    exact = plans['exact']
    best = brute_force(d, problem, mode)
    if best is None:
        assert not any(p.feasible for p in plans.values())
        return
    assert exact.feasible and exact.optimal
    assert math.isclose(exact.objective, best, abs_tol=1e-6), (exact.objective, best)
    for name in ('greedy', 'paper-greedy'):
        plan = plans[name]
        if plan.feasible:
            if problem == 1:
                assert plan.objective <= exact.objective + 1e-6, name
            else:
                assert plan.objective >= exact.objective - 1e-6, name
    if plans['paper-greedy'].feasible:
        # Ours starts from the paper's layout and only ever improves it.
        assert plans['greedy'].feasible
        if problem == 1:
            assert plans['greedy'].objective >= plans['paper-greedy'].objective - 1e-6
        else:
            assert plans['greedy'].objective <= plans['paper-greedy'].objective + 1e-6


COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])


@settings(max_examples=60, **COMMON)
@given(deployments(), st.sampled_from((1, 2)))
def test_discrete_plans_are_feasible_and_exact_is_brute_force(d, problem):
    check_plans(d, problem, 'discrete')


@settings(max_examples=40, **COMMON)
@given(deployments(max_nodes=3, max_span=3), st.just(1))
def test_continuous_plans_are_feasible_and_exact_is_brute_force(d, problem):
    check_plans(d, problem, 'continuous')
