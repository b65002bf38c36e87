"""Whether this machine can start each node: its launch resolved exactly as an agent here would.

It looks at the file system, the ament index and PATH of the machine it runs on. validate uses
it; the agent resolves the same way when it starts (agent/catalogue.py), so what validate
accepts is what the agent can start. Beyond the executable it looks at what the executable
needs at once: the interpreter a script's ``#!`` line names, the script an interpreter command
runs (``[python3, /path/node.py]``, ``[bash, run.sh]``) and the package executable of
``[ros2, run, PACKAGE, EXECUTABLE]``: a node missing any of them starts, exits at once and is
restarted in a loop.
"""

import os
import re
import shutil
from dataclasses import dataclass
from typing import Callable, Dict, Mapping, Optional, Sequence, Tuple

from ..model import types as t
from .catalogue import _ament_prefix, build_argv

AmentPrefix = Callable[[str], Optional[str]]

_PYTHON = re.compile(r'^python[0-9.]*$')
_SHELLS = ('bash', 'sh', 'dash', 'zsh', 'ksh')
# Python's options that take a value (attached, -Wignore, or next, -W ignore), and those after
# which no script is run (-c command, -m module).
_PYTHON_VALUED, _PYTHON_NO_SCRIPT = 'WX', 'cm'
_PYTHON_LONG_VALUED = ('--check-hash-based-pycs',)
_SHELL_VALUED_LONG = ('--rcfile', '--init-file')
# A '#!' line longer than this is not one the kernel reads (BINPRM_BUF_SIZE).
_SHEBANG_BYTES = 256


@dataclass(frozen=True)
class LaunchProblem:
    """Why a node cannot be started here; ``field`` is where in its launch: 'command[1]',
    'arguments[0]', 'executable' or '' (the launch as a whole)."""

    field: str
    text: str

    def __str__(self) -> str:
        return self.text


def launch_problems(d: t.Deployment, environ: Optional[Mapping[str, str]] = None,
                    ament_prefix: Optional[AmentPrefix] = None,
                    cwd: Optional[str] = None) -> Dict[str, LaunchProblem]:
    """Node name -> why this machine cannot start it, for each managed node with a launch.
    ``cwd``: the directory relative paths are taken from (the agent's; default this one)."""
    environ = os.environ if environ is None else environ
    prefix = _ament_prefix if ament_prefix is None else ament_prefix
    out = {}
    for node in d.nodes:
        if not node.managed or not node.launch.startable:
            continue
        # The agent's child gets the agent's PATH unless the launch sets its own.
        path = str(node.launch.env.get('PATH', environ.get('PATH', os.defpath)))
        problem = node_problem(node, path, prefix, cwd or os.getcwd())
        if problem is not None:
            out[node.name] = problem
    return out


def node_problem(node: t.Node, search_path: str, ament_prefix: AmentPrefix,
                 cwd: str) -> Optional[LaunchProblem]:
    """Why this machine cannot start ``node`` (its launch resolved as the agent would), or None."""
    launch = node.launch
    head_field = 'command[0]' if launch.command else 'executable'
    argv, problem = build_argv(node, search_path, ament_prefix=ament_prefix)
    if problem:
        return LaunchProblem(head_field, problem)
    head = argv[0]
    if launch.command and os.sep in launch.command[0]:
        # A command given as a path is run as written: nothing has looked at it yet.
        found = _file_problem(head, cwd, executable=True, what='command')
        if found:
            return LaunchProblem(head_field, found)
    found = _shebang_problem(head, search_path, cwd)
    if found:
        return LaunchProblem(head_field, found)
    # The words the launch itself gives (command, then arguments), as argv holds them.
    given = list(launch.command[1:] if launch.command else ()) + list(launch.arguments)
    words = [os.path.basename(head)] + given
    found_at = _needed_problem(words, search_path, ament_prefix, cwd)
    if found_at is None:
        return None
    index, text = found_at
    if launch.command and index < len(launch.command):
        return LaunchProblem(f'command[{index}]', text)
    offset = len(launch.command) if launch.command else 1
    return LaunchProblem(f'arguments[{index - offset}]', text)


def _needed_problem(words: Sequence[str], search_path: str, ament_prefix: AmentPrefix,
                    cwd: str) -> Optional[Tuple[int, str]]:
    """(index in ``words``, problem) of the script or package executable an interpreter
    command needs, when it is missing; ``words[0]`` is the program's name."""
    program = words[0]
    if _PYTHON.match(program):
        index = _python_script(words)
        if index is None:
            return None
        script = words[index]
        if os.path.isdir(_absolute(script, cwd)):
            # Python runs a folder's __main__.py.
            main = os.path.join(script, '__main__.py')
            problem = _file_problem(main, cwd, executable=False, what=f'script of {program}')
            return (index, problem) if problem else None
        problem = _file_problem(script, cwd, executable=False, what=f'script of {program}')
        return (index, problem) if problem else None
    if program in _SHELLS:
        index = _shell_script(words)
        if index is None:
            return None
        script = words[index]
        if program == 'bash' and os.sep not in script \
                and not os.path.exists(_absolute(script, cwd)):
            # bash looks for a script it does not find in the working directory on PATH.
            found = shutil.which(script, mode=os.F_OK, path=search_path)
            if found:
                script = found
        problem = _file_problem(script, cwd, executable=False, what=f'script of {program}')
        return (index, problem) if problem else None
    if program == 'ros2' and len(words) > 1 and words[1] == 'run':
        return _ros2_run_problem(words, ament_prefix)
    return None


def _python_script(words: Sequence[str]) -> Optional[int]:
    """The index of the script python runs, or None (-c, -m, stdin, or none given)."""
    i = 1
    while i < len(words):
        word = words[i]
        if word == '--':
            return i + 1 if i + 1 < len(words) else None
        if word == '-' or not word.startswith('-'):
            return None if word == '-' else i
        if word.startswith('--'):
            i += 2 if word in _PYTHON_LONG_VALUED else 1
            continue
        for k, letter in enumerate(word[1:], start=1):
            if letter in _PYTHON_NO_SCRIPT:
                return None
            if letter in _PYTHON_VALUED:
                if k == len(word) - 1:
                    i += 1          # its value is the next word
                break
        i += 1
    return None


def _shell_script(words: Sequence[str]) -> Optional[int]:
    """The index of the script a shell runs, or None (-c, -s, or none given)."""
    i = 1
    while i < len(words):
        word = words[i]
        if word in ('--', '-'):
            return i + 1 if i + 1 < len(words) else None
        if word.startswith('--'):
            i += 2 if word in _SHELL_VALUED_LONG else 1
            continue
        if word[:1] not in '-+' or len(word) == 1:
            return i
        letters = word[1:]
        if word[0] == '-' and ('c' in letters or 's' in letters):
            return None
        # -o NAME and -O NAME (and their + forms) take the next word.
        i += 1 + sum(1 for letter in letters if letter in 'oO')
    return None


def _ros2_run_problem(words: Sequence[str], ament_prefix: AmentPrefix
                      ) -> Optional[Tuple[int, str]]:
    """``ros2 run [--prefix P] PACKAGE EXECUTABLE``: the executable in the ament index."""
    i = 2
    while i < len(words) and words[i].startswith('-'):
        i += 2 if words[i] == '--prefix' else 1
    if i + 1 >= len(words):
        return (min(i, len(words) - 1), 'ros2 run: no package and executable given')
    package, executable = words[i], words[i + 1]
    prefix = ament_prefix(package)
    if not prefix:
        return (i, f'ros2 run: package {package!r} not found in the ament index '
                   '(AMENT_PREFIX_PATH: is its workspace sourced for the agent?)')
    candidate = os.path.join(prefix, 'lib', package, executable)
    if not os.path.isfile(candidate) or not os.access(candidate, os.X_OK):
        return (i + 1, f'ros2 run: executable {executable!r} of package {package!r} not '
                       f'found (no executable file {candidate})')
    return None


def _absolute(path: str, cwd: str) -> str:
    return path if os.path.isabs(path) else os.path.join(cwd, path)


def _file_problem(path: str, cwd: str, executable: bool, what: str) -> str:
    """'' when ``path`` is a file this user may read (and run, if ``executable``)."""
    full = _absolute(path, cwd)
    where = '' if os.path.isabs(path) else \
        f" (a relative path is taken from the agent's working directory; looked for in {cwd})"
    if not os.path.exists(full):
        return f'{what} {path!r} does not exist{where}'
    if not os.path.isfile(full):
        return f'{what} {path!r} is not a file{where}'
    if executable and not os.access(full, os.X_OK):
        return f'{what} {path!r} is not executable{where}'
    if not executable and not os.access(full, os.R_OK):
        return f'{what} {path!r} is not readable by this user{where}'
    return ''


def _shebang_problem(path: str, search_path: str, cwd: str) -> str:
    """'' unless ``path`` is a script whose ``#!`` interpreter is missing."""
    try:
        with open(_absolute(path, cwd), 'rb') as f:
            first = f.read(_SHEBANG_BYTES).split(b'\n', 1)[0]
    except OSError:
        return ''
    if not first.startswith(b'#!'):
        return ''
    words = first[2:].decode('utf-8', 'replace').split()
    if not words:
        return f'script {path!r} has an empty #! line'
    interpreter = words[0]
    if os.path.basename(interpreter) == 'env' and len(words) > 1:
        program = next((w for w in words[1:] if not w.startswith('-') and '=' not in w), '')
        if program and not shutil.which(program, path=search_path):
            return f'script {path!r} is run by {program!r} (its #! line), not found on PATH'
        return ''
    if not os.path.isfile(interpreter) or not os.access(interpreter, os.X_OK):
        return f'script {path!r} is run by {interpreter!r} (its #! line), which does not exist'
    return ''


__all__ = ['LaunchProblem', 'launch_problems', 'node_problem']
