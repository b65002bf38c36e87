"""What the runtime core sees and what it decides: plain frozen values, no ROS.

The live decider builds an ``Observations`` from the monitors' topics and the agents' reports;
the simulator builds one from its simulated world; a unit test writes one by hand. The policy
only ever sees this snapshot and the time passed in with it.
"""

from dataclasses import dataclass, field
from typing import FrozenSet, Mapping, Optional

from ..model.types import DeciderSettings, frozen_map
from ..protocol import HostShare


def is_fresh(stamp: float, now: float, settings: DeciderSettings) -> bool:
    """Whether an observation received at ``stamp`` still counts at ``now``."""
    return now - stamp <= settings.observation_max_age_s


@dataclass(frozen=True)
class ScaleObs:
    """One scale's measured CPU (reference-core percent), received at ``stamp``."""

    cpu_total: float
    stamp: float
    cpu_by_node: Mapping[str, float] = field(default_factory=frozen_map)


@dataclass(frozen=True)
class LinkObs:
    """The master's link to one remote scale, received at ``stamp``."""

    up: bool
    stamp: float
    available_kbps: Optional[float] = None   # None = not measured yet: use the nominal
    used_kbps: float = 0.0
    rtt_ms: Optional[float] = None
    # What the remote scale's warden says of its agent (alive, restarting, gone, fenced).
    peer_agent: Optional[str] = None


@dataclass(frozen=True)
class ConnectionObs:
    """One connection's measured rate, received at ``stamp``."""

    rate_hz: float
    stamp: float
    below_for_s: float = 0.0                 # the probe's open stretch below freq_min
    bytes_per_s: float = 0.0
    below: bool = False                      # the probe's verdict (runtime/delta.py)
    senders: int = 0                         # writers heard lately (0: not told apart there)
    senders_for_s: float = 0.0               # how long two or more have been heard at once


@dataclass(frozen=True)
class CopyObs:
    """One copy of a node on one scale, as its agent reports it."""

    state: str                          # the agent's report: running, standby, backoff, ...
    ready: bool = False
    # When the decider heard that this copy stopped serving against its will (it exited, or was
    # restarted), and why; None when it has not since it last served.
    crashed_at: Optional[float] = None
    exit_reason: str = ''
    # Of that exit: the process's exit code (None: not known, or not an exit) and the last
    # line it wrote to its log ('' none), as the agent read them.
    exit_code: Optional[int] = None
    log_tail: str = ''


@dataclass(frozen=True)
class Observations:
    """A frozen snapshot of everything the decider knows at time ``now`` (its own clock)."""

    now: float
    running: Mapping[str, str]                       # node -> scale where it actually runs
    scales: Mapping[str, ScaleObs] = field(default_factory=frozen_map)
    links: Mapping[str, LinkObs] = field(default_factory=frozen_map)   # link_observation_key
    connections: Mapping[str, ConnectionObs] = field(default_factory=frozen_map)
    lost_scales: FrozenSet[str] = frozenset()        # scales whose agent went silent
    # Keys of ``links`` with no fresh report because the agent that watches the link (the
    # master's, or a remote scale's for a link between two remote scales) is silent or has
    # just started: a dead agent is not a cut link.
    unjudged_links: FrozenSet[str] = frozenset()
    # Scales whose agent has not been heard for observation_max_age_s (never heard: counted from
    # the start of watching), with how long: nothing is placed there. Lost scales are among them.
    silent_agents: Mapping[str, float] = field(default_factory=frozen_map)
    # Connections measured by the probes of a silent agent, or of one heard again too recently
    # for its new probes to have measured: neither judged nor timed (a dead agent is not a slow
    # connection).
    unjudged_connections: FrozenSet[str] = frozenset()
    # node -> scale -> its copy there, from the agents not lost (standby and crashed copies
    # included, unlike ``running``).
    copies: Mapping[str, Mapping[str, CopyObs]] = field(default_factory=frozen_map)
    # Remote scales whose warden, heard over a live link, says their nodes may still serve:
    # the agent process lives (restarting in place, or silent on ROS while it runs) or is gone
    # and its warden has not stopped them yet. None of them is placed elsewhere while the
    # agent is silent (never two copies).
    fencing: FrozenSet[str] = frozenset()
    # Shared scales (scales.<s>.shared): their host's capacity and the other deployments'
    # claims there, what it refuses this deployment and who asks its nodes to leave, as its
    # agent last reported (agent/ledger.py).
    shares: Mapping[str, HostShare] = field(default_factory=frozen_map)


MIGRATE = 'migrate'            # master -> remote (Algorithm 1's else branch)
MIGRATE_BACK = 'migrate_back'  # remote -> master (Algorithm 1's violation branch)
MOVE_AWAY = 'move_away'        # remote -> a better remote than the master: it must leave
REBALANCE = 'rebalance'        # remote -> a more powerful remote (beyond the paper)
RELOCATE = 'relocate'          # a node of a lost scale placed elsewhere
FAILOVER = 'failover'          # a crashed serving copy replaced by a standby copy elsewhere
# A node leaves a shared host that refused it or whose room a higher priority asks for: room
# decides its return, not the hysteresis T.
YIELD = 'yield'


@dataclass(frozen=True)
class Decision:
    """One move, with the reason that is logged and published."""

    kind: str
    node: str
    from_scale: str
    to_scale: str
    reason: str
