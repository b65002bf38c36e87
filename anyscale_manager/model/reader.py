"""An error-collecting reader of nested maps: every read records its problem instead of raising.

A deployment file is read in one pass whatever is wrong with it, so that every problem is
reported at once. A value that cannot be read is replaced by a default and its path marked
damaged: a later check that depends on it asks whether it was read as written, and stays quiet
rather than repeat the problem as a consequence.
"""

import difflib
import math
import re
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Set, Tuple

from . import types as t

# The default of a read that has none: the key is required.
MISSING: Any = object()


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a deployment: the file, the path in it, what was expected."""

    source: str
    path: str
    message: str

    def __str__(self) -> str:
        where = f'{self.source}: {self.path}' if self.path else self.source
        return f'{where}: {self.message}'


class DeploymentError(ValueError):
    """A deployment file that cannot be used; carries every problem found."""

    def __init__(self, problems: Iterable[Problem]):
        self.problems = list(problems)
        super().__init__('\n'.join(str(p) for p in self.problems))


def describe(value: Any) -> str:
    """A value as it is quoted in a problem, cut to fit on its line."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + '...'


def did_you_mean(word: Any, candidates: Iterable[Any]) -> str:
    """' (did you mean X?)' for the closest candidate, or '' when none is close."""
    close = difflib.get_close_matches(str(word), [str(c) for c in candidates], n=1)
    return f' (did you mean {close[0]}?)' if close else ''


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Context:
    """What one reading of a file found: its problems, the paths whose value was not read as
    written, and the names each collection declares."""

    def __init__(self, source: str):
        self.source = source
        self.problems: List[Problem] = []
        self._damaged: List[str] = []
        self.declared: Dict[str, Set[str]] = {}   # collection -> every name it mentions
        self.broken: Set[str] = set()             # collections whose names could not be read

    def error(self, path: str, message: str, damages: bool = True) -> None:
        """Record a problem once; ``damages``: the value at ``path`` was replaced by a default
        (an unknown key damages nothing: it is only left out)."""
        self.add(Problem(self.source, path, message), damages)

    def add(self, problem: Problem, damages: bool = True) -> None:
        if problem not in self.problems:
            self.problems.append(problem)
        if damages:
            self.mark_damaged(problem.path)

    def mark_damaged(self, path: str) -> None:
        self._damaged.append(path)

    def damaged(self, path: str, inside: bool = True) -> bool:
        """True when ``path``, what holds it (or, with ``inside``, anything in it) was not read
        as written."""
        return any(p == path or path.startswith((f'{p}.', f'{p}['))
                   or inside and p.startswith((f'{path}.', f'{path}['))
                   for p in self._damaged if p)

    def all_read(self, collection: str, *keys: str) -> bool:
        """Whether every section the collection declares was read, with these keys of each."""
        names = self.declared.get(collection, ())
        return collection not in self.broken \
            and not any(self.damaged(p, inside=False)
                        for p in (collection, f'{collection}.names')) \
            and not any(self.damaged(f'{collection}.{n}', inside=False) for n in names) \
            and not any(self.damaged(f'{collection}.{n}.{k}') for n in names for k in keys)


class Section:
    """One map in the file: typed reads that record errors instead of raising."""

    def __init__(self, ctx: Context, path: str, data: Any):
        self.ctx = ctx
        self.path = path
        self.ok = isinstance(data, dict)
        if not self.ok:
            ctx.error(path, f'expected a map, got {describe(data)}')
        self.data: Dict[Any, Any] = data if self.ok else {}
        self.seen: Set[Any] = set()
        self.known: Set[str] = set()   # every key the reader asked for: "did you mean" candidates

    def sub(self, key: str) -> str:
        return f'{self.path}.{key}' if self.path else key

    def has(self, key: str) -> bool:
        self.known.add(key)
        return key in self.data

    def read(self, *keys: str) -> bool:
        """Whether these keys were read as written (absent counts as read): a check of how
        they fit together means something only then."""
        return not any(self.ctx.damaged(self.sub(k)) for k in keys)

    def raw(self, key: str, default: Any = MISSING) -> Any:
        self.seen.add(key)
        self.known.add(key)
        if key not in self.data:
            if default is MISSING and self.ok:   # else "expected a map" said it all
                self.ctx.error(self.sub(key), 'required key is missing')
            return default
        return self.data[key]

    def section(self, key: str, required: bool = True) -> 'Section':
        value = self.raw(key, MISSING if required else {})
        return Section(self.ctx, self.sub(key), value if value is not MISSING else {})

    def string(self, key: str, default: Any = MISSING,
               pattern: Optional['re.Pattern[str]'] = None,
               choices: Optional[Tuple[str, ...]] = None) -> Any:
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return default
        if not isinstance(v, str):
            self.ctx.error(self.sub(key), f'expected a string, got {describe(v)}')
            return default if default is not MISSING else ''
        if choices is not None and v not in choices:
            self.ctx.error(self.sub(key), f'expected one of {", ".join(choices)}, got {v!r}'
                                          f'{did_you_mean(v, choices)}')
        if pattern is not None and not pattern.match(v):
            self.ctx.error(self.sub(key), f'{v!r} is not a valid name here')
        return v

    def number(self, key: str, default: Any = MISSING, low: float = -math.inf,
               high: float = math.inf, low_open: bool = False, unit: str = '') -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not is_number(v):
            self.ctx.error(self.sub(key), f'expected a number{unit and " in " + unit}, '
                                          f'got {describe(v)}')
            return default if default is not MISSING else 0.0
        bad_low = v <= low if low_open else v < low
        if bad_low or v > high:
            lo = '(' if low_open else '['
            self.ctx.error(self.sub(key), f'{v} is out of range: expected a value in '
                                          f'{lo}{low}, {high}]{unit and " " + unit}')
        return float(v)

    def integer(self, key: str, default: Any = MISSING, low: int = 0,
                high: int = 2 ** 31) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, int) or isinstance(v, bool):
            self.ctx.error(self.sub(key), f'expected an integer, got {describe(v)}')
            return default if default is not MISSING else 0
        if not low <= v <= high:
            self.ctx.error(self.sub(key), f'{v} is out of range: expected {low}..{high}')
        return v

    def boolean(self, key: str, default: Any = MISSING) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, bool):
            self.ctx.error(self.sub(key), f'expected true or false, got {describe(v)}')
            return default if default is not MISSING else False
        return v

    def _list(self, key: str, default: Any, item_ok: Callable[[Any], bool],
              what: str) -> Any:
        v = self.raw(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, list):
            self.ctx.error(self.sub(key), f'expected a list of {what}, got {describe(v)}')
            return ()
        if not v:
            # rcl's parameter parser rejects empty sequences: omit the key instead.
            self.ctx.error(self.sub(key), 'an empty list is not a valid ROS parameter; '
                                          'leave the key out instead')
            return ()
        bad = [i for i, x in enumerate(v) if not item_ok(x)]
        if bad:
            self.ctx.error(f'{self.sub(key)}[{bad[0]}]',
                           f'expected {what}, got {describe(v[bad[0]])}')
            return ()
        return tuple(v)

    def strings(self, key: str, default: Any = MISSING) -> Any:
        return self._list(key, default, lambda x: isinstance(x, str), 'strings')

    def numbers(self, key: str, default: Any = MISSING) -> Any:
        v = self._list(key, default, is_number, 'numbers')
        if isinstance(v, tuple) and v and len({type(x) for x in v}) > 1:
            # A ROS parameter array has one type: [1, 2.5] fails to load as parameters.
            self.ctx.error(self.sub(key), 'mixes integers and decimals, which ROS parameter '
                                          'files reject: write every value as a decimal')
        return tuple(float(x) for x in v) if isinstance(v, tuple) else v

    def scalar_map(self, key: str) -> Mapping[str, Any]:
        v = self.raw(key, {})
        if not isinstance(v, dict):
            self.ctx.error(self.sub(key), f'expected a map, got {describe(v)}')
            return t.frozen_map()
        out = {}
        for k, x in v.items():
            if isinstance(x, (dict, type(None))) or (isinstance(x, list) and not x):
                self.ctx.error(f'{self.sub(key)}.{k}',
                               f'expected a scalar or a non-empty list, got {describe(x)}')
            else:
                out[str(k)] = x
        return t.frozen_map(out)

    def done(self) -> None:
        for key in self.data:
            if key not in self.seen:
                self.ctx.error(self.sub(str(key)), f'unknown key{did_you_mean(key, self.known)}',
                               damages=False)
