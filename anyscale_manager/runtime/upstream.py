"""A connection starved by its own publisher: explained upstream, not a reason to move.

A connection below freq_min moves its migrated end home (Algorithm 1), on the reading that the
link or the subscriber's scale starves it. When the publisher itself is down (crashed, in its
restart backoff, still starting), came back within ``grace_s`` (its rate window is still
filling), or is itself below freq_min on a connection that crosses no link, no move of the
subscriber can help: the move would cost a gap at the consumer and hold the node on the master
for T. Pure, driven by the decider's observations and clock.
"""

from typing import Dict, Mapping

from ..model.types import DeciderSettings, Deployment
from .observations import Observations


class UpstreamWatch:
    """When each publisher was last seen not serving, and what that explains."""

    def __init__(self, deployment: Deployment, settings: DeciderSettings):
        self.deployment = deployment
        self.settings = settings
        self._publishers = {c.publisher for c in deployment.connections}
        self._down_at: Dict[str, float] = {}       # publisher -> last seen not serving

    def update(self, obs: Observations, running: Mapping[str, str]) -> None:
        for node in self._publishers:
            if not self._serving(obs, running, node):
                self._down_at[node] = obs.now

    def _serving(self, obs: Observations, running: Mapping[str, str], node: str) -> bool:
        scale = running.get(node)
        if scale is None:
            # A node no agent starts (the decider, a driver of the user's) is not reported:
            # nothing says it is down.
            return not self.deployment.node(node).managed
        copy = (obs.copies.get(node) or {}).get(scale)
        return copy is None or (copy.state == 'running' and copy.ready)

    def explains(self, obs: Observations, running: Mapping[str, str], connection: str) -> str:
        """Why ``connection``'s low rate is its publisher's own doing, or ''."""
        c = self.deployment.connection(connection)
        pub = c.publisher
        if not self._serving(obs, running, pub):
            copies = obs.copies.get(pub) or {}
            where = running.get(pub, '')
            if where in copies:
                state = copies[where].state
            else:
                state = ', '.join(f'{cp.state} on {s}' for s, cp in sorted(copies.items())) \
                    or 'reported nowhere'
            return f'its publisher {pub} is not serving ({state})'
        down_at = self._down_at.get(pub)
        if down_at is not None and obs.now - down_at < self.settings.grace_s:
            return f'its publisher {pub} came back within grace_s = {self.settings.grace_s:g} s'
        here = running.get(pub)
        for other in self.deployment.connections:
            if other.publisher != pub or other.name == connection or not other.monitored:
                continue
            if running.get(other.subscriber) != here:
                continue        # it crosses a link: no word on the publisher itself
            seen = obs.connections.get(other.name)
            if seen is not None and seen.below:
                return f'its publisher {pub} is below freq_min on {other.name} too, which ' \
                       'crosses no link'
        return ''
