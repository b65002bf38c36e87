"""The last step of every program of the package that runs rclpy, after a SIGINT too."""

import rclpy
from rclpy.utilities import get_default_context


def shut_rclpy_down(context=None) -> None:
    """``rclpy.try_shutdown`` for a process that a SIGINT may be stopping.

    rclpy's signal handler shuts the contexts down on a thread of its own. ``try_shutdown``
    checks ``ok()`` and then shuts down, not atomically against that thread: a program that
    leaves its spin on ``stop_asked()`` can get there second and fail with "rcl_shutdown
    already called on the given context". A context shut down is what was asked for; the
    call is made again (a no-op on the context now) to finish the rest, and any other error
    is raised.
    """
    ctx = context if context is not None else get_default_context()
    try:
        rclpy.try_shutdown(context=context)
    except RuntimeError:
        if ctx.ok():
            raise
        rclpy.try_shutdown(context=context)
