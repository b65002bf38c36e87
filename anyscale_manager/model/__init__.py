"""The deployment: scales, links, nodes, settings, connections; YAML in, frozen dataclasses out."""

from .loader import (DeploymentError, Problem, load_deployment, load_from_parameters,
                     load_mapping, nest_parameters)
from .types import (AgentSettings, Connection, DeciderSettings, Deployment, Launch, Link,
                    MonitorSettings, Node, Scale, Settings)

__all__ = [
    'AgentSettings', 'Connection', 'DeciderSettings', 'Deployment', 'DeploymentError', 'Launch',
    'Link', 'MonitorSettings', 'Node', 'Problem', 'Scale', 'Settings', 'load_deployment',
    'load_from_parameters', 'load_mapping', 'nest_parameters',
]
