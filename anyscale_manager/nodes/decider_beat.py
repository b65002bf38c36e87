"""The decider's beat: a thread of its own that beats and hears the other deciders' beats.

Twenty beats a second through the rclpy executor cost about 7 % of a core per decider (the
executor rebuilds its wait set for every wake-up); a plain thread that publishes and takes the
beats itself costs about 1 %. The thread owns a node no executor spins (one DDS participant per
context: no extra discovery), publishes this decider's beat every ``beat_s``, takes the beats
that arrived, feeds them to the leadership (runtime/leadership.py), checks it and acts on a
change of role (a takeover publishes at once), all under the decider's lock, which every
executor callback holds too.

A beat says "this decider decides": a callback stuck with the lock stops the beats, and so
does an executor that has not turned for ``period_s + takeover_s``; a standby then takes over,
and the stuck leader steps down when it wakes.
"""

import threading
import time
from typing import List

from rclpy.node import Node
from std_msgs.msg import String

from . import qos
from .. import protocol as p
from ..runtime.leadership import LEADER

# Beats taken per wake-up at most (a burst of forged ones must not hold the lock for long).
MAX_TAKEN = 200


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
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name='decider beat', daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(2.0)
        self.node.destroy_node()

    def _run(self) -> None:
        d = self.decider
        while not self._stop.is_set():
            started = d._now()
            try:
                self.step(started)
            except Exception as e:  # noqa: B902 - the beat must outlive any one bad turn
                d.get_logger().error(f'decider beat failed: {type(e).__name__}: {e}',
                                     throttle_duration_sec=5.0)
            self._stop.wait(max(0.0, d.settings.beat_s - (d._now() - started)))

    def step(self, now: float) -> None:
        d = self.decider
        texts = self._take()
        with self.lock:
            now = d._now()          # after the wait for the lock: no beat went out meanwhile
            for text in texts:
                d.heard_beat_text(text, now)
            d.check_role(now)
            stuck = now - self.executor_alive > d.settings.period_s + d.settings.takeover_s
            beat = None if stuck and d.lead.role == LEADER else p.DeciderBeat(
                stamp=time.time(), deployment=d.deployment.name, decider=d.identity,
                role=d.lead.role, term=d.lead.term, generation=d.generation)
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
                out.append(taken[0].data)
        return out
