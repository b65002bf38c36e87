"""Where a deployment comes from: a ROS 2 parameters file in YAML, or a node's parameters."""

from typing import Any, Dict, Hashable, Mapping

import yaml

from .reader import Context, DeploymentError, Problem

# The top-level keys of a deployment: a node's other parameters are not part of it.
SECTIONS = ('deployment', 'scales', 'links', 'nodes', 'connections', 'decider', 'monitoring',
            'agent', 'security')


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
        mark = getattr(e, 'problem_mark', None)
        where = f'line {mark.line + 1}, column {mark.column + 1}' if mark else ''
        what = getattr(e, 'problem', None) or str(e)
        raise DeploymentError([Problem(source, where, f'invalid YAML: {what}')]) from e


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
