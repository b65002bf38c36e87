"""The decider's beat: a thread of its own that beats and hears the other deciders' beats.

Twenty beats a second through the rclpy executor cost about 7 % of a core per decider (the
executor rebuilds its wait set for every wake-up); a plain thread that publishes and takes the
beats itself costs about 1 %. The thread owns a node no executor spins (one DDS participant per
context: no extra discovery), and every ``beat_s`` takes the beats that arrived, feeds them to
the leadership (runtime/leadership.py), checks it and acts on a change of role (a takeover
publishes at once), all under the decider's lock, which every executor callback holds too; then
it beats.

A beat is published only while someone else reads the topic (a standby or any other decider, a
status view): the graph shows a subscription to it beside this thread's own. A decider alone
would only encode, sign and publish twenty messages a second to nobody, about 0.6 % of a core
on the robot. A decider that starts subscribes before it listens ``discovery_s`` for a leader,
and the leader beats from its first turn after the graph shows it, as DDS matches the two. The
leadership counts a beat as given all the same, and the beats it hears of itself (its own
subscription receives them) are dropped before they are decoded. A leader alone wakes every
``ALONE_WAIT_S`` rather than every ``beat_s``, and that quiet time is no stall (nobody could
have taken over meanwhile: Leadership.listened); a longer one is (a standby may have started and
found no beat), and until its thread has looked again it commands nothing. A standby's turns
time its takeover and stay at ``beat_s``.

A beat says "this decider decides": a callback stuck with the lock stops the beats, and so
does an executor that has not turned for ``period_s + takeover_s``; a standby then takes over,
and the stuck leader steps down when it wakes.
"""

import json
import threading
import time
from typing import List

from rclpy.node import Node
from std_msgs.msg import String

from . import qos
from .. import protocol as p
from ..runtime.leadership import LEADER

# How often a leader nobody listens to wakes (at most a quarter of discovery_s).
ALONE_WAIT_S = 0.5
# Beats taken per wake-up at most (a burst of forged ones must not hold the lock for long).
MAX_TAKEN = 200


def alone_wait_s(settings) -> float:
    """How long a leader nobody listens to waits between two turns of its beat thread."""
    return max(settings.beat_s, min(ALONE_WAIT_S, settings.discovery_s / 4.0))


class BeatThread:
    def __init__(self, decider, lock: threading.RLock):
        self.decider = decider
        self.lock = lock
        self.executor_alive = decider._now()    # the executor's last turn (set by it)
        self.node = Node(f'{decider.get_name()}_beat', context=decider.context,
                         start_parameter_services=False)
        self.pub = self.node.create_publisher(String, p.TOPIC_DECIDER, qos.BEAT)
        self.sub = self.node.create_subscription(String, p.TOPIC_DECIDER, lambda _m: None,
                                                 qos.BEAT)
        # This decider's beats as its own subscription receives them: skipped undecoded.
        self._own = '"id":' + json.dumps(decider.identity.id)
        self.wait_s = decider.settings.beat_s      # until the next turn of the thread
        self._stopping = False
        self.thread = threading.Thread(target=self._run, name='decider beat', daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stopping = True
        if self.thread.is_alive():
            self.thread.join(2.0)
        self.node.destroy_node()

    def _run(self) -> None:
        d = self.decider
        while not self._stopping:
            started = d._now()
            try:
                self.step(started)
            except Exception as e:  # noqa: B902 - the beat must outlive any one bad turn
                d.get_logger().error(f'decider beat failed: {type(e).__name__}: {e}',
                                     throttle_duration_sec=5.0)
            # A plain sleep: a timed wait on an Event costs twice as much a wake-up.
            time.sleep(max(0.0, self.wait_s - (d._now() - started)))

    def listened(self) -> bool:
        """Whether anyone but this decider reads the beats: a subscription to the topic in the
        graph beside this thread's own. When the graph cannot be read, it beats."""
        try:
            return self.node.count_subscribers(p.TOPIC_DECIDER) > 1
        except Exception:  # noqa: B902 - a beat too many is harmless, one missing is not
            return True

    def step(self, now: float) -> None:
        d = self.decider
        texts = self._take()
        listened = self.listened()
        with self.lock:
            now = d._now()          # after the wait for the lock: no beat went out meanwhile
            for text in texts:
                d.heard_beat_text(text, now)
            # Judged as what it was through the time since the last wake: a leader that others
            # listened to and that stalled (stopped, starved) steps down even if, resumed, it
            # reads the graph before DDS has heard the others again and finds nobody.
            d.check_role(now)
            d.lead.listened(listened, now)
            stuck = now - self.executor_alive > d.settings.period_s + d.settings.takeover_s
            beats = not (stuck and d.lead.role == LEADER)
            beat = p.DeciderBeat(
                stamp=time.time(), deployment=d.deployment.name, decider=d.identity,
                role=d.lead.role, term=d.lead.term, generation=d.core.generation) \
                if beats and listened else None
            if beats and beat is None:
                d.lead.beaten(now)      # nobody to tell: the beat counts as given
            # A leader nobody listens to wakes every ALONE_WAIT_S only: to hear a decider or
            # a status view that appears (and beat for it from then on) well within
            # discovery_s, the time a starting decider listens before it leads.
            alone = not listened and d.lead.role == LEADER
            self.wait_s = alone_wait_s(d.settings) if alone else d.settings.beat_s
        if beat is not None:
            self.pub.publish(String(data=d.sealer.seal(beat)))
            # When it went out: a takeover's first layout, published in check_role, can take
            # a while, and a beat stamped before it would make the new leader count that
            # work as a stall of its own.
            with self.lock:
                d.lead.beaten(d._now())

    def _take(self) -> List[str]:
        out = []
        with self.sub.handle:
            for _ in range(MAX_TAKEN):
                taken = self.sub.handle.take_message(self.sub.msg_type, False)
                if taken is None:
                    break
                if self._own not in taken[0].data:
                    out.append(taken[0].data)
        return out
