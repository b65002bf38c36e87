"""The workload as a lifecycle (managed) node: ``workload --lifecycle``, as Nav2's AMCL is.

It starts unconfigured. Configure creates its (lifecycle) publishers; activate creates its
subscriptions and timers and, with ``--once``, publishes its one message; deactivate destroys
the subscriptions and timers again. An inactive copy therefore has no subscription in the graph
(DDS sends a host data only for a subscription there) and nothing that wakes it up: a standby
copy costs memory and a DDS participant, no CPU and no link bandwidth.

Its lifecycle services are created under its own name (``~/change_state`` ...), so the agent
can remap them per scale (``-r ~/change_state:=~/robot/change_state``). An exception inside a
transition is logged with its reason and ends in ERROR, whose handler tears everything down and
leaves the node unconfigured (rclpy Jazzy would end in ERROR without a word); a transition that
is not valid from the current state is refused instead of stopping the node.
"""

import time
from typing import Callable

from lifecycle_msgs.srv import ChangeState
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from .workload import OutputGate, WorkloadBehaviour, WorkloadSpec, publisher_qos
from .workload_messages import Endpoint, message_class

SUCCESS = TransitionCallbackReturn.SUCCESS
ERROR = TransitionCallbackReturn.ERROR


class LifecycleWorkloadNode(WorkloadBehaviour, LifecycleNode):
    """The workload's behaviour, with publishers, subscriptions and timers per lifecycle state."""

    def __init__(self, spec: WorkloadSpec, clock: Callable[[], float] = time.monotonic,
                 **kwargs):
        super().__init__(spec.name, **kwargs)
        self._init_behaviour(spec, clock)
        self._input_subs = []
        self._active_timers = []
        self._restore_sub = None
        self._refuse_invalid_transitions()
        self.get_logger().info(f'unconfigured: will be {self.describe()} once active')

    # --- transitions -----------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('configure', self._configure, state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('activate', self._activate, state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('deactivate', self._deactivate, state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('cleanup', self._cleanup, state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition('shutdown', self._shutdown, state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._tidy()
        except Exception as e:
            # FAILURE from on_error finalizes the node: only a restart can help it now.
            self.get_logger().error(f'error handling failed, finalizing: '
                                    f'{type(e).__name__}: {e}')
            return TransitionCallbackReturn.FAILURE
        self.get_logger().warning(f'error handled (after {state.label}): everything torn down, '
                                  'unconfigured')
        return SUCCESS

    def _transition(self, name: str, body: Callable[[LifecycleState], str],
                    state: LifecycleState) -> TransitionCallbackReturn:
        try:
            said = body(state)
        except Exception as e:
            self.get_logger().error(f'{name} failed (from {state.label}): '
                                    f'{type(e).__name__}: {e}')
            return ERROR
        self.get_logger().info(said)
        return SUCCESS

    def _configure(self, state: LifecycleState) -> str:
        self._pubs = [self._new_publisher(e) for e in self.spec.outputs]
        # Its state's restore input: the one subscription an inactive copy keeps.
        self._restore_sub = self._subscribe_restore()
        return f'configured: inactive, {len(self._pubs)} publisher(s) ready' + (
            f', taking its state on {self.spec.restore}' if self._restore_sub else '')

    def _activate(self, state: LifecycleState) -> str:
        if super().on_activate(state) != SUCCESS:       # enables the lifecycle publishers
            raise RuntimeError('a lifecycle publisher refused to activate')
        self._pending = False
        self._gate = OutputGate(self.spec.rate_hz)      # no due time left from last time
        self._first_output_logged = False
        # Created once per activation and re-armed while active (see WorkloadNode).
        self._retry = self.create_timer(1.0, self._on_retry)
        self._retry.cancel()
        self._active_timers.append(self._retry)
        self._input_subs = self._subscribe_inputs()
        if self.spec.once:
            self._publish()
        elif self.spec.is_sensor:
            self._active_timers.append(self.create_timer(1.0 / self.spec.rate_hz, self._publish))
        return f'activated: {self.describe()}'

    def _deactivate(self, state: LifecycleState) -> str:
        self._drop_inputs_and_timers()
        if self.pose is not None:
            self.pose.pause()
        if super().on_deactivate(state) != SUCCESS:     # publish() is dropped from now on
            raise RuntimeError('a lifecycle publisher refused to deactivate')
        if self.spec.once:
            # A transient-local writer hands its last message to every reader that joins
            # later, inactive or not: a fresh writer has none to hand.
            for pub in self._pubs:
                self.destroy_lifecycle_publisher(pub)
            self._pubs = [self._new_publisher(e) for e in self.spec.outputs]
        return 'deactivated: no subscriptions, no timers, publishing nothing'

    def _cleanup(self, state: LifecycleState) -> str:
        self._drop_publishers()
        return 'cleaned up: unconfigured'

    def _shutdown(self, state: LifecycleState) -> str:
        self._tidy()
        return f'shut down (from {state.label})'

    # --- helpers ---------------------------------------------------------------------------
    def _new_publisher(self, output: Endpoint):
        return self.create_lifecycle_publisher(message_class(output.msg_type), output.topic,
                                               publisher_qos(self.spec))

    def _drop_inputs_and_timers(self) -> None:
        for sub in self._input_subs:
            self.destroy_subscription(sub)
        for timer in self._active_timers:
            self.destroy_timer(timer)
        self._input_subs, self._active_timers, self._retry = [], [], None
        self._pending = False

    def _drop_publishers(self) -> None:
        for pub in self._pubs:
            self.destroy_lifecycle_publisher(pub)
        self._pubs = []
        if self._restore_sub is not None:
            self.destroy_subscription(self._restore_sub)
            self._restore_sub = None

    def _tidy(self) -> None:
        self._drop_inputs_and_timers()
        self._drop_publishers()

    def _refuse_invalid_transitions(self) -> None:
        """Answer a change_state that is not valid from the current state with success=False.

        rclpy Jazzy raises inside the service callback instead (fixed later, ros2/rclpy#1319),
        which ends the spin and the process: one stray request would kill a standby copy.
        """
        service = self._service_change_state
        handle = service.callback

        def guarded(request: ChangeState.Request, response: ChangeState.Response):
            try:
                return handle(request, response)
            except RuntimeError as e:      # rclpy's RCLError: no such transition from here
                self.get_logger().warning(
                    f'change_state refused: transition {request.transition.id}'
                    f'{" " + request.transition.label if request.transition.label else ""}'
                    f' is not valid from {self._state_machine.current_state[1]} ({e})')
                response.success = False
                return response
        service.callback = guarded
