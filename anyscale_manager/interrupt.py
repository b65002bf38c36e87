"""Ctrl-C for every program of the package, however it was started."""

import signal


def restore_ctrl_c() -> None:
    """Make SIGINT interrupt again when this process inherited it ignored.

    A program started in the background of a non-interactive shell (``decider ... &`` in a
    script, some service managers) inherits SIGINT ignored; Python and rclpy then leave it
    ignored, so Ctrl-C or ``kill -INT`` (the ROS way to stop a node) does nothing to it, nor to
    the nodes an agent starts, which inherit it. Called first by every entry point.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
