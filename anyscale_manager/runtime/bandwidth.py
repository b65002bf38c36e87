"""A link's bandwidth: what it carries, measured actively (a probe) or read off a congestion.

Pure: every method takes ``now`` on the caller's monotonic clock (see runtime/rates.py).
"""

import math
from typing import Collection, Dict, Iterable, Mapping, Optional, Sequence, Tuple

from .rates import _positive

PROBE = 'probe'
CONGESTION = 'congestion'
# What the crossing connections deliver is read over this last stretch of their arrivals: short
# enough that a throttle shows in it within a heartbeat or two, long enough to hold several
# messages of a 10 Hz topic.
DELIVERY_SPAN_S = 0.5


class BandwidthEstimate:
    """The last figure of what a link carries, where it came from, and when to probe it.

    Two sources:

    - an active probe (a bulk TCP transfer): its throughput plus the traffic measured crossing
      the link while it ran, since a bulk TCP flow only gets what the (unyielding, UDP) ROS
      traffic leaves it. A probe is due every ``interval_s`` while the link is up, not congested
      and carrying less than ``busy_fraction`` of the last figure (else the nominal): a probe
      never adds load to a link that is full or already judged congested;
    - a congestion: while the link's queue holds the heartbeats (see HeartbeatTracker) and the
      connections crossing it deliver less than ``shortfall`` of the bandwidth they are
      declared to need, the link carries less than that need. How much less the delivery does
      not say (a datagram larger than the MTU is lost whole when one of its fragments is, so a
      full queue delivers far less than the link carries): ``congested`` records ``shortfall``
      x the need (or the last figure, if lower) at once, without a probe, so that the decider's
      bandwidth rule sends back the flows that no longer fit within a heartbeat or two instead
      of after a probe. A congestion that outlasts ``settle_s`` with the evidence still there
      (what was sent back was not enough) lowers the figure to ``shortfall`` x what is
      delivered then (``shortfall`` x the need, if lower): the largest flows have gone, so
      fragment loss no longer hides what the link carries, and what still does not arrive
      does not fit. (A link throttled below what DDS discovery alone puts on it delivers
      nearly nothing: the figure falls near 0 and everything that crosses it is sent back
      within ``settle_s`` and a beat.) Such a figure is probed as soon as the link is no
      longer congested (``min_gap_s`` after the figure and after the last probe), to learn the
      capacity later moves out are weighed against.
    """

    def __init__(self, interval_s: float, nominal_kbps: float, busy_fraction: float = 0.75,
                 min_gap_s: float = 1.0, shortfall: float = 0.9, settle_s: float = 1.0):
        self.interval_s = _positive(interval_s, 'interval_s')
        self.nominal_kbps = _positive(nominal_kbps, 'nominal_kbps')
        for value, what in ((busy_fraction, 'busy_fraction'), (shortfall, 'shortfall')):
            if not 0.0 < value <= 1.0:
                raise ValueError(f'{what} must be in (0, 1], got {value!r}')
        self.busy_fraction = busy_fraction
        self.shortfall = shortfall
        self.min_gap_s = _positive(min_gap_s, 'min_gap_s')
        self.settle_s = _positive(settle_s, 'settle_s')
        self.available_kbps: Optional[float] = None
        self.source: Optional[str] = None
        self.measured_at: Optional[float] = None
        self.last_attempt: Optional[float] = None
        self.failures = 0
        self.last_error = ''

    def due(self, now: float, link_up: bool, used_kbps: float, congested: bool = False) -> bool:
        """Whether to probe now (see the class)."""
        if not link_up or congested:
            return False
        since = math.inf if self.last_attempt is None else now - self.last_attempt
        congestion_age_s = self._congestion_age_s(now)
        if congestion_age_s is not None:
            return since >= self.min_gap_s and congestion_age_s >= self.min_gap_s
        if since < self.interval_s:
            return False
        reference = self.available_kbps if self.available_kbps is not None \
            else self.nominal_kbps
        return used_kbps < self.busy_fraction * reference

    def started(self, now: float) -> None:
        self.last_attempt = now

    def remeasure(self) -> None:
        """Make a probe due at once (the link came back: the robot may be somewhere else)."""
        self.last_attempt = None

    def record(self, now: float, probe_kbps: float,
               used_kbps: float = 0.0) -> Optional[float]:
        if not math.isfinite(probe_kbps) or probe_kbps <= 0:
            return self.failed(now, f'unusable throughput {probe_kbps!r}')
        self._set(now, probe_kbps + max(0.0, used_kbps), PROBE)
        self.failures = 0
        self.last_error = ''
        return self.available_kbps

    def congested(self, now: float, delivered_kbps: float, needed_kbps: float) -> Optional[float]:
        """On a link judged congested, the connections crossing it are declared to need
        ``needed_kbps`` and deliver ``delivered_kbps``: the new figure when that is evidence
        (see the class), else None."""
        if not (math.isfinite(delivered_kbps) and math.isfinite(needed_kbps)) \
                or needed_kbps <= 0 or delivered_kbps >= self.shortfall * needed_kbps:
            return None
        congestion_age_s = self._congestion_age_s(now)
        if congestion_age_s is not None and congestion_age_s < self.settle_s:
            return None
        figure = self.shortfall * needed_kbps
        if congestion_age_s is not None:        # still short after settle_s
            figure = min(figure, self.shortfall * max(0.0, delivered_kbps))
        if self.available_kbps is not None:
            figure = min(figure, self.available_kbps)
        self._set(now, figure, CONGESTION)
        return self.available_kbps

    def failed(self, now: float, reason: str) -> Optional[float]:
        """Note a failed probe; the previous estimate (if any) stands and keeps ageing."""
        self.failures += 1
        self.last_error = reason
        return self.available_kbps

    def age_s(self, now: float) -> Optional[float]:
        return None if self.measured_at is None else max(0.0, now - self.measured_at)

    def _congestion_age_s(self, now: float) -> Optional[float]:
        """How long ago the figure was read off a congestion; None when it came from a probe."""
        if self.source != CONGESTION or self.measured_at is None:
            return None
        return now - self.measured_at

    def _set(self, now: float, kbps: float, source: str) -> None:
        self.available_kbps = kbps
        self.source = source
        self.measured_at = now


def steady_throughput_bps(samples: Sequence[Tuple[float, int]],
                          skip_fraction: float = 0.25) -> Optional[float]:
    """Bytes per second of a bulk transfer from (time, cumulative bytes) receiver samples.

    The first ``skip_fraction`` of the transfer's duration is left out: a token bucket lets its
    burst through at line rate and TCP is still in slow start there, both of which overstate a
    shaped link. Returns None when the samples are too few to say anything.
    """
    if not 0.0 <= skip_fraction < 1.0:
        raise ValueError(f'skip_fraction must be in [0, 1), got {skip_fraction!r}')
    if len(samples) < 2:
        return None
    t0, t1 = samples[0][0], samples[-1][0]
    if t1 <= t0:
        return None
    start = t0 + skip_fraction * (t1 - t0)
    for t, b in samples:
        if t >= start:
            first_t, first_b = t, b
            break
    last_t, last_b = samples[-1]
    if last_t - first_t <= 0.0 or last_b <= first_b:
        return None
    return (last_b - first_b) / (last_t - first_t)


def crossing_connections(connections: Iterable[Tuple[str, str, str]],
                         placed: Mapping[str, Collection[str]], a: str,
                         b: str) -> Dict[str, str]:
    """The connections (name, publisher, subscriber) that cross the link between a and b, each
    with the scale of the subscriber's copy that receives across it. ``placed``: node -> the
    scales where a copy of it runs. During a handover a node runs on both ends for a moment,
    and its flows cross as long as a copy on one end feeds a copy on the other (a copy moved
    home still receives across the link until it is stopped or deactivated)."""
    out: Dict[str, str] = {}
    if a == b:
        return out
    for name, pub, sub in connections:
        pubs = set(placed.get(pub, ())) & {a, b}
        subs = set(placed.get(sub, ())) & {a, b}
        across = [s for s in (a, b) if s in subs and pubs - {s}]
        if across:
            out[name] = across[0]
    return out


def delivered_kbps(recent: Mapping[str, Tuple[float, float, float]]) -> float:
    """kbit/s the connections deliver, from (recent B/s, the reading's age in s, the age past
    which it is stale) each; a stale reading counts as delivering nothing (on a congested link
    the far end's reports wait in the same full queue: the last one through describes the link
    before it filled)."""
    return used_kbps({n: (bps if age <= stale_s else 0.0)
                      for n, (bps, age, stale_s) in recent.items()}, recent)


def used_kbps(bytes_per_s: Mapping[str, float], names: Iterable[str]) -> float:
    """kbit/s carried by the named connections, from their measured bytes per second."""
    return sum(max(0.0, bytes_per_s.get(n, 0.0)) for n in names) * 8.0 / 1000.0
