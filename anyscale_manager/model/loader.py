"""Read a deployment YAML (a valid ROS 2 parameters file) into validated frozen dataclasses.

The file looks like::

    /**:
      ros__parameters:
        deployment: {name: ..., description: ...}
        scales: {names: [robot, laptop], robot: {...}, laptop: {...}}
        links: {names: [wifi], wifi: {ends: [robot, laptop], ...}}
        nodes: {names: [...], amcl: {launch: {...}, cpu: 50.0, ...}}
        connections: {names: [...], laser_amcl: {topic: /scan, ...}}
        decider: {...}
        monitoring: {...}
        agent: {...}
        security: {key_file: ..., replay_window_s: ...}

Every error names the file, the path inside it and what was expected; all errors are collected
and reported at once, one line each. Reading is in three parts: the sections, each by its
reader (model/sections.py, on the error-collecting reader of model/reader.py), then the
whole-deployment checks (model/checks.py) on whatever was read, so that a typo in one key does
not hide a contradiction elsewhere in the same file.
"""

from typing import Any, Mapping, Optional, Sequence

from . import types as t
from .checks import CHECKS
from .params_file import parameters_source
from .reader import Context, DeploymentError, Problem, Section, did_you_mean
from .sections import read_deployment
from .yaml_io import deployment_parameters, nest_parameters, read_yaml, unwrap_ros

__all__ = ['DeploymentError', 'Problem', 'did_you_mean', 'load_deployment',
           'load_from_parameters', 'load_mapping', 'nest_parameters']


def load_mapping(data: Any, source: str = '<mapping>', wrapped: bool = True) -> t.Deployment:
    """Validate a parsed deployment; ``wrapped`` means it still has the ROS file wrapper."""
    ctx = Context(source)
    if wrapped:
        data = unwrap_ros(ctx, data)
        if data is None:
            raise DeploymentError(ctx.problems)
    root = Section(ctx, '', data)
    if not root.ok:
        raise DeploymentError(ctx.problems)
    deployment = read_deployment(root)
    for check in CHECKS:
        for problem in check(deployment, ctx):
            ctx.add(problem)
    if ctx.problems:
        raise DeploymentError(ctx.problems)
    return deployment


def load_deployment(path: str) -> t.Deployment:
    """Load and validate a deployment file; raises DeploymentError naming every problem."""
    return load_mapping(read_yaml(path), str(path))


def load_from_parameters(flat: Mapping[str, Any], source: Optional[str] = None,
                         argv: Optional[Sequence[str]] = None) -> t.Deployment:
    """Rebuild a deployment from a node's parameters (loaded with --params-file). Its errors
    name ``source``, by default the parameters files of ``argv`` (the command line the node's
    rcl arguments came from; default this process's), '<ROS parameters>' when it has none."""
    if source is None:
        source = parameters_source(argv)
    return load_mapping(deployment_parameters(flat), source, wrapped=False)
