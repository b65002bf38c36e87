"""How often a link's status goes out: at once when what the decider acts on changes (the link
up or down, congested or not, a new figure of its bandwidth, the peer agent its warden names),
else once a period short enough that the decider never reads it as old. The heartbeats that
judge the link go on at their own rate; this paces only the report of them. Pure.
"""

from typing import Optional

from ..protocol import LinkStatus

# At most this long between two reports of an unchanged link, and at most a third of the age
# past which the decider counts an observation as missing (decider.observation_max_age_s).
LINK_STATUS_PERIOD_S = 1.0


def link_status_period_s(observation_max_age_s: float) -> float:
    return min(LINK_STATUS_PERIOD_S, observation_max_age_s / 3.0)


def link_status_due(last: Optional[LinkStatus], new: LinkStatus, since_last_s: float,
                    period_s: float) -> bool:
    """Whether ``new`` goes out, ``since_last_s`` after ``last`` (None: none sent yet) went."""
    if last is None or since_last_s >= period_s:
        return True
    return (new.up, new.congested, new.bandwidth_available_kbps, new.peer_agent) != \
        (last.up, last.congested, last.bandwidth_available_kbps, last.peer_agent)


__all__ = ['LINK_STATUS_PERIOD_S', 'link_status_due', 'link_status_period_s']
