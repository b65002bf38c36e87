"""The package's layers import downward only, and the pure core knows nothing of ROS.

model <- planning <- runtime <- agent and view <- nodes, with the wire's modules (protocol,
protocol_auth, interrupt) and the finder of the files the package ships (config_files) just
above model: a layer imports only those below it and itself,
so what two layers need lives in the lower one. The core (model, planning, runtime, agent, sim
and the wire's modules) imports no ROS client library nor message package, and nothing reaches
around a layer with importlib. Read from the source (ast), whatever is imported at run time.
"""

import ast
import os

import pytest

from conftest import REPO

PACKAGE = 'anyscale_manager'
ROOT = os.path.join(REPO, PACKAGE)
# The modules of the wire, the signal handling and the shipped files' finder, at the package's
# top, form one layer.
WIRE = {'protocol': 'wire', 'protocol_auth': 'wire', 'interrupt': 'wire',
        'config_files': 'wire'}
RANK = {'model': 0, 'wire': 1, 'planning': 2, 'runtime': 3, 'agent': 4, 'view': 4, 'nodes': 5}
PURE = ('model', 'wire', 'planning', 'runtime', 'agent', 'sim')
ROS = ('rclpy', 'rosidl_runtime_py', 'rosidl_parser', 'launch', 'launch_ros')


def modules():
    """(path relative to the repository, module name, parsed tree) of every package module."""
    out = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = sorted(d for d in dirs if not d.startswith(('.', '__')))
        for name in sorted(files):
            if name.endswith('.py'):
                path = os.path.join(folder, name)
                rel = os.path.relpath(path, REPO)
                module = rel[:-3].replace(os.sep, '.')
                if module.endswith('.__init__'):
                    module = module[:-len('.__init__')]
                with open(path, encoding='utf-8') as f:
                    out.append((rel, module, ast.parse(f.read(), rel)))
    return out


MODULES = modules()


def layer(module):
    """The part of the package a module belongs to: model, runtime, wire, sim, cli, ..."""
    parts = module.split('.')
    if parts[0] != PACKAGE or len(parts) == 1:
        return None
    return WIRE.get(parts[1], parts[1])


def imports(module, tree):
    """(line, imported module) of every import in ``tree``, relative ones resolved; for
    ``from X import y`` both X and X.y (y may be a module)."""
    package = module if is_package(module) else module.rpartition('.')[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')[:len(package.split('.')) - node.level + 1]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ''
            yield node.lineno, target
            for alias in node.names:
                yield node.lineno, f'{target}.{alias.name}'


def is_package(module):
    return os.path.isdir(os.path.join(REPO, *module.split('.')))


def test_the_walk_sees_every_layer():
    seen = {layer(m) for _, m, _ in MODULES}
    assert set(RANK) | set(PURE) <= seen
    assert ('anyscale_manager/runtime/turn.py', 'anyscale_manager.runtime.turn') in {
        (rel, m) for rel, m, _ in MODULES}


def test_relative_imports_are_resolved():
    tree = ast.parse('from .. import protocol as p\nfrom ..model.types import Deployment\n'
                     'from .constraints import evaluate\n')
    found = {t for _, t in imports('anyscale_manager.runtime.turn', tree)}
    assert {'anyscale_manager.protocol', 'anyscale_manager.model.types',
            'anyscale_manager.runtime.constraints'} <= found


LAYERED = [m for m in MODULES if layer(m[1]) in RANK]
CORE = [m for m in MODULES if layer(m[1]) in PURE]


@pytest.mark.parametrize('rel, module, tree', LAYERED, ids=[rel for rel, _, _ in LAYERED])
def test_a_layer_imports_only_the_layers_below_it(rel, module, tree):
    mine = RANK[layer(module)]
    wrong = {}
    for line, target in imports(module, tree):
        other = layer(target)
        if other is None or other == layer(module):
            continue
        if other not in RANK or RANK[other] >= mine:
            wrong.setdefault(line, f'{rel}:{line} imports {target} ({other} is not below '
                                   f'{layer(module)})')
    assert not wrong, '\n'.join(wrong.values())


@pytest.mark.parametrize('rel, module, tree', CORE, ids=[rel for rel, _, _ in CORE])
def test_the_pure_core_imports_no_ros(rel, module, tree):
    wrong = {}
    for line, target in imports(module, tree):
        top = target.split('.')[0]
        if top in ROS or top.endswith(('_msgs', '_interfaces')):
            wrong.setdefault(line, f'{rel}:{line} imports {target}')
    assert not wrong, '\n'.join(wrong.values())


def dynamic_imports(tree):
    """(line, argument) of every importlib.import_module and __import__ call."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, 'id', '')
            if name in ('import_module', '__import__'):
                yield node.lineno, node.args[0] if node.args else None


def names_a_message_package(arg):
    """f'{pkg}.msg': the ROS message package a 'pkg/msg/Type' from a deployment names."""
    return isinstance(arg, ast.JoinedStr) and isinstance(arg.values[-1], ast.Constant) \
        and arg.values[-1].value == '.msg'


def test_no_importlib_reaches_into_the_package():
    """Only the command-line entry loads modules by name (a subcommand's, when it is asked
    for); elsewhere a dynamic import may only load the ROS message package of a type that a
    deployment names, never a module of this package."""
    wrong, entry = [], 0
    for rel, module, tree in MODULES:
        for line, arg in dynamic_imports(tree):
            if module == f'{PACKAGE}.cli':
                entry += 1
            elif not names_a_message_package(arg):
                wrong.append(f'{rel}:{line} imports by name: {ast.unparse(arg or ast.Tuple())}')
    assert not wrong, '\n'.join(wrong)
    assert entry, 'cli.py no longer imports its subcommands by name: update this test'


def test_the_checks_catch_what_they_are_for():
    upward = ast.parse('from ..runtime.constraints import usable_cpu\n')
    assert [t for _, t in imports('anyscale_manager.planning.instance', upward)
            if layer(t) == 'runtime']
    reach = ast.parse('import importlib\n'
                      "planning = importlib.import_module('anyscale_manager.planning')\n"
                      "m = importlib.import_module(f'{p}.msg')\n")
    assert [names_a_message_package(a) for _, a in dynamic_imports(reach)] == [False, True]
