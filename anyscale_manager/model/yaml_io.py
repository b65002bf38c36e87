"""Where a deployment comes from: a ROS 2 parameters file in YAML, or a node's parameters."""

from typing import Any, Dict, Hashable, Mapping

import yaml

from .reader import Context, DeploymentError, Problem

# The top-level keys of a deployment: a node's other parameters are not part of it.
SECTIONS = ('deployment', 'scales', 'links', 'nodes', 'connections', 'decider', 'monitoring',
            'agent', 'security', 'discovery')


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses duplicate keys instead of keeping the last one."""


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode,
                       deep: bool = False) -> Dict[Hashable, Any]:
    seen: Dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f'duplicate key {key!r} (first at line {seen[key] + 1})',
                key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                                 _construct_mapping)


def parse_yaml(text: str) -> Any:
    """``text`` parsed, a key given twice refused (yaml.YAMLError, with its mark)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


def read_yaml(path: str) -> Any:
    """The parsed file; DeploymentError when it cannot be read or is not YAML (the line and
    column of the first mistake) or repeats a key."""
    source = str(path)
    try:
        with open(path, encoding='utf-8') as f:
            return yaml.load(f, Loader=_UniqueKeyLoader)
    except OSError as e:
        raise DeploymentError([Problem(source, '', f'cannot read: {e.strerror}')]) from e
    except yaml.YAMLError as e:
        raise DeploymentError([yaml_problem(source, e)]) from e


# What PyYAML's most frequent complaints usually mean in a hand-written file.
_HINTS = (
    ('mapping values are not allowed', "a value holding ': ' must be quoted, and a key "
                                       'nested under another must be indented under it'),
    ('expected <block end>', 'a line indented differently from the keys beside it'),
    ("'\\t' that cannot start any token", 'YAML indents with spaces, not tabs'),
    ("could not find expected ':'", "a key without its ':', or a quote left open"),
    ('found undefined alias', "'*' starts an alias in YAML: quote a value that begins with it"),
)


def mark_text(mark: Any) -> str:
    """'line 3, column 5' of a PyYAML mark (counted from 1, as editors do)."""
    return f'line {mark.line + 1}, column {mark.column + 1}'


def yaml_problem(source: str, e: yaml.YAMLError) -> Problem:
    """A PyYAML error as one line: where, what the parser expected or found, what that
    usually means, and the construct it was reading (where it starts)."""
    mark = getattr(e, 'problem_mark', None)
    what = getattr(e, 'problem', None) or str(e).replace('\n', ' ')
    text = f'invalid YAML: {what}'
    hint = next((h for key, h in _HINTS if key in what), '')
    if hint:
        text += f' ({hint})'
    context, context_mark = getattr(e, 'context', None), getattr(e, 'context_mark', None)
    if context and context_mark is not None and mark is not None \
            and context_mark.line != mark.line:
        text += f'; {context} that starts at {mark_text(context_mark)}'
    return Problem(source, mark_text(mark) if mark else '', text)


def unwrap_ros(ctx: Context, data: Any) -> Any:
    """What the ROS parameters-file wrapper ``/**: {ros__parameters: {...}}`` holds; None,
    with the problem recorded, when ``data`` is not one."""
    if not isinstance(data, dict) or len(data) != 1:
        ctx.error('', 'expected a ROS 2 parameters file: one top-level key such as /** '
                      'holding ros__parameters')
        return None
    (key, inner), = data.items()
    if not isinstance(inner, dict) or set(inner) != {'ros__parameters'}:
        ctx.error(str(key), 'expected exactly one key, ros__parameters')
        return None
    return inner['ros__parameters']


def nest_parameters(flat: Mapping[str, Any]) -> Dict[str, Any]:
    """Turn ROS parameter names with dots (``scales.robot.gain``) back into nested maps."""
    root: Dict[str, Any] = {}
    for name in sorted(flat):
        value = flat[name]
        if isinstance(value, (list, tuple)):
            value = list(value)
        parts = name.split('.')
        here = root
        for part in parts[:-1]:
            here = here.setdefault(part, {})
            if not isinstance(here, dict):
                break
        else:
            here[parts[-1]] = value
    return root


def deployment_parameters(flat: Mapping[str, Any]) -> Dict[str, Any]:
    """A node's parameters that belong to the deployment, nested as in the file."""
    return nest_parameters({k: v for k, v in flat.items() if k.split('.', 1)[0] in SECTIONS})
