"""anyscale-manager validate FILE...: check deployments and print a readable summary.

The model (model/) reads and checks a file by itself; this command adds what only the machine
it runs on can tell: whether the key file is readable and whether an agent here could start
each node's launch (agent/launch_check.py: its executable, and the script or package executable
an interpreter command needs), each problem naming the word of the launch at fault.
"""

import argparse
import sys
from typing import List, TextIO, Tuple

from .agent.launch_check import launch_problems
from .model.advice import warnings
from .model.loader import DeploymentError, did_you_mean, load_deployment
from .model.summary import summary
from .model.types import Deployment
from .protocol_auth import KeyFileError, load_key

__all__ = ['add_arguments', 'machine_check', 'run', 'summary']


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('files', nargs='+', metavar='FILE', help='deployment YAML files')
    parser.add_argument('--quiet', action='store_true', help='print only errors and warnings')
    parser.add_argument('--scale', metavar='NAME',
                        help='validate for the scale this machine is: a node that may run on it '
                             'and cannot be started here is an error (without it, a warning); '
                             'the launches of nodes that never run on it are not checked')


def machine_check(d: Deployment, scale: str = '') -> Tuple[List[str], List[str]]:
    """(errors, warnings) about launches this machine cannot start; with ``scale``, the file is
    validated for that scale: its nodes' launches are errors, other nodes' are not looked at."""
    errors, notes = [], []
    for node, problem in launch_problems(d).items():
        where = f'nodes.{node}.launch' + (f'.{problem.field}' if problem.field else '')
        if not scale:
            notes.append(f'{d.source}: {where}: {problem}: an agent on this machine '
                         'cannot start it (validate --scale NAME makes this an error)')
        elif scale in d.allowed_scales(node):
            errors.append(f'{d.source}: {where}: {problem}: the agent of scale '
                          f'{scale}, on this machine, cannot start it')
    return errors, notes


def _emit(stream: TextIO, lines: List[str]) -> None:
    """Whole lines in one write, flushed. The summary goes to stdout and the warnings to
    stderr: whoever merges the two streams (a terminal, a launcher reading both pipes) gets
    each write whole, so a warning never starts inside a line of the summary."""
    stream.write(''.join(f'{line}\n' for line in lines))
    stream.flush()


def run(args: argparse.Namespace) -> int:
    failed = False
    scale = args.scale or ''
    for path in args.files:
        try:
            d = load_deployment(path)
        except DeploymentError as e:
            failed = True
            _print_problems(path, [str(p) for p in e.problems])
            continue
        problems = []
        if scale and scale not in d.scale_names:
            problems.append(f'{path}: --scale: unknown scale {scale!r}'
                            f'{did_you_mean(scale, d.scale_names)}; the scales of this file '
                            f'are {", ".join(d.scale_names)}')
        if d.security.key_file:
            try:
                load_key(d.security.key_file)
            except KeyFileError as e:
                problems.append(f'{path}: {e}')
        errors, notes = machine_check(d, scale if scale in d.scale_names else '')
        problems += errors
        if problems:
            failed = True
            _print_problems(path, problems)
            continue
        if not args.quiet:
            _emit(sys.stdout, [summary(d)])
        _emit(sys.stderr, [f'warning: {w}' for w in warnings(d) + notes])
    return 2 if failed else 0


def _print_problems(path: str, problems: List[str]) -> None:
    _emit(sys.stderr, [f'{path}: {len(problems)} problem(s):'] + [f'  {p}' for p in problems])
