"""A deployment whose derived sets and look-ups are computed once.

``Deployment`` is immutable, but its derived sets (critical nodes, migratable nodes, allowed
scales, ...) are recomputed on every access, and the policy asks for them many times per step.
The simulator hands the policy this equivalent object instead: same fields, same answers, cached.
"""

from dataclasses import fields
from functools import cached_property
from typing import Dict, Optional, Tuple

from ..model.types import Connection, Deployment, Link, Node, Scale


class MemoDeployment(Deployment):
    """Same fields and answers as its ``Deployment``; derived values cached per instance."""

    def _memo(self, name: str) -> Dict:
        return self.__dict__.setdefault(name, {})

    @cached_property
    def scale_names(self) -> Tuple[str, ...]:
        return Deployment.scale_names.fget(self)

    @cached_property
    def node_names(self) -> Tuple[str, ...]:
        return Deployment.node_names.fget(self)

    @cached_property
    def master(self) -> Scale:
        return Deployment.master.fget(self)

    @cached_property
    def remote_scales(self) -> Tuple[Scale, ...]:
        return Deployment.remote_scales.fget(self)

    @cached_property
    def critical_nodes(self) -> Tuple[str, ...]:
        return Deployment.critical_nodes.fget(self)

    @cached_property
    def data_providers(self) -> Tuple[str, ...]:
        return Deployment.data_providers.fget(self)

    @cached_property
    def migratable_nodes(self) -> Tuple[str, ...]:
        return Deployment.migratable_nodes.fget(self)

    def _cached(self, table: str, key, compute):
        memo = self._memo(table)
        if key not in memo:
            memo[key] = compute()
        return memo[key]

    def scale(self, name: str) -> Scale:
        return self._cached('_scale', name, lambda: Deployment.scale(self, name))

    def node(self, name: str) -> Node:
        return self._cached('_node', name, lambda: Deployment.node(self, name))

    def connection(self, name: str) -> Connection:
        return self._cached('_connection', name, lambda: Deployment.connection(self, name))

    def link_between(self, a: str, b: str) -> Optional[Link]:
        return self._cached('_link', (a, b), lambda: Deployment.link_between(self, a, b))

    def connections_of(self, node: str) -> Tuple[Connection, ...]:
        return self._cached('_conns', node, lambda: Deployment.connections_of(self, node))

    def coresidence_group(self, node: str) -> Tuple[str, ...]:
        return self._cached('_group', node, lambda: Deployment.coresidence_group(self, node))

    def own_scales(self, node: str) -> Tuple[str, ...]:
        return self._cached('_own', node, lambda: Deployment.own_scales(self, node))

    def allowed_scales(self, node: str) -> Tuple[str, ...]:
        return self._cached('_allowed', node, lambda: Deployment.allowed_scales(self, node))


def memoize(deployment: Deployment) -> Deployment:
    """An equivalent deployment with cached derived values (returned as is if already one)."""
    if isinstance(deployment, MemoDeployment):
        return deployment
    return MemoDeployment(**{f.name: getattr(deployment, f.name) for f in fields(deployment)})
