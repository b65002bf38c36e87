"""Offline planners: regression, feasibility checker, solvers and `anyscale-manager plan`."""

import json
import math
import os
import subprocess
import sys
from dataclasses import replace

import pytest

from anyscale_manager.cli import main as cli_main
from anyscale_manager.model import load_deployment
from anyscale_manager.model.capacity import usable_cpu
from anyscale_manager.model.types import (Connection, DeciderSettings, Deployment, Launch,
                                          Link, Node, Scale, Settings)
from anyscale_manager.planning import Instance, Regression, check_layout, fit_profile, solve
from anyscale_manager.planning.generate import generate_deployment

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
IROS = os.path.join(REPO, 'config', 'iros2016')
TESTBED = os.path.join(REPO, 'config', 'icar2015_testbed.yaml')


def instance(i: int) -> Deployment:
    """A case-study instance as the paper models it: every computer's whole capacity usable."""
    d = load_deployment(os.path.join(IROS, f'instance_{i}.yaml'))
    return replace(d, decider=replace(d.decider, cpu_headroom=1.0))


def sig3(x: float) -> str:
    return f'{x:.3g}'


# --- regression ---------------------------------------------------------------------------
@pytest.mark.parametrize('cpu, perf, form, expected', [
    ((80, 120, 160, 200), (40, 70, 90, 100), 'log', (66.62, 56.308)),
    ((17, 39, 59), (20, 70, 100), 'log', (63.707, 132.16)),
    ((25, 39, 50), (10, 65, 100), 'log', (129.12, 188.36)),
    ((19, 41, 66), (20, 50, 100), 'quadratic', (135.4, 55.126, 4.6383)),
])
def test_iros_curves_match_the_published_coefficients(cpu, perf, form, expected):
    r = Regression(form, x_scale=100.0).fit(cpu, perf)
    assert [sig3(c) for c in r.coef_] == [sig3(c) for c in expected]
    assert 0.9 < r.r2_ <= 1.0


def test_iros_instance_profiles_use_the_reference_curves():
    d = instance(1)
    fitted = {n.name: fit_profile(n.settings).cpu_to_performance
              for n in d.nodes if n.configurable}
    assert sig3(fitted['tracker_1'].coef_[0]) == '66.6'
    assert sig3(fitted['amcl_1'].coef_[0]) == '135'
    # x = CPU / 100: the tracker at 100 CPU is exactly b.
    assert fitted['tracker_1'].predict(100.0) == pytest.approx(56.3076, abs=1e-3)


def test_regression_is_an_estimator():
    r = Regression('linear')
    assert r.fit([1, 2, 3], [3, 5, 7]) is r
    assert r.coef_ == pytest.approx((2.0, 1.0))
    assert r.r2_ == pytest.approx(1.0)
    assert r.predict(10) == pytest.approx(21.0)
    assert list(r.predict([0, 1])) == pytest.approx([1.0, 3.0])
    assert r.formula() == '2 x + 1'
    cubic = Regression('poly3').fit([0, 1, 2, 3, 4], [x ** 3 - 2 * x + 1 for x in range(5)])
    assert cubic.coef_ == pytest.approx((1.0, 0.0, -2.0, 1.0), abs=1e-9)
    noisy = Regression('linear').fit([1, 2, 3, 4], [1, 3, 2, 4])
    assert 0.0 < noisy.r2_ < 1.0


@pytest.mark.parametrize('form, x, y, message', [
    ('cubic', [1, 2], [1, 2], 'unknown regression form'),
    ('poly2', [1, 2], [1, 2], 'at least 3 distinct'),
    ('log', [0, 1, 2], [1, 2, 3], 'positive'),
    ('linear', [1, 2], [1], 'equally long'),
])
def test_regression_rejects_bad_input(form, x, y, message):
    with pytest.raises(ValueError, match=message):
        Regression(form).fit(x, y)


def test_unfitted_regression_refuses_to_predict():
    with pytest.raises(RuntimeError, match='not fitted'):
        Regression().predict(1.0)


def test_parameter_inversion_gives_the_value_to_set():
    d = instance(1)
    model = fit_profile(d.node('model_1').settings)
    tracker = fit_profile(d.node('tracker_1').settings)
    assert tracker.parameter_for_cpu(120.0) == 15.0           # a sample: its own value
    assert tracker.parameter_for_cpu(140.0) == pytest.approx(17.5)
    value = model.parameter_for_cpu(30.0)
    assert 4.0 < value < 3500.0
    assert model.parameter_to_cpu.predict(value) == pytest.approx(30.0, abs=1e-6)
    assert model.parameter_to_performance.predict(3500.0) == pytest.approx(70.0)
    # Outside the fitted range the nearer end is reported, never an extrapolation.
    assert model.parameter_to_cpu.inverse(1000.0) == pytest.approx(10000.0)


def test_a_fit_with_too_few_samples_for_its_form_falls_back_to_a_line():
    s = Settings(parameter='hz', values=(1.0, 2.0), cpu=(10.0, 20.0), performance=(5.0, 9.0),
                 form='poly2', parameter_form='poly3')
    p = fit_profile(s)
    assert p.cpu_to_performance.form == 'linear'
    assert p.parameter_for_cpu(15.0) == pytest.approx(1.5)


# --- a tiny hand-made deployment ------------------------------------------------------------
def scale(name, capacity, kind='robot', master=False):
    return Scale(name=name, role='master' if master else 'remote', kind=kind,
                 capacity_cpu=capacity, cores=2, clock_ghz=2.0, gain=1.0, host=name)


def node(name, cpu, perf=1.0, **kw):
    return Node(name=name, launch=Launch(), cpu=cpu, performance=perf, **kw)


def conn(pub, sub, bw):
    return Connection(name=f'{pub}__{sub}', topic=f'/{pub}', publisher=pub, subscriber=sub,
                      bandwidth_kbps=bw)


def tiny(link_bw=100.0, with_link=True, capacity=100.0) -> Deployment:
    """src (pinned to r) feeds a and b; a and b must share a scale; b is configurable."""
    settings = Settings(parameter='hz', values=(1.0, 2.0, 3.0), cpu=(10.0, 20.0, 30.0),
                        performance=(10.0, 18.0, 22.0), form='poly2', parameter_form='linear')
    return Deployment(
        name='tiny', source='<test>',
        scales=(scale('r', capacity, master=True), scale('s', 200.0, kind='server')),
        links=(Link('r_s', ('r', 's'), link_bw, 'wireless'),) if with_link else (),
        nodes=(node('src', 20.0, residence=('r',)),
               node('a', 30.0, coresidence=('b',)),
               node('b', 20.0, 18.0, settings=settings, coresidence=('a',))),
        connections=(conn('src', 'a', 5.0), conn('src', 'b', 7.0), conn('a', 'b', 50.0)))


def test_checker_accepts_a_feasible_layout():
    d = tiny()
    assert check_layout(d, {'src': 'r', 'a': 's', 'b': 's'}, {'b': 30.0}) == ()


@pytest.mark.parametrize('layout, cpu, capacity, kind, words', [
    ({'src': 's', 'a': 's', 'b': 's'}, {}, None, 'residence', ['src', 'residence']),
    ({'src': 'r', 'a': 'r', 'b': 's'}, {}, None, 'coresidence', ['a', 'share a scale']),
    ({'src': 'r', 'a': 'r', 'b': 'r'}, {'b': 30.0}, {'r': 70.0}, 'cpu', ['scale r', '80', '70']),
    ({'src': 'r', 'a': 's', 'b': 's'}, {}, {'s': 40.0}, 'cpu', ['scale s', '40']),
    ({'src': 'r', 'a': 's'}, {}, None, 'placement', ['b', 'no placement']),
    ({'src': 'r', 'a': 's', 'b': 'mars'}, {}, None, 'placement', ['mars']),
    ({'src': 'r', 'a': 's', 'b': 's', 'ghost': 'r'}, {}, None, 'placement', ['ghost']),
    ({'src': 'r', 'a': 's', 'b': 's'}, {'b': 31.0}, None, 'setting', ['b', '31', '10-30']),
    ({'src': 'r', 'a': 's', 'b': 's'}, {'a': 5.0}, None, 'setting', ['fixed CPU']),
])
def test_checker_names_each_violation(layout, cpu, capacity, kind, words):
    found = check_layout(tiny(), layout, cpu, capacity)
    assert kind in [v.kind for v in found], found
    reason = next(v.reason for v in found if v.kind == kind)
    for w in words:
        assert w in reason


def test_checker_sums_both_directions_on_a_link_and_needs_a_link():
    d = tiny(link_bw=11.0)
    found = check_layout(d, {'src': 'r', 'a': 's', 'b': 's'})
    assert [v.kind for v in found] == ['bandwidth']
    assert '12' in found[0].reason and 'r_s' in found[0].reason
    # Traffic from r to s plus traffic from s to r on one link.
    d2 = replace(tiny(link_bw=60.0), connections=tiny().connections + (conn('b', 'src', 50.0),))
    assert [v.kind for v in check_layout(d2, {'src': 'r', 'a': 's', 'b': 's'})] == ['bandwidth']
    nolink = check_layout(tiny(with_link=False), {'src': 'r', 'a': 's', 'b': 's'})
    assert sorted(v.kind for v in nolink) == ['no_link', 'no_link']


@pytest.mark.parametrize('solver', ['greedy', 'paper-greedy', 'exact'])
@pytest.mark.parametrize('problem', [1, 2])
def test_solvers_on_the_tiny_deployment(solver, problem):
    d = tiny(link_bw=11.0)    # a and b must stay with src on r: 20 + 30 + b <= 100
    plan = solve(d, problem=problem, solver=solver)
    assert plan.feasible, plan.violations
    assert {p.scale for p in plan.layout.values()} == {'r'}
    if problem == 1:
        assert plan.layout['b'].cpu == 30.0       # the largest share that still fits
        assert plan.layout['b'].parameter_value == pytest.approx(3.0)
    else:
        assert plan.objective == 0.0
        assert dict(plan.server_capacity) == {'s': 0.0}


@pytest.mark.parametrize('solver', ['greedy', 'paper-greedy', 'exact'])
def test_no_feasible_layout_is_reported_with_reasons(solver):
    d = tiny(link_bw=11.0, capacity=55.0)   # src + a + b (at least 10) need 60 on r
    plan = solve(d, problem=1, solver=solver)
    assert not plan.feasible
    assert plan.layout == {} and math.isnan(plan.objective) and not plan.optimal
    assert plan.violations
    assert any('r' in v for v in plan.violations)
    d2 = replace(tiny(), nodes=tiny().nodes + (node('huge', 500.0, residence=('r',)),))
    plan2 = solve(d2, problem=1, solver=solver)
    assert not plan2.feasible
    assert any('huge' in v and 'CPU' in v for v in plan2.violations)


@pytest.mark.parametrize('kwargs, message', [
    ({'problem': 3}, 'problem'), ({'solver': 'magic'}, 'solver'),
    ({'settings': 'fuzzy'}, 'settings'), ({'time_limit_s': 0}, 'time_limit_s'),
])
def test_solve_rejects_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        solve(tiny(), **kwargs)


def headroom_case(headroom: float) -> Deployment:
    """a (50) and b (44) fit a robot of 100 together, but not the 90 a headroom of 0.9 leaves."""
    return Deployment(
        name='headroom', source='<test>',
        scales=(scale('r', 100.0, master=True), scale('s', 400.0, kind='server')),
        links=(Link('r_s', ('r', 's'), 1000.0, 'wireless'),),
        nodes=(node('a', 50.0), node('b', 44.0)),
        connections=(conn('a', 'b', 1.0),),
        decider=DeciderSettings(cpu_headroom=headroom))


@pytest.mark.parametrize('solver', ['greedy', 'paper-greedy', 'exact'])
def test_problem2_fills_a_scale_only_to_what_the_decider_lets_it_use(solver):
    whole = solve(headroom_case(1.0), problem=2, solver=solver)
    assert whole.scale_load['r'] == 94.0 and whole.objective == 0.0
    d = headroom_case(0.9)
    plan = solve(d, problem=2, solver=solver)
    assert plan.feasible, plan.violations
    assert plan.scale_load['r'] == 50.0 and plan.objective == 44.0
    assert plan.scale_load['r'] <= usable_cpu(d.scale('r').capacity_cpu, d.decider) == 90.0


@pytest.mark.parametrize('solver', ['greedy', 'paper-greedy', 'exact'])
def test_problem1_respects_the_usable_cpu_too(solver):
    d = replace(headroom_case(0.9), scales=(scale('r', 100.0, master=True), scale('t', 60.0)),
                links=(Link('r_t', ('r', 't'), 1000.0, 'wireless'),))
    plan = solve(d, problem=1, solver=solver)
    assert plan.feasible, plan.violations
    assert plan.scale_load['r'] <= 90.0 and plan.scale_load['t'] <= 54.0


def test_the_checker_and_the_reasons_speak_of_usable_cpu():
    d = headroom_case(0.9)
    found = check_layout(d, {'a': 'r', 'b': 'r'})
    assert [v.kind for v in found] == ['cpu']
    assert 'needs CPU 94' in found[0].reason and '90 usable' in found[0].reason
    assert 'capacity 100 x cpu_headroom 0.9' in found[0].reason
    assert check_layout(headroom_case(1.0), {'a': 'r', 'b': 'r'}) == ()
    pinned = replace(d, nodes=(node('a', 50.0, residence=('r',)),
                               node('b', 44.0, residence=('r',))))
    plan = solve(pinned, problem=1)
    assert not plan.feasible
    assert any('90 usable' in v and '94' in v for v in plan.violations), plan.violations


# --- the case study -----------------------------------------------------------------------
@pytest.fixture(scope='module')
def iros_plans():
    out = {}
    for i in range(1, 11):
        d = instance(i)
        for problem in (1, 2):
            for solver in ('greedy', 'paper-greedy', 'exact'):
                out[i, problem, solver] = solve(d, problem, solver)
    return out


@pytest.mark.parametrize('i', range(1, 11))
def test_every_solver_is_feasible_and_exact_is_proven(iros_plans, i):
    d = instance(i)
    for problem in (1, 2):
        for solver in ('greedy', 'paper-greedy', 'exact'):
            plan = iros_plans[i, problem, solver]
            assert plan.feasible, (i, problem, solver, plan.violations)
            layout = {n: p.scale for n, p in plan.layout.items()}
            cpu = {n: p.cpu for n, p in plan.layout.items()}
            assert check_layout(d, layout, cpu, plan.server_capacity) == ()
            assert set(plan.layout) == set(d.node_names)
        exact = iros_plans[i, problem, 'exact']
        assert exact.optimal and exact.gap is not None and exact.gap <= 1e-6


@pytest.mark.parametrize('i', range(1, 11))
def test_our_greedy_is_near_optimal_on_every_instance(iros_plans, i):
    best1 = iros_plans[i, 1, 'exact'].objective
    assert iros_plans[i, 1, 'greedy'].objective >= 0.99 * best1
    assert iros_plans[i, 1, 'greedy'].objective <= best1 + 1e-6
    assert iros_plans[i, 1, 'paper-greedy'].objective <= iros_plans[i, 1, 'greedy'].objective
    best2 = iros_plans[i, 2, 'exact'].objective
    assert best2 - 1e-6 <= iros_plans[i, 2, 'greedy'].objective <= 1.005 * best2


def test_problem2_keeps_nominal_settings_and_grows_only_servers(iros_plans):
    d = instance(4)
    plan = iros_plans[4, 2, 'exact']
    for n in d.nodes:
        assert plan.layout[n.name].cpu == n.cpu
    assert set(plan.server_capacity) == {'c3'}
    assert plan.objective == pytest.approx(plan.server_capacity['c3'])
    assert plan.server_capacity['c3'] == pytest.approx(plan.scale_load['c3'])
    for robot in ('c1', 'c2'):
        assert plan.scale_load[robot] <= 100.0
    assert plan.layout['tracker_1'].parameter_value == pytest.approx(15.0)


def test_problem1_reports_parameter_values_consistent_with_the_fits(iros_plans):
    d = instance(7)
    plan = iros_plans[7, 1, 'greedy']
    for n in d.nodes:
        p = plan.layout[n.name]
        if not n.configurable:
            assert (p.cpu, p.performance, p.parameter_value) == (n.cpu, n.performance, None)
            continue
        s = n.settings
        assert s.cpu_min <= p.cpu <= s.cpu_max and p.cpu == int(p.cpu)
        profile = fit_profile(s)
        assert p.performance == pytest.approx(profile.performance(p.cpu))
        assert min(s.values) <= p.parameter_value <= max(s.values)
        assert profile.parameter_to_cpu.predict(p.parameter_value) == pytest.approx(p.cpu,
                                                                                    abs=1e-6)


@pytest.mark.parametrize('i', [2, 5, 8])
def test_discrete_settings_pick_samples(i):
    d = instance(i)
    exact = solve(d, 1, 'exact', settings='discrete')
    greedy = solve(d, 1, 'greedy', settings='discrete')
    assert exact.optimal and greedy.feasible
    assert greedy.objective <= exact.objective + 1e-6
    for plan in (exact, greedy):
        for n in d.nodes:
            p = plan.layout[n.name]
            if n.configurable:
                k = n.settings.cpu.index(p.cpu)
                assert p.performance == n.settings.performance[k]
                assert p.parameter_value == n.settings.values[k]


def test_the_testbed_plans_with_every_node_fixed():
    d = load_deployment(TESTBED)
    for problem in (1, 2):
        for solver in ('greedy', 'paper-greedy', 'exact'):
            plan = solve(d, problem, solver)
            assert plan.feasible, (problem, solver, plan.violations)
            for n in d.nodes:
                assert plan.layout[n.name].cpu == n.cpu
                assert plan.layout[n.name].scale in d.allowed_scales(n.name)
    assert solve(d, 2, 'exact').objective == 0.0     # everything fits on the robot


def test_instance_residence_matches_the_model():
    for d in (load_deployment(TESTBED), instance(6), generate_deployment(60, 6, seed=3)):
        inst = Instance(d)
        for n in d.nodes:
            u = inst.unit_of[inst.node_index[n.name]]
            assert tuple(inst.scales[s] for s in inst.unit_allowed[u]) == \
                d.allowed_scales(n.name)
            assert {inst.nodes[m] for m in inst.units[u]} == set(d.coresidence_group(n.name))


def test_generated_deployments_plan_feasibly():
    d = generate_deployment(120, 8, seed=1)
    assert len(d.nodes) == 120 and len(d.scales) == 8
    for problem in (1, 2):
        greedy = solve(d, problem, 'greedy')
        paper = solve(d, problem, 'paper-greedy')
        assert greedy.feasible and paper.feasible
        if problem == 1:
            assert greedy.objective >= paper.objective - 1e-6
        else:
            assert greedy.objective <= paper.objective + 1e-6


def test_exact_stops_at_its_time_limit_and_reports_no_proof():
    d = generate_deployment(300, 12, seed=2)
    plan = solve(d, 1, 'exact', time_limit_s=0.3)
    assert not plan.optimal
    assert plan.solve_time_s < 5.0
    if plan.feasible:
        assert plan.gap is None or plan.gap > 0


# --- the command ----------------------------------------------------------------------------
def test_plan_command_prints_a_table(capsys):
    path = os.path.join(IROS, 'instance_4.yaml')
    assert cli_main(['plan', path, '--problem', '1', '--solver', 'exact']) == 0
    out = capsys.readouterr().out
    for word in ('tracker_1', 'particles=', 'objective:', 'proven optimal', 'computers:',
                 'c3', 'links (both directions summed):', 'c1_c2'):
        assert word in out


def test_plan_command_json(capsys):
    path = os.path.join(IROS, 'instance_3.yaml')
    assert cli_main(['plan', path, '--problem', '2', '--json', '--solver', 'exact']) == 0
    data = json.loads(capsys.readouterr().out)
    for key in ('objective', 'layout', 'server_capacity', 'optimal', 'solve_time_s'):
        assert key in data
    assert data['optimal'] is True and data['server_capacity'] == {'c2': data['objective']}
    assert set(data['layout']['model_1']) >= {'scale', 'cpu', 'performance', 'parameter_value'}


INFEASIBLE = '''
/**:
  ros__parameters:
    deployment: {name: overloaded}
    scales:
      names: [robot, laptop]
      robot: {role: master, kind: robot, capacity_cpu: 100.0, cores: 2, clock_ghz: 1.6,
              gain: 1.0, host: robot}
      laptop: {role: remote, kind: server, capacity_cpu: 400.0, cores: 4, clock_ghz: 2.8,
               gain: 1.0, host: laptop}
    links:
      names: [wifi]
      wifi: {ends: [robot, laptop], bandwidth_kbps: 1000.0, medium: wireless}
    nodes:
      names: [driver, planner]
      driver: {cpu: 80.0, residence: [robot]}
      planner: {cpu: 70.0, residence: [robot]}
    connections:
      names: [plan]
      plan: {topic: /plan, publisher: planner, subscriber: driver, bandwidth_kbps: 10.0}
'''


def run_cli(*args):
    env = dict(os.environ)
    return subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', 'plan', *args],
                          capture_output=True, text=True, timeout=120, env=env, cwd=REPO)


def test_plan_command_exits_1_naming_the_constraint(tmp_path):
    path = tmp_path / 'overloaded.yaml'
    path.write_text(INFEASIBLE)
    for solver in ('greedy', 'exact'):
        r = run_cli(str(path), '--solver', solver)
        assert r.returncode == 1, r.stderr
        assert 'no feasible layout' in r.stderr
        assert 'robot' in r.stderr and '150' in r.stderr     # the pinned load vs capacity
    r = run_cli(str(path), '--json')
    assert r.returncode == 1
    assert json.loads(r.stdout)['feasible'] is False


def test_plan_command_exits_2_on_a_bad_file(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters: {scales: [1, 2\n')
    r = run_cli(str(bad))
    assert r.returncode == 2 and 'invalid YAML' in r.stderr and 'bad.yaml' in r.stderr
    wrong = tmp_path / 'wrong.yaml'
    wrong.write_text(INFEASIBLE.replace('capacity_cpu: 100.0', 'capacity_cpu: lots'))
    r = run_cli(str(wrong))
    assert r.returncode == 2 and 'capacity_cpu' in r.stderr
    r = run_cli(str(tmp_path / 'missing.yaml'))
    assert r.returncode == 2 and 'cannot read' in r.stderr
    r = run_cli(os.path.join(IROS, 'instance_1.yaml'), '--time-limit', '0')
    assert r.returncode == 2 and 'time-limit' in r.stderr
