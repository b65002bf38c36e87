"""QoS of the project's topics, in one place so publishers and subscribers cannot drift apart."""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def _profile(depth: int, reliable: bool, latched: bool = False) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


# Writing latched state (the layout; each agent's state): a late joiner gets the last value.
LATCHED = _profile(1, reliable=True, latched=True)
# Reading a latched topic: it has several writers (each agent; a rival decider), and a reader's
# depth is shared by all of them: room for each, and for a burst of one.
LATCHED_READER = _profile(20, reliable=True, latched=True)
# Periodic status topics: reliable so a decider misses no reading; any subscriber matches.
STATUS = _profile(10, reliable=True)
# Decisions and other logs a listener should not miss in a burst.
EVENTS = _profile(100, reliable=True)
# Reading monitors: best effort matches reliable and best-effort publishers alike.
MONITOR_READER = _profile(20, reliable=False)
# Probes: best effort and volatile reach every publisher; the probes drain their subscriptions
# every 50 ms while a topic is fast, and 100 messages hold a 1 kHz topic for twice that.
PROBE = _profile(100, reliable=False)
# Deciders' beats (every decider.beat_s): the newest counts, a lost one is replaced at once.
BEAT = _profile(10, reliable=False)
