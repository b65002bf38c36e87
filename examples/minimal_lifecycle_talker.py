"""A minimal lifecycle node that a scale can keep as an inactive standby copy.

    python3 minimal_lifecycle_talker.py --ros-args -p rate_hz:=5.0

While active it publishes a counter (std_msgs/msg/Int64) on ``counter`` at ``rate_hz`` and
starts again from 0 when a std_msgs/msg/Empty arrives on ``reset``. The timer and that
subscription exist only while it is active: an inactive copy wakes up for nothing and pulls no
data over the network, since DDS sends a computer data only for a subscription there.

Its state is its count, and the last message on ``counter`` holds it. A count that arrives on
``restore`` (configured or active) is where it continues from: the copy that takes over from
another continues the count instead of starting again from 0. Declared in a deployment as

    state: {topic: /counter, restore: /restore}

the agent hands each copy it activates the last count it heard, on that copy's own ``restore``.
Its lifecycle services are its own (``~/change_state`` ...), so whoever starts a copy can remap
them per scale. The contract it follows is in docs/lifecycle.md.
"""

import sys

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from std_msgs.msg import Empty, Int64

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR


class MinimalLifecycleTalker(LifecycleNode):
    def __init__(self, **kwargs):
        super().__init__('minimal_lifecycle_talker', **kwargs)
        self.declare_parameter('rate_hz', 2.0, ParameterDescriptor(
            description='counter messages per second while active (read on configure)'))
        self._publisher = None
        self._timer = None
        self._reset = None
        self._restore = None
        self._period_s = 0.0
        self._count = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        rate_hz = self.get_parameter('rate_hz').value
        if not rate_hz > 0:
            # FAILURE: the node stays unconfigured, and says why.
            self.get_logger().error(f'configure refused: rate_hz must be > 0, got {rate_hz}')
            return FAILURE
        try:
            self._period_s = 1.0 / rate_hz
            self._publisher = self.create_lifecycle_publisher(Int64, 'counter', 10)
            # The one subscription an inactive copy keeps: its state, handed to it before it is
            # activated.
            self._restore = self.create_subscription(Int64, 'restore', self._on_restore, 1)
        except Exception as e:
            return self._failed('configure', e)
        self.get_logger().info(f'configured: inactive, {rate_hz:g} Hz once active')
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            super().on_activate(state)      # enables the lifecycle publisher
            self._timer = self.create_timer(self._period_s, self._tick)
            self._reset = self.create_subscription(Empty, 'reset', self._on_reset, 10)
            self._tick()                    # serve at once, not one period later
        except Exception as e:
            return self._failed('activate', e)
        self.get_logger().info('activated: publishing the counter')
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._drop_timer_and_subscription()
            super().on_deactivate(state)    # publish() is dropped from now on
        except Exception as e:
            return self._failed('deactivate', e)
        self.get_logger().info('deactivated: no timer, no subscription')
        return SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._drop_everything()
            self._count = 0
        except Exception as e:
            return self._failed('cleanup', e)
        self.get_logger().info('cleaned up: unconfigured')
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._drop_everything()
        except Exception as e:
            return self._failed('shutdown', e)
        self.get_logger().info(f'shut down from {state.label}')
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        # SUCCESS here leaves the node unconfigured, ready to be configured again.
        self._drop_everything()
        self.get_logger().warning('error handled: unconfigured')
        return SUCCESS

    def _failed(self, transition: str, error: Exception) -> TransitionCallbackReturn:
        # rclpy would turn the exception into ERROR without a word: say why first.
        self.get_logger().error(f'{transition} failed: {type(error).__name__}: {error}')
        return ERROR

    def _tick(self) -> None:
        self._publisher.publish(Int64(data=self._count))
        self._count += 1

    def _on_reset(self, _msg: Empty) -> None:
        self._count = 0

    def _on_restore(self, msg: Int64) -> None:
        if msg.data < 0:
            # A state it cannot take is refused with its reason; the count goes on as it was.
            self.get_logger().error(f'restore refused: a count is >= 0, got {msg.data}')
            return
        self._count = msg.data + 1     # the last count published, then the next one
        self.get_logger().info(f'restored: continuing from {self._count}')

    def _drop_timer_and_subscription(self) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._reset is not None:
            self.destroy_subscription(self._reset)
            self._reset = None

    def _drop_everything(self) -> None:
        self._drop_timer_and_subscription()
        if self._restore is not None:
            self.destroy_subscription(self._restore)
            self._restore = None
        if self._publisher is not None:
            self.destroy_lifecycle_publisher(self._publisher)
            self._publisher = None


def main(args=None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = MinimalLifecycleTalker()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
