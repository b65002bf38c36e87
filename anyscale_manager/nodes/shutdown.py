"""The last step of every program of the package that runs rclpy, after a SIGINT too."""

import rclpy
from rclpy.utilities import get_default_context


def shut_rclpy_down(context=None) -> None:
    """``rclpy.try_shutdown`` for a process that a SIGINT may be stopping.

    rclpy's signal handler shuts the contexts down on a thread of its own. ``try_shutdown``
    checks ``ok()`` and then shuts down, not atomically against that thread: a program that
    leaves its spin on ``stop_asked()`` can get there second and fail with "rcl_shutdown
    already called on the given context". A context shut down is what was asked for: that
    error is taken as done (the call is made again, which for the default context lets rclpy
    forget it and its signal handlers; the context's own shutdown callbacks, none in this
    package, are not run), and any other is raised.
    """
    ctx = context if context is not None else get_default_context()
    try:
        rclpy.try_shutdown(context=context)
    except RuntimeError as e:
        if ctx.ok() or 'already called' not in str(e):
            raise
        rclpy.try_shutdown(context=context)
