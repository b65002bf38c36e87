"""The agent's hands on its lifecycle nodes: get_state / change_state clients it keeps.

One ``CopyClients`` per lifecycle node of the catalogue, addressing this scale's copy only (its
services are remapped under ``/<node>/<scale>/`` when the agent starts it, so a copy on
another scale never answers). Requests are asynchronous: the answer reaches the node's
``agent.lifecycle.Driver`` from the executor, and ``on_answer`` lets the agent act on it at once
(an activation is reported the moment it is done, not at the next tick).
"""

from typing import Callable

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.node import Node

from ..agent.lifecycle import Driver, Request


class CopyClients:
    def __init__(self, node: Node, services: str, driver: Driver, clock: Callable[[], float],
                 on_answer: Callable[[], None]):
        self._node = node
        self.services = services
        self.driver = driver
        self._clock = clock
        self._on_answer = on_answer
        self._get = node.create_client(GetState, f'{services}/get_state')
        self._change = node.create_client(ChangeState, f'{services}/change_state')

    def reachable(self) -> bool:
        return self._get.service_is_ready() and self._change.service_is_ready()

    def poll(self) -> None:
        """Make the call the driver asks for now, if any."""
        request = self.driver.next_request(self._clock(), self.reachable)
        if request is None:
            return
        try:
            if request.kind == 'get':
                future = self._get.call_async(GetState.Request())
            else:
                # By id alone: a label wins over the id in rclpy, and the three shutdown
                # transitions share the label 'shutdown'.
                future = self._change.call_async(ChangeState.Request(
                    transition=Transition(id=request.transition_id)))
        except Exception as e:     # a client destroyed under us, an rcl error: said, not raised
            self.driver.lost(request.serial, f'{type(e).__name__}: {e}', self._clock())
            return
        future.add_done_callback(lambda f, r=request: self._done(r, f))

    def _done(self, request: Request, future) -> None:
        now = self._clock()
        try:
            response = future.result()
        except Exception as e:
            self.driver.lost(request.serial, f'{type(e).__name__}: {e}', now)
        else:
            if response is None:
                self.driver.lost(request.serial, 'no response', now)
            elif request.kind == 'get':
                self.driver.answered_state(request.serial, response.current_state.label, now)
            else:
                self.driver.answered_change(request.serial, bool(response.success), now)
        self._on_answer()

    def destroy(self) -> None:
        self._node.destroy_client(self._get)
        self._node.destroy_client(self._change)
