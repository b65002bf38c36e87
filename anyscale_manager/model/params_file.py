"""The parameters files of a ROS command line (``--ros-args --params-file FILE``), and whether
each is one rcl will read.

The decider and the agents take their deployment as a ROS 2 parameters file, which rcl reads
in ``rclpy.init``; what it says of a bad one is a parser's message (``Error parsing a event near
line 4``), and a deployment rebuilt from parameters no longer knows its file. Here, before rcl
sees it, each file is checked as rcl reads it: YAML, node names over ``ros__parameters`` (the
``/**: {ros__parameters: {...}}`` shape), lists of one type; each problem names the file, the
line and column and what was expected. Duplicate keys are refused too: rcl keeps one of them
without a word. Pure apart from reading the files.
"""

import re
import sys
from typing import Any, List, Optional, Sequence, Tuple

import yaml

from .reader import Problem, did_you_mean
from .yaml_io import SECTIONS, mark_text, parse_yaml, yaml_problem

ROS_ARGS, END = '--ros-args', '--'
PARAMS_FILE = '--params-file'
# rcl's arguments that take a value (the next word).
_VALUED = {PARAMS_FILE, '-p', '--param', '-r', '--remap', '-e', '--enclave', '--log-level',
           '--log-config-file', '--log-file-name'}
PARAMETERS = 'ros__parameters'
FALLBACK_SOURCE = '<ROS parameters>'
SHAPE = '/**: {ros__parameters: {...}}'
# The words rcl's parser reads as booleans when unquoted (YAML 1.1's, 'y' and 'n' included).
_BOOLEANS = frozenset('y Y yes Yes YES true True TRUE on On ON '
                      'n N no No NO false False FALSE off Off OFF'.split())
_INTEGER = re.compile(r'^[-+]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)$')


def ros_arguments(argv: Sequence[str]) -> List[Tuple[str, str]]:
    """(flag, value) of each valued rcl argument of ``argv``, in order: only those inside a
    ``--ros-args`` ... [``--``] section count."""
    out: List[Tuple[str, str]] = []
    inside, i = False, 0
    while i < len(argv):
        word = argv[i]
        if word == ROS_ARGS:
            inside = True
        elif inside and word == END:
            inside = False
        elif inside and word in _VALUED and i + 1 < len(argv):
            out.append((word, argv[i + 1]))
            i += 1
        i += 1
    return out


def params_files(argv: Sequence[str]) -> List[str]:
    """The files given with ``--params-file``, in order."""
    return [value for flag, value in ros_arguments(argv) if flag == PARAMS_FILE]


def parameters_source(argv: Optional[Sequence[str]] = None) -> str:
    """What a deployment rebuilt from a node's parameters is named by in its errors: its
    parameters files (``argv``, default this process's command line), with the deployment
    settings overridden by ``-p``; FALLBACK_SOURCE when no file is given."""
    argv = sys.argv if argv is None else argv
    args = ros_arguments(argv)
    files = [value for flag, value in args if flag == PARAMS_FILE]
    if not files:
        return FALLBACK_SOURCE
    overrides = [value.split(':=', 1)[0] for flag, value in args if flag in ('-p', '--param')]
    ours = [name for name in overrides if name.split('.', 1)[0] in SECTIONS]
    text = ', '.join(files)
    return text + (f' (with -p {", ".join(ours)})' if ours else '')


def check_params_files(argv: Sequence[str]) -> List[Problem]:
    """Every problem of every ``--params-file`` of ``argv`` (none: nothing to say)."""
    out: List[Problem] = []
    for path in params_files(argv):
        out += file_problems(path)
    return out


def file_problems(path: str) -> List[Problem]:
    """What keeps rcl from reading ``path`` as a parameters file, each with its line and
    column and what was expected; [] when it reads."""
    try:
        with open(path, encoding='utf-8') as f:
            text = f.read()
    except OSError as e:
        return [Problem(path, '', f'cannot read: {e.strerror or e}')]
    except UnicodeDecodeError as e:
        return [Problem(path, '', f'not UTF-8 text ({e.reason} at byte {e.start})')]
    try:
        parse_yaml(text)                # syntax, and keys given twice
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        return [yaml_problem(path, e)]
    if root is None:
        return [Problem(path, '', f'empty: expected a ROS 2 parameters file, {SHAPE}')]
    problems: List[Problem] = []
    if not isinstance(root, yaml.MappingNode) or not root.value:
        problems.append(_at(path, root, 'expected a ROS 2 parameters file: a map of node '
                                        f'names (/** for every node) each holding '
                                        f'{PARAMETERS}, {SHAPE}; got {_kind(root)}'))
        return problems
    for key, value in root.value:
        _node_names(path, key, value, problems)
    return problems


def _node_names(path: str, key: Any, value: Any, problems: List[Problem]) -> None:
    """Under a node name (or namespace): either ros__parameters alone, or more names."""
    name = str(key.value)
    if not isinstance(value, yaml.MappingNode) or not value.value:
        problems.append(_at(path, value, f'{name!r}: expected {PARAMETERS}: under a node name '
                                         f'({SHAPE}); got {_kind(value)}'))
        return
    keys = [str(k.value) for k, _ in value.value]
    if PARAMETERS in keys:
        for k, v in value.value:
            if k.value != PARAMETERS:
                problems.append(_at(path, k, f'{str(k.value)!r} beside {PARAMETERS} under '
                                             f'{name!r}: expected {PARAMETERS} alone there '
                                             "(the deployment's sections go inside it)"))
            elif not isinstance(v, yaml.MappingNode):
                problems.append(_at(path, v, f'{name!r}.{PARAMETERS}: expected a map of '
                                             f'parameters, got {_kind(v)}'))
            else:
                _lists(path, v, problems)
        return
    for k, v in value.value:
        if str(k.value) != PARAMETERS and did_you_mean(k.value, [PARAMETERS]):
            problems.append(_at(path, k, f'{str(k.value)!r} under {name!r}: expected '
                                         f'{PARAMETERS}{did_you_mean(k.value, [PARAMETERS])}'))
        elif not isinstance(v, yaml.MappingNode):
            # rcl: "Cannot have a value before ros__parameters".
            problems.append(_at(path, k, f'{str(k.value)!r} under {name!r}: a parameter '
                                         f'outside {PARAMETERS}: expected {SHAPE} (is '
                                         f'{PARAMETERS}: missing or misspelt?)'))
        else:
            _node_names(path, k, v, problems)


def _lists(path: str, node: Any, problems: List[Problem]) -> None:
    """rcl refuses a list whose items are not all of one type (1.0 and 2 included)."""
    todo = [node]
    while todo:
        here = todo.pop()
        if isinstance(here, yaml.MappingNode):
            todo.extend(v for _, v in here.value)
        elif isinstance(here, yaml.SequenceNode):
            items = [n for n in here.value if isinstance(n, yaml.ScalarNode)]
            kinds = [_rcl_type(n) for n in items]
            for item, kind in zip(items, kinds):
                if kind != kinds[0]:
                    hint = (f': write {item.value}.0' if kinds[0] == 'float'
                            and kind == 'integer' else '')
                    problems.append(_at(path, item, f'a list of {kinds[0]}s holds the '
                                                    f'{kind} {item.value}: a ROS parameter '
                                                    f'list holds one type{hint}'))
                    break


def _rcl_type(node: Any) -> str:
    """The type rcl gives a scalar: a quoted one is a string; else boolean, integer, float
    or string, in that order, by rcl's words (its booleans are not PyYAML's)."""
    text = node.value
    if node.style in ('"', "'"):
        return 'string'
    if text in _BOOLEANS:
        return 'boolean'
    if _INTEGER.match(text):
        return 'integer'
    if text.lstrip('+-') in ('.inf', '.Inf', '.INF', '.nan', '.NaN', '.NAN'):
        return 'float'
    try:
        float(text.replace('_', ' '))
        return 'float'
    except ValueError:
        return 'string'


def _kind(node: Any) -> str:
    if isinstance(node, yaml.MappingNode):
        return 'an empty map' if not node.value else 'a map'
    if isinstance(node, yaml.SequenceNode):
        return 'a list'
    if node.tag == 'tag:yaml.org,2002:null':
        return 'nothing'
    return repr(node.value)[:60]


def _at(path: str, node: Any, message: str) -> Problem:
    return Problem(path, mark_text(node.start_mark), message)


def refuse_bad_params_files(program: str, argv: Sequence[str]) -> int:
    """For a node's main() before rclpy.init: print each problem of its parameters files to
    stderr and return 2, or return 0 when there is none."""
    problems = check_params_files(argv)
    if not problems:
        return 0
    files = 'files' if len(params_files(argv)) > 1 else 'file'
    sys.stderr.write(f'{program}: cannot start: {len(problems)} problem(s) in its parameters '
                     f'{files}:\n' + ''.join(f'  {p}\n' for p in problems))
    sys.stderr.flush()
    return 2


__all__ = ['FALLBACK_SOURCE', 'check_params_files', 'file_problems',
           'params_files', 'parameters_source', 'refuse_bad_params_files', 'ros_arguments']
